"""Experts: tabular Q-learning in an environment (how the paper trained its demonstrators) and
exact policy evaluation on a tabular MDP (how a learned policy is scored against the optimum).
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

from .domain import Domain
from .util.precision import float64_all

__all__ = ["q_learning", "policy_values", "policy_return"]


def _as_env(env_or_domain):
    if isinstance(env_or_domain, Domain):
        return env_or_domain.make_env()
    if not hasattr(env_or_domain, "step") or not hasattr(env_or_domain, "reset"):
        raise ValueError(f"expected a gymnasium environment or a Domain, got {type(env_or_domain).__name__}")
    return env_or_domain


def q_learning(env_or_domain, skill=None, *, num_episodes: int = 4096, episode_length: Optional[int] = None,
               alpha: float = 0.3, epsilon: float = 0.2, num_envs: int = 256, discount: Optional[float] = None,
               seed: int = 0, q0=None) -> np.ndarray:
    """Tabular Q-learning with epsilon-greedy exploration; returns Q (S, A).

    For the npbrs environments (:class:`~npbrs.domains.highway.SkillEnv`) ``num_envs`` copies
    run in lock-step on the environment's own vectorised dynamics (``sample_step``), and each
    step applies one update per visited (state, action) with the mean of its copies' TD errors
    (duplicates would otherwise multiply the step size). Any other gymnasium environment with
    discrete spaces runs one episode at a time through ``reset``/``step`` with its own reward.
    Episodes are truncated, never terminated, so every update bootstraps.

    Args:
        env_or_domain: a gymnasium environment (or ``Domain``, whose environment is made).
        skill: skill name or weight vector (D,) for an npbrs environment; None keeps the
            environment's own reward (for an npbrs environment: the ``skill`` it was made with).
        num_episodes: number of episodes in total (over all copies).
        episode_length: steps per episode; default the environment's ``max_episode_steps``.
        alpha: learning rate.
        epsilon: probability of a uniformly random action.
        num_envs: copies run in parallel (npbrs environments only).
        discount: default the environment's MDP discount (0.95 for other environments).
        seed: seed of the exploration and of the environment.
        q0: optional initial Q (S, A) (zeros by default).
    Returns:
        Q: float array (S, A).
    """
    env = _as_env(env_or_domain)
    base = env.unwrapped
    S, A = int(base.observation_space.n), int(base.action_space.n)
    Q = np.zeros((S, A)) if q0 is None else np.array(q0, dtype=np.float64)
    if Q.shape != (S, A):
        raise ValueError(f"q0 must have shape ({S}, {A}), got {Q.shape}")
    if not (0.0 < alpha <= 1.0):
        raise ValueError(f"alpha must lie in (0, 1], got {alpha}")
    if not (0.0 <= epsilon <= 1.0):
        raise ValueError(f"epsilon must lie in [0, 1], got {epsilon}")
    mdp = getattr(base, "mdp", None)
    gamma = float(discount if discount is not None else (mdp.discount if mdp is not None else 0.95))
    if episode_length is None:
        episode_length = getattr(base, "max_episode_steps", None) or getattr(env.spec, "max_episode_steps", None)
        if episode_length is None:
            raise ValueError("episode_length is required for an environment without max_episode_steps")
    rng = np.random.default_rng(seed)

    def act(states):
        greedy = Q[states]
        # random tie-breaking, so that an untrained row is not always action 0
        best = greedy >= greedy.max(-1, keepdims=True)
        choice = np.argmax(best * rng.random(best.shape), axis=-1)
        explore = rng.random(np.shape(states)) < epsilon
        return np.where(explore, rng.integers(A, size=np.shape(states)), choice)

    if hasattr(base, "sample_step") and mdp is not None:
        w = base.reward_weights if skill is None else base.skill_weights(skill)
        rounds = -(-int(num_episodes) // num_envs)
        for _ in range(rounds):
            states = rng.choice(S, size=num_envs, p=mdp.initial)
            for _ in range(int(episode_length)):
                actions = act(states)
                nxt, feats = base.sample_step(rng, states, actions)
                td = feats @ w + gamma * Q[nxt].max(-1) - Q[states, actions]
                idx = states * A + actions
                total = np.bincount(idx, weights=td, minlength=S * A)
                count = np.bincount(idx, minlength=S * A)
                seen = count > 0
                Q.reshape(-1)[seen] += alpha * total[seen] / count[seen]
                states = nxt
        return Q

    if skill is not None:
        raise ValueError(f"skill can only be given for an npbrs environment, not {type(base).__name__}")
    for episode in range(int(num_episodes)):
        state, _ = env.reset(seed=seed + episode)
        for _ in range(int(episode_length)):
            action = int(act(np.array([state]))[0])
            nxt, reward, terminated, truncated, _ = env.step(action)
            target = reward + (0.0 if terminated else gamma * Q[nxt].max())
            Q[state, action] += alpha * (target - Q[state, action])
            state = nxt
            if terminated or truncated:
                break
    return Q


def _policy_matrix(mdp, policy) -> np.ndarray:
    S, A = mdp.num_states, mdp.num_actions
    policy = np.asarray(policy)
    if policy.shape == (S,):
        if not np.issubdtype(policy.dtype, np.integer) or policy.min() < 0 or policy.max() >= A:
            raise ValueError(f"a deterministic policy must hold actions in 0..{A - 1}")
        return np.eye(A)[policy]
    if policy.shape == (S, A):
        pi = policy.astype(np.float64)
        if np.any(pi < 0) or np.any(np.abs(pi.sum(-1) - 1.0) > 1e-6):
            s = int(np.argmax((pi < 0).any(-1) | (np.abs(pi.sum(-1) - 1.0) > 1e-6)))
            raise ValueError(f"policy row of state {s} is not a probability distribution")
        return pi
    raise ValueError(f"policy must have shape ({S},) or ({S}, {A}), got {policy.shape}")


def policy_values(mdp, reward, policy) -> np.ndarray:
    """Exact state values V_pi (S,) of a policy: the solution of V = r_pi + gamma * P_pi V.

    Args:
        mdp: the TabularMDP.
        reward: (S, A) reward table.
        policy: (S,) actions or (S, A) action probabilities.
    Returns:
        V: float array (S,).
    """
    S, A, B = mdp.successors.shape
    reward = np.asarray(reward, dtype=np.float64)
    if reward.shape != (S, A):
        raise ValueError(f"reward must have shape ({S}, {A}), got {reward.shape}")
    pi = _policy_matrix(mdp, policy)
    r_pi = (pi * reward).sum(-1)
    weights = pi[:, :, None] * mdp.probs  # (S, A, B)
    rows = np.broadcast_to(np.arange(S)[:, None, None], (S, A, B))
    keep = weights > 0
    P = sp.csr_matrix((weights[keep], (rows[keep], mdp.successors[keep])), shape=(S, S))
    return spsolve((sp.identity(S, format="csr") - mdp.discount * P).tocsc(), r_pi)


def policy_return(mdp, reward, policy) -> float:
    """Expected discounted return of a policy from the MDP's initial distribution (exact)."""
    return float(mdp.initial @ policy_values(mdp, reward, policy))


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
