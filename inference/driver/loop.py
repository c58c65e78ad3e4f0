"""The sweep loop of one fit: chains started or resumed, swept, restarted at warmup's end,
counted, checkpointed and stopped (by the planned sweeps, the run-length rule, a decision or
Ctrl-C); see :func:`run_fit`."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import signal
import threading
import time
from typing import Optional

import jax
import numpy as np
from jax.sharding import Mesh

from npbrs.domains.demos import Demonstrations
from npbrs.models.emissions import Emission, make_emission

from ..analysis.diagnostics import (LABEL_INVARIANT, label_invariant_diagnostic, shares_start, superchain_ids,
                                    unconverged)
from ..threads import threads_for
from .chains import Chains, choose_chain_method, restart_lagging, warmup_scores
from .compiled import compiled_kernel, default_moves, mdp_key, use_compilation_cache
from .config import ModelConfig
from .devices import resize_trajectories, trajectory_devices
from .progress import Progress, latest_log_joint
from .results import STEP_COUNTS, FitResult
from . import runs

__all__ = ["run_fit", "run_length_status", "DECISION_DIVISOR", "ENDS_MEMORY_LIMIT"]

#: ``switching="state"``: the most memory (bytes) the kept draws of the end probabilities may take
ENDS_MEMORY_LIMIT = 4 * 2 ** 30
#: ``switching="auto"`` decides after this fraction (1 / it) of the sticky fit's sampling sweeps,
#: on their best draw: a fit that then switches to state-dependent ends does not draw the rest of
#: the sticky samples it would discard; one that stays sticky draws them, the same draws as
#: without the pause
DECISION_DIVISOR = 4


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


def run_fit(mdp, demos, cfg: ModelConfig, emission: Optional[Emission] = None, *, init_segmentation=None,
            progress_bar: bool = True, checkpoint_path=None, resume: bool = False, devices=None,
            compile_beside: bool = True, decide=None) -> FitResult:
    """One fit of the model ``cfg`` (validated; see :func:`~npbrs.inference.driver.fit.fit` for the
    other arguments; ``emission``: an Emission instance to use instead of ``cfg.emission``'s).
    ``decide``: partial result -> (stop, record), called once the first ``max(samples //
    DECISION_DIVISOR, 1)`` sampling sweeps are drawn (when fewer than ``samples``): ``stop`` ends
    the run there (its result holds those draws), else it goes on as without the call; the
    result's ``switching`` is ``record``, which checkpoints keep (a resumed run past the decision
    does not decide again; one stopped there stops again)."""
    use_compilation_cache()
    if not isinstance(demos, Demonstrations):
        raise ValueError(f"demos must be npbrs.domains.Demonstrations, got {type(demos).__name__}")
    demos.validate(mdp, check_transitions=True)  # (before any work: demonstrations this MDP cannot make)
    if resume and checkpoint_path is None:
        raise ValueError("resume=True needs checkpoint_path")
    if checkpoint_path is not None and not resume and os.path.exists(checkpoint_path):
        # an interrupted run's only copy: a new run must not overwrite (and then delete) it
        raise ValueError(f"{checkpoint_path} holds the checkpoint of an earlier, interrupted run; continue it "
                         "with resume=True (npbrs fit --resume), or move it away, or write the new run elsewhere")
    every = cfg.sampler.checkpoint_every
    if emission is not None:
        em, em_key = emission, f"instance:{id(emission)}"
    else:
        em = make_emission(cfg.emission.name, mdp, **cfg.emission.options)
        em_key = json.dumps([cfg.emission.to_dict(), type(em).__module__ + "." + type(em).__qualname__, mdp_key(mdp)],
                            sort_keys=True)
    fixed = em.fixed_max_skills
    if fixed is not None and cfg.max_skills != fixed:
        # e.g. unsegmented IRL ("single"): one skill slot for every step
        cfg = cfg.replace(max_skills=int(fixed), sampler=dataclasses.replace(cfg.sampler, init_skills=None))
    cfg = default_moves(cfg, em)
    sampler = cfg.sampler
    C, W, S = sampler.chains, sampler.warmup, sampler.samples
    total = W + S
    mesh = None
    if isinstance(devices, Mesh):
        mesh, devices = devices, None
    elif isinstance(devices, str):
        if devices != "all":
            raise ValueError(f"devices must be a number, a list of jax.Device, 'all' or a Mesh, got {devices!r}")
        devices = jax.devices()
    method, mesh, threads = choose_chain_method(sampler.chain_method, C, mesh, devices)
    if cfg.prior.switching == "state":
        # every kept draw holds the ends, (K, S) per chain
        kept = C * max(S, sampler.max_samples or 0) * cfg.max_skills * int(mdp.num_states) * 8
        if kept > ENDS_MEMORY_LIMIT:
            raise ValueError(f"switching='state' keeps each draw's end probabilities, {cfg.max_skills} skills x "
                             f"{mdp.num_states} states: {kept / 2 ** 30:.1f} GiB for {C} chains x "
                             f"{max(S, sampler.max_samples or 0)} draws, over the {ENDS_MEMORY_LIMIT / 2 ** 30:.0f} "
                             "GiB npbrs allows; keep fewer draws (num_samples) or chains, or use switching='sticky'")
    compiled = compiled_kernel(cfg, em, em_key, demos, trajectory_devices(mesh), int(mdp.num_states))
    kernel = compiled.kernel
    z0 = None
    if init_segmentation is not None:
        z0 = kernel.check_segmentation(getattr(init_segmentation, "segmentation", init_segmentation))
    # a run length chosen by convergence: from W + S sweeps on, a block at a time up to W + max_samples
    extend = sampler.max_samples > S
    block, cap = max(S // 2, 1), W + (sampler.max_samples if extend else S)
    meta = {"config": runs.recorded_config(cfg), "emission": em.describe(), "fingerprint": demos.fingerprint(),
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
        leaves, draws, saved = runs.check_checkpoint(checkpoint_path, meta)
        # (a checkpoint written before the per-step counts were kept resumes without them)
        if "features" in draws:
            draws["features"] = draws["features"][:, :, :num_real]
        like = jax.eval_shape(lambda k: kernel.init(k, W, None, (), {}), keys)
        if len(leaves) == len(jax.tree.leaves(like)) and any(
                np.shape(a) != tuple(e.shape) for a, e in zip(leaves, jax.tree.leaves(like))):
            # written on other devices (another padding of the trajectories): the real
            # trajectories' rows are the same, padding rows come from a fresh start
            leaves = resize_trajectories(leaves, like, compiled.init(keys, W, z0, mesh))
        state = runs.restore_state(leaves, like, checkpoint_path)
        done, wall = int(saved["sweeps_done"]), float(saved["wall_time"])
        restart = saved.get("restart")
        # (past the decision its record holds; a run stopped by it decides again, as before)
        decision = None if saved.get("stopped") else saved.get("decision")

    start = time.perf_counter()
    bar = Progress(total, done, progress_bar, chains=C)
    try:
        if state is None:
            if mesh is None and compile_beside:
                compiled.compile_sweep_beside_init(method, keys, W, z0)
            state = compiled.init(keys, W, z0, mesh, threads if method == "sequential" else 0)
        if threads > 1:  # (fewer where the sweep calls a library kernel that can block XLA's pool)
            threads = threads_for(threads, lambda: compiled.sweep_program(jax.tree.map(lambda x: x[0], state)))
        chains = Chains(compiled, method, state, mesh, threads)
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
        host_state = chains.state()  # (on several hosts every process takes part in the gather)
        if jax.process_index() == 0:  # one writer of the file
            runs.write_checkpoint(checkpoint_path, state=host_state, draws=draws, meta=write)

    def finish():
        """The run's result from the draws so far. Called at the decision too, where the run may
        go on: the result shares the draws' arrays, which is safe because the decision drops it
        before the run adds to them."""
        kept = dict(draws)
        warmup = {k[len("warmup_"):]: kept.pop(k) for k in list(kept) if k.startswith("warmup_")}
        result = FitResult.from_states(
            chains.state(), kept, demos, config=runs.recorded_config(cfg), emission=em.describe(),
            feature_names=tuple(getattr(mdp, "feature_names", ())), wall_time=wall + time.perf_counter() - start,
            sample_names=compiled.hyper_names, init_segmentation=z0,
            mdp_fingerprint=mdp.fingerprint() if hasattr(mdp, "fingerprint") else "", warmup_stats=warmup or None,
            run_length=run_length, restart=restart)
        return result if decision is None else dataclasses.replace(result, switching=dict(decision))

    if done > total:  # resumed after the planned sweeps: the extension's next point
        total = min(cap, total + -(-(done - total) // block) * block)
        bar.extend(total)
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
                        latest = latest_log_joint(records)
                        if latest is not None:
                            bar.set_postfix("; ".join([f"log joint {latest:.1f}"] + ([rhat_text] if rhat_text else [])))
                    (pending if done >= W else warm).append(records)
                    if done >= W and STEP_COUNTS in draws:  # a sampling sweep: into the per-step counts
                        _count_skills(draws[STEP_COUNTS], chains.skills(num_real, num_steps))
                    done += 1
                    if done == W and restarting:
                        flush()  # (the warmup's log joints, into draws)
                        restart = restart_lagging(chains, warmup_scores(draws["warmup_log_joint"]),
                                                   sampler.restart_margin, mesh)
                    bar.update(1)
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
                run_length = run_length_status(draws, sampler, done - W, cap - W, elapsed, restart)
                if run_length["stopped"] != "running":
                    break
                total = min(total + block, cap)
                bar.extend(total)
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


def run_length_status(draws: dict, sampler, drawn: int, most: int, elapsed: float, restart=None) -> dict:
    """Where a run whose length is chosen by convergence stands after ``drawn`` sampling sweeps
    (of at most ``most``, ``elapsed`` seconds since it started): the R-hat of each label-invariant
    scalar over the draws so far and the rule that stops it ("converged", "max_samples",
    "time_budget"), or "running". ``restart``: the run's restart record (chains that share a
    start are judged by the nested R-hat over superchains, as :attr:`FitResult.rhat` is)."""
    C = next(iter(draws[n] for n in LABEL_INVARIANT)).shape[0]
    superchains = superchain_ids(restart, C)
    rank = label_invariant_diagnostic(draws, "rhat")
    shared = shares_start(superchains)
    rhat = label_invariant_diagnostic(draws, "nested_rhat", superchains) if shared else rank
    if not unconverged(draws, rhat, target_rhat=sampler.target_rhat,
                       rank_rhat=rank if shared else None)[0]:  # (R-hat alone: the rule's target)
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

