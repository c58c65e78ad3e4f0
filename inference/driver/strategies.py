"""The strategies around a run: the choice of switching model (``switching="auto"``) and growing
the skill slots (``grow``); each calls :func:`~npbrs.inference.driver.loop.run_fit` for its fits."""

from __future__ import annotations

import dataclasses
import os
import warnings
from typing import Optional

import numpy as np

from npbrs.domains.demos import Demonstrations
from npbrs.models.bphmm import Termination, switching_log_evidence

from .config import ModelConfig, PriorConfig
from .loop import DECISION_DIVISOR, run_fit
from .progress import user_stacklevel
from .results import FitResult

__all__ = ["fit_auto", "fit_grown", "switching_evidence", "saturation", "state_stage_path", "SWITCHING_MARGIN",
           "STATE_WARMUP_DIVISOR", "EVIDENCE_KAPPA_PRIOR", "DECISION_DIVISOR", "GROW_LIMIT", "SATURATED"]

#: ``switching="auto"``: the log Bayes factor (nats) of state-dependent ends over sticky switching,
#: given the sticky fit's skill sequences, above which ``fit`` refits with state-dependent ends
#: (``benchmarks/bench_worlds.py``: the labyrinth's fits +175 to +200, the grid's +733; rooms' -26
#: to -48; the highway table's -16 to -44)
SWITCHING_MARGIN = 10.0
#: ``switching="auto"``: the fit with state-dependent ends warms up for this fraction (1 / it) of
#: the run's warmup sweeps: it starts from the sticky fit's skills (on the grid and the labyrinth
#: 50 warmup sweeps scored held-out data as 200 did)
STATE_WARMUP_DIVISOR = 4
#: kappa's Gamma (shape, rate) in the sticky model's evidence when kappa is fixed in the fit
EVIDENCE_KAPPA_PRIOR = (1.0, 0.02)
#: ``grow``: the most skill slots it grows to, and the share of the sampling draws that must use
#: every slot for it to grow
GROW_LIMIT = 64
SATURATED = 0.5


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


def _with(cfg: ModelConfig, *, switching=None, moves=None, warmup=None, max_skills=None) -> ModelConfig:
    """``cfg`` with a stage's changes (None: unchanged)."""
    prior = cfg.prior if switching is None else dataclasses.replace(cfg.prior, switching=switching)
    sampler = cfg.sampler
    if moves is not None:
        sampler = dataclasses.replace(sampler, moves=moves)
    if warmup is not None:
        sampler = dataclasses.replace(sampler, warmup=warmup)
    return cfg.replace(prior=prior, sampler=sampler, max_skills=cfg.max_skills if max_skills is None else max_skills)


def fit_auto(mdp, demos, cfg: ModelConfig, emission=None, **run) -> FitResult:
    """``switching="auto"``: the sticky fit, then, when its skill sequences (decided after its
    first sampling sweeps, :data:`DECISION_DIVISOR`; the sticky fit stops there) favour
    state-dependent ends by more than :data:`SWITCHING_MARGIN` nats, a fit with them started
    from its segmentation (with checkpoints: at :func:`state_stage_path`; on ``resume`` the
    sticky fit continues from its own first, a finished or stopped one with nothing to redo).

    Args:
        mdp, demos, cfg, emission: the fit's (``cfg`` validated, its switching "auto").
        **run: :func:`~npbrs.inference.driver.loop.run_fit`'s other arguments.
    Returns:
        the chosen model's FitResult, its ``switching`` recording the evidence and the choice.
    """
    path = run.get("checkpoint_path")
    if path is not None and not run.get("resume") and os.path.exists(state_stage_path(path)):
        raise ValueError(f"{state_stage_path(path)} holds the checkpoint of an earlier, interrupted run; continue "
                         "it with resume=True (npbrs fit --resume), or move it away, or write the new run elsewhere")
    record = growth_record()  # (every fit in turn, the sticky fits' and then the state fits')

    def decide(partial: FitResult):
        """(whether to leave the sticky fit, the choice's record) from its first sampling sweeps."""
        choice = dict(switching_evidence(partial, mdp, demos, cfg.prior), margin=SWITCHING_MARGIN, chosen="sticky")
        if choice["log_bayes_factor"] > SWITCHING_MARGIN:
            choice["chosen"] = "state"
        return choice["chosen"] == "state", choice

    result = fit_grown(mdp, demos, _with(cfg, switching="sticky"), emission, record, decide=decide, **run)
    if result.switching is None:  # (a run of one sampling sweep, or resumed from a checkpoint without the record)
        result = dataclasses.replace(result, switching=decide(result)[1])
    choice = dict(result.switching)
    if choice["chosen"] == "state":  # (``result``: the sticky fit, stopped at the decision)
        moves = dict(cfg.sampler.moves)
        # it refines the sticky fit's skills: no sticky search phase, and no greedy moves unless
        # asked for (they kept little there; they are half the state sweep's compile)
        for name in ("sticky_phase", "greedy_merge", "greedy_split"):
            moves.setdefault(name, 0 if name != "sticky_phase" else 0.0)
        stage = _with(cfg, switching="state", moves=moves, warmup=cfg.sampler.warmup // STATE_WARMUP_DIVISOR,
                      max_skills=int(result.config["max_skills"]))
        # its init and sweep compile one after the other: side by side the labyrinth's fit (2
        # chains) peaked at 2.76 GB, one after the other at 1.90-1.92 GB (1 s more)
        result = fit_grown(mdp, demos, stage, emission, record,
                           **dict(run, init_segmentation=result, compile_beside=False,
                                  checkpoint_path=None if path is None else state_stage_path(path)))
    return dataclasses.replace(result, switching=choice)


def growth_record() -> dict:
    """``FitResult.truncation``'s lists, empty: one entry a fit."""
    return {"max_skills": [], "skills": [], "saturated": [], "switching": []}


def fit_grown(mdp, demos, cfg: ModelConfig, emission=None, record: Optional[dict] = None, **run) -> FitResult:
    """One fit (:func:`~npbrs.inference.driver.loop.run_fit`), refitted with twice the skill slots
    while they are all in use, when ``cfg.sampler.grow``.

    Args:
        mdp, demos, cfg, emission: the fit's.
        record: :func:`growth_record`'s lists, to which each fit is added (under "auto" one record
            holds both models' fits); the result keeps it as ``truncation`` once the slots grew.
        **run: :func:`~npbrs.inference.driver.loop.run_fit`'s other arguments.
    Returns:
        the last fit's FitResult.
    """
    record = growth_record() if record is None else record
    grow = cfg.sampler.grow
    result = run_fit(mdp, demos, cfg, emission, **run)
    while True:
        K, share = saturation(result)
        record["max_skills"].append(K)
        record["skills"].append(int(result.num_skills))
        record["saturated"].append(share)
        record["switching"].append(cfg.prior.switching)
        if K < 2 or share <= SATURATED:
            break
        if not grow or 2 * K > GROW_LIMIT:
            warnings.warn(f"npbrs.fit: all {K} skill slots were in use in {share:.0%} of the sampling draws, "
                          "so the truncation may be hiding skills; "
                          + (f"refit with max_skills={2 * K} or with grow=True" if not grow else
                             f"grow=True stops at {GROW_LIMIT} slots"), UserWarning, stacklevel=user_stacklevel())
            break
        cfg = _with(cfg, max_skills=2 * K)
        run = dict(run, init_segmentation=result)
        result = run_fit(mdp, demos, cfg, emission, **run)
    if max(record["max_skills"]) > record["max_skills"][0]:
        result = dataclasses.replace(result, truncation={k: list(v) for k, v in record.items()})  # (a copy: "auto" adds on)
    return result


def saturation(result: FitResult):
    """(max_skills, the share of the run's sampling draws that used every skill slot)."""
    K = int(result.config.get("max_skills", 0))
    used = np.asarray(result.stats.get("num_skills", np.zeros((0, 0))))
    return K, float(np.mean(used >= K)) if used.size and K else 0.0
