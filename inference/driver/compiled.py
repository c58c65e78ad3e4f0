"""The compiled sampler: a kernel and its sweep, init and record programs, kept between fits.

Also the compilation cache's folder (:func:`compilation_cache_dir`) and the moves a fit turns on
when its configuration leaves them open (:func:`default_moves`).
"""

from __future__ import annotations

import dataclasses
import json
import os
import threading
from collections import OrderedDict
from concurrent.futures import Future
from functools import partial
from operator import attrgetter
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from npbrs.domains.util.compiling import jit
from npbrs.domains.demos import Demonstrations
from npbrs.domains.util.precision import float64
from npbrs.models.bphmm import Termination
from npbrs.models.emissions import Emission, HMMData

from ..sampler.kernel import BPHMMKernel, initial_skills, initial_window
from ..sampler.options import MOVE_DEFAULTS
from ..threads import on_threads, threads_for
from .config import ModelConfig
from .devices import constrain, pad_trajectories, place_kernel

__all__ = ["Compiled", "compiled_kernel", "default_moves", "compilation_cache_dir", "use_compilation_cache",
           "mdp_key", "init_chains", "sweep_one", "sweep_batched", "clear_compiled", "kept_compiled", "strong", "to_host", "DEFAULT_GREEDY_TRIALS",
           "DEFAULT_STICKY_PHASE"]


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



def mdp_key(mdp) -> str:
    # the MDP's arrays, and the identity of a domain's own next-value operator
    return f"{mdp.fingerprint()}:{id(mdp.next_value_fn) if mdp.next_value_fn else 0}"


class Compiled:
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
            self._placed = {mesh: place_kernel(self.kernel, mesh)}  # one mesh kept
        return self._placed[mesh]

    def init(self, keys, num_warmup: int, z0=None, mesh: Optional[Mesh] = None, per_chain: int = 0):
        """Every chain's initial state (keys (C, 2)), on the host, the chains stacked on axis 0;
        z0: an initial segmentation (N, T) shared by the chains, or None (random windows).
        ``per_chain`` > 0 (sequential chains, no mesh): each chain's state by the unbatched init
        (the program a sequential sweep's state comes from; the batched one's draws up to
        rounding), on up to ``per_chain`` threads at once (fewer where the program calls a library
        kernel that can block XLA's pool: :func:`~npbrs.inference.threads.max_threads`)."""
        nw = jnp.int32(num_warmup)
        if mesh is None and per_chain:
            calls = [(self.kernel, key, z0, nw) for key in keys]
            # (the trace is the one compile_sweep_beside_init made, and the call reuses the lowering)
            threads = threads_for(per_chain, lambda: init_chains.trace(self.kernel, keys[0], z0, nw).lower())
            states = on_threads(init_chains, calls, threads)
            return jax.tree.map(lambda *xs: np.stack(xs), *[to_host(s) for s in states])
        if mesh is None:
            return to_host(init_chains(self.kernel, keys, z0, nw))
        return to_host(init_chains(self.placed(mesh), keys, z0, nw, mesh))

    def compile_sweep_beside_init(self, method: str, keys, num_warmup: int, z0=None):
        """Start compiling ``method``'s sweep on a thread of its own, for the state that
        :meth:`init` (without a mesh; per chain for sequential chains) will return, so that a
        fit's two largest programs compile side by side (XLA's compile of one program keeps
        about 1.6 cores busy). The initial state's shapes come from tracing the init, which its
        call then reuses. Returns the thread. A failure there is left to the sweep's first call,
        which compiles the sweep itself then; a call made while the thread compiles waits for
        its program."""
        sequential = method == "sequential"  # (a sequential sweep takes one chain's state)
        like = init_chains.trace(self.kernel, keys[0] if sequential else keys, z0, jnp.int32(num_warmup)).out_info
        state = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype), like)
        fn, extra = (sweep_one, (jax.ShapeDtypeStruct((), jnp.bool_),)) if sequential else (sweep_batched, ())

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
        return sweep_one.lower(self.kernel, self.hyper_names, state, jax.ShapeDtypeStruct((), jnp.bool_))

    def step(self, method: str, mesh: Optional[Mesh] = None):
        """state -> (next state, record): batched over chains ("vectorized"), or (state,
        greedy_open) -> (next state, record) of one chain ("sequential"; greedy_open: the run's
        ``BPHMMKernel.greedy_open``); on ``mesh``'s devices when given (state and data placed there)."""
        fn = {"vectorized": sweep_batched, "sequential": sweep_one}[method]
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
def init_chains(kernel, keys, z0, num_warmup, mesh=None):
    # keys (C, 2): the chains' states, batched; one key (2,): one chain's (the kernel's init tells)
    state = strong(kernel.init(keys, num_warmup, None if z0 is None else {"z": z0}, (), {}))
    return constrain(state, mesh, batched=jnp.ndim(keys) > 1)


@partial(jit, static_argnums=(1, 4))
def sweep_one(kernel, hyper_names, state, greedy_open, mesh=None):
    # greedy_open: the run's (every chain's) BPHMMKernel.greedy_open
    new = constrain(strong(kernel.sweep(state, (state.step, state.num_warmup, greedy_open))), mesh, batched=False)
    return new, _record(kernel, hyper_names, new)


@partial(jit, static_argnums=(1, 3))
def sweep_batched(kernel, hyper_names, state, mesh=None):
    new = constrain(strong(kernel.sample(state, (), {})), mesh, batched=True)
    return new, jax.vmap(partial(_record, kernel, hyper_names))(new)



def strong(tree):
    """The same arrays without weak types: a state read back from a checkpoint has none, so
    every sweep sees the same input types (and runs the same compiled code) either way."""
    def strong(x):
        if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
            return x
        return jax.lax.convert_element_type(x, x.dtype)

    return jax.tree.map(strong, tree)


def to_host(tree):
    """NumPy copies of a pytree's arrays; an array spread over several hosts' devices is
    gathered (every process gets the whole)."""
    def host(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            from jax.experimental import multihost_utils

            return np.asarray(multihost_utils.process_allgather(x, tiled=True))
        return np.asarray(jax.device_get(x))

    return jax.tree.map(host, tree)


_COMPILED: "OrderedDict[str, Compiled]" = OrderedDict()
_COMPILED_MAX = 4
#: Greedy merge and split trials per warmup sweep that ``fit`` runs when the configuration does
#: not say (emissions with ``fit_evidence``): from random windows the Gibbs sweeps keep copies of
#: a skill, or lump two skills, in some runs on the paper's domains (``docs/reproducing.md``; the
#: choice of one trial of each: ``docs/design.md``). They start at the kernel's default
#: fraction of warmup, ``MOVE_DEFAULTS["greedy_from"]``.
DEFAULT_GREEDY_TRIALS = {"greedy_merge": 1, "greedy_split": 1}
#: with state-dependent ends (``switching="state"``), the fraction of warmup searched under the
#: sticky BP-HMM (the kernel's ``moves["sticky_phase"]``; ``docs/design.md``)
DEFAULT_STICKY_PHASE = 0.5


def compiled_kernel(cfg: ModelConfig, em: Emission, em_key: str, demos: Demonstrations, multiple: int = 1,
              num_states: int = 0) -> Compiled:
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
    data = pad_trajectories(HMMData.from_demonstrations(demos, bucket=sampler.bucket), multiple)
    kernel = BPHMMKernel(em, data, cfg.max_skills, **kwargs)
    entry = Compiled(kernel, tuple(prior.hyperpriors))
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



# float64 inside, the user's setting outside (npbrs.domains.util.precision)
compilation_cache_dir, use_compilation_cache = float64(compilation_cache_dir), float64(use_compilation_cache)
default_moves = float64(default_moves)


def clear_compiled() -> None:
    """Forget the kernels kept between fits (:func:`compiled_kernel`'s cache), so that their
    compiled programs can be released (e.g. with ``jax.clear_caches()``)."""
    _COMPILED.clear()


def kept_compiled() -> list:
    """The compiled kernels kept between fits (:class:`Compiled`), the most recently used last."""
    return list(_COMPILED.values())
