"""Devices: the mesh a fit runs on, and placing the kernel and the chains' states on it.

A mesh has up to two axes: "chains" (the chains spread over its devices) and "trajectories"
(each chain's demonstrations sharded over its devices, padded with empty trajectories).
"""

from __future__ import annotations

import math
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from npbrs.domains.util.precision import float64
from npbrs.models.emissions import HMMData

__all__ = ["CHAINS", "TRAJECTORIES", "PER_TRAJECTORY", "device_mesh", "check_mesh", "trajectory_devices",
           "state_shardings", "constrain", "place_state", "place_kernel", "pad_trajectories", "resize_trajectories"]

CHAINS, TRAJECTORIES = "chains", "trajectories"
# the state's fields with a trajectory axis (after the chain axis when batched)
PER_TRAJECTORY = ("features", "eta", "z", "log_lik", "log_marginals", "best_z", "best_features")


def device_mesh(devices=None, num_chains: int = 1) -> Mesh:
    """The mesh that ``fit(..., devices=devices)`` runs on: a 2-D ``jax.sharding.Mesh`` with
    axes ("chains", "trajectories") of shape (g, n // g), g = gcd(num_chains, n), over the n
    devices: the chains are spread over the devices first (they need no communication), the
    rest shard each chain's trajectories.

    Args:
        devices: None (every device, ``jax.devices()``: on several hosts, all of theirs), a
            number n (the first n of ``jax.devices()``) or a sequence of ``jax.Device``.
        num_chains: the chains of the run.
    Raises:
        ValueError: more devices asked for than there are, an empty or repeated list.
    """
    available = jax.devices()
    if devices is None:
        chosen = list(available)
    elif isinstance(devices, (int, np.integer)) and not isinstance(devices, bool):
        if not 1 <= devices <= len(available):
            raise ValueError(f"devices={int(devices)}: there are {len(available)} devices "
                             f"({available[0].platform}); ask for 1 to {len(available)}")
        chosen = list(available[:int(devices)])
    else:
        try:
            chosen = list(devices)
        except TypeError:
            raise ValueError(f"devices must be a number of devices or a sequence of jax.Device, got "
                             f"{type(devices).__name__}") from None
        if not chosen:
            raise ValueError("devices is empty")
        bad = [d for d in chosen if not isinstance(d, jax.Device)]
        if bad:
            raise ValueError(f"devices must be jax.Device objects (e.g. from jax.devices()), got {bad[0]!r}")
        if len(set(chosen)) != len(chosen):
            raise ValueError(f"devices lists a device twice: {chosen}")
        unknown = [d for d in chosen if d not in available]
        if unknown:
            raise ValueError(f"devices: {unknown[0]} is not one of jax.devices()")
    n = len(chosen)
    g = math.gcd(int(num_chains), n)
    return Mesh(np.array(chosen, dtype=object).reshape(g, n // g), (CHAINS, TRAJECTORIES))


def check_mesh(mesh, num_chains: int, method: str) -> Optional[Mesh]:
    """The validated mesh, or None when it has one device (nothing to place)."""
    if not isinstance(mesh, Mesh):
        raise ValueError(f"mesh must be a jax.sharding.Mesh, got {type(mesh).__name__}")
    unknown = [name for name in mesh.axis_names if name not in (CHAINS, TRAJECTORIES)]
    if unknown:
        raise ValueError(f"mesh axis {unknown[0]!r}: fit knows the axes {CHAINS!r} (chains on separate devices) "
                         f"and {TRAJECTORIES!r} (each chain's trajectories sharded); name the mesh's axes so")
    chains = dict(mesh.shape).get(CHAINS, 1)
    if num_chains % chains:
        raise ValueError(f"the mesh's {CHAINS!r} axis has {chains} devices, which does not divide num_chains = "
                         f"{num_chains}; use a divisor of num_chains (or shard trajectories over the rest)")
    if chains > 1 and method == "sequential":
        raise ValueError(f"chain_method='sequential' runs one chain at a time, so the mesh's {CHAINS!r} axis "
                         f"({chains} devices) has nothing to place; use chain_method='vectorized'")
    return mesh if mesh.devices.size > 1 else None


def _axis(mesh, name):
    return name if name in mesh.axis_names and mesh.shape[name] > 1 else None


def trajectory_devices(mesh: Optional[Mesh]) -> int:
    return 1 if mesh is None else int(dict(mesh.shape).get(TRAJECTORIES, 1))


def state_shardings(state, mesh: Mesh, batched: bool):
    """NamedShardings of a state's leaves: the chain axis (when batched) over the mesh's
    "chains" axis, the per-trajectory fields' trajectory axis over its "trajectories" axis, the
    rest (skills' parameters, scalars) replicated."""
    lead = (_axis(mesh, CHAINS),) if batched else ()
    traj = _axis(mesh, TRAJECTORIES)

    def field(name):
        spec = PartitionSpec(*lead, traj) if name in PER_TRAJECTORY else PartitionSpec(*lead)
        return jax.tree.map(lambda x: NamedSharding(mesh, spec if np.ndim(x) >= len(spec) else PartitionSpec()),
                            getattr(state, name))

    return type(state)(*[field(name) for name in state._fields])


def constrain(state, mesh: Optional[Mesh], batched: bool):
    """Inside a compiled sweep: keep the new state where the old one lives."""
    if mesh is None:
        return state
    return jax.lax.with_sharding_constraint(state, state_shardings(state, mesh, batched))


def _place(x, sharding):
    """A host array as a (possibly multi-host) global array: each process puts its devices'
    blocks from its own copy, which every process holds."""
    x = np.asarray(x)
    return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])


def place_state(state, mesh: Mesh, batched: bool):
    return jax.tree.map(_place, state, state_shardings(state, mesh, batched))


def place_kernel(kernel, mesh: Mesh):
    """The kernel with its demonstrations sharded over the mesh's trajectories axis (axis 0 of
    states, actions, mask) and the emission's and MDP's arrays replicated on every device."""
    data = {id(x) for x in jax.tree.leaves(kernel.data)}
    traj = NamedSharding(mesh, PartitionSpec(_axis(mesh, TRAJECTORIES)))
    rep = NamedSharding(mesh, PartitionSpec())
    leaves, treedef = jax.tree.flatten(kernel)
    return jax.tree.unflatten(treedef, [_place(x, traj if id(x) in data else rep) for x in leaves])


def pad_trajectories(data: HMMData, multiple: int) -> HMMData:
    """The data with trajectories without steps appended up to a multiple of ``multiple``
    (the sampler leaves them out: the real trajectories' draws are unchanged)."""
    N = data.states.shape[0]
    extra = -N % multiple
    if not extra:
        return data
    return HMMData(*[jnp.concatenate([x, jnp.zeros((extra,) + x.shape[1:], x.dtype)]) for x in data])


def resize_trajectories(leaves, like, fill):
    """Checkpoint leaves (a state of any trajectory count, e.g. written on other devices)
    resized to the trajectories of ``like``: rows past it dropped, missing rows (padding for
    devices) taken from ``fill``, a state of ``like``'s shapes."""
    paths = [path for path, _ in jax.tree_util.tree_flatten_with_path(like)[0]]
    expected = jax.tree.leaves(like)
    filler = jax.tree.leaves(fill)
    out = []
    for leaf, path, e, f in zip(leaves, paths, expected, filler):
        name = getattr(path[0], "name", None) if path else None
        leaf = np.asarray(leaf)
        if (name in PER_TRAJECTORY and leaf.ndim == len(e.shape) >= 2 and leaf.shape[0] == e.shape[0]
                and leaf.shape[2:] == tuple(e.shape[2:]) and leaf.shape[1] != e.shape[1]):
            n = e.shape[1]
            leaf = leaf[:, :n] if leaf.shape[1] > n else np.concatenate([leaf, np.asarray(f)[:, leaf.shape[1]:]], 1)
        out.append(leaf)
    return out




device_mesh = float64(device_mesh)  # float64 inside, the user's setting outside (npbrs.domains.util.precision)
