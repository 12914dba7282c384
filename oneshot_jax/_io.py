"""The file of a saved `FitResult`: one `.npz` file, documented format, versioned.

`save_result` writes it; `read_result` reads the fields back, from which
`oneshot_jax.load_result` builds the `FitResult` (`oneshot_jax._fit_result`: this module
comes below the data classes it saves, so that `FitResult.save` can call it).

The file is a NumPy `.npz` archive (readable with `numpy.load` alone, no pickle):

- `__meta__`: a JSON document (a 0-d unicode array) with `format`
  ("oneshot_jax.FitResult"), `version` (1), the structure of theta (`theta_tree`: nested
  `{"dict": {...}}`, `{"list": [...]}`, `{"tuple": [...]}`, `{"none": null}` and
  `{"leaf": i}` nodes for the parameters, `{"static": j}` nodes for integer and boolean
  arrays (`{"scalar": true}` added for NumPy scalars) and `{"const": v}` nodes for Python
  booleans, or null for a structure JSON cannot describe), `names`, `stop_reason` (a
  `RESULTS` name), `num_steps`, `wall_time`, `best`, `solver` (the settings of each
  solver), the metric names, `starts_stop_reason` and `starts_solver_stop`, `diagnostics` and
  `stop_info` (JSON objects), `theta_order` (a list of names), `units` (a JSON object),
  `validation_loss` (a number or null), `warnings` (the fit's warnings, a list of
  strings) and `static_signature` (what `load_result(like=)`
  compares beyond shapes and names: the static fields of theta's equinox modules and its
  non-parameter leaves such as an activation function, each in words), `n_u` (the
  fitted data's input columns, which `FitResult.simulate`/`predict` check) and
  `model_signature` (the model's static settings, which `load_result(model=)` checks),
  and `digest`: the SHA-256 of the arrays (names, dtypes, shapes, bytes) and of the rest
  of `__meta__`, by which an edited file is told from the saved one (a file without it,
  written before it was added, is read without that check).
- arrays: `theta/<i>` and `std/<i>` (theta's parameter leaves in leaf order),
  `static/<j>` (theta's integer and boolean arrays), `x0`,
  `x0_std`, `x0_covariance`, `x0_estimated`, `loss`, `residuals`, `fixed`, `covariance`,
  `history/loss`, `history/grad_norm`, `history/step`, `history/stage` (and
  `history/validation` for a fit with validation data, `window_starts` for one with
  windows, `weight` for one with `weight=`, `x0_bounds/lower` and `x0_bounds/upper` for
  one with `x0_bounds=`),
  `history/theta/<i>`, `metrics/<name>`, and for multistart fits `starts/theta/<i>`,
  `starts/loss`, `starts/x0` and, with validation data, `starts/validation_loss`.

Values round-trip exactly (same dtypes and bits). Functions cannot be saved: a theta that
holds equinox modules (a neural residual) is saved by its arrays, and `load_result`
needs `like=` (a theta of the same structure, e.g. theta0) to rebuild it, and refuses a
`like` whose activation function or module sizes differ from the saved ones; the model is
never saved (pass `model=` to `load_result` to simulate). A file that is damaged (cut
short, edited, or another program's archive) is refused with one ValueError naming it.
"""

import contextlib
import dataclasses
import functools
import hashlib
import json
import os
import tempfile
import zipfile
import zlib
from itertools import zip_longest
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

from . import _pytree
from ._checks import _step_input_struct, check_path
from ._model import Model
from ._results import from_name, name_of

FORMAT = "oneshot_jax.FitResult"
VERSION = 1


def _encode_tree(tree):
    """theta's structure as JSON and its integer and boolean arrays (saved beside the
    parameters), or (None, []) when it holds other node types (functions, modules)."""
    counter = iter(range(10**9))
    statics = []

    def enc(node):
        if node is None:
            return {"none": None}
        if isinstance(node, dict):
            # JAX flattens a dict in sorted key order (the order of the saved leaves);
            # another mapping (an OrderedDict keeps its own order) is saved with `like=`.
            if type(node) is not dict or not all(isinstance(k, str) for k in node):
                raise TypeError
            return {"dict": {k: enc(node[k]) for k in sorted(node)}}
        if isinstance(node, list):
            return {"list": [enc(v) for v in node]}
        if type(node) is tuple:
            return {"tuple": [enc(v) for v in node]}
        if _pytree.is_parameter(node):
            return {"leaf": next(counter)}
        if isinstance(node, bool):
            return {"const": node}
        if isinstance(node, (np.ndarray, np.generic, jax.Array)) and (
            np.issubdtype(node.dtype, np.integer) or node.dtype == np.bool_
        ):
            statics.append(np.asarray(node))
            spec = {"static": len(statics) - 1}
            return {**spec, "scalar": True} if isinstance(node, np.generic) else spec
        raise TypeError

    try:
        return enc(tree), statics
    except TypeError:
        return None, []


def _decode_tree(spec, leaves, statics=None):
    """The pytree of `spec` with `leaves` at its parameters, and the saved `statics` (or
    None, for trees shaped like the parameters only: std, history) elsewhere."""
    if "none" in spec:
        return None
    if "dict" in spec:
        return {k: _decode_tree(v, leaves, statics) for k, v in spec["dict"].items()}
    if "list" in spec:
        return [_decode_tree(v, leaves, statics) for v in spec["list"]]
    if "tuple" in spec:
        return tuple(_decode_tree(v, leaves, statics) for v in spec["tuple"])
    if "const" in spec:
        return None if statics is None else spec["const"]
    if "static" in spec:
        if statics is None:
            return None
        a = statics[spec["static"]]
        return a[()] if spec.get("scalar") else a
    return leaves[spec["leaf"]]


def _plain(value):
    """`value` as JSON data: NumPy and JAX numbers as Python ones (ints stay ints), arrays
    as nested lists, dicts and sequences item by item."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, (np.ndarray, np.generic, jax.Array)):
        return np.asarray(value).tolist()
    return value


def _describe(obj) -> str:
    """A non-parameter part of theta (an activation function, a size, a flag) in words that
    do not change between processes or JAX versions: a function by its name (a
    `functools.partial` with its arguments; a function's body is not compared), a number
    or a string by its value, an integer or boolean array by its values (a digest above 16
    entries), anything else by its type."""
    if isinstance(obj, functools.partial):
        args = [_describe(a) for a in obj.args]
        args += [f"{k}={_describe(v)}" for k, v in sorted(obj.keywords.items())]
        return f"partial({_describe(obj.func)}, {', '.join(args)})"
    fn = getattr(obj, "fun", None) or getattr(obj, "__wrapped__", None) or obj  # custom_jvp, jit
    if callable(fn) and hasattr(fn, "__qualname__") and not isinstance(fn, type):
        return f"function {getattr(fn, '__name__', fn.__qualname__)}"
    if obj is None or isinstance(obj, (bool, int, float, complex, str)):
        return repr(obj)
    if isinstance(obj, (tuple, list)):
        return f"({', '.join(map(_describe, obj))})"
    if isinstance(obj, np.ndarray) or hasattr(obj, "dtype"):
        a = np.asarray(obj)
        if a.size <= 16:  # an exponent, an index, a mask: by its values
            return f"array{a.shape} {a.dtype} {a.ravel().tolist()}"
        digest = hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()[:12]
        return f"array{a.shape} {a.dtype} sha256 {digest}"
    return type(obj).__qualname__


def _static_signature(theta, root="theta") -> list:
    """What `load_result(like=)` compares beyond the parameters' shapes and names, none of
    which the file holds: the static fields of theta's equinox modules (sizes, flags,
    scales) and its non-parameter leaves (e.g. an activation function), each in words."""
    out = []

    def walk(node, where):
        if isinstance(node, eqx.Module):
            for f in dataclasses.fields(node):
                value = getattr(node, f.name, None)
                name = f"{where}.{f.name}"
                if f.metadata.get("static", False):
                    out.append(f"{name} = {_describe(value)}")
                else:
                    walk(value, name)
        elif isinstance(node, dict):
            for k in sorted(node, key=str):
                walk(node[k], f"{where}[{k!r}]")
        elif isinstance(node, (list, tuple)):
            for i, v in enumerate(node):
                walk(v, f"{where}[{i}]")
        elif node is not None and not _pytree.is_parameter(node):
            out.append(f"{where} = {_describe(node)}")

    walk(theta, root)
    return out


def _digest(arrays, meta) -> str:
    """SHA-256 of a file's arrays (name, dtype, shape, bytes) and its metadata without the
    digest: what `read_result` compares to refuse a file edited after saving."""
    h = hashlib.sha256(
        json.dumps({k: v for k, v in meta.items() if k != "digest"}, sort_keys=True).encode()
    )
    for key in sorted(k for k in arrays if k != "__meta__"):
        a = np.ascontiguousarray(arrays[key])
        h.update(f"{key}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _leaves(tree):
    return [np.asarray(a) for a in jax.tree_util.tree_leaves(tree)]


def save_result(result, path):
    """Save a `FitResult` to one `.npz` file (NumPy arrays and a JSON header, no pickle),
    the same as `result.save(path)`; `load_result` reads it back.

    **Arguments:**

    - `result`: the `FitResult`.
    - `path`: the file; the suffix `.npz` is added when missing.

    **Returns:**

    The path written.
    """
    if not all(hasattr(result, a) for a in ("theta", "std", "history", "stop_reason")):
        hint = ""
        if all(hasattr(getattr(result, "result", None), a) for a in ("theta", "std", "history")):
            name = type(result).__name__
            article = "An" if name[:1].upper() in "AEIOU" else "A"
            hint = (
                f" {article} {name} is not saved whole: save its `.result` (a "
                "`FitResult`; the other fields, such as stages or rounds, are not kept)"
            )
            if hasattr(result, "rounds"):  # (`fit_orthogonal`: an augmented model's fit)
                hint = (
                    f" {article} {name} is not saved whole, and its `.result` is the last "
                    "round's fit of the augmented model (its x0, inputs and outputs are "
                    "not your model's; it loads with that model only): keep `.theta` and "
                    "`.x0`, the estimates for your model (e.g. `eqx.tree_serialise_leaves` "
                    "for theta)"
                )
        raise TypeError(
            f"`result` must be a `FitResult` (what `fit` returns), got "
            f"{type(result).__name__}.{hint}"
        )
    path = _as_path(path)
    if path.is_dir():  # (before the suffix: "results/" is no file beside the folder)
        raise ValueError(
            f"`path`: {str(path)!r} is a folder; give the file to write, e.g. "
            f"{str(path / 'fit.npz')!r}."
        )
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    if path.is_dir():
        raise ValueError(f"`path`: {str(path)!r} is a folder; give the file to write.")
    if path.parent.exists() and not path.parent.is_dir():
        raise ValueError(f"`path`: {str(path.parent)!r} is a file, not a folder.")
    if not path.parent.is_dir():
        raise ValueError(
            f"`path`: the folder {str(path.parent)!r} does not exist; create it first "
            "(pathlib.Path(folder).mkdir(parents=True))."
        )
    params, _ = _pytree.split(result.theta)
    theta_tree, statics = _encode_tree(result.theta)
    arrays = {}
    for i, a in enumerate(_leaves(params)):
        arrays[f"theta/{i}"] = a
    for j, a in enumerate(statics):
        arrays[f"static/{j}"] = a
    for i, a in enumerate(_leaves(result.std)):
        arrays[f"std/{i}"] = a
    for i, a in enumerate(_leaves(result.history.theta)):
        arrays[f"history/theta/{i}"] = a
    for key in ("loss", "grad_norm", "step", "stage"):
        arrays[f"history/{key}"] = np.asarray(getattr(result.history, key))
    if result.window_starts is not None:
        arrays["window_starts"] = np.asarray(result.window_starts)
    if getattr(result, "weight", None) is not None:
        arrays["weight"] = np.asarray(result.weight)
    if getattr(result, "x0_bounds", None) is not None:
        arrays["x0_bounds/lower"], arrays["x0_bounds/upper"] = map(np.asarray, result.x0_bounds)
    if result.history.validation is not None:
        arrays["history/validation"] = np.asarray(result.history.validation)
    for key in ("x0", "x0_std", "x0_covariance", "x0_estimated", "loss", "residuals"):
        arrays[key] = np.asarray(getattr(result, key))
    arrays["fixed"] = np.asarray(result.fixed)
    arrays["covariance"] = np.asarray(result.covariance)
    for key, value in result.metrics.items():
        arrays[f"metrics/{key}"] = np.asarray(value)
    if result.starts is not None:
        for i, a in enumerate(_leaves(result.starts.theta)):
            arrays[f"starts/theta/{i}"] = a
        arrays["starts/loss"] = np.asarray(result.starts.loss)
        if result.starts.x0 is not None:
            arrays["starts/x0"] = np.asarray(result.starts.x0)
        if result.starts.validation_loss is not None:
            arrays["starts/validation_loss"] = np.asarray(result.starts.validation_loss)
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "theta_tree": theta_tree,
        "names": list(result.names),
        "stop_reason": name_of(result.stop_reason),
        "num_steps": int(result.num_steps),
        "wall_time": float(result.wall_time),
        "best": int(result.best),
        "solver": [dict(s) for s in result.solver],
        "metrics": {
            k: ("float" if isinstance(v, float) else "array") for k, v in result.metrics.items()
        },
        "starts_stop_reason": None if result.starts is None else list(result.starts.stop_reason),
        "starts_solver_stop": None if result.starts is None else list(result.starts.solver_stop),
        "diagnostics": _plain(result.diagnostics),
        "stop_info": _plain(result.stop_info),
        "theta_order": list(result.theta_order),
        "units": dict(result.units),
        "validation_loss": result.validation_loss,
        "warnings": list(result.warnings),
        "static_signature": _static_signature(result.theta),
        "n_u": result.n_u,
        "missing": result.missing,
        # (a result loaded without a model keeps the record of the file it came from)
        "model_signature": (
            _model_signature(result.model)
            if result.model is not None
            else getattr(result, "saved_model_signature", None)
        ),
    }
    meta["digest"] = _digest(arrays, meta)
    arrays["__meta__"] = np.array(json.dumps(meta))
    with replaced(path) as fh:
        np.savez(fh, **arrays)
    return path


@contextlib.contextmanager
def replaced(path, mode="wb"):
    """A file opened for writing (`mode`) that replaces the file at `path` once written
    and closed: a temporary file in the same folder, renamed onto `path` (`os.replace`,
    atomic). A reader sees the old file or the new one, never a partial one; a write that
    fails (a full disk, an interrupt) leaves the old file as it was and nothing beside it.
    The new file gets the mode a file created by `open` would have."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, mode) as fh:
            yield fh
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # (mkstemp creates it 0600)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _as_path(path) -> Path:
    check_path(path, what="the result's file", optional=False)
    return Path(path)


def _damaged(path, what):
    return ValueError(f"`path`: {path} is damaged or was not written by FitResult.save: {what}.")


_META_KEYS = (
    "theta_tree",
    "names",
    "stop_reason",
    "num_steps",
    "wall_time",
    "best",
    "solver",
    "metrics",
    "starts_stop_reason",
)


def _read_arrays(path):
    """Every array of the `.npz` file, never unpickling (a saved result holds none). The
    file is opened here, so that it is closed whatever NumPy makes of it (`np.load` of a
    path leaves it open when the archive is damaged)."""
    try:
        fh = open(path, "rb")  # (closed below, whatever is raised)
    except OSError as err:
        raise _damaged(path, f"not a readable .npz archive ({type(err).__name__}: {err})") from err
    with fh:
        return _read_open(path, fh)


def _read_open(path, fh):
    try:
        npz = np.load(fh, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
        if "pickle" in str(err):  # NumPy's advice (load it unsafely) is not ours to give
            raise _damaged(path, "not an .npz archive of arrays") from None
        raise _damaged(path, f"not a readable .npz archive ({type(err).__name__}: {err})") from err
    if not isinstance(npz, np.lib.npyio.NpzFile):
        raise _damaged(path, "a single NumPy array, not an .npz archive")
    arrays = {}
    with npz:
        for key in npz.files:
            try:
                arrays[key] = npz[key]
            except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as err:
                if "pickle" in str(err):
                    raise _damaged(
                        path, f"its entry {key!r} holds Python objects, not numbers"
                    ) from None
                raise _damaged(
                    path, f"its entry {key!r} cannot be read ({type(err).__name__}: {err})"
                ) from err
    return arrays


def read_result(path, *, like=None, model=None) -> dict:
    """The fields of the `FitResult` saved at `path` (`load_result` builds it), with
    `history` and `starts` as dicts of the fields of a `FitHistory` and a `Starts` (or
    None), and without the model. `like` and `model` as for `load_result` (the model is
    checked against the file's record of it, `check_model`, not returned)."""
    path = _as_path(path)
    if not path.is_file() and Path(f"{path}.npz").is_file():  # as `save` names it
        path = Path(f"{path}.npz")
    if path.is_dir():
        raise ValueError(f"`path`: {str(path)!r} is a folder, not a saved result's file.")
    if not path.is_file():
        raise FileNotFoundError(f"`path`: no saved result at {path}.")
    arrays = _read_arrays(path)
    if "__meta__" not in arrays:
        raise ValueError(f"`path`: {path} is not a saved oneshot_jax FitResult (no __meta__).")
    try:
        meta = json.loads(str(arrays["__meta__"]))
    except ValueError as err:
        raise _damaged(path, f"its __meta__ is not valid JSON ({err})") from err
    if not isinstance(meta, dict):
        raise _damaged(path, "its __meta__ is not a JSON object")
    if meta.get("format") != FORMAT:
        raise ValueError(f"`path`: {path} holds {meta.get('format')!r}, not a {FORMAT}.")
    if meta.get("version") != VERSION:
        raise ValueError(
            f"`path`: {path} has format version {meta.get('version')}; this oneshot_jax "
            f"reads version {VERSION}."
        )
    if "digest" in meta and meta["digest"] != _digest(arrays, meta):  # (older files: none)
        raise _damaged(path, "its contents differ from those it was saved with (edited)")
    missing = [k for k in _META_KEYS if k not in meta]
    if missing:
        raise _damaged(path, f"its __meta__ lacks {', '.join(missing)}")
    check_model(meta, model)

    def group(prefix):
        n = sum(1 for k in arrays if k.startswith(prefix) and k[len(prefix) :].isdigit())
        return [arrays[f"{prefix}{i}"] for i in range(n)]

    static = None
    if like is not None:
        like_params, static = _pytree.split(like)
        treedef = jax.tree_util.tree_structure(like_params)

        n_saved = sum(1 for k in arrays if k.startswith("theta/") and k[6:].isdigit())
        if n_saved != treedef.num_leaves:
            raise ValueError(
                f"`like` has {treedef.num_leaves} parameter leaves, the saved theta {n_saved}: "
                "pass a theta of the fitted structure (e.g. theta0)."
            )
        # The same leaves: each of the saved shape, and the free entries of the same names
        # (a `like` with other keys or sizes would rename the parameters or refit none).
        for i, leaf in enumerate(jax.tree_util.tree_leaves(like_params)):
            saved = np.shape(arrays[f"theta/{i}"])
            if np.shape(leaf) != saved:
                raise ValueError(
                    f"`like`: its parameter leaf {i} has shape {np.shape(leaf)}, the saved "
                    f"theta's {saved}: pass a theta of the fitted structure (e.g. theta0)."
                )
        if "fixed" in arrays:
            all_names = _pytree.leaf_names(like_params)
            free = [n for n, f in zip(all_names, np.asarray(arrays["fixed"], bool)) if not f]
            if len(all_names) == np.size(arrays["fixed"]) and free != list(meta["names"]):
                diff = next((a, b) for a, b in zip_longest(free, meta["names"]) if a != b)
                raise ValueError(
                    f"`like` names the parameters differently from the saved theta (first "
                    f"difference: {diff[0]!r} in `like`, {diff[1]!r} saved): pass a theta of "
                    "the fitted structure (e.g. theta0)."
                )

        # What the file does not hold (files of earlier versions have no signature).
        saved_sig, like_sig = meta.get("static_signature"), _static_signature(like)
        if saved_sig is not None and saved_sig != like_sig:
            diff = next((a, b) for a, b in zip_longest(like_sig, saved_sig) if a != b)
            raise ValueError(
                f"`like` differs from the saved theta outside its parameters (an activation "
                f"function, a module's static fields, an integer array): `like` has {diff[0]}, "
                f"the file has {diff[1]}. Pass a theta of the fitted structure (e.g. "
                f"theta0)."
            )

        def build(leaves, whole=False):
            return jax.tree_util.tree_unflatten(treedef, leaves)
    elif meta["theta_tree"] is not None:

        def build(leaves, whole=False):
            return _decode_tree(meta["theta_tree"], leaves, group("static/") if whole else None)

    else:
        raise ValueError(
            "the saved theta's structure is not plain dicts/lists/tuples (it holds other "
            "pytree nodes, e.g. equinox modules): pass `like=` a theta of that structure."
        )

    try:
        _check_shapes(arrays, meta, group)
        return _fields(arrays, meta, group, build, static)
    except KeyError as err:
        raise _damaged(path, f"it lacks the entry {err.args[0]!r}") from err
    except (IndexError, TypeError, ValueError, AttributeError) as err:
        raise _damaged(
            path, f"its entries do not fit together ({type(err).__name__}: {err})"
        ) from err


def _check_shapes(arrays, meta, group):
    """Raise a ValueError where the file's arrays do not fit together as `save` writes
    them: a file without its `digest` (of an earlier version, or edited with the digest
    removed) is not otherwise checked, and a wrong shape would surface later, far from
    the file (in `print(result)`, `predict` or a plot)."""
    theta, std = group("theta/"), group("std/")
    for i, a in enumerate(theta):
        if a.dtype.kind not in "biuf":
            raise ValueError(f"theta leaf {i} holds {a.dtype} values, not numbers")
    if [a.shape for a in std] != [a.shape for a in theta]:
        raise ValueError(
            f"std's leaves have shapes {[a.shape for a in std]}, theta's {[a.shape for a in theta]}"
        )
    p = len(meta["names"])
    entries = sum(int(a.size) for a in theta)
    fixed = np.asarray(arrays["fixed"])
    if fixed.shape != (entries,) or entries - int(np.count_nonzero(fixed)) != p:
        raise ValueError(
            f"fixed has shape {fixed.shape} and frees {fixed.size - np.count_nonzero(fixed)} "
            f"entries: ({entries},), one flag per entry of theta, freeing the {p} named ones, "
            "expected"
        )
    if arrays["covariance"].shape not in ((p, p), (0, 0)):  # ((0, 0): not computed)
        raise ValueError(f"covariance has shape {arrays['covariance'].shape}, not ({p}, {p})")
    x0, x0_cov = arrays["x0"], arrays["x0_covariance"]
    if x0.ndim not in (1, 2) or arrays["x0_std"].shape != x0.shape:
        raise ValueError(f"x0 has shape {x0.shape}, x0_std {arrays['x0_std'].shape}")
    if arrays["x0_estimated"].shape not in (x0.shape[-1:], x0.shape if x0.ndim == 2 else ()):
        raise ValueError(f"x0 has shape {x0.shape}, x0_estimated {arrays['x0_estimated'].shape}")
    # (over the estimated entries of x0, or (0, 0): not computed)
    if x0_cov.ndim < 2 or x0_cov.shape[-1] != x0_cov.shape[-2] or x0_cov.shape[-1] > x0.shape[-1]:
        raise ValueError(f"x0_covariance has shape {x0_cov.shape}, x0 {x0.shape}")
    if np.ndim(arrays["loss"]) != 0 or np.ndim(arrays["residuals"]) < 2:
        raise ValueError(
            f"loss has shape {np.shape(arrays['loss'])} and residuals "
            f"{np.shape(arrays['residuals'])}: a scalar and (..., T, n_z) expected"
        )
    n = np.shape(arrays["history/loss"])
    for key in ("grad_norm", "step", "stage"):
        if np.shape(arrays[f"history/{key}"]) != n:
            raise ValueError(
                f"history's {key} has shape {np.shape(arrays[f'history/{key}'])}, its loss {n}"
            )
    for i, (h, a) in enumerate(zip(group("history/theta/"), theta, strict=True)):
        if h.shape != (*n, *a.shape):
            raise ValueError(
                f"history's theta leaf {i} has shape {h.shape}, not {(*n, *a.shape)} (its "
                f"{n[0] if n else 0} rows of theta leaf {i})"
            )


def _fields(arrays, meta, group, build, static) -> dict:
    """The fields of the `FitResult` of a file's arrays and metadata."""
    params = build(group("theta/"), whole=True)
    history = dict(
        loss=arrays["history/loss"],
        grad_norm=arrays["history/grad_norm"],
        theta=build(group("history/theta/")),
        step=arrays["history/step"],
        stage=arrays["history/stage"],
        validation=arrays["history/validation"] if "history/validation" in arrays else None,
    )
    metrics = {
        k: (float(arrays[f"metrics/{k}"]) if kind == "float" else arrays[f"metrics/{k}"])
        for k, kind in meta["metrics"].items()
    }
    starts = None
    if meta["starts_stop_reason"] is not None:
        starts = dict(
            theta=build(group("starts/theta/")),
            loss=arrays["starts/loss"],
            x0=arrays.get("starts/x0"),  # (None in a file saved before it was kept)
            validation_loss=arrays.get("starts/validation_loss"),
            stop_reason=tuple(meta["starts_stop_reason"]),
            # (a file written before `starts_solver_stop` existed: the stops as they were)
            solver_stop=tuple(meta.get("starts_solver_stop") or meta["starts_stop_reason"]),
        )
    order = tuple(meta.get("theta_order") or ())  # (dicts as written: JAX sorts them)
    return dict(
        theta=_pytree.ordered_by_names(_pytree.combine(params, static), order),
        x0=arrays["x0"],
        loss=arrays["loss"],
        stop_reason=from_name(meta["stop_reason"]),
        num_steps=int(meta["num_steps"]),
        wall_time=float(meta["wall_time"]),
        history=history,
        residuals=arrays["residuals"],
        names=tuple(meta["names"]),
        fixed=arrays["fixed"],
        covariance=arrays["covariance"],
        std=_pytree.ordered_by_names(build(group("std/")), order),
        x0_covariance=arrays["x0_covariance"],
        x0_std=arrays["x0_std"],
        x0_estimated=arrays["x0_estimated"],
        metrics=metrics,
        starts=starts,
        best=int(meta["best"]),
        solver=tuple(meta["solver"]),
        diagnostics=dict(meta.get("diagnostics") or {}),
        stop_info=dict(meta.get("stop_info") or {}),
        theta_order=order,
        units=dict(meta.get("units") or {}),
        validation_loss=meta.get("validation_loss"),
        warnings=tuple(meta.get("warnings") or ()),  # (older files: none)
        window_starts=arrays["window_starts"] if "window_starts" in arrays else None,
        n_u=meta.get("n_u"),
        missing=meta.get("missing") or "raise",  # (older files: none)
        weight=arrays.get("weight"),
        x0_bounds=(arrays["x0_bounds/lower"], arrays["x0_bounds/upper"])
        if "x0_bounds/lower" in arrays
        else None,
        saved_model_signature=(
            None if meta.get("model_signature") is None else tuple(meta["model_signature"])
        ),
    )


# The model's labels (`Model(states=..., outputs=...)`): not what it computes, so a result
# loads with the same dynamics named otherwise or not at all (and files saved before the
# labels existed load).
_LABELS = ("model.states = ", "model.outputs = ")


def _model_signature(model) -> list:
    """What the file records of the model: its static settings (a `Model.from_ode`'s dt,
    method, substeps, input; whether it is timed), not its functions, whose names a
    script that loads the result may choose differently, nor its labels (`_LABELS`)."""
    return [
        s
        for s in _static_signature(model, "model")
        if " = function " not in s and not s.startswith(_LABELS)
    ]


def check_model_fits(model, fields):
    """Refuse a `model` for `load_result` whose functions do not fit the loaded result:
    traced once on abstract values (`eqx.filter_eval_shape`) with the saved theta, its step must
    keep the state of the saved x0 and its observation give as many outputs as the saved
    residuals have (a model of another structure loaded without complaint, and its
    `simulate` and `predict` then answered for another system)."""
    if model is None or fields.get("n_u") is None:
        return
    x0, res = np.asarray(fields["x0"]), np.asarray(fields["residuals"])
    x = jax.ShapeDtypeStruct(x0.shape[-1:], x0.dtype)
    n_u = int(fields["n_u"]) + (1 if model.timed else 0)  # (a timed model sees the interval)
    u = jax.ShapeDtypeStruct((n_u,), x0.dtype)
    u_step = _step_input_struct(model, u)
    theta = fields["theta"]
    try:
        # (equinox's: theta's non-array leaves, a network's activation, stay static)
        x_next = eqx.filter_eval_shape(model.step, x, u_step, theta)
        z = eqx.filter_eval_shape(model.observe, x, u, theta)
    except Exception as err:  # (any error of the user's functions, named below)
        raise ValueError(
            f"`model` does not run with the saved result's theta, {x.shape[0]} states and "
            f"{fields['n_u']} inputs: {type(err).__name__}: {str(err).rstrip('.')}. Pass "
            "the fitted model."
        ) from err
    if getattr(x_next, "shape", None) != x.shape:
        raise ValueError(
            f"`model` does not fit the saved result: its step returns a state of shape "
            f"{getattr(x_next, 'shape', type(x_next).__name__)}, the saved x0 has "
            f"{x.shape}. Pass the fitted model."
        )
    n_z = res.shape[-1] if res.ndim else None
    if n_z is not None and getattr(z, "shape", None) != (n_z,):
        raise ValueError(
            f"`model` does not fit the saved result: it gives outputs of shape "
            f"{getattr(z, 'shape', type(z).__name__)}, the saved residuals have {n_z} "
            f"output(s). Pass the fitted model."
        )


def check_model(meta, model):
    """Refuse a `model` for `load_result` that differs from the saved result's in what the
    file's `meta` records of it (`_model_signature`); files without that record (earlier
    versions) pass."""
    if model is not None and not isinstance(model, Model):
        raise TypeError(
            f"`model` must be a oneshot_jax.Model (or None), got {type(model).__name__}."
        )
    if model is None:
        return
    saved = meta.get("model_signature")
    if saved is None:
        return
    given = _model_signature(model)
    if saved != given:
        # Entry by entry, by name ("model.step.dt = 0.05"): a model of another kind lacks
        # some of the saved entries, so a pairing by position would compare unrelated ones.
        def named(sig):
            return dict(e.split(" = ", 1) if " = " in e else (e, "") for e in sig)

        mine, theirs = named(given), named(saved)
        # An entry both have with different values says most ("model.timed"), then
        # one that only one of them has.
        both = [k for k in theirs if k in mine and mine[k] != theirs[k]]
        one = [k for k in [*theirs, *mine] if (k in mine) != (k in theirs)]
        key = (both + one or [None])[0]
        if key is None:
            diff = next((a, b) for a, b in zip_longest(given, saved) if a != b)
            what = f"`model` has {diff[0]}, the file {diff[1]}"
        else:

            def shown(sig):
                return f"{key} = {sig[key]}" if key in sig else f"no {key}"

            what = f"`model` has {shown(mine)}, the file has {shown(theirs)}"
        raise ValueError(
            f"`model` differs from the model the result was fitted with: {what}. Pass the "
            "fitted model (its dt, method, substeps, input)."
        )
