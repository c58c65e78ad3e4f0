"""The chains of a run: how they are swept (batched, one at a time, on threads), and the restart
of lagging chains at the end of warmup."""

from __future__ import annotations

import math
import warnings
from typing import Optional

import jax
import numpy as np
from jax.sharding import Mesh

from ..threads import cores, on_threads
from .compiled import Compiled, to_host
from .devices import CHAINS, TRAJECTORIES, check_mesh, device_mesh, place_state
from .progress import user_stacklevel

__all__ = ["Chains", "choose_chain_method", "warmup_scores", "restart_lagging"]


class Chains:
    """The chains' states under one chain method, advanced one sweep at a time (on ``mesh``'s
    devices when given); sequential chains on ``threads`` threads at once ("threads")."""

    def __init__(self, compiled: Compiled, method: str, state, mesh: Optional[Mesh] = None, threads: int = 1):
        self.method = method
        self.threads = threads
        self.kernel = compiled.kernel
        self.fn = compiled.step(method, mesh)
        self.num_chains = int(np.shape(jax.tree_util.tree_leaves(state)[0])[0])
        if method == "sequential":
            self.states = [jax.tree.map(lambda x, c=c: x[c], state) for c in range(self.num_chains)]
            if mesh is not None:
                self.states = [place_state(s, mesh, batched=False) for s in self.states]
        else:
            self.states = state if mesh is None else place_state(state, mesh, batched=True)

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
            host = [to_host(recs) for recs in records]
            per_sweep = [{k: np.stack([r[k] for r in recs]) for k in recs[0]} for recs in host]
        else:
            per_sweep = [to_host(r) for r in records]
        return {k: np.stack([r[k] for r in per_sweep], axis=1) for k in per_sweep[0]}

    def skills(self, num_trajectories: int, num_steps: int) -> np.ndarray:
        """Every chain's current skill sequences on the host, (C, num_trajectories, num_steps)
        (the demonstrations' rows and steps, without a shape bucket's padding)."""
        if self.method == "sequential":
            z = np.stack([to_host(s.z) for s in self.states])
        else:
            z = to_host(self.states.z)
        return z[:, :num_trajectories, :num_steps]

    def state(self):
        """Every chain's state on the host, chains stacked on axis 0."""
        if self.method == "sequential":
            return jax.tree.map(lambda *xs: np.stack(xs), *[to_host(s) for s in self.states])
        return to_host(self.states)



def choose_chain_method(method: str, num_chains: int, mesh, devices):
    """(chain method, mesh or None, threads) of a run: "parallel" is the vectorized sweep with
    the chains over the local devices (``jax.sharding``; it was ``jax.pmap`` before), the
    largest number of them that divides the chains; "threads" is "sequential" with the chains'
    sweeps on up to as many threads as the process has cores (``fit``'s sweeps and
    :meth:`Compiled.init` take fewer for a program that calls a library kernel where that can
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
                              stacklevel=user_stacklevel())
            mesh = Mesh(np.array(local[:used], dtype=object).reshape(used, 1), (CHAINS, TRAJECTORIES))
    if num_chains == 1:  # unbatched (a batch of one traces every batching rule: 1.5-2.5 s more per fit)
        method = "sequential"
    return method, (None if mesh is None else check_mesh(mesh, num_chains, method)), threads



def warmup_scores(log_joint) -> np.ndarray:
    """(C,) each chain's score at the end of warmup: the mean of its log joint over the last
    tenth of the warmup sweeps (at least the last one), ``log_joint`` (C, W). One draw's log
    joint spreads by up to a few hundred nats within one region on 10^5 steps; the mean over
    the last tenth keeps that noise from deciding a restart."""
    log_joint = np.asarray(log_joint, dtype=np.float64)
    last = max(1, log_joint.shape[1] // 10)
    return log_joint[:, -last:].mean(axis=1)


def restart_lagging(chains: "Chains", scores, margin: float, mesh=None) -> dict:
    """At the end of warmup: the chains whose score (``scores``, (C,), :func:`warmup_scores`)
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
            state = to_host(chains.states)
            moved = jax.tree.map(lambda x: np.take(x, source, axis=0), state)._replace(rng_key=state.rng_key)
            chains.states = jax.device_put(moved) if mesh is None else place_state(moved, mesh, batched=True)
        else:
            chains.states = [chains.states[int(s)]._replace(rng_key=chains.states[c].rng_key)
                             for c, s in enumerate(source)]
    return {"margin": float(margin), "scores": [float(v) for v in scores], "from": [int(c) for c in source]}


