"""Files of a run: saved results (netCDF), checkpoints (``.npz``) and MDP files (``.npz``).

Every file is written atomically: to a temporary file in the same directory, then renamed
over the target, so a crash leaves either the old file or the new one, never half of one.

**Saved run** (``RUN.nc``): a result's ArviZ ``InferenceData`` in netCDF-4 (h5netcdf engine),
written by ``FitResult.save`` and read back by :func:`load_run` (its groups:
:mod:`npbrs.inference.driver.results`). This module imports the results; they never import it.

**Checkpoint** (``.npz``, no pickles): ``meta`` (a JSON string: format "npbrs-checkpoint",
version, config, emission description, fingerprint, seed, sweeps done and total, chains,
wall time, and the kernel state's leaf shapes), ``state.NNN`` (the kernel state's leaves in
``jax.tree_util`` order, every chain stacked on axis 0) and ``draw.NAME`` (the draws kept so
far, (chain, draw, ...)).

**MDP file** (``.npz``): ``successors`` (S, A, B) int, ``probs`` (S, A, B) float,
``features`` (S, A, D) float, ``feature_names`` (D,) str, ``discount`` () float and, optional,
``initial`` (S,) float, ``state_vectors`` (S, M) float, ``name`` () str. A domain's own
expected-next-value operator is code, not data, and is not saved (the successor arrays give
the same values).
"""

from __future__ import annotations

import json
import os

import numpy as np

from npbrs.domains.util.files import atomic_savez, atomic_write
from npbrs.domains.util.precision import float64_all

from .results import NETCDF_ENGINE, FitResult

__all__ = ["load_run", "load", "save_mdp", "load_mdp", "write_checkpoint", "read_checkpoint", "restore_state", "check_checkpoint",
           "recorded_config", "atomic_write"]

CHECKPOINT_FORMAT, CHECKPOINT_VERSION = "npbrs-checkpoint", 1


# ------------------------------------------------------------------------------ saved runs
def load_run(path) -> FitResult:
    """Read a run written by ``FitResult.save`` back into a FitResult."""
    from ..arviz_import import arviz

    az = arviz()

    if not os.path.exists(path):
        raise FileNotFoundError(f"no run file {path}")
    with az.rc_context({"data.load": "eager"}):
        try:
            idata = az.from_netcdf(path, engine=NETCDF_ENGINE)
        except OSError as e:
            raise ValueError(f"{path}: not a netCDF run file ({e})") from None
    try:
        return FitResult.from_arviz(idata)
    except (KeyError, ValueError) as e:
        raise ValueError(f"{path}: {e}") from None


load = load_run


# ------------------------------------------------------------------------------ MDP files
def save_mdp(mdp, path) -> None:
    """Write a TabularMDP's arrays to an ``.npz`` file at exactly ``path``, atomically."""
    arrays = {"successors": np.asarray(mdp.successors), "probs": np.asarray(mdp.probs),
              "features": np.asarray(mdp.features), "feature_names": np.asarray(list(mdp.feature_names), dtype=str),
              "discount": np.float64(mdp.discount), "initial": np.asarray(mdp.initial),
              "name": np.asarray(str(mdp.name))}
    if mdp.state_vectors is not None:
        arrays["state_vectors"] = np.asarray(mdp.state_vectors)
    atomic_savez(path, arrays)


def load_mdp(path):
    """A TabularMDP from an ``.npz`` file (see the module docstring); the arrays are validated."""
    from npbrs.domains.mdp import TabularMDP

    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise ValueError(f"{path}: not an .npz MDP file ({e})") from None
    with data:
        files = set(data.files)
        missing = [k for k in ("successors", "probs", "features", "discount") if k not in files]
        if missing:
            raise ValueError(f"{path}: missing array{'s' if len(missing) > 1 else ''} {', '.join(missing)}")
        unknown = files - {"successors", "probs", "features", "feature_names", "discount", "initial",
                           "state_vectors", "name"}
        if unknown:
            raise ValueError(f"{path}: unknown arrays {', '.join(sorted(unknown))}")
        kwargs = {k: np.asarray(data[k]) for k in files}
    if kwargs["discount"].shape != ():
        raise ValueError(f"{path}: discount must be a scalar, got shape {kwargs['discount'].shape}")
    kwargs["discount"] = float(kwargs["discount"])
    if "feature_names" in kwargs:
        kwargs["feature_names"] = tuple(str(n) for n in kwargs["feature_names"].tolist())
    if "name" in kwargs:
        kwargs["name"] = str(kwargs["name"])
    try:
        return TabularMDP(**kwargs)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None


# ------------------------------------------------------------------------------ checkpoints
def _leaf_to_host(x):
    import jax

    if jax.dtypes.issubdtype(getattr(x, "dtype", np.float64), jax.dtypes.prng_key):
        return np.asarray(jax.random.key_data(x)), str(jax.random.key_impl(x))
    return np.asarray(x), None


def write_checkpoint(path, *, state, draws: dict, meta: dict) -> None:
    """Write a checkpoint atomically.

    Args:
        state: the kernel state of every chain (a pytree, chains on axis 0 of every leaf).
        draws: {name: (C, D_done, ...)} the draws kept so far.
        meta: plain data (config, fingerprint, sweeps done, ...), stored as JSON.
    """
    import jax

    leaves = jax.tree_util.tree_leaves(state)
    arrays, keys = {}, {}
    for i, leaf in enumerate(leaves):
        arrays[f"state.{i:03d}"], impl = _leaf_to_host(leaf)
        if impl is not None:
            keys[str(i)] = impl
    for name, v in draws.items():
        arrays[f"draw.{name}"] = np.asarray(v)
    meta = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, **meta, "key_leaves": keys,
            "state_leaves": [[list(a.shape), str(a.dtype)] for k, a in arrays.items() if k.startswith("state.")],
            "draw_names": sorted(draws)}
    arrays["meta"] = np.asarray(json.dumps(meta, sort_keys=True))
    atomic_savez(path, arrays)


def read_checkpoint(path):
    """Read a checkpoint written by :func:`write_checkpoint`.

    Returns:
        (leaves, draws, meta): the kernel state's leaves (put them back into the state with
        :func:`restore_state`), {name: array} the draws so far, and the meta dict.
    """
    import jax

    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise ValueError(f"{path}: not a checkpoint file ({e})") from None
    with data:
        if "meta" not in data.files:
            raise ValueError(f"{path}: not an npbrs checkpoint (no meta)")
        meta = json.loads(str(data["meta"]))
        if meta.get("format") != CHECKPOINT_FORMAT:
            raise ValueError(f"{path}: not an npbrs checkpoint")
        if int(meta.get("version", 0)) > CHECKPOINT_VERSION:
            raise ValueError(f"{path}: checkpoint version {meta['version']} is newer than this npbrs reads")
        n = len(meta["state_leaves"])
        leaves = [np.asarray(data[f"state.{i:03d}"]) for i in range(n)]
        draws = {name: np.asarray(data[f"draw.{name}"]) for name in meta["draw_names"]}
    for i, impl in meta.get("key_leaves", {}).items():
        leaves[int(i)] = jax.random.wrap_key_data(leaves[int(i)], impl=impl)
    return leaves, draws, meta


def restore_state(leaves, like, path="checkpoint"):
    """The kernel state from a checkpoint's leaves, in the structure of ``like`` (a pytree of
    arrays or ``jax.ShapeDtypeStruct``), after checking every leaf's shape and dtype."""
    import jax

    expected, treedef = jax.tree_util.tree_flatten(like)
    if len(expected) != len(leaves):
        raise ValueError(f"{path}: the checkpoint's sampler state has {len(leaves)} arrays but this kernel's has "
                         f"{len(expected)}; it was written by a different version of the sampler")
    for i, (a, e) in enumerate(zip(leaves, expected)):
        if tuple(a.shape) != tuple(e.shape) or a.dtype != e.dtype:
            raise ValueError(f"{path}: sampler state array {i} has shape {a.shape} and dtype {a.dtype}, but this "
                             f"kernel expects {tuple(e.shape)} and {e.dtype}; it was written by a different sampler")
    return jax.tree_util.tree_unflatten(treedef, leaves)


def recorded_config(cfg) -> dict:
    """The configuration a run records (its result's ``config``) and a checkpoint must match to
    be resumed: all of ``cfg`` but how often checkpoints are written."""
    data = cfg.to_dict()
    data["sampler"] = {k: v for k, v in data["sampler"].items() if k != "checkpoint_every"}
    return data


def check_checkpoint(path, meta):
    """The checkpoint at ``path`` as (leaves, draws, meta), refused (ValueError) unless it belongs
    to the run described by ``meta`` (demonstrations, configuration, start, emission, sweeps)."""
    leaves, draws, saved = read_checkpoint(path)
    if saved.get("fingerprint") != meta["fingerprint"]:
        raise ValueError(f"{path}: the checkpoint was written for other demonstrations (fingerprint "
                         f"{str(saved.get('fingerprint'))[:12]}, these are {meta['fingerprint'][:12]})")
    if saved.get("config") != meta["config"]:
        ours, theirs = meta["config"], saved.get("config") or {}
        diff = sorted(_differences(ours, theirs))
        raise ValueError(f"{path}: the checkpoint was written with another configuration (differs in "
                         f"{', '.join(diff) or 'its layout'})")
    if saved.get("init") != meta["init"]:
        started = {None: "random windows"}
        raise ValueError(f"{path}: the checkpoint's chains started from "
                         f"{started.get(saved.get('init'), 'another init_segmentation')}, not from "
                         f"{started.get(meta['init'], 'this init_segmentation')}")
    if saved.get("emission") != json.loads(json.dumps(meta["emission"])):
        raise ValueError(f"{path}: the checkpoint was written with another emission ({saved.get('emission')})")
    done = int(saved["sweeps_done"])
    if not 0 <= done <= meta["total_sweeps"]:
        raise ValueError(f"{path}: {done} sweeps done of {meta['total_sweeps']}")
    return leaves, draws, saved


def _differences(a, b, prefix=""):
    if isinstance(a, dict) and isinstance(b, dict):
        for k in set(a) | set(b):
            yield from _differences(a.get(k), b.get(k), f"{prefix}{k}.")
    elif a != b:
        yield prefix.rstrip(".")



float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
