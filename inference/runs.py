"""Files of a run: saved results (netCDF), checkpoints (``.npz``) and MDP files (``.npz``).

Every file is written atomically: to a temporary file in the same directory, then renamed
over the target, so a crash leaves either the old file or the new one, never half of one.

**Saved run** (``RUN.nc``): an ArviZ ``InferenceData`` in netCDF-4 (h5netcdf engine) with groups

- ``posterior``: the draws, dims (chain, draw, ...): every emission parameter site (e.g.
  ``theta`` (chain, draw, skill, theta_dim_0)), ``features`` (chain, draw, trajectory, skill),
  ``skill_steps`` (chain, draw, skill: steps assigned to each skill slot), sampled
  hyperparameters, and the label-invariant scalars ``log_joint``, ``num_skills``, ``num_switches``;
- ``sample_stats``: ``lp`` (the log joint) and every per-draw scalar of the kernel
  (``log_joint``, ``num_skills``, ``num_switches``, ``accept``, ...);
- ``constant_data``: the best segmentation ``segmentation`` (trajectory, step; -1 on padding)
  with ``lengths`` (trajectory), its skills' parameters ``best_<site>`` (skill, ...), their
  sampler slots ``skill_slots`` (skill), and each chain's best segmentation in slot labels
  ``chain_best_z`` (chain, trajectory, step); its attributes hold the run's description:
  ``npbrs_format`` ("npbrs-run"), ``npbrs_version`` (1), ``config`` (the
  :class:`~npbrs.inference.config.ModelConfig` as JSON), ``emission`` (the emission's
  ``describe()`` as JSON), ``fingerprint`` (of the demonstrations), ``feature_names`` (JSON),
  ``best_chain``, ``best_log_joint``, ``wall_time``, ``mdp_fingerprint`` (of the MDP fitted in;
  ``observed_data``'s attribute ``mdp_fingerprint`` is the demonstrations' own, when recorded);
- ``observed_data`` (when the result carries them): the demonstrations, ``states``, ``actions``
  and, when known, ``skills`` (trajectory, step; -1 on padding) with ``lengths``;
- ``warmup_sample_stats`` (when known): the label-invariant scalars of the warmup sweeps
  (chain, draw);
- ``log_likelihood`` (after ``FitResult.add_log_likelihood``): ``demonstrations`` (chain, draw,
  trajectory), each trajectory's log-likelihood under each draw, its skill set and transition
  weights integrated (what ``az.loo`` and ``az.compare`` read).

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

from npbrs.domains.files import atomic_write
from npbrs.domains.precision import float64_all

__all__ = ["save_run", "load_run", "load", "to_inference_data", "from_inference_data", "save_mdp", "load_mdp",
           "write_checkpoint", "read_checkpoint", "restore_state", "atomic_write"]

RUN_FORMAT, RUN_VERSION = "npbrs-run", 1
CHECKPOINT_FORMAT, CHECKPOINT_VERSION = "npbrs-checkpoint", 1


# ------------------------------------------------------------------------------ saved runs
def _padded(rows, pad=-1) -> np.ndarray:
    T = max(len(r) for r in rows)
    out = np.full((len(rows), T), pad, dtype=np.int64)
    for i, r in enumerate(rows):
        out[i, :len(r)] = r
    return out


def _site_dims(name: str, shape, param_sites) -> list:
    if name == "features":
        return ["trajectory", "skill"]
    if name == "skill_steps":
        return ["skill"]
    if name in param_sites and len(shape) >= 1:
        return ["skill"] + [f"{name}_dim_{i}" for i in range(len(shape) - 1)]
    return [f"{name}_dim_{i}" for i in range(len(shape))]


def to_inference_data(result):
    """A :class:`~npbrs.inference.results.FitResult` as ArviZ ``InferenceData`` (see the module docstring)."""
    import arviz as az
    import xarray as xr

    from .results import LABEL_INVARIANT

    C, D = np.shape(result.stats["log_joint"])
    chain_draw = {"chain": np.arange(C), "draw": np.arange(D)}
    sites = set(result.skill_params)
    posterior = {name: (["chain", "draw"] + _site_dims(name, v.shape[2:], sites), np.asarray(v))
                 for name, v in result.samples.items()}
    for name in LABEL_INVARIANT:
        posterior[name] = (["chain", "draw"], np.asarray(result.stats[name]))
    sample_stats = {"lp": (["chain", "draw"], np.asarray(result.stats["log_joint"]))}
    sample_stats.update({k: (["chain", "draw"], np.asarray(v)) for k, v in result.stats.items()})
    constant = {"segmentation": (["trajectory", "step"], _padded(result.segmentation)),
                "lengths": (["trajectory"], np.array([len(s) for s in result.segmentation], np.int64)),
                "skill_slots": (["skill"], np.asarray(result.skill_slots, np.int64))}
    for name, v in result.skill_params.items():
        v = np.asarray(v)
        constant["best_" + name] = (["skill"] + [f"{name}_dim_{i}" for i in range(v.ndim - 1)], v)
    if result.init_segmentation is not None:
        constant["init_segmentation"] = (["trajectory", "step"], _padded(result.init_segmentation))
    if result.chain_best_z is not None:
        constant["chain_best_z"] = (["chain", "trajectory", "step"], np.asarray(result.chain_best_z, np.int64))
    attrs = {"npbrs_format": RUN_FORMAT, "npbrs_version": RUN_VERSION,
             "config": json.dumps(result.config, sort_keys=True),
             "emission": json.dumps(result.emission, sort_keys=True),
             "fingerprint": result.fingerprint, "feature_names": json.dumps(list(result.feature_names)),
             "best_chain": int(result.best_chain), "best_log_joint": float(result.best_log_joint),
             "wall_time": float(result.wall_time), "mdp_fingerprint": str(result.mdp_fingerprint or "")}
    groups = {"posterior": xr.Dataset(posterior, coords=chain_draw),
              "sample_stats": xr.Dataset(sample_stats, coords=chain_draw),
              "constant_data": xr.Dataset(constant, attrs=attrs)}
    if result.demos is not None:
        demos = result.demos
        observed = {"states": (["trajectory", "step"], _padded(demos.states)),
                    "actions": (["trajectory", "step"], _padded(demos.actions)),
                    "lengths": (["trajectory"], demos.lengths)}
        if demos.skills is not None:
            observed["skills"] = (["trajectory", "step"], _padded(demos.skills))
        groups["observed_data"] = xr.Dataset(observed, attrs={"mdp_fingerprint": demos.mdp_fingerprint or ""})
    if result.warmup_stats:
        W = next(iter(result.warmup_stats.values())).shape[1]
        groups["warmup_sample_stats"] = xr.Dataset(
            {k: (["chain", "draw"], np.asarray(v)) for k, v in result.warmup_stats.items()},
            coords={"chain": chain_draw["chain"], "draw": np.arange(W)})
    if result.log_likelihood is not None:
        groups["log_likelihood"] = xr.Dataset(
            {"demonstrations": (["chain", "draw", "trajectory"], np.asarray(result.log_likelihood))}, coords=chain_draw)
    return az.InferenceData(**groups)


def from_inference_data(idata):
    """The :class:`~npbrs.inference.results.FitResult` stored in an ``InferenceData`` written by
    :func:`to_inference_data`."""
    from npbrs.domains.demos import Demonstrations

    from .results import LABEL_INVARIANT, FitResult, trajectory_rows

    if "constant_data" not in idata.groups() or idata.constant_data.attrs.get("npbrs_format") != RUN_FORMAT:
        raise ValueError("not an npbrs run (no constant_data group with npbrs_format = 'npbrs-run')")
    const = idata.constant_data
    attrs = const.attrs
    if int(attrs["npbrs_version"]) > RUN_VERSION:
        raise ValueError(f"run format version {attrs['npbrs_version']} is newer than this npbrs reads ({RUN_VERSION})")
    lengths = np.asarray(const["lengths"].values)
    seg = np.asarray(const["segmentation"].values)
    segmentation = trajectory_rows(seg, lengths)
    skill_params = {name[5:]: np.asarray(const[name].values) for name in const.data_vars if name.startswith("best_")}
    samples = {name: np.asarray(v.values) for name, v in idata.posterior.data_vars.items()
               if name not in LABEL_INVARIANT}
    stats = {name: np.asarray(v.values) for name, v in idata.sample_stats.data_vars.items() if name != "lp"}
    demos = None
    if "observed_data" in idata.groups():
        obs = idata.observed_data
        n = np.asarray(obs["lengths"].values)
        cols = {k: [np.asarray(obs[k].values)[i, :m] for i, m in enumerate(n)]
                for k in ("states", "actions", "skills") if k in obs.data_vars}
        demos = Demonstrations(**cols, mdp_fingerprint=str(obs.attrs.get("mdp_fingerprint", "")) or None)
    return FitResult(segmentation=segmentation, num_skills=len(const["skill_slots"]), skill_params=skill_params,
                     skill_slots=np.asarray(const["skill_slots"].values), best_chain=int(attrs["best_chain"]),
                     best_log_joint=float(attrs["best_log_joint"]), stats=stats, samples=samples,
                     config=json.loads(attrs["config"]), fingerprint=str(attrs["fingerprint"]),
                     wall_time=float(attrs["wall_time"]), emission=json.loads(attrs["emission"]),
                     feature_names=tuple(json.loads(attrs["feature_names"])),
                     chain_best_z=(np.asarray(const["chain_best_z"].values) if "chain_best_z" in const else None),
                     demos=demos, init_segmentation=(trajectory_rows(const["init_segmentation"].values, lengths)
                                                     if "init_segmentation" in const else None),
                     log_likelihood=(np.asarray(idata.log_likelihood["demonstrations"].values)
                                     if "log_likelihood" in idata.groups() else None),
                     mdp_fingerprint=str(attrs.get("mdp_fingerprint", "")),
                     warmup_stats=({k: np.asarray(v.values) for k, v in idata.warmup_sample_stats.data_vars.items()}
                                   if "warmup_sample_stats" in idata.groups() else None))


def save_run(result, path) -> None:
    """Write a FitResult to a netCDF file at ``path``, atomically."""
    idata = to_inference_data(result)
    atomic_write(path, lambda tmp: idata.to_netcdf(tmp, engine="h5netcdf"), suffix=".nc.tmp")


def load_run(path):
    """Read a run written by :func:`save_run` (or ``FitResult.save``) back into a FitResult."""
    import arviz as az

    if not os.path.exists(path):
        raise FileNotFoundError(f"no run file {path}")
    with az.rc_context({"data.load": "eager"}):
        try:
            idata = az.from_netcdf(path, engine="h5netcdf")
        except OSError as e:
            raise ValueError(f"{path}: not a netCDF run file ({e})") from None
    try:
        return from_inference_data(idata)
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

    def write(tmp):
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)

    atomic_write(path, write, suffix=".npz.tmp")


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

    def write(tmp):
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)

    atomic_write(path, write, suffix=".npz.tmp")


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


float64_all(globals())  # npbrs.domains.precision: float64 inside, the user's setting outside
