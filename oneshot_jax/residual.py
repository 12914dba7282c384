r"""Learned residual terms for hybrid (physics plus black-box) models.

A hybrid model adds a learned term r(x, u) to the physical right-hand side, e.g.

    dx/dt = f_phys(x, u, theta_phys) + B r(x, u),

and fits theta_phys and the residual's parameters together on the multi-step cost of
eq. (5) (Donati et al., "Combining off-white and sparse black models in multi-step
physics-based systems identification", arXiv 2405.18186). Put the residual inside theta
next to the physical parameters: `theta = {"k": 1.0, "c": 0.1, "r": MLP(...)}`, and call
it from the model: `theta["r"](jnp.concatenate([x, u]))` or `theta["r"](x, u)`.

Two residuals, both equinox modules whose floating arrays are the trained parameters and
whose other fields (sizes, names, functions, scales) are static:

- `MLP`: a multilayer perceptron, initialised to output exactly zero, so that the hybrid
    starts as the physical model.
- `Dictionary`: a linear combination Theta(x, u) @ W of named candidate terms
    (`Features`: monomials in states and inputs up to a degree, plus user functions), to
    be made sparse with the proximal steps of `oneshot_jax.sparsity`; `equations()` prints
    the learned terms as an equation.
"""

import itertools
import math
import numbers
from collections.abc import Callable, Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._counts import real
from ._pytree import is_parameter

__all__ = ["MLP", "Features", "Dictionary", "count_parameters"]


def count_parameters(tree) -> int:
    """The number of trained scalars in `tree`: the total size of its parameter leaves
    (floating arrays and Python numbers, as `fit` takes them).

    These are the entries that a fit updates (and that an L1 or group-lasso penalty may
    select); static fields of equinox modules (sizes, activations, names) and integer
    arrays do not count.
    """
    return int(sum(np.size(a) for a in jax.tree_util.tree_leaves(tree) if is_parameter(a)))


def _positive_int(value, name, minimum=1):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"`{name}` must be an integer >= {minimum}, got {value!r}.")
    return int(value)


def _float_dtype(dtype):
    """`dtype` of a residual's parameters: None (JAX's default floating dtype) or floating."""
    if dtype is None:
        return jnp.result_type(float)
    try:
        floating = jnp.issubdtype(dtype, jnp.floating)
    except TypeError:
        floating = False
    if not floating:
        raise ValueError(
            f"`dtype` must be a floating dtype (jnp.float32, jnp.float64), got {dtype!r}."
        )
    return dtype


def _split_key(key, n):
    """`n` keys from `key`, or a TypeError that says what a key is."""
    try:
        return jax.random.split(key, n)
    except (TypeError, ValueError) as err:
        got = repr(key)
        if hasattr(key, "shape") and hasattr(key, "dtype"):
            got = f"an array of shape {key.shape} and dtype {key.dtype}"
        raise TypeError(
            "`key` must be a JAX PRNG key, jax.random.key(0) or jax.random.PRNGKey(0) (one "
            f"key, not a batch), got {got}."
        ) from err


def _real_scalar(value, name):
    """`value` as a Python float: a finite real number, given as a Python or NumPy scalar
    or a concrete 0-d array (a static constant of the module, not a trained parameter)."""
    if np.ndim(value):
        raise ValueError(
            f"`{name}` must be one finite number (a static constant, not trained), got an "
            f"array of shape {np.shape(value)}."
        )
    v = real(value)
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real):
        raise ValueError(f"`{name}` must be a finite real number, got {value!r}.")
    if not math.isfinite(v):
        raise ValueError(f"`{name}` must be finite, got {float(v)!r}.")
    return float(v)


def _float_tuple(value, size, name, positive=False):
    """An optional per-entry constant as a tuple of Python floats (static, hashable)."""
    if value is None:
        return None
    try:
        arr = np.broadcast_to(np.asarray(value, dtype=np.float64), (size,))
    except (TypeError, ValueError) as err:
        raise ValueError(
            f"`{name}` must be a scalar or have shape ({size},), got {np.shape(value)}."
        ) from err
    if not np.all(np.isfinite(arr)) or (positive and np.any(arr <= 0)):
        kind = "finite and > 0" if positive else "finite"
        raise ValueError(f"`{name}` must be {kind}, got {value!r}.")
    return tuple(float(a) for a in arr)


class MLP(eqx.Module):
    """A multilayer perceptron for a residual term, zero at initialisation.

    Maps a 1-D feature vector (typically the concatenated state and input,
    `jnp.concatenate([x, u])`, of size n_x + n_u) to `out_size` outputs:

        y = scale * (W_L s(... s(W_1 a + b_1) ...) + b_L),   a = (v - offset) / input_scale,

    with s the activation, `offset` = `input_offset` and, when `bound` is given, y
    replaced by bound * tanh(y / bound) (slope 1 at zero, |y| <= bound). With
    `zero_last=True` the last layer's weight and bias start at zero, so y = 0 exactly and
    a hybrid model starts as its physical part; the first gradient step moves the last
    layer, and the hidden layers follow from the next step on (their gradient is
    proportional to W_L).

    **Arguments:**

    - `in_size`: the length of the feature vector.
    - `out_size`: the number of outputs.
    - `widths`: the hidden layers' widths, e.g. `(32, 32)`; `()` is an affine map.
    - `activation`: the hidden layers' nonlinearity (default `jax.nn.tanh`).
    - `key`: a `jax.random` key for the (LeCun-uniform, equinox's default) initialisation.
    - `scale`: a constant output factor > 0 (static, not trained), to put the output in
        the units of the term it corrects.
    - `bound`: None, or a bound > 0 on |y| (elementwise), applied by a tanh.
    - `zero_last`: True or False: start with the last layer at zero (the hybrid is the
        physical model).
        With False the output starts at the size set by `scale`.
    - `input_offset`, `input_scale`: constants (scalars or length-`in_size`) that centre
        and scale the features, e.g. the mean and standard deviation of the data.
    - `dtype`: the parameters' dtype (by default JAX's default floating dtype); match the
        model's state.
    """

    layers: tuple[eqx.nn.Linear, ...]
    activation: Callable
    in_size: int = eqx.field(static=True)
    out_size: int = eqx.field(static=True)
    scale: float = eqx.field(static=True)
    bound: float | None = eqx.field(static=True)
    input_offset: tuple[float, ...] | None = eqx.field(static=True)
    input_scale: tuple[float, ...] | None = eqx.field(static=True)

    def __init__(
        self,
        in_size: int,
        out_size: int,
        widths: Sequence[int] = (32, 32),
        activation: Callable = jax.nn.tanh,
        *,
        key,
        scale: float = 1.0,
        bound: float | None = None,
        zero_last: bool = True,
        input_offset=None,
        input_scale=None,
        dtype=None,
    ):
        in_size = _positive_int(in_size, "in_size")
        out_size = _positive_int(out_size, "out_size")
        try:
            widths = tuple(widths)
        except TypeError as err:
            raise ValueError(f"`widths` must be a sequence of integers, got {widths!r}.") from err
        widths = tuple(_positive_int(w, "widths") for w in widths)
        if not callable(activation):
            raise ValueError(f"`activation` must be callable, got {activation!r}.")
        scale = _real_scalar(scale, "scale")
        if scale <= 0:
            # (0 makes the residual identically zero with a zero gradient: it never learns)
            raise ValueError(
                f"`scale` must be > 0 (the output's size in the units of the term it "
                f"corrects), got {scale!r}."
            )
        if not isinstance(zero_last, (bool, np.bool_)):
            raise TypeError(f"`zero_last` must be True or False, got {zero_last!r}.")
        if bound is not None and not 0 < _real_scalar(bound, "bound") < math.inf:
            raise ValueError(f"`bound` must be None or a finite number > 0, got {bound!r}.")
        input_offset = _float_tuple(input_offset, in_size, "input_offset")
        input_scale = _float_tuple(input_scale, in_size, "input_scale", positive=True)
        dtype = _float_dtype(dtype)
        sizes = (in_size, *widths, out_size)
        keys = _split_key(key, len(sizes) - 1)
        layers = [
            eqx.nn.Linear(a, b, dtype=dtype, key=k) for a, b, k in zip(sizes[:-1], sizes[1:], keys)
        ]
        if zero_last:
            last = layers[-1]
            layers[-1] = eqx.tree_at(
                lambda layer: (layer.weight, layer.bias),
                last,
                (jnp.zeros_like(last.weight), jnp.zeros_like(last.bias)),
            )
        self.layers = tuple(layers)
        self.activation = activation
        self.in_size = in_size
        self.out_size = out_size
        self.scale = float(scale)
        self.bound = None if bound is None else float(bound)
        self.input_offset = input_offset
        self.input_scale = input_scale

    def __call__(self, features):
        """The residual at one feature vector of shape (in_size,); returns (out_size,)."""
        if np.shape(features) != (self.in_size,):
            raise ValueError(
                f"`features` must have shape ({self.in_size},) (this MLP's in_size), got "
                f"{np.shape(features)}."
            )
        h = jnp.asarray(features)
        if not jnp.issubdtype(h.dtype, jnp.inexact):  # (an integer offset would truncate)
            h = h.astype(self.layers[0].weight.dtype)
        if self.input_offset is not None:
            h = h - jnp.asarray(self.input_offset, jnp.result_type(h))
        if self.input_scale is not None:
            h = h / jnp.asarray(self.input_scale, jnp.result_type(h))
        for layer in self.layers[:-1]:
            h = self.activation(layer(h))
        y = self.scale * self.layers[-1](h)
        if self.bound is not None:
            y = self.bound * jnp.tanh(y / self.bound)
        return y


def _names(names, default_prefix, n, name):
    if names is None:
        return tuple(f"{default_prefix}{i}" for i in range(n))
    if isinstance(names, str):  # (a string is a sequence of its letters)
        raise TypeError(f"`{name}` must be a sequence of {n} strings, got the string {names!r}.")
    names = tuple(names)
    if len(names) != n or not all(isinstance(s, str) and s for s in names):
        raise ValueError(f"`{name}` must be {n} non-empty strings, got {names!r}.")
    return names


def _monomial_name(indices, var_names):
    parts = []
    for i, group in itertools.groupby(indices):
        power = len(list(group))
        parts.append(var_names[i] if power == 1 else f"{var_names[i]}^{power}")
    return "*".join(parts)


class Features(eqx.Module):
    """A library of named candidate terms Theta(x, u), the columns of a `Dictionary`.

    In order: the constant `1` (if `constant`), every monomial in the n_x + n_u variables
    (x then u) of degree 1 to `degree` (degree by degree, each in lexicographic order of
    the variables, e.g. `x0`, `x1`, `u0`, `x0^2`, `x0*x1`, ...), then the user
    `functions`; minus the names in `exclude`. There are C(n_x + n_u + degree, degree) - 1
    monomials. Terms that the physical model already has (the linear terms, say) are best
    excluded: a dictionary column equal to a physical term makes the two coefficients
    interchangeable.

    **Arguments:**

    - `n_x`, `n_u`: the numbers of states and inputs (n_u may be 0).
    - `degree`: the largest monomial degree (0 for no monomials).
    - `constant`: include the constant term `1`.
    - `functions`: extra terms: a mapping (or sequence of pairs) name -> `fn(x, u)`
        returning a scalar, e.g. `{"sin(x0)": lambda x, u: jnp.sin(x[0])}`.
    - `exclude`: names of terms to leave out.
    - `x_names`, `u_names`: variable names for the printed terms (default `x0, x1, ...`
        and `u0, ...`).

    Call it as `features(x, u)` on a state (n_x,) and an input (n_u,) to get the
    (n_features,) vector; `names` holds the terms' names.
    """

    n_x: int = eqx.field(static=True)
    n_u: int = eqx.field(static=True)
    names: tuple[str, ...] = eqx.field(static=True)
    products: tuple[tuple[int, ...], ...] = eqx.field(static=True)
    functions: tuple[Callable, ...] = eqx.field(static=True)

    def __init__(
        self,
        n_x: int,
        n_u: int = 0,
        degree: int = 1,
        *,
        constant: bool = False,
        functions: Mapping[str, Callable] | Sequence[tuple[str, Callable]] | None = None,
        exclude: Sequence[str] = (),
        x_names: Sequence[str] | None = None,
        u_names: Sequence[str] | None = None,
    ):
        n_x = _positive_int(n_x, "n_x")
        n_u = _positive_int(n_u, "n_u", minimum=0)
        degree = _positive_int(degree, "degree", minimum=0)
        var_names = _names(x_names, "x", n_x, "x_names") + _names(u_names, "u", n_u, "u_names")
        if len(set(var_names)) != len(var_names):
            raise ValueError(f"`x_names` and `u_names` must be distinct, got {var_names}.")
        n_var = n_x + n_u
        products = [()] if constant else []
        for d in range(1, degree + 1):
            products.extend(itertools.combinations_with_replacement(range(n_var), d))
        names = ["1" if not p else _monomial_name(p, var_names) for p in products]

        if functions is None:
            functions = []
        elif isinstance(functions, Mapping):
            functions = list(functions.items())
        else:
            try:
                functions = [tuple(f) for f in functions]
            except TypeError as err:
                raise ValueError(
                    "`functions` must map names to callables fn(x, u) -> scalar."
                ) from err
        x_s = jax.ShapeDtypeStruct((n_x,), jnp.result_type(float))
        u_s = jax.ShapeDtypeStruct((n_u,), jnp.result_type(float))
        for item in functions:
            if len(item) != 2 or not isinstance(item[0], str) or not callable(item[1]):
                raise ValueError(
                    f"`functions` must map names to callables fn(x, u) -> scalar, got {item!r}."
                )
            name, fn = item
            try:
                out = jax.eval_shape(fn, x_s, u_s)
            except Exception as err:  # noqa: BLE001 - re-raised naming the argument
                raise ValueError(
                    f"`functions` entry {name!r} failed on x of shape ({n_x},) and u of shape "
                    f"({n_u},): {type(err).__name__}: {err}"
                ) from err
            if getattr(out, "shape", None) != ():
                raise ValueError(
                    f"`functions` entry {name!r} must return a scalar, got "
                    f"{getattr(out, 'shape', out)}."
                )
        names += [name for name, _ in functions]
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if names.count(n) > 1})
            raise ValueError(
                f"`functions` names must differ from each other and from the "
                f"monomials; repeated: {dup}."
            )
        if isinstance(exclude, str):
            raise TypeError(
                f"`exclude` must be a sequence of term names, got the string {exclude!r} "
                f"(one term: exclude=({exclude!r},))."
            )
        exclude = tuple(exclude)
        unknown = sorted(set(exclude) - set(names))
        if unknown:
            raise ValueError(f"`exclude` names terms that are not in the library: {unknown}.")
        keep_p = [p for p, n in zip(products, names) if n not in exclude]
        keep_f = [(n, f) for n, f in functions if n not in exclude]
        self.n_x, self.n_u = n_x, n_u
        self.products = tuple(keep_p)
        self.functions = tuple(f for _, f in keep_f)
        self.names = tuple(n for n in names if n not in exclude)
        if not self.names:
            raise ValueError(
                "the library is empty: `exclude` removes every term"
                if exclude and names
                else "the library is empty: give a `degree` >= 1 or `functions`."
            )

    def __len__(self):
        return len(self.names)

    def __call__(self, x, u):
        """Theta(x, u): the (n_features,) vector of every term at one state and input."""
        if np.shape(x) != (self.n_x,):
            raise ValueError(f"`x` must have shape ({self.n_x},), got {np.shape(x)}.")
        if np.shape(u) != (self.n_u,):
            raise ValueError(f"`u` must have shape ({self.n_u},), got {np.shape(u)}.")
        x, u = jnp.asarray(x), jnp.asarray(u)
        v = jnp.concatenate([x, u]) if self.n_u else x
        if not jnp.issubdtype(v.dtype, jnp.inexact):  # (integer data: `functions` would truncate)
            v = v.astype(jnp.result_type(float))
            x, u = x.astype(v.dtype), u.astype(v.dtype)
        # `products` is ordered by degree (see __init__): one gather per degree.
        cols = []
        for d, group in itertools.groupby(self.products, key=len):
            group = list(group)
            if d == 0:
                cols.append(jnp.ones((len(group),), v.dtype))
                continue
            idx = np.asarray(group, dtype=np.int32)  # (n_d, d)
            # Repeated products, not powers: exact derivatives at zero.
            col = v[idx[:, 0]]
            for c in range(1, d):
                col = col * v[idx[:, c]]
            cols.append(col)
        mono = jnp.concatenate(cols) if cols else jnp.zeros((0,), v.dtype)
        extra = [jnp.asarray(fn(x, u), v.dtype) for fn in self.functions]
        return jnp.concatenate([mono, jnp.stack(extra)]) if extra else mono

    def rms(self, x, u):
        """The root-mean-square of every term over samples x (K, n_x), u (K, n_u).

        A natural `scale` for `Dictionary`. Leading axes (trajectories, time) are pooled.
        """
        x = jnp.asarray(x)
        u = jnp.asarray(u)
        if (
            x.shape[-1:] != (self.n_x,)
            or u.shape[-1:] != (self.n_u,)
            or x.shape[:-1] != u.shape[:-1]
        ):
            raise ValueError(
                f"`x` and `u` must have shapes (..., {self.n_x}) and (..., {self.n_u}) with the "
                f"same leading axes, got {x.shape} and {u.shape}."
            )
        n = math.prod(x.shape[:-1])  # (reshape(-1, 0) is ambiguous for n_u = 0)
        theta = jax.vmap(self)(x.reshape(n, self.n_x), u.reshape(n, self.n_u))
        return np.sqrt(np.mean(np.asarray(theta, np.float64) ** 2, axis=0))


def _format_equation(lhs, terms, precision):
    if not terms:
        return f"{lhs} = 0"
    out = f"{lhs} ="
    for i, (c, name) in enumerate(terms):
        mag = f"{abs(c):.{precision}g}"
        body = mag if name == "1" else f"{mag} {name}"
        sign = "-" if c < 0 else "+"
        out += f" {'-' if c < 0 else ''}{body}" if i == 0 else f" {sign} {body}"
    return out


class Dictionary(eqx.Module):
    """A sparse dictionary residual r(x, u) = (Theta(x, u) / scale) @ coef.

    Theta are the named candidate terms of `features`; `coef` (n_features, n_out) is the
    trained part, zero at the start (the hybrid starts as its physical model). With an L1
    or group-lasso proximal step on `coef` (`oneshot_jax.sparsity`) most entries become
    exactly zero, and `equations()` prints what remains.

    **Normalisation.** An L1 penalty lambda sum |w_j| treats every term alike only if the
    terms have comparable sizes: x^3 with x ~ 10 is a thousand times x. With `scale` (one
    positive number per term, e.g. `features.rms(x_data, u_data)`), the dictionary uses
    Theta_j / scale_j, so `coef[j]` is the contribution of term j in units of its typical
    size and the penalty weighs contributions, not raw coefficients. `coefficients` and
    `equations()` report the physical coefficients coef[j] / scale[j].

    **Arguments:**

    - `features`: a `Features` library.
    - `n_out`: the number of outputs (the equations this residual enters).
    - `out_names`: names of the outputs, for `equations()` (default `r0, r1, ...`).
    - `scale`: None (no normalisation) or positive per-term scales, shape (n_features,).
    - `coef`: the initial (normalised) coefficients, default zeros.
    - `dtype`: the dtype of `coef` (by default JAX's default floating dtype).
    """

    coef: jax.Array
    features: Features
    out_names: tuple[str, ...] = eqx.field(static=True)
    scale: tuple[float, ...] | None = eqx.field(static=True)

    def __init__(
        self, features: Features, n_out: int, *, out_names=None, scale=None, coef=None, dtype=None
    ):
        if not isinstance(features, Features):
            raise ValueError(
                f"`features` must be a oneshot_jax.residual.Features library, got {features!r}."
            )
        n_out = _positive_int(n_out, "n_out")
        n = len(features)
        shape = (n, n_out)
        dtype = _float_dtype(dtype)
        if coef is None:
            coef = jnp.zeros(shape, dtype)
        else:
            coef = jnp.asarray(coef, dtype)
            if coef.shape != shape:
                raise ValueError(
                    f"`coef` must have shape {shape} (n_features, n_out), got {coef.shape}."
                )
            if not bool(jnp.all(jnp.isfinite(coef))):
                raise ValueError("`coef` contains NaN or inf values.")
        self.coef = coef
        self.features = features
        self.out_names = _names(out_names, "r", n_out, "out_names")
        self.scale = _float_tuple(scale, n, "scale", positive=True)

    @property
    def names(self) -> tuple[str, ...]:
        """The terms' names, one per row of `coef`."""
        return self.features.names

    def __call__(self, x, u):
        """r(x, u) of shape (n_out,) at one state (n_x,) and input (n_u,)."""
        theta = self.features(x, u).astype(self.coef.dtype)
        if self.scale is not None:
            theta = theta / jnp.asarray(self.scale, theta.dtype)
        return theta @ self.coef

    @property
    def coefficients(self):
        """The physical coefficients coef / scale (n_features, n_out): r = Theta @ this."""
        if self.scale is None:
            return self.coef
        return self.coef / jnp.asarray(self.scale, self.coef.dtype)[:, None]

    def equations(self, precision: int = 4) -> str:
        """The learned terms as equations, one line per output, exact zeros left out.

        E.g. `dx1 = -0.98 x0^3 + 0.1 x1*u0`; an output with no non-zero term reads `= 0`.
        `precision`: the significant digits of each coefficient (an integer >= 0).
        """
        if isinstance(precision, bool) or not isinstance(precision, numbers.Integral):
            raise ValueError(f"`precision` must be an integer >= 0, got {precision!r}.")
        if precision < 0:
            raise ValueError(f"`precision` must be an integer >= 0, got {precision!r}.")
        c = np.asarray(self.coefficients)
        lines = []
        for k, lhs in enumerate(self.out_names):
            terms = [(float(c[j, k]), nm) for j, nm in enumerate(self.names) if c[j, k] != 0]
            lines.append(_format_equation(lhs, terms, precision))
        return "\n".join(lines)
