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

    - `devices`: a sequence of devices, or None.

    **Returns:**

    A `jax.sharding.Mesh` of shape (len(devices),).
    """
    if isinstance(devices, jax.Device):
        devices = [devices]  # one device: a mesh of one
    devices = jax.devices() if devices is None else list(devices)
    if not devices:
        raise ValueError("`devices` must hold at least one device.")
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
    if isinstance(ndim, bool) or not isinstance(ndim, (int, np.integer)) or ndim < 1:
        raise ValueError(
            f"`ndim` must be an integer >= 1 (the array's number of axes, the first the "
            f"trajectories), got {ndim!r}."
        )
    return NamedSharding(mesh, PartitionSpec(AXIS, *([None] * (ndim - 1))))


def replicate(tree, mesh):
    """Every array leaf of `tree` (theta, a weight) placed whole on every device of `mesh`."""
    _check_mesh(mesh, fleet=False)  # (any mesh: a replicated array has no split axis)
    sharding = NamedSharding(mesh, PartitionSpec())
    return jax.tree_util.tree_map(lambda a: jax.device_put(a, sharding), tree)


def shard_fleet(x0, u, z=None, *, mesh=None):
    """Place the trajectories of a fleet with their leading axis split over `mesh`.

    **Arguments:**

    - `x0`: (N, n_x) initial states. `u`: (N, T, n_u) inputs.
    - `z`: (N, T, n_z) measured outputs, or None.
    - `mesh`: a 1-D mesh from `fleet_mesh` (default: `fleet_mesh()`).

    **Returns:**

    `(x0, u)` or `(x0, u, z)` as `jax.Array`s sharded along the trajectory axis.

    **Raises:**

    `ValueError` when the leading axes disagree or N is not a multiple of the number of
    devices in `mesh` (see the module docstring for why nothing is padded).
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
    n_dev = mesh.devices.size
    if N % n_dev:
        raise ValueError(
            f"the number of trajectories N = {N} must be a multiple of the number of devices "
            f"({n_dev}) to shard the trajectory axis evenly; drop or duplicate trajectories, "
            "or build the mesh on fewer devices (`fleet_mesh(jax.devices()[:k])`)."
        )
    out = tuple(jax.device_put(a, fleet_sharding(mesh, ndims[k])) for k, a in arrays.items())
    return out
