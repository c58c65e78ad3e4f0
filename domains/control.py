"""Control evaluation (the paper's Figures 7 and 10): use inferred skills to act, score with the true ones.

Each demonstration is replayed in the domain's tabular dynamics from its own first state. At
step t the agent takes the greedy optimal action (hard value iteration) of the reward of the
*inferred* skill z_t, and the step is scored with the *true* skill's reward at step t,
r_true(s_t, a_t) = ``domain.rewards()[true skill, s_t, a_t]``: the expected reward of the
step over its next state (the domains' features are expectations over s'), which makes a
score a deterministic function of the visited states and actions. A trajectory's score is
the undiscounted sum over its steps.

Randomness is shared between methods (common random numbers): trajectory i draws its
uniforms u_1, u_2, ... from ``numpy.random.default_rng([seed, i])`` before any rollout, and
the next state of step t is found by inverse-CDF sampling of P(. | s_t, a_t) with u_t. Two
methods that are in the same state and take the same action therefore reach the same next
state, and the expert (true segmentation, true rewards) gets exactly its own score.
"""

from __future__ import annotations

from typing import Dict, Sequence

import numpy as np

from .solvers import greedy_policy, value_iteration
from .util.precision import float64_all

__all__ = ["evaluate_control", "expert_control", "skill_policies", "replay"]


def skill_policies(mdp, skills) -> np.ndarray:
    """Deterministic policies (K, S) of skills given as reward tables, reward weights or policies.

    Args:
        mdp: the TabularMDP.
        skills: (K, S, A) float reward tables; (K, D) float reward weights over
            ``mdp.features``; or (K, S) integer actions (used as they are).
    Returns:
        (K, S) int64 actions: the greedy optimal policy of each reward (lowest action on ties).
    """
    arr = np.asarray(skills)
    S, A, D = mdp.num_states, mdp.num_actions, mdp.num_features
    if arr.ndim == 2 and arr.dtype.kind in "iu":
        if arr.shape[1] != S:
            raise ValueError(f"skill policies must have shape (K, {S}), got {arr.shape}")
        bad = (arr < 0) | (arr >= A)
        if np.any(bad):
            k, s = (int(i) for i in np.argwhere(bad)[0])
            raise ValueError(f"skill {k}, state {s}: action {arr[k, s]} is outside 0..{A - 1}")
        return arr.astype(np.int64)
    if arr.dtype.kind not in "fiu":
        raise ValueError(f"skills must be numeric arrays, got dtype {arr.dtype}")
    if arr.ndim == 2:
        if arr.shape[1] != D:
            raise ValueError(f"float skills of shape {arr.shape} are read as reward weights (K, D) and need D = "
                             f"{D} (features {list(mdp.feature_names)}); pass integer policies as (K, {S}) ints")
        arr = mdp.reward(arr)
    if arr.ndim != 3 or arr.shape[1:] != (S, A):
        raise ValueError(f"skills must be reward tables (K, {S}, {A}), reward weights (K, {D}) or policies "
                         f"(K, {S}); got shape {arr.shape}")
    if arr.shape[0] < 1:
        raise ValueError("no skills given")
    return np.asarray(greedy_policy(value_iteration(mdp, arr.astype(np.float64)).Q), dtype=np.int64)


def _labels(seqs, lengths, what: str, num_labels=None) -> list:
    seqs = list(seqs)
    if len(seqs) != len(lengths):
        raise ValueError(f"{what} has {len(seqs)} trajectories but the demonstrations have {len(lengths)}")
    out = []
    for i, (seq, n) in enumerate(zip(seqs, lengths)):
        arr = np.asarray(seq)
        if arr.ndim != 1 or len(arr) != n:
            raise ValueError(f"trajectory {i}: {what} has shape {arr.shape} but the demonstration has {n} steps")
        if arr.dtype.kind not in "iu":
            if arr.dtype.kind != "f" or np.any(arr != np.round(arr)):
                raise ValueError(f"trajectory {i}: {what} must be integer skill labels, got dtype {arr.dtype}")
        arr = arr.astype(np.int64)
        bad = (arr < 0) | ((arr >= num_labels) if num_labels is not None else False)
        if np.any(bad):
            t = int(np.argmax(bad))
            allowed = f"0..{num_labels - 1}" if num_labels is not None else "0.."
            raise ValueError(f"trajectory {i}, step {t}: {what} label {arr[t]} is outside {allowed}")
        out.append(arr)
    return out


def replay(mdp, start_states, labels: Sequence[np.ndarray], policies, seed: int = 0):
    """Roll trajectories out acting with policy ``policies[labels[i][t]]`` at step t.

    Args:
        mdp: the TabularMDP.
        start_states: (N,) first state of each trajectory.
        labels: N int arrays, the skill acting at every step (their lengths set the rollouts').
        policies: (K, S) int actions.
        seed: trajectory i uses the uniforms of ``numpy.random.default_rng([seed, i])``.
    Returns:
        states, actions: lists of N int64 arrays of the rollouts.
    """
    lengths = np.array([len(z) for z in labels])
    N, T = len(lengths), int(lengths.max())
    u = np.zeros((N, T))
    for i, n in enumerate(lengths):
        u[i, :n] = np.random.default_rng([int(seed), i]).random(n)
    z = np.zeros((N, T), np.int64)
    for i, seq in enumerate(labels):
        z[i, :len(seq)] = seq
    states = np.zeros((N, T), np.int64)
    actions = np.zeros((N, T), np.int64)
    s = np.asarray(start_states, dtype=np.int64)
    B = mdp.num_successors
    for t in range(T):
        a = policies[z[:, t], s]
        states[:, t], actions[:, t] = s, a
        cdf = np.cumsum(mdp.probs[s, a], -1)  # (N, B)
        idx = np.minimum((cdf < u[:, t, None]).sum(-1), B - 1)  # first slot with cdf >= u
        s = mdp.successors[s, a, idx].astype(np.int64)
    return [states[i, :n] for i, n in enumerate(lengths)], [actions[i, :n] for i, n in enumerate(lengths)]


def evaluate_control(domain, demos, segmentation, skill_rewards, seed: int = 0) -> Dict:
    """Replay every demonstration acting with the inferred skills; score with the true ones.

    Args:
        domain: the Domain (its MDP and true skill rewards).
        demos: Demonstrations with true skills (``demos.skills``).
        segmentation: N int arrays, the inferred skill (0..K-1) of every step.
        skill_rewards: the inferred skills: (K, S, A) reward tables, (K, D) reward weights, or
            (K, S) integer policies (see :func:`skill_policies`).
        seed: the seed of the shared random numbers; use the same one for every method.
    Returns:
        dict with "reward" (mean total true reward per trajectory), "rewards" (N,) the totals,
        "switches" (mean skill switches per trajectory of ``segmentation``), "skills" (the
        number of distinct skills it uses), "states" and "actions" (the rollouts).
    """
    mdp = domain.mdp
    if demos.skills is None:
        raise ValueError("control evaluation scores with the true skills, but the demonstrations carry none")
    demos.validate(mdp)
    lengths = demos.lengths
    true = _labels(demos.skills, lengths, "true skills", domain.num_skills)
    policies = skill_policies(mdp, skill_rewards)
    inferred = _labels(segmentation, lengths, "segmentation", policies.shape[0])
    states, actions = replay(mdp, [s[0] for s in demos.states], inferred, policies, seed)
    true_rewards = domain.rewards()  # (K_true, S, A)
    totals = np.array([true_rewards[k, s, a].sum() for k, s, a in zip(true, states, actions)])
    return {"reward": float(totals.mean()), "rewards": totals,
            "switches": float(np.mean([np.count_nonzero(np.diff(z)) for z in inferred])),
            "skills": int(np.unique(np.concatenate(inferred)).size), "states": states, "actions": actions}


def expert_control(domain, demos, seed: int = 0) -> Dict:
    """:func:`evaluate_control` of the expert: the true segmentation and the true skills' optimal policies."""
    if demos.skills is None:
        raise ValueError("the expert's control needs the true skills, but the demonstrations carry none")
    return evaluate_control(domain, demos, demos.skills, domain.expert_policies(), seed)


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
