"""``fit``: segment demonstrations into skills with the BP-HMM sampler, with checkpoints.

``fit`` drives the kernel itself, not through numpyro's ``MCMC``: it calls the kernel's
``MCMCKernel`` methods (``init``, then ``sample`` once per sweep) as ``MCMC`` does, but in its
own Python loop over one ``jax.jit``-compiled sweep (all chains at once, or one chain at a time),
so that it can show progress, stop after any sweep, write a checkpoint and continue later with
exactly the draws of an uninterrupted run: every sweep is the same compiled function applied to
the same state, whatever the chunking. The collected fields are the kernel's ``sample_field`` and
``default_fields`` (as under ``MCMC``), plus ``skill_steps`` (steps assigned to each slot) and
the sampled hyperparameters.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import signal
import sys
import threading
import time
from concurrent.futures import Future
import warnings
from collections import OrderedDict
from functools import partial
from operator import attrgetter
from typing import Optional, Union

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from npbrs.domains.demos import Demonstrations
from npbrs.models.bphmm import Termination, switching_log_evidence
from npbrs.models.emissions import Emission, HMMData, get_emission_class

from npbrs.domains.util.compiling import jit
from npbrs.domains.util.precision import float64_all

from ..sampler.kernel import BPHMMKernel, initial_skills, initial_window
from ..sampler.options import MOVE_DEFAULTS
from .config import EmissionConfig, ModelConfig, PriorConfig
from .threads import cores, on_threads, threads_for
from .results import (LABEL_INVARIANT, STEP_COUNTS, ConvergenceWarning, FitResult, label_invariant_diagnostic,
                      unconverged)

__all__ = ["fit", "make_emission", "resolve_config", "default_moves", "compilation_cache_dir", "use_compilation_cache",
           "device_mesh", "CHAINS", "TRAJECTORIES", "DEFAULT_GREEDY_TRIALS"]


def compilation_cache_dir(environ=None) -> Optional[str]:
    """The folder where ``fit`` (and ``npbrs fit``/``demo``) keep JAX's compiled programs, so that
    a model of the same shapes and options again (other demonstrations, another seed or sweep
    count, a resumed run, the demo once more, a new process) skips most of the compilation:
    ``$NPBRS_CACHE_DIR``, else ``$XDG_CACHE_HOME/npbrs/jax`` (``~/.cache/npbrs/jax``). None, no
    cache, when ``NPBRS_CACHE_DIR`` is empty or "off", or when ``JAX_COMPILATION_CACHE_DIR`` is
    set (JAX then uses that folder itself)."""
    environ = os.environ if environ is None else environ
    if environ.get("JAX_COMPILATION_CACHE_DIR"):
        return None
    own = environ.get("NPBRS_CACHE_DIR")
    if own is not None:
        return None if own.strip().lower() in ("", "off") else os.path.expanduser(own)
    base = environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "npbrs", "jax")


def use_compilation_cache() -> Optional[str]:
    """Turn on JAX's persistent compilation cache in :func:`compilation_cache_dir` unless the
    process has chosen a cache folder already (``jax_compilation_cache_dir``, which is then left
    alone) or the cache is off; returns the folder in use, or None.

    This is the one process-wide setting npbrs makes, on the first ``fit`` (never at import):
    the folder holds compiled programs only, and a cache entry that cannot be read or written
    (corrupt, half-written by another process, a full disk) is a warning from JAX and a
    recompilation, never an error (tested with corrupted entries)."""
    current = jax.config.jax_compilation_cache_dir
    if current:
        return current
    path = compilation_cache_dir()
    if path:
        jax.config.update("jax_compilation_cache_dir", path)
    return path


def make_emission(emission, mdp, **options) -> Emission:
    """An emission model from a registered name (``"reward"``, ``"policy"``, ...) or an instance."""
    if isinstance(emission, Emission):
        if options:
            raise ValueError(f"emission options {sorted(options)} given with an emission instance")
        return emission
    if not isinstance(emission, str):
        raise ValueError(f"emission must be a registered name or an Emission, got {emission!r}")
    cls = get_emission_class(emission)
    try:
        return cls.from_mdp(mdp, **options)
    except TypeError as e:  # an unknown or missing option
        raise ValueError(f"emission.options: {emission!r} does not take these options ({e})") from None


# ------------------------------------------------------------------------------ configuration
def resolve_config(config=None, **overrides) -> ModelConfig:
    """A validated :class:`ModelConfig` from ``config`` (a ModelConfig, a dict, a TOML path or
    None for the defaults) with ``fit``'s keyword arguments applied on top (None: not given)."""
    if config is None:
        cfg = ModelConfig()
    elif isinstance(config, ModelConfig):
        cfg = config
    elif isinstance(config, dict):
        cfg = ModelConfig.from_dict(config)
    elif isinstance(config, (str, os.PathLike)):
        cfg = ModelConfig.from_toml(config)
    else:
        raise ValueError(f"config must be a ModelConfig, a dict or a TOML path, got {type(config).__name__}")
    data = cfg.to_dict()
    emission, options = overrides.pop("emission", None), overrides.pop("emission_options", None)
    if isinstance(emission, Emission):
        description = dict(emission.describe())
        data["emission"] = {"name": description.pop("name", emission.name), "options": description}
        if options:
            raise ValueError(f"emission options {sorted(options)} given with an emission instance")
    elif emission is not None:
        if isinstance(emission, type):
            emission = EmissionConfig(emission).name
        same = emission == data["emission"]["name"]
        data["emission"] = {"name": emission, "options": data["emission"]["options"] if same else {}}
    if options is not None:
        data["emission"]["options"] = dict(options)
    if overrides.get("max_skills") is not None:
        data["max_skills"] = overrides.pop("max_skills")
    switching = overrides.pop("switching", None)
    if switching is not None:
        data["prior"]["switching"] = switching
    hyperpriors = overrides.pop("hyperpriors", None)
    for name in PriorConfig.NAMES:
        value = overrides.pop(name, None)
        if value is not None:
            current = data["prior"][name]
            if isinstance(current, dict):
                current = {**current, "value": value}
            else:
                current = value
            data["prior"][name] = current
    if hyperpriors is not None:
        if not isinstance(hyperpriors, dict):
            raise ValueError(f"hyperpriors must be a dict {{name: (shape, rate)}}, got {hyperpriors!r}")
        for name, prior in hyperpriors.items():
            if name not in PriorConfig.NAMES:
                raise ValueError(f"prior.{name}: unknown hyperparameter; expected alpha, kappa or gamma")
            try:
                shape, rate = prior
            except (TypeError, ValueError):
                raise ValueError(f"prior.{name}: a hyperprior is (shape, rate), got {prior!r}") from None
            current = data["prior"][name]
            value = current["value"] if isinstance(current, dict) else current
            data["prior"][name] = {"value": value, "shape": shape, "rate": rate}
    renames = {"num_chains": "chains", "num_samples": "samples", "num_warmup": "warmup"}
    for key in ("num_chains", "num_samples", "num_warmup", "seed", "chain_method", "init_skills", "init_window",
                "moves", "bucket", "max_samples", "target_rhat", "time_budget", "restart_margin"):
        value = overrides.pop(key, None)
        if value is not None:
            data["sampler"][renames.get(key, key)] = value
    overrides.pop("max_skills", None)
    if overrides:
        raise ValueError(f"unknown options {sorted(overrides)}")
    return ModelConfig.from_dict(data)


# ------------------------------------------------------------------------------ compiled kernels
def _mdp_key(mdp) -> str:
    # the MDP's arrays, and the identity of a domain's own next-value operator
    return f"{mdp.fingerprint()}:{id(mdp.next_value_fn) if mdp.next_value_fn else 0}"


class _Compiled:
    """A kernel and its sweep-and-record functions (kept between fits of one model).

    The functions are compiled once per kernel *structure* and shapes, not per kernel: the
    kernel (its demonstrations, MDP arrays and emission) is an argument of the jitted module
    functions below, so a new dataset of the same shapes reuses the compiled sweep."""

    def __init__(self, kernel: BPHMMKernel, hyper_names):
        self.kernel = kernel
        self.hyper_names = tuple(hyper_names)
        self._placed = {}
        self._sweep_lowered = None  # a Future of the sequential sweep's lowered program

    def placed(self, mesh: Optional[Mesh]) -> BPHMMKernel:
        """The kernel with its arrays on ``mesh``'s devices (the data sharded over its
        trajectories axis, the rest replicated), or the kernel itself (None)."""
        if mesh is None:
            return self.kernel
        if mesh not in self._placed:
            self._placed = {mesh: _place_kernel(self.kernel, mesh)}  # one mesh kept
        return self._placed[mesh]

    def init(self, keys, num_warmup: int, z0=None, mesh: Optional[Mesh] = None, per_chain: int = 0):
        """Every chain's initial state (keys (C, 2)), on the host, the chains stacked on axis 0;
        z0: an initial segmentation (N, T) shared by the chains, or None (random windows).
        ``per_chain`` > 0 (sequential chains, no mesh): each chain's state by the unbatched init
        (the program a sequential sweep's state comes from; the batched one's draws up to
        rounding), on up to ``per_chain`` threads at once (fewer where the program calls a library
        kernel that can block XLA's pool: :func:`~npbrs.inference.driver.threads.max_threads`)."""
        nw = jnp.int32(num_warmup)
        if mesh is None and per_chain:
            calls = [(self.kernel, key, z0, nw) for key in keys]
            # (the trace is the one compile_sweep_beside_init made, and the call reuses the lowering)
            threads = threads_for(per_chain, lambda: _init_chains.trace(self.kernel, keys[0], z0, nw).lower())
            states = on_threads(_init_chains, calls, threads)
            return jax.tree.map(lambda *xs: np.stack(xs), *[_to_host(s) for s in states])
        if mesh is None:
            return _to_host(_init_chains(self.kernel, keys, z0, nw))
        return _to_host(_init_chains(self.placed(mesh), keys, z0, nw, mesh))

    def compile_sweep_beside_init(self, method: str, keys, num_warmup: int, z0=None):
        """Start compiling ``method``'s sweep on a thread of its own, for the state that
        :meth:`init` (without a mesh; per chain for sequential chains) will return, so that a
        fit's two largest programs compile side by side (XLA's compile of one program keeps
        about 1.6 cores busy). The initial state's shapes come from tracing the init, which its
        call then reuses. Returns the thread. A failure there is left to the sweep's first call,
        which compiles the sweep itself then; a call made while the thread compiles waits for
        its program."""
        sequential = method == "sequential"  # (a sequential sweep takes one chain's state)
        like = _init_chains.trace(self.kernel, keys[0] if sequential else keys, z0, jnp.int32(num_warmup)).out_info
        state = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype), like)
        fn, extra = (_sweep_one, (jax.ShapeDtypeStruct((), jnp.bool_),)) if sequential else (_sweep_batched, ())

        lowered = Future()
        self._sweep_lowered = lowered if sequential else None

        def compile_sweep():
            try:
                with jax.enable_x64(True):
                    program = fn.lower(self.kernel, self.hyper_names, state, *extra)
                    lowered.set_result(program)
                    program.compile()
            except Exception as error:  # (the first sweep's call compiles it, and raises what it raises)
                if not lowered.done():
                    lowered.set_exception(error)

        thread = threading.Thread(target=compile_sweep, name="npbrs-compile-sweep", daemon=True)
        thread.start()
        return thread

    def sweep_program(self, state):
        """The sequential sweep's lowered program for one chain's ``state`` (the one
        :meth:`compile_sweep_beside_init` lowered, else lowered here: one kernel's states all
        have the same shapes; the sweep's call reuses the lowering)."""
        if self._sweep_lowered is not None:
            try:
                return self._sweep_lowered.result()
            except Exception:  # (lowered again below, which raises what it raises)
                pass
        return _sweep_one.lower(self.kernel, self.hyper_names, state, jax.ShapeDtypeStruct((), jnp.bool_))

    def step(self, method: str, mesh: Optional[Mesh] = None):
        """state -> (next state, record): batched over chains ("vectorized"), or (state,
        greedy_open) -> (next state, record) of one chain ("sequential"; greedy_open: the run's
        ``BPHMMKernel.greedy_open``); on ``mesh``'s devices when given (state and data placed there)."""
        fn = {"vectorized": _sweep_batched, "sequential": _sweep_one}[method]
        if mesh is None:
            return partial(fn, self.kernel, self.hyper_names)
        return partial(fn, self.placed(mesh), self.hyper_names, mesh=mesh)


def _record(kernel: BPHMMKernel, hyper_names, state) -> dict:
    """The fields kept after a sweep, of one chain."""
    out = {}
    for name in dict.fromkeys((kernel.sample_field,) + tuple(kernel.default_fields)):
        value = attrgetter(name)(state)
        if isinstance(value, dict):
            out.update(value)
        elif hasattr(value, "_fields"):
            out.update(value._asdict())
        else:
            out[name] = value
    K = kernel.max_skills
    mask = kernel.data.mask
    out["skill_steps"] = jnp.sum(jax.nn.one_hot(state.z, K, dtype=jnp.int32) * mask[..., None], axis=(0, 1))
    for name in hyper_names:
        out[name] = getattr(state.hyper, name)
    return out


@partial(jit, static_argnums=4, once=True)
def _init_chains(kernel, keys, z0, num_warmup, mesh=None):
    # keys (C, 2): the chains' states, batched; one key (2,): one chain's (the kernel's init tells)
    state = _strong(kernel.init(keys, num_warmup, None if z0 is None else {"z": z0}, (), {}))
    return _constrain(state, mesh, batched=jnp.ndim(keys) > 1)


@partial(jit, static_argnums=(1, 4))
def _sweep_one(kernel, hyper_names, state, greedy_open, mesh=None):
    # greedy_open: the run's (every chain's) BPHMMKernel.greedy_open
    new = _constrain(_strong(kernel.sweep(state, (state.step, state.num_warmup, greedy_open))), mesh, batched=False)
    return new, _record(kernel, hyper_names, new)


@partial(jit, static_argnums=(1, 3))
def _sweep_batched(kernel, hyper_names, state, mesh=None):
    new = _constrain(_strong(kernel.sample(state, (), {})), mesh, batched=True)
    return new, jax.vmap(partial(_record, kernel, hyper_names))(new)


def _warmup_scores(log_joint) -> np.ndarray:
    """(C,) each chain's score at the end of warmup: the mean of its log joint over the last
    tenth of the warmup sweeps (at least the last one), ``log_joint`` (C, W). One draw's log
    joint spreads by up to a few hundred nats within one region on 10^5 steps; the mean over
    the last tenth keeps that noise from deciding a restart."""
    log_joint = np.asarray(log_joint, dtype=np.float64)
    last = max(1, log_joint.shape[1] // 10)
    return log_joint[:, -last:].mean(axis=1)


def _restart_lagging(chains: "_Chains", scores, margin: float, mesh=None) -> dict:
    """At the end of warmup: the chains whose score (``scores``, (C,), :func:`_warmup_scores`)
    is more than ``margin`` nats below the best chain's continue from the best chain's state,
    with their own random keys (``SamplerConfig.restart_margin``). Returns the record kept as
    the result's ``restart``: the margin, each chain's score and the chain whose state it
    continues from."""
    batched = chains.method != "sequential"
    scores = np.asarray(scores, dtype=np.float64)
    finite = np.isfinite(scores)
    best = int(np.argmax(np.where(finite, scores, -np.inf)))
    # (a chain whose score is not finite lags a finite best; with no finite score none moves)
    lagging = ~(scores >= scores[best] - margin) & bool(np.any(finite))
    source = np.where(lagging, best, np.arange(len(scores)))
    if np.any(lagging):
        if batched:  # (on the host: a gather per leaf on the device would compile a program per shape)
            state = _to_host(chains.states)
            moved = jax.tree.map(lambda x: np.take(x, source, axis=0), state)._replace(rng_key=state.rng_key)
            chains.states = jax.device_put(moved) if mesh is None else _place_state(moved, mesh, batched=True)
        else:
            chains.states = [chains.states[int(s)]._replace(rng_key=chains.states[c].rng_key)
                             for c, s in enumerate(source)]
    return {"margin": float(margin), "scores": [float(v) for v in scores], "from": [int(c) for c in source]}


# ------------------------------------------------------------------------------ devices
CHAINS, TRAJECTORIES = "chains", "trajectories"
# the state's fields with a trajectory axis (after the chain axis when batched)
_PER_TRAJECTORY = ("features", "eta", "z", "log_lik", "log_marginals", "best_z", "best_features")


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


def _check_mesh(mesh, num_chains: int, method: str) -> Optional[Mesh]:
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


def _trajectory_devices(mesh: Optional[Mesh]) -> int:
    return 1 if mesh is None else int(dict(mesh.shape).get(TRAJECTORIES, 1))


def _state_shardings(state, mesh: Mesh, batched: bool):
    """NamedShardings of a state's leaves: the chain axis (when batched) over the mesh's
    "chains" axis, the per-trajectory fields' trajectory axis over its "trajectories" axis, the
    rest (skills' parameters, scalars) replicated."""
    lead = (_axis(mesh, CHAINS),) if batched else ()
    traj = _axis(mesh, TRAJECTORIES)

    def field(name):
        spec = PartitionSpec(*lead, traj) if name in _PER_TRAJECTORY else PartitionSpec(*lead)
        return jax.tree.map(lambda x: NamedSharding(mesh, spec if np.ndim(x) >= len(spec) else PartitionSpec()),
                            getattr(state, name))

    return type(state)(*[field(name) for name in state._fields])


def _constrain(state, mesh: Optional[Mesh], batched: bool):
    """Inside a compiled sweep: keep the new state where the old one lives."""
    if mesh is None:
        return state
    return jax.lax.with_sharding_constraint(state, _state_shardings(state, mesh, batched))


def _place(x, sharding):
    """A host array as a (possibly multi-host) global array: each process puts its devices'
    blocks from its own copy, which every process holds."""
    x = np.asarray(x)
    return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])


def _place_state(state, mesh: Mesh, batched: bool):
    return jax.tree.map(_place, state, _state_shardings(state, mesh, batched))


def _place_kernel(kernel: BPHMMKernel, mesh: Mesh) -> BPHMMKernel:
    """The kernel with its demonstrations sharded over the mesh's trajectories axis (axis 0 of
    states, actions, mask) and the emission's and MDP's arrays replicated on every device."""
    data = {id(x) for x in jax.tree.leaves(kernel.data)}
    traj = NamedSharding(mesh, PartitionSpec(_axis(mesh, TRAJECTORIES)))
    rep = NamedSharding(mesh, PartitionSpec())
    leaves, treedef = jax.tree.flatten(kernel)
    return jax.tree.unflatten(treedef, [_place(x, traj if id(x) in data else rep) for x in leaves])


def _pad_trajectories(data: HMMData, multiple: int) -> HMMData:
    """The data with trajectories without steps appended up to a multiple of ``multiple``
    (the sampler leaves them out: the real trajectories' draws are unchanged)."""
    N = data.states.shape[0]
    extra = -N % multiple
    if not extra:
        return data
    return HMMData(*[jnp.concatenate([x, jnp.zeros((extra,) + x.shape[1:], x.dtype)]) for x in data])


def _resize_trajectories(leaves, like, fill):
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
        if (name in _PER_TRAJECTORY and leaf.ndim == len(e.shape) >= 2 and leaf.shape[0] == e.shape[0]
                and leaf.shape[2:] == tuple(e.shape[2:]) and leaf.shape[1] != e.shape[1]):
            n = e.shape[1]
            leaf = leaf[:, :n] if leaf.shape[1] > n else np.concatenate([leaf, np.asarray(f)[:, leaf.shape[1]:]], 1)
        out.append(leaf)
    return out


_COMPILED: "OrderedDict[str, _Compiled]" = OrderedDict()
_COMPILED_MAX = 4
#: Greedy merge and split trials per warmup sweep that ``fit`` runs when the configuration does
#: not say (emissions with ``fit_evidence``): from random windows the Gibbs sweeps keep copies of
#: a skill, or lump two skills, in some runs on the paper's domains (README, "Reproduction"; the
#: choice of one trial of each: ``benchmarks/NOTES.md``). They start at the kernel's default
#: fraction of warmup, ``MOVE_DEFAULTS["greedy_from"]``.
DEFAULT_GREEDY_TRIALS = {"greedy_merge": 1, "greedy_split": 1}
#: with state-dependent ends (``switching="state"``), the fraction of warmup searched under the
#: sticky BP-HMM (the kernel's ``moves["sticky_phase"]``; ``benchmarks/NOTES.md``, session 41)
DEFAULT_STICKY_PHASE = 0.5


def _compiled(cfg: ModelConfig, em: Emission, em_key: str, demos: Demonstrations, multiple: int = 1,
              num_states: int = 0) -> _Compiled:
    """The kernel of this model and data, reused when the same model is fitted again (its
    compiled sweep is the expensive part of a short run); ``multiple``: pad the trajectories to
    a multiple of it (the devices that shard them)."""
    prior, sampler = cfg.prior, cfg.sampler
    key = json.dumps([em_key, demos.fingerprint(), cfg.max_skills, prior.to_dict(), sampler.init_skills,
                      sampler.init_window, sampler.moves, sampler.warmup, sampler.bucket, multiple, num_states],
                     sort_keys=True)
    if key in _COMPILED:
        _COMPILED.move_to_end(key)
        return _COMPILED[key]
    kwargs = dict(alpha=prior.alpha.value, kappa=prior.kappa.value, gamma=prior.gamma.value,
                  hyperpriors=prior.hyperpriors or None, init_skills=sampler.init_skills,
                  init_window=sampler.init_window, moves=dict(sampler.moves))
    if prior.switching == "state":
        kwargs["termination"] = Termination(int(num_states), prior.end_concentration, prior.end_mean)
    data = _pad_trajectories(HMMData.from_demonstrations(demos, bucket=sampler.bucket), multiple)
    kernel = BPHMMKernel(em, data, cfg.max_skills, **kwargs)
    entry = _Compiled(kernel, tuple(prior.hyperpriors))
    _COMPILED[key] = entry
    while len(_COMPILED) > _COMPILED_MAX:
        _COMPILED.popitem(last=False)
    return entry


def default_moves(cfg: ModelConfig, emission: Emission) -> ModelConfig:
    """``cfg`` with the warmup's greedy moves on where the configuration does not set them and
    there is more than one skill slot: ``DEFAULT_GREEDY_TRIALS`` merge trials per sweep if the
    emission has ``fit_evidence``, and as many split trials (a split's allocation fits by it too), from the kernel's
    ``MOVE_DEFAULTS["greedy_from"]`` x warmup on (unless ``greedy_from`` is set; see
    ``npbrs.inference.sampler.greedy``), the emission's ``redraw_unused`` (sweeps between
    prior redraws of unused skills' parameters) where it is above the kernel's 1, and the
    initial segmentation's window length and skills where the configuration leaves them open (the
    kernel's :func:`~npbrs.inference.sampler.kernel.initial_window` and
    :func:`~npbrs.inference.sampler.kernel.initial_skills`), and with state-dependent ends a sticky
    first ``DEFAULT_STICKY_PHASE`` of warmup. The run's configuration records them."""
    if cfg.sampler.init_window is None:
        cfg = cfg.replace(sampler=dataclasses.replace(cfg.sampler, init_window=initial_window(emission)))
    if cfg.sampler.init_skills is None:
        cfg = cfg.replace(sampler=dataclasses.replace(cfg.sampler,
                                                      init_skills=initial_skills(emission, cfg.max_skills)))
    moves = dict(cfg.sampler.moves)
    if int(emission.redraw_unused) > 1:
        moves.setdefault("redraw_unused", int(emission.redraw_unused))
    if cfg.max_skills >= 2 and emission.supports_greedy_merge():
        moves.setdefault("greedy_merge", DEFAULT_GREEDY_TRIALS["greedy_merge"])
        moves.setdefault("greedy_split", DEFAULT_GREEDY_TRIALS["greedy_split"])
        if moves.get("greedy_merge", 0) or moves.get("greedy_split", 0):
            moves.setdefault("greedy_from", MOVE_DEFAULTS["greedy_from"])
    if cfg.prior.switching == "state":
        moves.setdefault("sticky_phase", DEFAULT_STICKY_PHASE)
    if moves == cfg.sampler.moves:
        return cfg
    return cfg.replace(sampler=dataclasses.replace(cfg.sampler, moves=moves))


# ------------------------------------------------------------------------------ the run
class _Interrupt:
    """Turns Ctrl-C into a flag checked between sweeps (a second Ctrl-C interrupts at once)."""

    def __init__(self):
        self.flag = False
        self._old = None

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self._old = signal.getsignal(signal.SIGINT)

            def handler(signum, frame):
                if self.flag:
                    raise KeyboardInterrupt
                self.flag = True

            signal.signal(signal.SIGINT, handler)
        return self

    def __exit__(self, *exc):
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)
        return False


def _strong(tree):
    """The same arrays without weak types: a state read back from a checkpoint has none, so
    every sweep sees the same input types (and runs the same compiled code) either way."""
    def strong(x):
        if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
            return x
        return jax.lax.convert_element_type(x, x.dtype)

    return jax.tree.map(strong, tree)


def _to_host(tree):
    """NumPy copies of a pytree's arrays; an array spread over several hosts' devices is
    gathered (every process gets the whole)."""
    def host(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            from jax.experimental import multihost_utils

            return np.asarray(multihost_utils.process_allgather(x, tiled=True))
        return np.asarray(jax.device_get(x))

    return jax.tree.map(host, tree)


class _Chains:
    """The chains' states under one chain method, advanced one sweep at a time (on ``mesh``'s
    devices when given); sequential chains on ``threads`` threads at once ("threads")."""

    def __init__(self, compiled: _Compiled, method: str, state, mesh: Optional[Mesh] = None, threads: int = 1):
        self.method = method
        self.threads = threads
        self.kernel = compiled.kernel
        self.fn = compiled.step(method, mesh)
        self.num_chains = int(np.shape(jax.tree_util.tree_leaves(state)[0])[0])
        if method == "sequential":
            self.states = [jax.tree.map(lambda x, c=c: x[c], state) for c in range(self.num_chains)]
            if mesh is not None:
                self.states = [_place_state(s, mesh, batched=False) for s in self.states]
        else:
            self.states = state if mesh is None else _place_state(state, mesh, batched=True)

    def advance(self):
        """One sweep of every chain; returns the records (a list of per-chain dicts or one batched dict)."""
        if self.method == "sequential":
            # the chains' greedy moves stop together, as vectorised chains' do (the same draws)
            # (on the host: each state's last sweep is done by now, and no small program compiles)
            greedy = np.any([self.kernel.greedy_open(s._replace(greedy_idle=np.asarray(s.greedy_idle)))
                             for s in self.states])
            outs = on_threads(self.fn, [(s, greedy) for s in self.states], self.threads)
            self.states = [state for state, _ in outs]
            return [rec for _, rec in outs]
        self.states, rec = self.fn(self.states)
        return rec

    def stack(self, records) -> dict:
        """Records of several sweeps as host arrays {name: (C, n, ...)}."""
        if self.method == "sequential":
            host = [_to_host(recs) for recs in records]
            per_sweep = [{k: np.stack([r[k] for r in recs]) for k in recs[0]} for recs in host]
        else:
            per_sweep = [_to_host(r) for r in records]
        return {k: np.stack([r[k] for r in per_sweep], axis=1) for k in per_sweep[0]}

    def skills(self, num_trajectories: int, num_steps: int) -> np.ndarray:
        """Every chain's current skill sequences on the host, (C, num_trajectories, num_steps)
        (the demonstrations' rows and steps, without a shape bucket's padding)."""
        if self.method == "sequential":
            z = np.stack([_to_host(s.z) for s in self.states])
        else:
            z = _to_host(self.states.z)
        return z[:, :num_trajectories, :num_steps]

    def state(self):
        """Every chain's state on the host, chains stacked on axis 0."""
        if self.method == "sequential":
            return jax.tree.map(lambda *xs: np.stack(xs), *[_to_host(s) for s in self.states])
        return _to_host(self.states)


def _user_stacklevel() -> int:
    """``warnings.warn``'s stacklevel, called where the warning is raised, that names the first
    frame outside npbrs: the user's own call of ``fit`` (however many of npbrs's functions and
    wrappers lie between), not a line of npbrs's."""
    import npbrs.domains
    import npbrs.inference
    import npbrs.models

    roots = tuple(os.path.dirname(os.path.abspath(m.__file__)) + os.sep
                  for m in (npbrs.domains, npbrs.models, npbrs.inference))
    frame, level = sys._getframe(1), 1
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(roots):
        frame, level = frame.f_back, level + 1
    return level


def _chain_method(method: str, num_chains: int, mesh, devices):
    """(chain method, mesh or None, threads) of a run: "parallel" is the vectorized sweep with
    the chains over the local devices (``jax.sharding``; it was ``jax.pmap`` before), the
    largest number of them that divides the chains; "threads" is "sequential" with the chains'
    sweeps on up to as many threads as the process has cores (``fit``'s sweeps and
    :meth:`_Compiled.init` take fewer for a program that calls a library kernel where that can
    hang: :func:`~npbrs.inference.driver.threads.max_threads`); "auto" is "threads" when JAX
    computes on the CPU, there are several chains and there is no mesh, else "vectorized"."""
    if mesh is not None and devices is not None:
        raise ValueError("give mesh or devices, not both (devices=... builds a mesh: see device_mesh)")
    if method == "auto":
        on_cpu = mesh is None and devices is None and jax.default_backend() == "cpu"
        method = "threads" if on_cpu and num_chains > 1 else "vectorized"
    threads = 1
    if method == "threads":
        if mesh is not None or devices is not None:
            raise ValueError("chain_method='threads' runs every chain on one device, on threads of the host; "
                             "with mesh or devices use chain_method='vectorized' (or 'parallel')")
        method, threads = "sequential", max(1, min(num_chains, cores()))
    if devices is not None:
        mesh = device_mesh(devices, num_chains)
        if method == "sequential":  # one chain at a time: every device shards its trajectories
            mesh = Mesh(mesh.devices.reshape(1, -1), mesh.axis_names)
    if method == "parallel":
        method = "vectorized"
        if mesh is None:
            local = jax.local_devices()
            used = math.gcd(num_chains, len(local))
            if used == 1 and num_chains > 1:
                warnings.warn(f"chain_method='parallel': {num_chains} chains on {len(local)} device"
                              f"{'s' if len(local) > 1 else ''}; running them vectorized on one",
                              stacklevel=_user_stacklevel())
            mesh = Mesh(np.array(local[:used], dtype=object).reshape(used, 1), (CHAINS, TRAJECTORIES))
    if num_chains == 1:  # unbatched (a batch of one traces every batching rule: 1.5-2.5 s more per fit)
        method = "sequential"
    return method, (None if mesh is None else _check_mesh(mesh, num_chains, method)), threads


class _Progress:
    """Sweeps done, shown while a fit runs.

    The first sweep of a run compiles the sampler, so it is shown as "compiling" and left out
    of the rate: the ETA comes from the sweeps after it. In a terminal or a notebook this is a
    tqdm bar; when the output is not a terminal (a log file, CI), a plain line every
    ``total / 10`` sweeps instead of carriage returns.
    """

    def __init__(self, total: int, initial: int, enabled: bool, stream=None, chains: int = 1, counted: int = 1):
        """``chains``: the run's; ``counted``: the chains whose sweeps count one by one (``chains``
        where they are swept in turn or on threads), 1 where a sweep moves every chain at once."""
        self.total, self.n, self.enabled = int(total), int(initial), bool(enabled)
        self.chains, self.counted = int(chains), int(counted)
        self.stream = sys.stderr if stream is None else stream
        self.phase, self.postfix = "compiling", ""
        self.timed_from = None  # (time, sweeps) after the first sweep
        self.bar = None
        self.plain = self.enabled and not _interactive(self.stream)
        self.every = max(1, self.total // 10)
        if self.enabled and not self.plain:
            from tqdm.auto import tqdm

            self.bar = tqdm(total=total, initial=initial, unit="sweep", dynamic_ncols=True, leave=True,
                            smoothing=0, file=self.stream)
            self.bar.set_description("compiling", refresh=True)
        elif self.plain:
            self._line(f"compiling the sampler (the first sweep); {self.total - self.n} sweeps to run"
                       + (f" ({self.chains} chains' sweeps, counted one by one)" if self.counted > 1 else ""))

    def _line(self, text):
        print(f"npbrs fit: {text}", file=self.stream, flush=True)

    def set_phase(self, phase: str):
        self.phase = phase
        if self.bar is not None and self.timed_from is not None:
            self.bar.set_description(phase, refresh=False)

    def set_postfix(self, text: str):
        self.postfix = text
        if self.bar is not None:
            self.bar.set_postfix_str(text, refresh=False)

    def update(self, k: int):
        self.n += k
        now = time.perf_counter()
        if self.timed_from is None:  # the first sweep: compiled; time the rest from here
            self.timed_from = (now, self.n)
            if self.bar is not None:
                self.bar.set_description(self.phase, refresh=False)
                self.bar.update(k)
                self.bar.initial, self.bar.start_t = self.bar.n, self.bar._time()
            elif self.plain:
                self._line(f"compiled; sweep {self.n}/{self.total} ({self.phase})")
            return
        if self.bar is not None:
            self.bar.update(k)
        elif self.plain and (self.n % self.every == 0 or self.n >= self.total):
            t0, n0 = self.timed_from
            rate = (now - t0) / max(self.n - n0, 1)
            eta = rate * (self.total - self.n)
            self._line(f"sweep {self.n}/{self.total} ({self.phase}), {rate:.2f} s per sweep, "
                       f"about {eta:.0f} s left" + (f", {self.postfix}" if self.postfix else ""))

    def extend(self, total: int):
        """More sweeps to run than first planned (a run extended until convergence)."""
        self.total = int(total)
        self.every = max(1, self.total // 10)
        if self.bar is not None:
            self.bar.total = self.total
            self.bar.refresh()

    def close_done(self, sweeps: int, seconds: float):
        """Close with the sweeps each chain has run and the run's wall time."""
        each = f" of each of {self.chains} chains" if self.chains > 1 else ""
        self.close(f"done: {sweeps} sweeps{each} in {seconds:.1f} s")

    def close(self, message: str = ""):
        if self.bar is not None:
            self.bar.close()
        elif self.plain and message:
            self._line(message)
        self.enabled = self.plain = False
        self.bar = None


def _latest_log_joint(records) -> Optional[float]:
    """The best chain's log joint after the sweep that gave ``records`` (a dict batched over
    chains, or a list of one chain's each), for the progress line; None where the records have
    none, or where their arrays live partly on other processes' devices (a multi-host run)."""
    values = [r.get("log_joint") for r in (records if isinstance(records, list) else [records])]
    if any(v is None or not getattr(v, "is_fully_addressable", True) for v in values):
        return None
    return float(max(np.max(np.asarray(v)) for v in values))


def _interactive(stream) -> bool:
    """A terminal, or a notebook (where tqdm draws a widget)."""
    try:
        if stream.isatty():
            return True
    except (AttributeError, ValueError):
        pass
    ipython = sys.modules.get("IPython")  # a notebook kernel: IPython is loaded and runs a kernel app
    shell = getattr(ipython, "get_ipython", lambda: None)() if ipython is not None else None
    return shell is not None and "IPKernelApp" in getattr(shell, "config", {})


def fit(mdp, demos: Demonstrations, config: Union[ModelConfig, dict, str, os.PathLike, None] = None, *,
        emission=None, emission_options: Optional[dict] = None, num_chains: Optional[int] = None,
        num_samples: Optional[int] = None, num_warmup: Optional[int] = None, max_skills: Optional[int] = None,
        seed: Optional[int] = None, chain_method: Optional[str] = None, alpha: Optional[float] = None,
        kappa: Optional[float] = None, gamma: Optional[float] = None, hyperpriors: Optional[dict] = None,
        init_skills: Optional[int] = None, init_window: Optional[int] = None, moves: Optional[dict] = None,
        bucket: Optional[bool] = None, max_samples: Optional[int] = None, target_rhat: Optional[float] = None,
        time_budget: Optional[float] = None, restart_margin: Optional[float] = None, init_segmentation=None,
        progress_bar: bool = True, checkpoint_path=None, checkpoint_every: Optional[int] = None, resume: bool = False,
        mesh: Optional[Mesh] = None, devices=None, grow: bool = False, switching: Optional[str] = None) -> FitResult:
    """Segment demonstrations into skills.

    The model and sampler come from ``config`` (defaults: :class:`ModelConfig`); the keyword
    arguments, when given, override its entries.

    Args:
        mdp: the TabularMDP the demonstrations live in.
        demos: :class:`~npbrs.domains.Demonstrations`.
        config: a :class:`~npbrs.inference.driver.config.ModelConfig`, its dict, or a TOML file.
        emission: a registered emission name ("reward", "policy", ...) or an Emission instance.
        emission_options: keyword options of the emission's ``from_mdp`` (e.g. prior_scale).
        num_chains, num_samples, num_warmup: MCMC sizes (sweeps per chain).
        max_skills: truncation K of the beta process (skill slots).
        seed: the random seed; the same seed gives the same draws, bit for bit.
        chain_method: "auto" (the default): "threads" when JAX computes on the CPU, with
            several chains and no ``mesh`` or ``devices`` (on up to
            :func:`~npbrs.inference.driver.threads.max_threads` threads: the process's cores;
            one fewer with a jaxlib before 0.11.2 when the sweep calls a LAPACK kernel (they
            can hang programs that run at once; fit's reward and policy emissions call none);
            with one thread, the sequential chains, whose unbatched programs ran faster than
            the batch on 2 cores); else "vectorized". "vectorized": the chains
            vmapped in one program (the choice for an accelerator). "sequential": one chain
            after another. "threads": the sequential sweep, each chain's on its own thread (up
            to ``max_threads`` at once): the same draws as "sequential", bit for bit, in about
            1/threads of its time. "parallel": the vectorized sweep with the chains spread over the local devices
            (the largest number of them that divides num_chains; a mesh with a "chains" axis,
            see ``mesh``; the same draws as "vectorized"). The sequential and vectorized sweeps
            give the same draws up to rounding (about 1e-10 in the weights). A single chain
            always sweeps as "sequential" (unbatched: its program traces and compiles faster
            than a batch of one).
        alpha, kappa, gamma: BP-HMM hyperparameters (IBP mass, stickiness, transition concentration).
        hyperpriors: {"alpha"|"kappa"|"gamma": (shape, rate)}: sample those under Gamma hyperpriors.
        init_skills, init_window: the initial segmentation (see :class:`BPHMMKernel`).
        moves: options of the kernel's trans-dimensional moves, e.g. {"birth_death": 2}. Unless
            it says otherwise, greedy merges and splits run late in warmup
            (:data:`DEFAULT_GREEDY_TRIALS` from ``MOVE_DEFAULTS["greedy_from"]`` x warmup on,
            see :func:`default_moves`) for emissions with ``fit_evidence``
            (the reward and policy emissions), until no chain has kept one in its last
            ``greedy_patience`` (10) greedy sweeps; ``{"greedy_merge": 0, "greedy_split": 0}``
            turns them off. The other options' defaults: ``npbrs.inference.sampler.options.MOVE_DEFAULTS``.
        bucket: pad the demonstrations to shape buckets (a quarter at most more trajectories
            and steps), so that another data set of similar size reuses the compiled sampler
            (see :class:`~npbrs.inference.driver.config.SamplerConfig`; off by default).
        max_samples, target_rhat, time_budget: a run length chosen by convergence: with
            ``max_samples`` above ``num_samples``, keep sampling (``num_samples // 2`` sweeps at a
            time) until every label-invariant scalar's R-hat is at most ``target_rhat`` (1.05),
            ``max_samples`` sweeps are drawn or ``time_budget`` seconds (0: none) have passed;
            the result's ``run_length`` says which (see
            :class:`~npbrs.inference.driver.config.SamplerConfig`). Off by default.
        restart_margin: at the end of warmup, a chain whose log joint (averaged over the last
            tenth of warmup) is more than this many nats below the best chain's continues from
            the best chain's state with its own random key; 50 by default, 0 is off (see
            :class:`~npbrs.inference.driver.config.SamplerConfig`). The result's ``restart``
            records the scores and which chains moved.
        init_segmentation: start every chain from this segmentation instead of random windows:
            per trajectory an integer label per step (any integers, e.g. a previous result's
            ``segmentation`` or hand labels), or a FitResult. The skills' initial parameters are
            fitted to their steps as in the default start.
        progress_bar: show progress: a bar in a terminal or notebook, a plain line every tenth
            of the sweeps otherwise (logs); the first sweep, which compiles the sampler, is shown
            as "compiling" and the ETA comes from the sweeps after it.
        checkpoint_path: write a checkpoint (``.npz``) there every ``checkpoint_every`` sweeps,
            at the end, and on Ctrl-C (then KeyboardInterrupt is re-raised).
        checkpoint_every: sweeps between checkpoints (default 100).
        resume: continue from ``checkpoint_path`` when it exists (without ``resume`` an existing
            checkpoint is refused, never overwritten; it must hold the same
            demonstrations and configuration); the result equals an uninterrupted run's.
        mesh: run on several devices: a ``jax.sharding.Mesh`` with an axis "chains" (the
            chains spread over its devices; its size must divide num_chains) and/or an axis
            "trajectories" (each chain's demonstrations sharded over its devices, padded with
            empty trajectories to a multiple of its size). The per-trajectory work (feature
            Gibbs, forward filtering, backward sampling) runs where the trajectories live and
            the per-skill count tables are summed across devices; the skills' parameters are
            replicated. The draws are those of the one-device run with the same seed (every
            discrete draw equal; sums over trajectories, such as the log joint, may differ in
            the last digits with the order of their terms). On several hosts, call
            ``jax.distributed.initialize()`` first and give a mesh over ``jax.devices()``.
        devices: a shortcut for ``mesh``: a number of devices, a list of ``jax.Device`` or
            "all" (``jax.devices()``); see :func:`device_mesh` (chains spread first, the
            remaining devices shard the trajectories).
        grow: when every skill slot was in use in more than half of the sampling draws (the
            truncation ``max_skills`` may be hiding skills), fit again with twice the slots,
            starting from the run's best segmentation, until it is not so or ``GROW_LIMIT``
            (64) slots; the result is the last fit's, with ``truncation`` recording each fit's
            slots, skills, saturation and switching model (under "auto", the sticky fits and
            then the state fits, which start from the grown sticky fit). Without it such a run
            warns (``UserWarning``) and says how to refit. Not with ``checkpoint_path``.
        switching: "sticky" (the paper's BP-HMM), "state": skills end with a probability that
            depends on the state entered (options with a termination function, sampled; see
            :class:`~npbrs.inference.driver.config.PriorConfig`), as when a skill ends once its
            goal is reached, or "auto" (the default): the sticky fit, and when its skill
            sequences (its best draw among the first quarter of its sampling sweeps,
            :data:`DECISION_DIVISOR`) favour state-dependent ends by a log Bayes factor above
            :data:`SWITCHING_MARGIN` (:func:`switching_evidence`), the sticky fit stops there
            and a fit with them starts from that segmentation (a quarter of the warmup sweeps,
            :data:`STATE_WARMUP_DIVISOR`; no sticky search phase; no greedy moves unless
            ``moves`` asks for them); a sticky fit kept draws the rest of its sweeps, the same
            draws as without the pause. The result is the chosen model's, its ``switching``
            recording the evidence and the choice. With checkpoints the second fit's is at
            :func:`state_stage_path`, and ``resume`` continues the sticky fit from its own (a
            finished or stopped one: nothing to redo; a missing one: it is repeated, the same
            seed giving the same fit), then the state fit from its.
    Returns:
        a :class:`~npbrs.inference.driver.results.FitResult`.
    Warns:
        ConvergenceWarning: the draws fail the label-invariant diagnostics (an R-hat above 1.05
            or an ESS below 100; ``result.summary()`` says how each chain moved).
        UserWarning: every skill slot was in use in most of the draws (without ``grow``).
    Raises:
        ValueError: bad demonstrations, configuration, devices or checkpoint, before anything is
            compiled.

    The compiled sampler is kept in JAX's persistent compilation cache, in npbrs's folder
    (:func:`compilation_cache_dir`: ``~/.cache/npbrs/jax``), unless the process has a cache
    folder of its own already or ``NPBRS_CACHE_DIR=off`` (see :func:`use_compilation_cache`).

    The run draws its random numbers with JAX's partitionable threefry
    (``jax.threefry_partitionable(True)``, JAX's default, whatever the process set): each draw is
    numbered by its position, so that it does not depend on the devices or the padding.
    """
    with jax.threefry_partitionable(True):
        args = dict(locals())
        grow = args.pop("grow")
        if grow and checkpoint_path is not None:
            raise ValueError("grow=True refits with more skill slots, which a checkpoint of one run cannot hold; "
                             "give either grow or checkpoint_path")
        prior = resolve_config(config, switching=switching).prior
        result = _fit_grown(args, grow) if prior.switching != "auto" else _fit_auto(args, grow, prior)
    warn_if_unconverged(result)
    return result


def warn_if_unconverged(result: FitResult) -> None:
    """A :class:`ConvergenceWarning` naming the user's call when ``result`` fails the
    label-invariant diagnostics (what its summary says, in one line)."""
    text = result.convergence_warning()
    if text:
        warnings.warn(f"npbrs.fit: {text.splitlines()[0]}; result.summary() shows how each chain moved",
                      ConvergenceWarning, stacklevel=_user_stacklevel())


#: ``switching="auto"``: the log Bayes factor (nats) of state-dependent ends over sticky switching,
#: given the sticky fit's skill sequences, above which ``fit`` refits with state-dependent ends
#: (``benchmarks/NOTES.md``, session 42: the labyrinth's fits +175 to +200, the grid's +733;
#: rooms' -26 to -48, the highway table's -16 to -44)
SWITCHING_MARGIN = 10.0
#: ``switching="auto"``: the fit with state-dependent ends warms up for this fraction (1 / it) of
#: the run's warmup sweeps: it starts from the sticky fit's skills (session 42: on the grid and
#: the labyrinth 50 warmup sweeps scored held-out data as 200 did)
STATE_WARMUP_DIVISOR = 4
#: kappa's Gamma (shape, rate) in the sticky model's evidence when kappa is fixed in the fit
EVIDENCE_KAPPA_PRIOR = (1.0, 0.02)
#: ``switching="auto"`` decides after this fraction (1 / it) of the sticky fit's sampling sweeps,
#: on their best draw: a fit that then switches to state-dependent ends does not draw the rest of
#: the sticky samples it would discard (a quarter of the grid's fit time; ``benchmarks/NOTES.md``,
#: session 46); one that stays sticky draws them, the same draws as without the pause
DECISION_DIVISOR = 4


def state_stage_path(checkpoint_path) -> str:
    """Where ``switching="auto"`` keeps the checkpoint of its fit with state-dependent ends
    (the sticky fit's is ``checkpoint_path`` itself): "RUN.checkpoint.npz" -> "RUN.checkpoint.state.npz"."""
    root, ext = os.path.splitext(os.fspath(checkpoint_path))
    return f"{root}.state{ext}"


def switching_evidence(result: FitResult, mdp, demos: Demonstrations, prior: PriorConfig) -> dict:
    """The log evidence of ``result``'s skill sequences (its best draw's segmentation) under
    sticky switching and under state-dependent ends (the prior's end concentration and end-mean
    prior; kappa under its hyperprior if sampled, else :data:`EVIDENCE_KAPPA_PRIOR`), and their
    difference ("log_bayes_factor", state over sticky): see
    :func:`npbrs.models.bphmm.switching_log_evidence`."""
    lengths = [len(z) for z in result.segmentation]
    N, T = len(lengths), max(lengths)
    if result.config.get("sampler", {}).get("bucket"):  # (the bucket's shapes: its program is shared)
        from npbrs.models.emissions import bucket_size

        N, T = bucket_size(N), bucket_size(T)
    z = np.zeros((N, T), np.int64)
    states = np.zeros((N, T), np.int64)
    mask = np.arange(T)[None, :] < np.asarray(lengths + [0] * (N - len(lengths)))[:, None]
    for i, (seg, s) in enumerate(zip(result.segmentation, demos.states)):
        z[i, :len(seg)], states[i, :len(s)] = seg, s
    term = Termination(int(mdp.num_states), prior.end_concentration, prior.end_mean)
    kappa = prior.kappa
    kappa_prior = (kappa.shape, kappa.rate) if kappa.sampled else EVIDENCE_KAPPA_PRIOR
    sticky, state = switching_log_evidence(z, mask, states, int(mdp.num_states), term, float(prior.gamma.value),
                                           kappa_prior, num_skills=int(result.config["max_skills"]))
    return {"sticky": round(sticky, 3), "state": round(state, 3), "log_bayes_factor": round(state - sticky, 3)}


def _fit_auto(args: dict, grow: bool, prior: PriorConfig) -> FitResult:
    """``switching="auto"``: the sticky fit, then, when its skill sequences (decided after its
    first sampling sweeps, :data:`DECISION_DIVISOR`; the sticky fit stops there) favour
    state-dependent ends by more than :data:`SWITCHING_MARGIN` nats, a fit with them started
    from its segmentation (with checkpoints: at :func:`state_stage_path`; on ``resume`` the
    sticky fit continues from its own first, a finished or stopped one with nothing to redo)."""
    path = args["checkpoint_path"]
    if path is not None and not args["resume"] and os.path.exists(state_stage_path(path)):
        raise ValueError(f"{state_stage_path(path)} holds the checkpoint of an earlier, interrupted run; continue "
                         "it with resume=True (npbrs fit --resume), or move it away, or write the new run elsewhere")
    record = _growth_record()  # (every fit in turn, the sticky fits' and then the state fits')

    def decide(partial: FitResult):
        """(whether to leave the sticky fit, the choice's record) from its first sampling sweeps."""
        choice = dict(switching_evidence(partial, args["mdp"], args["demos"], prior), margin=SWITCHING_MARGIN,
                      chosen="sticky")
        if choice["log_bayes_factor"] > SWITCHING_MARGIN:
            choice["chosen"] = "state"
        return choice["chosen"] == "state", choice

    result = _fit_grown(dict(args, switching="sticky", decide=decide), grow, record)
    if result.switching is None:  # (a run of one sampling sweep, or resumed from a checkpoint without the record)
        result = dataclasses.replace(result, switching=decide(result)[1])
    choice = dict(result.switching)
    if choice["chosen"] == "state":  # (``result``: the sticky fit, stopped at the decision)
        given = resolve_config(args["config"], moves=args["moves"], num_warmup=args["num_warmup"]).sampler
        moves = dict(given.moves)
        # it refines the sticky fit's skills: no sticky search phase, and no greedy moves unless
        # asked for (they kept little there; they are half the state sweep's compile)
        for name in ("sticky_phase", "greedy_merge", "greedy_split"):
            moves.setdefault(name, 0 if name != "sticky_phase" else 0.0)
        stage = dict(args, switching="state", init_segmentation=result, moves=moves,
                     num_warmup=given.warmup // STATE_WARMUP_DIVISOR, max_skills=int(result.config["max_skills"]),
                     checkpoint_path=None if path is None else state_stage_path(path),
                     # its init and sweep compile one after the other: side by side the labyrinth's
                     # fit (2 chains) peaked at 2.76 GB, one after the other at 1.90-1.92 GB (1 s more;
                     # the fit's own peak, benchmarks/NOTES.md session 43)
                     compile_beside=False)
        result = _fit_grown(stage, grow, record)
    return dataclasses.replace(result, switching=choice)


def _growth_record() -> dict:
    """``FitResult.truncation``'s lists, empty: one entry a fit."""
    return {"max_skills": [], "skills": [], "saturated": [], "switching": []}


def _fit_grown(args: dict, grow: bool, record: Optional[dict] = None) -> FitResult:
    """One fit (:func:`_fit`), refitted with more skill slots while they are all in use when
    ``grow``. Each fit is added to ``record`` (:func:`_growth_record`; under "auto" one record
    holds both models' fits), which the result keeps as ``truncation`` once the slots grew."""
    record = _growth_record() if record is None else record
    result = _fit(**args)
    while True:
        K, share = saturation(result)
        record["max_skills"].append(K)
        record["skills"].append(int(result.num_skills))
        record["saturated"].append(share)
        record["switching"].append(args["switching"])
        if K < 2 or share <= SATURATED:
            break
        if not grow or 2 * K > GROW_LIMIT:
            warnings.warn(f"npbrs.fit: all {K} skill slots were in use in {share:.0%} of the sampling draws, "
                          "so the truncation may be hiding skills; "
                          + (f"refit with max_skills={2 * K} or with grow=True" if not grow else
                             f"grow=True stops at {GROW_LIMIT} slots"), UserWarning, stacklevel=_user_stacklevel())
            break
        args.update(max_skills=2 * K, init_segmentation=result)
        result = _fit(**args)
    if max(record["max_skills"]) > record["max_skills"][0]:
        result = dataclasses.replace(result, truncation={k: list(v) for k, v in record.items()})  # (a copy: "auto" adds on)
    return result


#: ``switching="state"``: the most memory (bytes) the kept draws of the end probabilities may take
ENDS_MEMORY_LIMIT = 4 * 2 ** 30

#: ``fit(grow=True)``: the most skill slots it grows to, and the share of the sampling draws that
#: must use every slot for it to grow
GROW_LIMIT = 64
SATURATED = 0.5


def saturation(result: FitResult):
    """(max_skills, the share of the run's sampling draws that used every skill slot)."""
    K = int(result.config.get("max_skills", 0))
    used = np.asarray(result.stats.get("num_skills", np.zeros((0, 0))))
    return K, float(np.mean(used >= K)) if used.size and K else 0.0


def _fit(mdp, demos, config, *, emission, emission_options, num_chains, num_samples, num_warmup, max_skills, seed,
         chain_method, alpha, kappa, gamma, hyperpriors, init_skills, init_window, moves, bucket, max_samples,
         target_rhat, time_budget, restart_margin, init_segmentation, progress_bar, checkpoint_path, checkpoint_every,
         resume, mesh, devices, switching, compile_beside=True, decide=None) -> FitResult:
    """One fit (``fit``'s arguments). ``decide``: partial result -> (stop, record), called once
    the first ``max(samples // DECISION_DIVISOR, 1)`` sampling sweeps are drawn (when fewer than
    ``samples``): ``stop`` ends the run there (its result holds those draws), else it goes on as
    without the call; the result's ``switching`` is ``record``, which checkpoints keep (a
    resumed run past the decision does not decide again; one stopped there stops again)."""
    use_compilation_cache()
    cfg = resolve_config(config, emission=emission, emission_options=emission_options, num_chains=num_chains,
                         num_samples=num_samples, num_warmup=num_warmup, max_skills=max_skills, seed=seed,
                         chain_method=chain_method, alpha=alpha, kappa=kappa, gamma=gamma, hyperpriors=hyperpriors,
                         init_skills=init_skills, init_window=init_window, moves=moves, bucket=bucket,
                         max_samples=max_samples, target_rhat=target_rhat, time_budget=time_budget,
                         restart_margin=restart_margin, switching=switching)
    if not isinstance(demos, Demonstrations):
        raise ValueError(f"demos must be npbrs.domains.Demonstrations, got {type(demos).__name__}")
    demos.validate(mdp)
    if checkpoint_every is not None:
        if isinstance(checkpoint_every, bool) or not isinstance(checkpoint_every, (int, np.integer)) \
                or checkpoint_every < 1:
            raise ValueError(f"checkpoint_every must be an integer >= 1, got {checkpoint_every!r}")
        if checkpoint_path is None:
            raise ValueError("checkpoint_every given without checkpoint_path")
    if resume and checkpoint_path is None:
        raise ValueError("resume=True needs checkpoint_path")
    if checkpoint_path is not None and not resume and os.path.exists(checkpoint_path):
        # an interrupted run's only copy: a new run must not overwrite (and then delete) it
        raise ValueError(f"{checkpoint_path} holds the checkpoint of an earlier, interrupted run; continue it "
                         "with resume=True (npbrs fit --resume), or move it away, or write the new run elsewhere")
    every = int(checkpoint_every or 100)
    if isinstance(emission, Emission):
        em, em_key = emission, f"instance:{id(emission)}"
    else:
        em = make_emission(cfg.emission.name, mdp, **cfg.emission.options)
        em_key = json.dumps([cfg.emission.to_dict(), type(em).__module__ + "." + type(em).__qualname__, _mdp_key(mdp)],
                            sort_keys=True)
    fixed = em.fixed_max_skills
    if fixed is not None and cfg.max_skills != fixed:
        # e.g. unsegmented IRL ("single"): one skill slot for every step
        cfg = cfg.replace(max_skills=int(fixed), sampler=dataclasses.replace(cfg.sampler, init_skills=None))
    cfg = default_moves(cfg, em)
    sampler = cfg.sampler
    C, W, S = sampler.chains, sampler.warmup, sampler.samples
    total = W + S
    if isinstance(devices, str):
        if devices != "all":
            raise ValueError(f"devices must be a number, a list of jax.Device or 'all', got {devices!r}")
        devices = jax.devices()
    method, mesh, threads = _chain_method(sampler.chain_method, C, mesh, devices)
    if cfg.prior.switching == "state":
        # every kept draw holds the ends, (K, S) per chain
        kept = C * max(S, sampler.max_samples or 0) * cfg.max_skills * int(mdp.num_states) * 8
        if kept > ENDS_MEMORY_LIMIT:
            raise ValueError(f"switching='state' keeps each draw's end probabilities, {cfg.max_skills} skills x "
                             f"{mdp.num_states} states: {kept / 2 ** 30:.1f} GiB for {C} chains x "
                             f"{max(S, sampler.max_samples or 0)} draws, over the {ENDS_MEMORY_LIMIT / 2 ** 30:.0f} "
                             "GiB npbrs allows; keep fewer draws (num_samples) or chains, or use switching='sticky'")
    compiled = _compiled(cfg, em, em_key, demos, _trajectory_devices(mesh), int(mdp.num_states))
    kernel = compiled.kernel
    z0 = None
    if init_segmentation is not None:
        z0 = kernel.check_segmentation(getattr(init_segmentation, "segmentation", init_segmentation))
    # a run length chosen by convergence: from W + S sweeps on, a block at a time up to W + max_samples
    extend = sampler.max_samples > S
    block, cap = max(S // 2, 1), W + (sampler.max_samples if extend else S)
    meta = {"config": cfg.to_dict(), "emission": em.describe(), "fingerprint": demos.fingerprint(),
            "seed": sampler.seed, "num_chains": C, "total_sweeps": cap,
            "init": None if z0 is None else hashlib.sha256(z0.tobytes()).hexdigest()}
    keys = jax.random.split(jax.random.PRNGKey(sampler.seed), C)

    state, draws, done, wall, restart = None, {}, 0, 0.0, None
    # how often each step was in each skill slot over the sampling sweeps (C, N, T, K), on the
    # host; kept with the draws (so checkpoints hold it); the result's ``skill_probabilities``
    num_steps = int(np.max(demos.lengths))
    draws[STEP_COUNTS] = np.zeros((C, demos.num_trajectories, num_steps, cfg.max_skills), np.int32)
    # warmup's end: chains far behind the best continue from its state (SamplerConfig.restart_margin)
    restarting = C > 1 and W > 0 and sampler.restart_margin > 0
    num_real = demos.num_trajectories
    # a decision after the first sampling sweeps (``decide``; switching="auto"): the sweep count
    # at which it is made, the record it returned, and whether it stopped the run there
    first = max(S // DECISION_DIVISOR, 1)
    decide_at = W + first if decide is not None and first < S else None
    decision, stopped = None, False
    if resume and os.path.exists(checkpoint_path):
        leaves, draws, saved = _read_checkpoint(checkpoint_path, meta)
        # (a checkpoint written before the per-step counts were kept resumes without them)
        if "features" in draws:
            draws["features"] = draws["features"][:, :, :num_real]
        from .runs import restore_state

        like = jax.eval_shape(lambda k: kernel.init(k, W, None, (), {}), keys)
        if len(leaves) == len(jax.tree.leaves(like)) and any(
                np.shape(a) != tuple(e.shape) for a, e in zip(leaves, jax.tree.leaves(like))):
            # written on other devices (another padding of the trajectories): the real
            # trajectories' rows are the same, padding rows come from a fresh start
            leaves = _resize_trajectories(leaves, like, compiled.init(keys, W, z0, mesh))
        state = restore_state(leaves, like, checkpoint_path)
        done, wall = int(saved["sweeps_done"]), float(saved["wall_time"])
        restart = saved.get("restart")
        # (past the decision its record holds; a run stopped by it decides again, as before)
        decision = None if saved.get("stopped") else saved.get("decision")

    start = time.perf_counter()
    counted = C if method == "sequential" else 1
    bar = _Progress(total * counted, done * counted, progress_bar, chains=C, counted=counted)
    try:
        if state is None:
            if mesh is None and compile_beside:
                compiled.compile_sweep_beside_init(method, keys, W, z0)
            state = compiled.init(keys, W, z0, mesh, threads if method == "sequential" else 0)
        if threads > 1:  # (fewer where the sweep calls a library kernel that can block XLA's pool)
            threads = threads_for(threads, lambda: compiled.sweep_program(jax.tree.map(lambda x: x[0], state)))
        chains = _Chains(compiled, method, state, mesh, threads)
    except BaseException:
        bar.close()
        raise
    pending = []

    warm = []  # warmup sweeps' label-invariant scalars, kept for trace plots as "warmup_<name>"

    def flush():
        for records, prefix, names in ((pending, "", None), (warm, "warmup_", LABEL_INVARIANT)):
            if records:
                new = chains.stack(records)
                if "features" in new:  # the demonstrations' trajectories, without padding
                    new["features"] = new["features"][:, :, :num_real]
                for k, v in new.items():
                    if names is None or k in names:
                        key = prefix + k
                        draws[key] = np.concatenate([draws[key], v], axis=1) if key in draws else v
                records.clear()

    def checkpoint(done_now):
        flush()
        write = dict(meta, sweeps_done=done_now, wall_time=wall + time.perf_counter() - start, restart=restart,
                     decision=decision, stopped=stopped)
        from .runs import write_checkpoint

        host_state = chains.state()  # (on several hosts every process takes part in the gather)
        if jax.process_index() == 0:  # one writer of the file
            write_checkpoint(checkpoint_path, state=host_state, draws=draws, meta=write)

    def finish():
        """The run's result from the draws so far. Called at the decision too, where the run may
        go on: the result shares the draws' arrays, which is safe because the decision drops it
        before the run adds to them."""
        kept = dict(draws)
        warmup = {k[len("warmup_"):]: kept.pop(k) for k in list(kept) if k.startswith("warmup_")}
        result = FitResult.from_states(
            chains.state(), kept, demos, config=cfg.to_dict(), emission=em.describe(),
            feature_names=tuple(getattr(mdp, "feature_names", ())), wall_time=wall + time.perf_counter() - start,
            sample_names=compiled.hyper_names, init_segmentation=z0,
            mdp_fingerprint=mdp.fingerprint() if hasattr(mdp, "fingerprint") else "", warmup_stats=warmup or None,
            run_length=run_length, restart=restart)
        return result if decision is None else dataclasses.replace(result, switching=dict(decision))

    if done > total:  # resumed after the planned sweeps: the extension's next point
        total = min(cap, total + -(-(done - total) // block) * block)
        bar.extend(total * (C if method == "sequential" else 1))
    run_length, rhat_text = None, ""
    try:
        with _Interrupt() as interrupt:
            while True:
                while done < total:
                    if done == decide_at and decision is None:
                        flush()
                        stopped, decision = decide(finish())
                        if stopped:
                            if checkpoint_path is not None:
                                checkpoint(done)
                            break
                    bar.set_phase("warmup" if done < W else "sample")
                    records = chains.advance()
                    if progress_bar:  # dispatch is asynchronous: time the sweep, not its dispatch
                        jax.block_until_ready(records)
                        latest = _latest_log_joint(records)
                        if latest is not None:
                            bar.set_postfix("; ".join([f"log joint {latest:.1f}"] + ([rhat_text] if rhat_text else [])))
                    (pending if done >= W else warm).append(records)
                    if done >= W and STEP_COUNTS in draws:  # a sampling sweep: into the per-step counts
                        _count_skills(draws[STEP_COUNTS], chains.skills(num_real, num_steps))
                    done += 1
                    if done == W and restarting:
                        flush()  # (the warmup's log joints, into draws)
                        restart = _restart_lagging(chains, _warmup_scores(draws["warmup_log_joint"]),
                                                   sampler.restart_margin, mesh)
                    bar.update(C if method == "sequential" else 1)
                    if checkpoint_path is not None and (done % every == 0 or done == total):
                        checkpoint(done)
                    elif len(pending) + len(warm) >= 100:
                        flush()
                    if interrupt.flag:
                        if checkpoint_path is not None:
                            checkpoint(done)
                        raise KeyboardInterrupt(f"stopped after {done} of {total} sweeps"
                                                + (f"; resume from {checkpoint_path}" if checkpoint_path else ""))
                flush()
                if not extend or stopped:
                    break
                elapsed = wall + time.perf_counter() - start
                run_length = _run_length(draws, sampler, done - W, cap - W, elapsed)
                if run_length["stopped"] != "running":
                    break
                total = min(total + block, cap)
                bar.extend(total * (C if method == "sequential" else 1))
                rhat_text = "R-hat " + ", ".join(f"{k} {'undefined' if v is None else format(v, '.3f')}"
                                                 for k, v in run_length["rhat"].items())
                bar.set_postfix(rhat_text)
    finally:
        bar.close_done(done, time.perf_counter() - start)
    return finish()


def _count_skills(counts: np.ndarray, z: np.ndarray) -> None:
    """Add one sweep's skill sequences z (C, N, T) (-1 on padding) to ``counts`` (C, N, T, K), in place."""
    for k in range(counts.shape[-1]):
        counts[..., k] += z == k


def _run_length(draws: dict, sampler, drawn: int, most: int, elapsed: float) -> dict:
    """Where a run whose length is chosen by convergence stands after ``drawn`` sampling sweeps
    (of at most ``most``, ``elapsed`` seconds since it started): the R-hat of each label-invariant
    scalar over the draws so far and the rule that stops it ("converged", "max_samples",
    "time_budget"), or "running"."""
    rhat = label_invariant_diagnostic(draws, "rhat")
    if not unconverged(draws, rhat, target_rhat=sampler.target_rhat)[0]:  # (R-hat alone: the rule's target)
        stopped = "converged"
    elif drawn >= most:
        stopped = "max_samples"
    elif sampler.time_budget and elapsed > sampler.time_budget:
        stopped = "time_budget"
    else:
        stopped = "running"
    return {"samples": int(drawn), "rhat": {k: (v if np.isfinite(v) else None) for k, v in rhat.items()},
            "stopped": stopped, "target_rhat": sampler.target_rhat,
            "max_samples": sampler.max_samples, "time_budget": sampler.time_budget}


def _read_checkpoint(path, meta):
    """The checkpoint's (leaves, draws, meta), refused unless it belongs to this run."""
    from .runs import read_checkpoint

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
