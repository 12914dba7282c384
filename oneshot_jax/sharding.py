r"""Fleets of trajectories sharded over devices: the trajectory axis split, theta replicated.

N trajectories that share theta (the paper's footnote 1: several experiments, or a fleet
of identical machines) are independent given theta until their contributions are summed:
the cost and grad_theta are means over the trajectory axis, and the Gauss-Newton normal
equations J^T J = sum_i J_i^T J_i are einsums over it. Placing x0 (N, n_x), u (N, T, n_u)
and z (N, T, n_z) with that axis split over a 1-D device mesh (`jax.sharding.NamedSharding`
with `PartitionSpec("trajectories")`) and theta replicated is then all it takes: the
library's functions, compiled by `jax.jit`, run each device's trajectories where they
are, and XLA's SPMD partitioner turns every mean or einsum over the trajectory axis into a
local reduction followed by one all-reduce across devices. Per-trajectory outputs
(grad_x0, residuals, Jacobian rows) stay sharded. Nothing in the library changes.

    from oneshot_jax import sharding

    mesh = sharding.fleet_mesh()              # all of jax.devices()
    x0, u, z = sharding.shard_fleet(x0, u, z, mesh=mesh)
    theta = sharding.replicate(theta, mesh)
    C, (g_theta, g_x0) = oneshot_jax.value_and_grad(model, theta, x0, u, z)
    result = oneshot_jax.fit(model, theta, x0, u, z)   # the data stay sharded in the fit

N must be a multiple of the number of devices: `shard_fleet` raises a `ValueError`
otherwise. Padding with dummy trajectories is not done, because the cost is the plain
mean over N (eq. 5 per trajectory, then the mean): a padded trajectory would change N and
add its own error; drop or duplicate trajectories yourself, or use fewer devices
(`fleet_mesh(devices[:k])`).

**Several hosts.** Start every process with `jax.distributed.initialize()` (coordinator
address, number of processes and process id as arguments, or from the cluster's
environment on Slurm, Open MPI and Cloud TPU) before any other JAX call; `jax.devices()`
then lists the devices of all hosts and `fleet_mesh()` spans them. Every process runs the
same program. `shard_fleet` places arrays that every process holds in full (the same
global N); for data loaded per host, build each array from the host's own trajectories
with `jax.make_array_from_process_local_data(fleet_sharding(mesh, ndim), local_array)`
(the local block of the trajectory axis, in process order). Scalars and the replicated
grad_theta come back on every host; sharded outputs are read per host through
`array.addressable_shards`.
"""

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

__all__ = ["AXIS", "fleet_mesh", "fleet_sharding", "shard_fleet", "replicate"]

AXIS = "trajectories"
"""The mesh axis name of the trajectory axis."""


def fleet_mesh(devices=None):
    """A 1-D `Mesh` over `devices` (default: all of `jax.devices()`), axis name `AXIS`.

    **Arguments:**

    - `devices`: a non-empty sequence of distinct `jax.Device`s (e.g. `jax.devices()[:k]`),
        one `jax.Device` (a mesh of one), or None.

    **Returns:**

    A `jax.sharding.Mesh` of shape (len(devices),).

    **Raises:**

    `TypeError` when `devices` is not a sequence of `jax.Device`s (a platform name such as
    "cpu", device ids); `ValueError` when it is empty or names a device twice.
    """
    if isinstance(devices, jax.Device):
        devices = [devices]  # one device: a mesh of one
    if devices is None:
        devices = jax.devices()
    elif isinstance(devices, (str, bytes)):
        # (a string is a sequence of its letters: "cpu" gave a mesh of characters)
        raise TypeError(
            f"`devices` must be a sequence of jax.Device objects (e.g. jax.devices('cpu')), "
            f"got the string {devices!r}."
        )
    else:
        try:
            devices = list(devices)
        except TypeError as err:
            raise TypeError(
                "`devices` must be a sequence of jax.Device objects (e.g. jax.devices()), or "
                f"None for all devices, got {type(devices).__name__} {devices!r}."
            ) from err
    if not devices:
        raise ValueError("`devices` must hold at least one device.")
    for i, d in enumerate(devices):
        if not isinstance(d, jax.Device):
            raise TypeError(
                f"`devices` must be a sequence of jax.Device objects (e.g. jax.devices()), got "
                f"{type(d).__name__} {d!r} at index {i}."
            )
    if len(set(devices)) != len(devices):
        twice = next(d for i, d in enumerate(devices) if d in devices[:i])
        raise ValueError(
            f"`devices` must be distinct devices: {twice} appears more than once (a mesh "
            "places one block of trajectories on each device)."
        )
    return Mesh(np.asarray(devices), (AXIS,))


def _check_mesh(mesh, fleet=True):
    """A TypeError unless `mesh` is a `Mesh` (with `fleet`: 1-D with axis name `AXIS`)."""
    if not isinstance(mesh, Mesh):
        raise TypeError(
            f"`mesh` must be a {'1-D ' if fleet else ''}jax.sharding.Mesh (as from "
            f"`fleet_mesh`), got {type(mesh).__name__}."
        )
    if fleet and mesh.axis_names != (AXIS,):
        raise ValueError(f"`mesh` must be 1-D with axis name {AXIS!r} (see `fleet_mesh`).")


def fleet_sharding(mesh, ndim):
    """`NamedSharding` splitting the leading (trajectory) axis of an `ndim`-D array."""
    _check_mesh(mesh)
    if isinstance(ndim, bool) or not isinstance(ndim, (int, np.integer)):
        raise TypeError(
            f"`ndim` must be an integer >= 1 (the array's number of axes, the first the "
            f"trajectories), got {ndim!r}."
        )
    if ndim < 1:
        raise ValueError(
            f"`ndim` must be an integer >= 1 (the array's number of axes, the first the "
            f"trajectories), got {ndim!r}."
        )
    return NamedSharding(mesh, PartitionSpec(AXIS, *([None] * (ndim - 1))))


def replicate(tree, mesh):
    """Every array leaf of `tree` (theta, a weight) placed whole on every device of `mesh`.

    Array leaves are arrays and numbers (of a numeric or boolean dtype); callable leaves
    (an equinox residual's activation function) are returned as they are. Any other leaf
    (a string, an object array) raises a `TypeError` naming its place in `tree`.
    """
    _check_mesh(mesh, fleet=False)  # (any mesh: a replicated array has no split axis)
    sharding = NamedSharding(mesh, PartitionSpec())

    def put(path, a):
        if isinstance(a, jax.Array):  # (also a typed PRNG key array)
            return jax.device_put(a, sharding)
        if isinstance(a, (np.ndarray, np.generic, bool, int, float, complex)):
            if np.asarray(a).dtype.kind in "biufc":
                return jax.device_put(a, sharding)
        elif callable(a):
            return a  # (a function of an equinox module: static data, nothing to place)
        where = jax.tree_util.keystr(path) or "(the whole tree)"
        got = f"{type(a).__name__} {a!r}"
        if isinstance(a, np.ndarray):
            got = f"an array of shape {a.shape} and dtype {a.dtype}"
        raise TypeError(
            f"`tree` must hold arrays or numbers to replicate; its leaf {where} is {got}."
        )

    return jax.tree_util.tree_map_with_path(put, tree)


def shard_fleet(x0, u, z=None, *, mesh=None):
    """Place the trajectories of a fleet with their leading axis split over `mesh`.

    **Arguments:**

    - `x0`: (N, n_x) initial states. `u`: (N, T, n_u) inputs.
    - `z`: (N, T, n_z) measured outputs, or None.
    - `mesh`: a 1-D mesh from `fleet_mesh` (default: `fleet_mesh()`).

    **Returns:**

    `(x0, u)` or `(x0, u, z)` as `jax.Array`s sharded along the trajectory axis.

    **Raises:**

    `ValueError` when the leading axes disagree, N = 0, `u` and `z` have different T, or N
    is not a multiple of the number of devices in `mesh` (see the module docstring for why
    nothing is padded).
    """
    mesh = fleet_mesh() if mesh is None else mesh
    _check_mesh(mesh)
    arrays = {"x0": x0, "u": u} if z is None else {"x0": x0, "u": u, "z": z}
    ndims = {"x0": 2, "u": 3, "z": 3}
    for name, a in arrays.items():
        if not isinstance(a, jax.Array):
            try:
                arrays[name] = np.asarray(a)
            except ValueError as err:  # NumPy's "inhomogeneous shape"
                raise ValueError(
                    f"`{name}` must be one array with a leading axis of trajectories: "
                    "trajectories of different lengths (a list of records) cannot be "
                    'sharded; pad them to one length with NaN in z and `missing="mask"`.'
                ) from err
    x0 = arrays["x0"]
    N = np.shape(x0)[0] if np.ndim(x0) == 2 else None
    for name, a in arrays.items():
        if np.ndim(a) != ndims[name] or np.shape(a)[0] != N:
            want = "(N, n_x)" if name == "x0" else f"(N, T, n_{name})"
            same = "" if name == "x0" else f" with the same N as `x0` (shape {np.shape(x0)})"
            raise ValueError(f"`{name}` must have shape {want}{same}, got shape {np.shape(a)}.")
    if N == 0:
        raise ValueError(
            f"`x0` must hold at least one trajectory (N >= 1), got shape {np.shape(x0)}."
        )
    if "z" in arrays and np.shape(arrays["z"])[1] != np.shape(arrays["u"])[1]:
        raise ValueError(
            f"`z` must have the same number of time steps T as `u`: got shape "
            f"{np.shape(arrays['z'])} for `z` and {np.shape(arrays['u'])} for `u`."
        )
    n_dev = mesh.devices.size
    if N % n_dev:
        raise ValueError(
            f"the number of trajectories N = {N} must be a multiple of the number of devices "
            f"({n_dev}) to shard the trajectory axis evenly; drop or duplicate trajectories, "
            "or build the mesh on fewer devices (`fleet_mesh(jax.devices()[:k])`)."
        )
    out = tuple(jax.device_put(a, fleet_sharding(mesh, ndims[k])) for k, a in arrays.items())
    return out
