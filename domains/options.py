"""Skills as options (Sutton, Precup and Singh 1999): an initiation set, a policy and a
termination probability per state, estimated from segmented demonstrations.

How the estimates are made, for skill k of a segmentation z of demonstrations (s_t, a_t):

- **Initiation set**: the states in which skill k's segments start or run, {s_t : z_t = k}.
- **Termination**: an option is asked whether to stop each time it arrives in a state. Every
  step t >= 1 with z_{t-1} = k is one arrival of skill k in s_t: it *terminated* there when
  z_t != k and *continued* when z_t = k (a trajectory's last step ends the recording, not the
  skill, and counts as neither). With n_stop(s) and n_go(s) those counts, the estimate is the
  posterior mean under a Beta(c r, c (1 - r)) prior,

      beta_k(s) = (n_stop(s) + c r) / (n_stop(s) + n_go(s) + c),

  where r = (sum_s n_stop(s) + 1) / (sum_s (n_stop(s) + n_go(s)) + 2) is skill k's termination
  rate over all its arrivals (Laplace-smoothed, so an option seen only to go on still stops
  somewhere) and c = ``prior_strength`` pseudo-arrivals: a state the skill was never seen to
  reach terminates at the skill's average rate, and the counts take over as they grow.
- **Policy**: given by the caller, the Boltzmann policy pi_k(a | s) (K, S, A) the model
  assigns the skill, and the greedy (optimal) policy (K, S) of its reward.

:func:`run_option` executes an option in a gymnasium environment whose observations are state
indices (``Discrete(S)``), until it terminates, the episode ends, or a step limit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, NamedTuple, Optional, Sequence

import jax.numpy as jnp
import numpy as np

from .util.precision import float64_all

__all__ = ["Option", "OptionRun", "estimate_options", "termination_counts", "arrival_counts", "run_option"]


@dataclass(frozen=True, eq=False)
class Option:
    """One skill as an option over the states of a tabular MDP.

    Attributes:
        skill: the skill's index (as in the segmentation it was estimated from).
        initiation: (S,) bool, the states where the option may start.
        termination: (S,) float, beta(s): the probability of stopping on arriving in s.
        policy: (S, A) float, the skill's (Boltzmann) action probabilities.
        greedy: (S,) int, the skill's optimal action in every state.
        stops, goes: (S,) the arrivals in each state after which the skill stopped / went on.
    """

    skill: int
    initiation: np.ndarray
    termination: np.ndarray
    policy: np.ndarray
    greedy: np.ndarray
    stops: np.ndarray
    goes: np.ndarray

    @property
    def num_states(self) -> int:
        return int(self.initiation.shape[0])

    def _state(self, state) -> int:
        s = int(state)
        if not 0 <= s < self.num_states:
            raise ValueError(f"state {state} is outside 0..{self.num_states - 1}")
        return s

    def can_start(self, state) -> bool:
        """Whether ``state`` is in the initiation set."""
        return bool(self.initiation[self._state(state)])

    def act(self, state, rng: np.random.Generator, greedy: bool = False) -> int:
        """An action in ``state``: the optimal one with ``greedy``, else drawn from the policy."""
        s = self._state(state)
        if greedy:
            return int(self.greedy[s])
        return int(rng.choice(self.policy.shape[1], p=self.policy[s]))

    def terminates(self, state, rng: np.random.Generator) -> bool:
        """Draw whether the option stops on arriving in ``state``."""
        return bool(rng.random() < self.termination[self._state(state)])


def arrival_counts(labels, states, mask, num_states: int, num_skills: int):
    """(stops, goes), each (K, S): how often a step of skill k was followed by another skill
    (the skill stopped) or by k again (it went on), counted in the state arrived in (see the
    module). labels, states: (N, T) int arrays; mask: (N, T) bool, the steps that count (a step
    t >= 1 counts when it and step t - 1 are both in the mask). Works on NumPy or JAX arrays,
    inside ``jit`` too: the sampler's conditional of state-dependent ends
    (:func:`npbrs.models.bphmm.end_counts`) counts with it."""
    K, S = num_skills, num_states
    prev, now = labels[:, :-1], labels[:, 1:]
    real = mask[:, 1:] & mask[:, :-1]
    index = (jnp.clip(prev, 0, K - 1) * S + jnp.clip(states[:, 1:], 0, S - 1)).ravel()
    stopped = (real & (now != prev)).astype(jnp.float64).ravel()
    went = (real & (now == prev)).astype(jnp.float64).ravel()
    stops = jnp.zeros(K * S).at[index].add(stopped).reshape(K, S)
    goes = jnp.zeros(K * S).at[index].add(went).reshape(K, S)
    return stops, goes


def termination_counts(states: Sequence[np.ndarray], labels: Sequence[np.ndarray], num_states: int,
                       num_skills: int):
    """Arrival counts of every skill in every state: (stops, goes), each (K, S) (see the module),
    for ragged trajectories: per trajectory, its states and skill labels."""
    states, labels = list(states), list(labels)
    for i, (s, z) in enumerate(zip(states, labels)):
        if np.shape(s) != np.shape(z):
            raise ValueError(f"trajectory {i}: {len(s)} states but {len(z)} skill labels")
    N, T = len(states), max([len(s) for s in states], default=1)
    padded_states, padded_labels, mask = np.zeros((N, T), np.int64), np.zeros((N, T), np.int64), np.zeros((N, T), bool)
    for i, (s, z) in enumerate(zip(states, labels)):
        padded_states[i, :len(s)], padded_labels[i, :len(z)], mask[i, :len(s)] = s, z, True
    stops, goes = arrival_counts(padded_labels, padded_states, mask, num_states, num_skills)
    return np.asarray(stops), np.asarray(goes)


def estimate_options(states: Sequence[np.ndarray], labels: Sequence[np.ndarray], policies, greedy,
                     prior_strength: float = 2.0) -> List[Option]:
    """One option per skill from segmented demonstrations (estimates as in the module docstring).

    Args:
        states: per trajectory, the visited states (int arrays).
        labels: per trajectory, the skill (0..K-1) of every step.
        policies: (K, S, A) action probabilities of the skills (rows sum to one).
        greedy: (K, S) int optimal actions of the skills.
        prior_strength: c, the prior's pseudo-arrivals per state (> 0).
    Returns:
        K :class:`Option` objects, option k for skill k.
    """
    policies = np.asarray(policies, dtype=np.float64)
    greedy = np.asarray(greedy)
    if policies.ndim != 3:
        raise ValueError(f"policies must have shape (K, S, A), got {policies.shape}")
    K, S, A = policies.shape
    if greedy.shape != (K, S):
        raise ValueError(f"greedy policies must have shape ({K}, {S}), got {greedy.shape}")
    if not np.allclose(policies.sum(-1), 1.0, atol=1e-6) or np.any(policies < 0):
        k, s = (int(i) for i in np.argwhere(~np.isclose(policies.sum(-1), 1.0, atol=1e-6) |
                                             np.any(policies < 0, -1))[0])
        raise ValueError(f"skill {k}, state {s}: action probabilities do not sum to one")
    if not (np.isfinite(prior_strength) and prior_strength > 0):
        raise ValueError(f"prior_strength must be a positive number, got {prior_strength!r}")
    states, labels = list(states), list(labels)
    if len(states) != len(labels):
        raise ValueError(f"{len(states)} trajectories of states but {len(labels)} of skill labels")
    for i, (s, z) in enumerate(zip(states, labels)):
        s, z = np.asarray(s), np.asarray(z)
        if s.size and (s.min() < 0 or s.max() >= S):
            raise ValueError(f"trajectory {i}: state {int(s[(s < 0) | (s >= S)][0])} is outside 0..{S - 1}")
        if z.size and (z.min() < 0 or z.max() >= K):
            raise ValueError(f"trajectory {i}: skill label {int(z[(z < 0) | (z >= K)][0])} is outside 0..{K - 1}")
    stops, goes = termination_counts(states, labels, S, K)
    initiation = np.zeros((K, S), bool)
    for s, z in zip(states, labels):
        initiation[np.asarray(z, np.int64), np.asarray(s, np.int64)] = True
    arrivals = stops + goes
    total = arrivals.sum(-1)
    rate = (stops.sum(-1) + 1.0) / (total + 2.0)  # (K,)
    c = float(prior_strength)
    beta = (stops + c * rate[:, None]) / (arrivals + c)
    return [Option(skill=k, initiation=initiation[k], termination=beta[k], policy=policies[k],
                   greedy=greedy[k].astype(np.int64), stops=stops[k], goes=goes[k]) for k in range(K)]


class OptionRun(NamedTuple):
    """What :func:`run_option` did: the states it acted in, its actions and rewards, the state
    it ended in, and why it ended ("terminated": the option stopped; "episode": the
    environment ended the episode; "max_steps": the step limit)."""

    states: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    final_state: int
    reason: str


def run_option(env, option: Option, *, state=None, seed: Optional[int] = None, greedy: bool = False,
               max_steps: int = 1000) -> OptionRun:
    """Run an option in a gymnasium environment until it terminates.

    Args:
        env: a gymnasium environment whose observations are state indices of the option's MDP.
        option: the :class:`Option`.
        state: the environment's current state, when it is already running; None resets it
            (``env.reset(seed=seed)``).
        seed: seeds the reset (when ``state`` is None) and the option's own draws.
        greedy: act with the optimal action instead of drawing from the policy.
        max_steps: the most steps taken.
    Returns:
        :class:`OptionRun`.
    Raises:
        ValueError: the start state is outside the option's initiation set, or the
            environment's observations are not state indices of the option's MDP.
    """
    if int(max_steps) < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}")
    n = getattr(getattr(env, "observation_space", None), "n", None)
    if n is None or int(n) != option.num_states:
        raise ValueError(f"the environment's observations must be the {option.num_states} state indices of the "
                         f"option's MDP (a Discrete({option.num_states}) space), got {getattr(env, 'observation_space', None)}")
    rng = np.random.default_rng(seed)
    if state is None:
        state, _ = env.reset(seed=seed)
    state = int(state)
    if not option.can_start(state):
        raise ValueError(f"state {state} is outside the initiation set of the option of skill {option.skill}")
    states, actions, rewards = [], [], []
    reason = "max_steps"
    for _ in range(int(max_steps)):
        action = option.act(state, rng, greedy)
        nxt, reward, terminated, truncated, _ = env.step(action)
        states.append(state)
        actions.append(action)
        rewards.append(float(reward))
        state = int(nxt)
        if terminated or truncated:
            reason = "episode"
            break
        if option.terminates(state, rng):
            reason = "terminated"
            break
    return OptionRun(np.asarray(states, np.int64), np.asarray(actions, np.int64), np.asarray(rewards),
                     state, reason)


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
