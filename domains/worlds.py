"""Worlds that look like what researchers bring: tabular state rewards, many trajectories, noisy
experts and skill switching that depends on where the agent is, with their generating model and
an oracle.

Three generators, each ``f(seed, **sizes) -> World`` (the same seed gives the same data):

- :func:`tabular_grid`: a small gridworld (5 x 5, actions up, down, left, right, stay) with a
  reward per state and 2-3 modes, each seeking its own corner region; 200 trajectories x 500
  steps; about 5% switching per step, and a mode tends to end once its goal region is reached
  (the switching probability there is ``goal_factor`` times what it is elsewhere), as in the
  published switching-IRL gridworld benchmark and in real behaviour.
- :func:`labyrinth`: a binary-tree labyrinth of depth 6 (63 junctions, 64 end nodes; actions
  left child, right child, back to the parent, stay), 200 trajectories of 15-25 steps from the
  entrance, skills explore, go to the water port and go home, whose ends depend on reaching the
  port or the entrance, as in the mouse labyrinth data.
- :func:`rooms`: the four-room gridworld with 5 goal-seeking skills; each trajectory uses its
  own 2 or 3 of them (the beta process's setting), sticky switching, ragged lengths.

Every world uses one-hot state features (a reward weight per state: what a new user without
features has), and its experts act by the Boltzmann policy of their skill's reward scaled by an
inverse temperature, pi_k(a | s) = exp(Q_k(s, a) - V_k(s)) with the soft Q-function of
``inverse_temperature * reward`` (the library's soft value iteration): exactly the reward
emission's model, with weights ``domain.skill_weights``.

The generating model (:class:`SkillProcess`): a trajectory draws its skill set m (for the
first two worlds, always all skills), its first state from ``mdp.initial``, its first skill from
``initial_skill[m]``; at step t the agent in state s_t with skill z_t acts a_t ~ pi_{z_t}(. | s_t)
and moves to s_{t+1} ~ P(. | s_t, a_t); then the skill of step t + 1 is drawn from
``transitions[m, s_{t+1}, z_t]``, which may depend on the state just entered. Trajectory lengths
are drawn independently of everything else.

The oracle (:meth:`World.oracle`): the generating model's held-out log-likelihood per step (the
actions given the states, the skill set and skill sequence summed out by the forward algorithm;
the state dynamics are the same under every model and drop out, as in
``FitResult.log_predictive``) and its Viterbi segmentation's accuracy on the training set; and
the same for the true policies under state-independent (sticky) switching, the BP-HMM's own
kind, which bounds what a fit of it can reach where the truth's switching depends on the state. It is
computed here in NumPy because the library's HMM routines (``npbrs.models.hmm``) take one
transition matrix per trajectory, not one per state, and ``domains`` imports nothing from
``models``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from itertools import combinations
from typing import Dict, List, NamedTuple, Sequence

import numpy as np

from .demos import Demonstrations
from .domain import Domain
from .mdp import TabularMDP, set_frozen
from .util.precision import float64_all

__all__ = ["World", "SkillProcess", "Oracle", "tabular_grid", "labyrinth", "rooms", "grid_mdp", "labyrinth_mdp",
           "rooms_mdp", "WORLDS"]

GRID_ACTIONS = ("up", "down", "left", "right", "stay")
_GRID_MOVES = ((-1, 0), (1, 0), (0, -1), (0, 1), (0, 0))
LABYRINTH_ACTIONS = ("left", "right", "back", "stay")


# ------------------------------------------------------------------------------- arguments
def _int(name: str, value, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be at least {minimum}, got {value}")
    return int(value)


def _real(name: str, value, low: float, high: float = math.inf, *, open_low: bool = False,
          open_high: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    value = float(value)
    ok = (math.isfinite(value) and (value > low if open_low else value >= low)
          and (value < high if open_high else value <= high))
    if not ok:
        interval = f"{'(' if open_low else '['}{low:g}, {high:g}{')' if open_high else ']'}"
        raise ValueError(f"{name} must lie in {interval}, got {value!r}")
    return value


def _seed(seed) -> np.random.Generator:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    return np.random.default_rng(int(seed))


def _lengths(rng, n: int, low: int, high: int) -> np.ndarray:
    return rng.integers(low, high + 1, size=n)


# ------------------------------------------------------------------------ the generating model
def _categorical(rng: np.random.Generator, probs: np.ndarray) -> np.ndarray:
    """One draw per row of probs (n, C); never an entry of probability 0."""
    cum = np.cumsum(probs, axis=-1)
    u = rng.random(probs.shape[0]) * cum[:, -1]
    return np.argmax(cum > u[:, None], axis=-1)


class Oracle(NamedTuple):
    """What the true generating model achieves.

    heldout_ll: held-out log-likelihood per step (nats; the sum over held-out trajectories of
    log p(actions | states) over their total steps); heldout_ll_per_trajectory: (n,);
    train_ll: the same per step on the training set; viterbi: per training trajectory the most
    probable skill sequence (jointly with the skill set); viterbi_accuracy: the fraction of
    training steps where it equals the true skill.

    sticky_heldout_ll, sticky_viterbi_accuracy: the same for the generating model with its
    switching made independent of the state (:meth:`SkillProcess.state_independent`, fitted to
    the training set's true skills): the true policies under a sticky HMM, about the best the
    BP-HMM (whose switching never depends on the state) can reach. Where the truth's switching
    depends on the state (the labyrinth, the tabular grid), the gap between the two held-out
    log-likelihoods is what no fit of the BP-HMM can close.
    """

    heldout_ll: float
    heldout_ll_per_trajectory: np.ndarray
    train_ll: float
    viterbi: List[np.ndarray]
    viterbi_accuracy: float
    sticky_heldout_ll: float = math.nan
    sticky_viterbi_accuracy: float = math.nan


@dataclass(frozen=True, eq=False)
class SkillProcess:
    """The true generating model of a world's skills (see the module docstring).

    Attributes:
        log_policies: (K, S, A) the experts' log-policies log pi_k(a | s).
        skill_sets: (M, K) bool, the skill sets a trajectory may use.
        skill_set_probs: (M,) their probabilities.
        initial_skill: (M, K) the first skill's distribution given the set (0 outside it).
        transitions: (M, S or 1, K, K), ``transitions[m, s, k, j]`` the probability that the
            skill after k is j when the agent has just entered state s (a state axis of size 1:
            switching that does not depend on the state); rows of skills outside the set are
            not used.
        skill_names: K names.
    """

    log_policies: np.ndarray
    skill_sets: np.ndarray
    skill_set_probs: np.ndarray
    initial_skill: np.ndarray
    transitions: np.ndarray
    skill_names: tuple = ()

    def __post_init__(self):
        lp = np.asarray(self.log_policies, dtype=np.float64)
        if lp.ndim != 3 or not np.allclose(np.exp(lp).sum(-1), 1.0, atol=1e-8):
            raise ValueError("log_policies must be (K, S, A) log-probabilities normalised over actions")
        K, S, _ = lp.shape
        sets = np.asarray(self.skill_sets, dtype=bool)
        M = sets.shape[0] if sets.ndim == 2 else -1
        if sets.shape != (M, K) or M < 1 or not np.all(sets.any(-1)):
            raise ValueError(f"skill_sets must be (M, {K}) booleans, each set non-empty")
        set_p = np.asarray(self.skill_set_probs, dtype=np.float64)
        if set_p.shape != (M,) or np.any(set_p < 0) or abs(set_p.sum() - 1) > 1e-9:
            raise ValueError(f"skill_set_probs must be ({M},) probabilities summing to 1")
        init = np.asarray(self.initial_skill, dtype=np.float64)
        if init.shape != (M, K) or np.any(init < 0) or np.any(init[~sets] > 0) or \
                not np.allclose(init.sum(-1), 1.0, atol=1e-9):
            raise ValueError(f"initial_skill must be (M, K) = ({M}, {K}) probabilities within each skill set")
        trans = np.asarray(self.transitions, dtype=np.float64)
        if trans.ndim != 4 or trans.shape[0] != M or trans.shape[1] not in (1, S) or trans.shape[2:] != (K, K):
            raise ValueError(f"transitions must have shape ({M}, {S} or 1, {K}, {K}), got {trans.shape}")
        for m in range(M):
            rows = trans[m][:, sets[m]]  # the rows of the set's skills, (S or 1, |set|, K)
            if np.any(rows < 0) or not np.allclose(rows.sum(-1), 1.0, atol=1e-9) or np.any(rows[..., ~sets[m]] > 0):
                raise ValueError(f"transitions[{m}]: each skill's row must be probabilities over the skills of "
                                 "its set")
        names = tuple(self.skill_names) if len(self.skill_names) else tuple(str(k) for k in range(K))
        if len(names) != K:
            raise ValueError(f"skill_names has {len(names)} names for {K} skills")
        set_frozen(self, log_policies=lp, skill_sets=sets, skill_set_probs=set_p, initial_skill=init,
                   transitions=trans, skill_names=names)

    @property
    def num_skills(self) -> int:
        return self.log_policies.shape[0]

    def _trans_at(self, m: np.ndarray, s: np.ndarray) -> np.ndarray:
        """(n, K, K) transition matrices of trajectories in sets m (n,) entering states s (n,)."""
        return self.transitions[m, s if self.transitions.shape[1] > 1 else 0]

    def state_independent(self, demos: Demonstrations, prior: float = 1e-3) -> "SkillProcess":
        """This model with switching that does not depend on the state: the transitions k -> j
        counted over ``demos``'s true skills (all sets pooled; ``prior``: a pseudo-count added
        to every count), restricted to each skill set and renormalised within it. Policies,
        skill sets and initial skills are kept. With many demonstrations from a model whose
        switching is already state-independent and the same for every set, it returns that
        model (up to sampling error)."""
        if demos.skills is None:
            raise ValueError("state_independent: the demonstrations have no true skills")
        K = self.num_skills
        prior = _real("prior", prior, 0.0, open_low=True)
        counts = np.zeros((K, K))
        for i, z in enumerate(demos.skills):
            z = np.asarray(z)
            if z.size and (z.min() < 0 or z.max() >= K):
                raise ValueError(f"state_independent: trajectory {i}'s skills are outside 0..{K - 1}")
            np.add.at(counts, (z[:-1], z[1:]), 1.0)
        within = (counts + prior)[None] * self.skill_sets[:, None, :]  # (M, K, K)
        trans = within / within.sum(-1, keepdims=True)
        return SkillProcess(log_policies=self.log_policies, skill_sets=self.skill_sets,
                            skill_set_probs=self.skill_set_probs, initial_skill=self.initial_skill,
                            transitions=trans[:, None], skill_names=self.skill_names)

    # ----------------------------------------------------------------------- sampling
    def sample(self, mdp: TabularMDP, lengths: Sequence[int], rng: np.random.Generator) -> Demonstrations:
        """Demonstrations of the given lengths, with their true skills."""
        lengths = np.asarray(lengths, dtype=np.int64)
        N, T = len(lengths), int(lengths.max())
        policies = np.exp(self.log_policies)
        states, actions, skills = (np.empty((N, T), dtype=np.int64) for _ in range(3))
        m = rng.choice(len(self.skill_set_probs), size=N, p=self.skill_set_probs)
        s = rng.choice(mdp.num_states, size=N, p=mdp.initial)
        k = _categorical(rng, self.initial_skill[m])
        for t in range(T):
            states[:, t], skills[:, t] = s, k
            a = _categorical(rng, policies[k, s])
            actions[:, t] = a
            if t + 1 < T:
                s = mdp.sample_next(rng, s, a)
                k = _categorical(rng, self._trans_at(m, s)[np.arange(N), k])
        cut = [slice(0, int(n)) for n in lengths]
        return Demonstrations([r[c] for r, c in zip(states, cut)], [r[c] for r, c in zip(actions, cut)],
                              [r[c] for r, c in zip(skills, cut)], mdp_fingerprint=mdp.fingerprint())

    # ------------------------------------------------------------------------ scoring
    def _emissions(self, demos: Demonstrations):
        states, actions, mask = demos.padded()
        log_emit = np.moveaxis(self.log_policies[:, states, actions], 0, -1)  # (N, T, K)
        return states, mask, log_emit

    def set_log_likelihoods(self, demos: Demonstrations) -> np.ndarray:
        """(N, M) log p(actions | states, skill set m) of every trajectory, the skill sequence
        summed out by the forward algorithm (scaled, in probability space)."""
        states, mask, log_emit = self._emissions(demos)
        N, T, _ = log_emit.shape
        M = len(self.skill_set_probs)
        shift = log_emit.max(-1, keepdims=True)  # per-step scaling keeps exp() in range
        emit = np.exp(log_emit - shift)
        m = np.broadcast_to(np.arange(M), (N, M))
        alpha = self.initial_skill[None] * emit[:, 0, None, :]  # (N, M, K)
        c = alpha.sum(-1)
        loglik = np.log(c) + shift[:, 0]
        alpha = alpha / c[..., None]
        for t in range(1, T):
            trans = self._trans_at(m, np.broadcast_to(states[:, t, None], (N, M)))  # (N, M, K, K)
            new = np.einsum("nmk,nmkj->nmj", alpha, trans) * emit[:, t, None, :]
            c = new.sum(-1)
            live = mask[:, t, None]
            loglik = np.where(live, loglik + np.log(np.where(live, c, 1.0)) + shift[:, t], loglik)
            alpha = np.where(live[..., None], new / np.where(live, c, 1.0)[..., None], alpha)
        return loglik

    def log_likelihoods(self, demos: Demonstrations) -> np.ndarray:
        """(N,) log p(actions | states) of every trajectory under the generating model."""
        with np.errstate(divide="ignore"):
            log_set = np.log(self.skill_set_probs)
        joint = self.set_log_likelihoods(demos) + log_set
        top = joint.max(-1)
        return top + np.log(np.exp(joint - top[:, None]).sum(-1))

    def log_likelihood_per_step(self, demos: Demonstrations) -> float:
        """Sum of :meth:`log_likelihoods` over the total number of steps (nats per step)."""
        return float(self.log_likelihoods(demos).sum() / demos.num_steps)

    def viterbi(self, demos: Demonstrations) -> List[np.ndarray]:
        """Per trajectory the most probable skill sequence, maximised jointly with the skill set."""
        states, mask, log_emit = self._emissions(demos)
        N, T, K = log_emit.shape
        M = len(self.skill_set_probs)
        with np.errstate(divide="ignore"):
            log_init, log_trans, log_set = (np.log(x) for x in
                                            (self.initial_skill, self.transitions, self.skill_set_probs))
        m = np.broadcast_to(np.arange(M), (N, M))
        delta = log_set[None, :, None] + log_init[None] + log_emit[:, 0, None, :]  # (N, M, K)
        back = np.empty((T, N, M, K), dtype=np.int64)
        back[0] = np.arange(K)
        for t in range(1, T):
            s = np.broadcast_to(states[:, t, None], (N, M))
            scores = delta[..., :, None] + log_trans[m, s if log_trans.shape[1] > 1 else 0]  # (N, M, K, K)
            best = scores.argmax(-2)
            live = mask[:, t, None, None]
            back[t] = np.where(live, best, np.arange(K))
            delta = np.where(live, np.take_along_axis(scores, best[..., None, :], -2)[..., 0, :]
                             + log_emit[:, t, None, :], delta)
        flat = delta.reshape(N, M * K).argmax(-1)
        mm, z = flat // K, flat % K
        path = np.empty((N, T), dtype=np.int64)
        for t in range(T - 1, -1, -1):
            path[:, t] = z
            z = back[t, np.arange(N), mm, z]
        return [path[i, :n] for i, n in enumerate(demos.lengths)]


# -------------------------------------------------------------------------------- the world
@dataclass(frozen=True, eq=False)
class World:
    """A generated world: its truth and its data.

    Attributes:
        name: "tabular_grid", "labyrinth" or "rooms".
        domain: the :class:`~npbrs.domains.domain.Domain`: the MDP (one-hot state features),
            the skill names and their reward weights (the inverse temperature folded in, so the
            reward emission with temperature 1 holds the truth exactly).
        demos: the training demonstrations, with true skills.
        heldout: held-out demonstrations from the same process (with true skills).
        model: the true generating :class:`SkillProcess`.
        params: the arguments the world was generated with, and derived values (e.g. the
            calibrated switching probabilities of the tabular grid).
    """

    name: str
    domain: Domain
    demos: Demonstrations
    heldout: Demonstrations
    model: SkillProcess
    params: Dict = field(default_factory=dict)

    @property
    def mdp(self) -> TabularMDP:
        return self.domain.mdp

    def oracle(self) -> Oracle:
        """The generating model's held-out log-likelihood per step and Viterbi accuracy."""
        held = self.model.log_likelihoods(self.heldout)
        path = self.model.viterbi(self.demos)
        truth = np.concatenate(self.demos.skills)
        accuracy = float(np.mean(np.concatenate(path) == truth))
        sticky = self.model.state_independent(self.demos)
        sticky_path = np.concatenate(sticky.viterbi(self.demos))
        return Oracle(heldout_ll=float(held.sum() / self.heldout.num_steps), heldout_ll_per_trajectory=held,
                      train_ll=self.model.log_likelihood_per_step(self.demos), viterbi=path,
                      viterbi_accuracy=accuracy, sticky_heldout_ll=sticky.log_likelihood_per_step(self.heldout),
                      sticky_viterbi_accuracy=float(np.mean(sticky_path == truth)))

    def __repr__(self):
        return (f"World({self.name!r}, {self.mdp.num_states} states, {self.model.num_skills} skills, "
                f"{self.demos!r}, heldout={self.heldout.num_trajectories})")


def _expert_log_policies(mdp: TabularMDP, weights: np.ndarray) -> np.ndarray:
    """(K, S, A) Boltzmann log-policies of the rewards phi . weights (the soft Q-functions)."""
    from .solvers import boltzmann_log_policy, soft_value_iteration

    solved = soft_value_iteration(mdp, mdp.reward(weights), method="vi", tol=1e-10)
    return np.asarray(boltzmann_log_policy(solved.Q), dtype=np.float64)


def _world(name, rng, mdp, skill_names, weights, process_parts, train_lengths, heldout_lengths, params,
           describe_state=None) -> World:
    domain = Domain(name=name, mdp=mdp, skill_names=skill_names, skill_weights=weights,
                    describe_state=describe_state)
    model = SkillProcess(log_policies=_expert_log_policies(mdp, weights), skill_names=tuple(skill_names),
                         **process_parts)
    demos = model.sample(mdp, train_lengths, rng)
    heldout = model.sample(mdp, heldout_lengths, rng)
    return World(name=name, domain=domain, demos=demos, heldout=heldout, model=model, params=params)


def _one_set(K: int, initial: np.ndarray, transitions: np.ndarray) -> dict:
    return {"skill_sets": np.ones((1, K), dtype=bool), "skill_set_probs": np.ones(1),
            "initial_skill": initial[None], "transitions": transitions[None]}


def _ending_transitions(end: np.ndarray, next_skill: np.ndarray) -> np.ndarray:
    """(S, K, K) transitions from each skill's end probability in each state entered, end (K, S),
    and the distribution of the skill after an end, next_skill (K, K) (zero diagonal)."""
    K = end.shape[0]
    e = end.T[:, :, None]  # (S, K, 1)
    return (1.0 - e) * np.eye(K)[None] + e * next_skill[None]


# ------------------------------------------------------------------------------- gridworlds
def _grid_dense(free: np.ndarray, slip: float) -> np.ndarray:
    """(S, 5, S) moves on the free cells of a grid (row-major order); a move into a wall or off
    the grid stays; with probability ``slip`` the move is a uniformly random one instead."""
    H, W = free.shape
    index = -np.ones((H, W), dtype=np.int64)
    cells = np.argwhere(free)
    index[free] = np.arange(len(cells))
    S, A = len(cells), len(_GRID_MOVES)
    P = np.zeros((S, A, S))
    for s, (r, c) in enumerate(cells):
        for b, (dr, dc) in enumerate(_GRID_MOVES):
            r2, c2 = r + dr, c + dc
            target = index[r2, c2] if 0 <= r2 < H and 0 <= c2 < W and free[r2, c2] else s
            for a in range(A):
                P[s, a, target] += (1.0 - slip) * (a == b) + slip / A
    return P


def grid_mdp(size: int = 5, slip: float = 0.0, discount: float = 0.9) -> TabularMDP:
    """An open size x size gridworld: actions up, down, left, right, stay; one-hot state
    features; a uniform initial state. State s is cell (s // size, s % size)."""
    size = _int("size", size, 2)
    slip = _real("slip", slip, 0.0, 1.0)
    discount = _real("discount", discount, 0.0, 1.0, open_high=True)
    free = np.ones((size, size), dtype=bool)
    cells = np.argwhere(free).astype(np.float64)
    return TabularMDP.from_dense(_grid_dense(free, slip), discount=discount, name=f"grid{size}x{size}",
                                 state_vectors=cells)


def _corner_regions(size: int, goal_size: int) -> List[np.ndarray]:
    """Cells (row, col) of goal_size x goal_size blocks in the corners: top-left, bottom-right,
    top-right, bottom-left."""
    lo, hi = range(goal_size), range(size - goal_size, size)
    return [np.array([(r, c) for r in rows for c in cols]) for rows, cols in
            ((lo, lo), (hi, hi), (lo, hi), (hi, lo))]


def _switch_rate(step: np.ndarray, p0: np.ndarray, end: np.ndarray, length: int) -> float:
    """Expected switches per step transition of a length-``length`` trajectory whose skill ends
    with probability end[k, s'] on entering s' and then becomes one of the others uniformly:
    the joint chain over (skill, state) propagated exactly. step (K, S, S): state transitions
    under skill k's policy; p0 (K, S): the first step's joint distribution."""
    K = end.shape[0]
    p, total = p0, 0.0
    for _ in range(length - 1):
        q = np.einsum("ks,kst->kt", p, step)
        moved = q * end
        total += moved.sum()
        p = q - moved + (moved.sum(0, keepdims=True) - moved) / (K - 1)
    return total / (length - 1)


def tabular_grid(seed: int = 0, *, size: int = 5, num_modes: int = 2, num_trajectories: int = 200,
                 length: int = 500, num_heldout: int = 50, switch_rate: float = 0.05, goal_factor: float = 10.0,
                 goal_size: int = 2, goal_reward: float = 1.0, inverse_temperature: float = 3.0,
                 slip: float = 0.0, discount: float = 0.9) -> World:
    """A gridworld with tabular state rewards and modes that end at their goals.

    Mode k's reward is ``goal_reward`` on a goal_size x goal_size block in a corner (top-left,
    bottom-right, top-right, bottom-left, in that order) and 0 elsewhere. A trajectory starts in
    a uniformly random cell with a uniformly random mode; on entering a cell, the current mode
    ends with probability q_k(s) = min(1, goal_factor * q) in its own goal block and q elsewhere,
    and the next mode is one of the others, uniformly. q is calibrated so that the expected
    number of switches per step transition of a trajectory of ``length`` steps is
    ``switch_rate`` (``world.params["switch_elsewhere"]`` and ``["switch_at_goal"]``).

    Args:
        seed: the seed; the same seed gives the same world and data.
        size: grid side; num_modes: 2, 3 or 4 modes.
        num_trajectories, length: training demonstrations (all of ``length`` steps).
        num_heldout: held-out trajectories (also of ``length`` steps).
        switch_rate: expected switches per step transition, in (0, 1).
        goal_factor: how much likelier a mode ends in its goal block than elsewhere (>= 1).
        goal_size: side of the goal blocks (at most size // 2, so that they do not overlap).
        goal_reward: the reward of a goal cell; inverse_temperature: the experts' beta.
        slip: probability that a move is a uniformly random one; discount: gamma.
    Returns:
        a :class:`World`.
    """
    rng = _seed(seed)
    size = _int("size", size, 2)
    num_modes = _int("num_modes", num_modes, 2)
    if num_modes > 4:
        raise ValueError(f"num_modes must be 2, 3 or 4 (one per corner), got {num_modes}")
    num_trajectories = _int("num_trajectories", num_trajectories, 1)
    length = _int("length", length, 2)
    num_heldout = _int("num_heldout", num_heldout, 1)
    switch_rate = _real("switch_rate", switch_rate, 0.0, 1.0, open_low=True, open_high=True)
    goal_factor = _real("goal_factor", goal_factor, 1.0)
    goal_size = _int("goal_size", goal_size, 1)
    if goal_size > size // 2:
        raise ValueError(f"goal_size must be at most size // 2 = {size // 2} so that the corner blocks do not "
                         f"overlap, got {goal_size}")
    goal_reward = _real("goal_reward", goal_reward, 0.0, open_low=True)
    beta = _real("inverse_temperature", inverse_temperature, 0.0, open_low=True)
    mdp = grid_mdp(size, slip=slip, discount=discount)
    S, K = mdp.num_states, num_modes
    goal = np.zeros((K, S), dtype=bool)
    for k, cells in enumerate(_corner_regions(size, goal_size)[:K]):
        goal[k, cells[:, 0] * size + cells[:, 1]] = True
    weights = beta * goal_reward * goal.astype(np.float64)
    log_pi = _expert_log_policies(mdp, weights)
    step = np.einsum("ksa,sat->kst", np.exp(log_pi), mdp.dense_transitions())
    p0 = np.full((K, S), 1.0 / (K * S))

    def ends(q):
        return np.where(goal, min(1.0, goal_factor * q), q)

    # the rate rises with q: bisect on it (q = 1 switches at every step)
    lo, hi = 0.0, 1.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if _switch_rate(step, p0, ends(mid), length) < switch_rate else (lo, mid)
    q = 0.5 * (lo + hi)
    achieved = _switch_rate(step, p0, ends(q), length)
    if abs(achieved - switch_rate) > 1e-3 * switch_rate + 1e-9:
        raise ValueError(f"switch_rate {switch_rate} cannot be reached with goal_factor {goal_factor} "
                         f"(closest: {achieved:.4g})")
    next_mode = (1.0 - np.eye(K)) / (K - 1)
    parts = _one_set(K, np.full(K, 1.0 / K), _ending_transitions(ends(q), next_mode))
    names = tuple(("top_left", "bottom_right", "top_right", "bottom_left")[:K])
    params = dict(seed=int(seed), size=size, num_modes=K, num_trajectories=num_trajectories, length=length,
                  num_heldout=num_heldout, switch_rate=switch_rate, goal_factor=goal_factor, goal_size=goal_size,
                  goal_reward=goal_reward, inverse_temperature=beta, slip=float(slip), discount=float(discount),
                  switch_elsewhere=q, switch_at_goal=min(1.0, goal_factor * q))
    return _world("tabular_grid", rng, mdp, names, weights, parts, np.full(num_trajectories, length),
                  np.full(num_heldout, length), params,
                  describe_state=lambda s: {"row": int(s) // size, "col": int(s) % size})


# -------------------------------------------------------------------------------- labyrinth
def labyrinth_mdp(depth: int = 6, discount: float = 0.9) -> TabularMDP:
    """A binary-tree labyrinth: nodes 0 .. 2^(depth+1) - 2 in breadth-first order (node 0 the
    entrance; node i's children 2i + 1 and 2i + 2; 2^depth - 1 junctions and 2^depth end
    nodes); actions left child, right child, back to the parent, stay (a move that does not
    exist, e.g. a child of an end node or the entrance's parent, stays); deterministic; one-hot
    state features; every trajectory starts at the entrance."""
    depth = _int("depth", depth, 1)
    discount = _real("discount", discount, 0.0, 1.0, open_high=True)
    S = 2 ** (depth + 1) - 1
    junctions = 2 ** depth - 1
    nodes = np.arange(S)
    succ = np.empty((S, len(LABYRINTH_ACTIONS), 1), dtype=np.int64)
    succ[:, 0, 0] = np.where(nodes < junctions, 2 * nodes + 1, nodes)
    succ[:, 1, 0] = np.where(nodes < junctions, 2 * nodes + 2, nodes)
    succ[:, 2, 0] = np.where(nodes > 0, (nodes - 1) // 2, nodes)
    succ[:, 3, 0] = nodes
    level = np.floor(np.log2(nodes + 1)).astype(np.int64)
    initial = np.zeros(S)
    initial[0] = 1.0
    return TabularMDP.from_successors(succ, np.ones(succ.shape), discount=discount, initial=initial,
                                      name=f"labyrinth{depth}",
                                      state_vectors=np.stack([level, nodes + 1 - 2 ** level], -1).astype(float))


def labyrinth(seed: int = 0, *, depth: int = 6, num_trajectories: int = 200, min_length: int = 15,
              max_length: int = 25, num_heldout: int = 100, inverse_temperature: float = 4.0,
              explore_scale: float = 1.0, port_end: float = 0.6, home_end: float = 0.6,
              explore_end: float = 0.1, travel_end: float = 0.02, discount: float = 0.9) -> World:
    """Mice in a binary-tree labyrinth: explore, go to the water port, go home.

    Rewards (one per node): "explore" draws a reward per node from Normal(0, explore_scale^2)
    (mild preferences over a near-random walk); "water" is 1 at the water port, an end node
    drawn with the seed; "home" is 1 at the entrance. Every trajectory starts at the entrance,
    with explore, water or home with probabilities 0.6, 0.35, 0.05. The water skill ends with
    probability ``port_end`` on reaching the port and ``travel_end`` elsewhere, home with
    ``home_end`` at the entrance and ``travel_end`` elsewhere, explore with ``explore_end``
    anywhere; after an end: explore -> water 0.6 / home 0.4, water -> home 0.7 / explore 0.3,
    home -> explore 0.7 / water 0.3. Lengths are uniform in min_length..max_length.

    Args:
        seed: the seed; depth: tree depth (6: 63 junctions and 64 end nodes, 127 nodes).
        num_trajectories, min_length, max_length: training demonstrations.
        num_heldout: held-out trajectories (same lengths' distribution).
        inverse_temperature: the experts' beta on the water and home rewards (of size 1).
        explore_scale: sd of the explore skill's node rewards (the inverse temperature does not
            scale them: exploring stays a near-random walk with mild preferences).
        port_end, home_end, explore_end, travel_end: the end probabilities above, in [0, 1].
        discount: gamma.
    Returns:
        a :class:`World`.
    """
    rng = _seed(seed)
    mdp = labyrinth_mdp(depth, discount=discount)
    num_trajectories = _int("num_trajectories", num_trajectories, 1)
    min_length = _int("min_length", min_length, 2)
    max_length = _int("max_length", max_length, min_length)
    num_heldout = _int("num_heldout", num_heldout, 1)
    beta = _real("inverse_temperature", inverse_temperature, 0.0, open_low=True)
    explore_scale = _real("explore_scale", explore_scale, 0.0)
    ends = {n: _real(n, v, 0.0, 1.0) for n, v in
            [("port_end", port_end), ("home_end", home_end), ("explore_end", explore_end), ("travel_end", travel_end)]}
    S = mdp.num_states
    port = int(rng.integers(2 ** depth - 1, S))
    rewards = np.zeros((3, S))
    rewards[0] = explore_scale * rng.standard_normal(S)
    rewards[1, port] = 1.0
    rewards[2, 0] = 1.0
    end = np.full((3, S), ends["travel_end"])
    end[0] = ends["explore_end"]
    end[1, port] = ends["port_end"]
    end[2, 0] = ends["home_end"]
    next_skill = np.array([[0.0, 0.6, 0.4], [0.3, 0.0, 0.7], [0.7, 0.3, 0.0]])
    parts = _one_set(3, np.array([0.6, 0.35, 0.05]), _ending_transitions(end, next_skill))
    params = dict(seed=int(seed), depth=depth, num_trajectories=num_trajectories, min_length=min_length,
                  max_length=max_length, num_heldout=num_heldout, inverse_temperature=beta,
                  explore_scale=explore_scale, discount=float(discount), water_port=port, **ends)
    train = _lengths(rng, num_trajectories, min_length, max_length)
    held = _lengths(rng, num_heldout, min_length, max_length)
    junctions = 2 ** depth - 1
    weights = np.concatenate([rewards[:1], beta * rewards[1:]])  # explore's preferences stay mild
    return _world("labyrinth", rng, mdp, ("explore", "water", "home"), weights, parts, train, held, params,
                  describe_state=lambda s: {"node": int(s), "depth": int(np.log2(int(s) + 1)),
                                            "end_node": int(s) >= junctions})


# ------------------------------------------------------------------------------------ rooms
def _rooms_free(size: int) -> np.ndarray:
    """Free cells of a four-room grid: a wall row and column through the middle, each wall
    with a doorway on either side of the crossing."""
    free = np.ones((size, size), dtype=bool)
    mid = size // 2
    free[mid, :] = False
    free[:, mid] = False
    for d in (mid // 2, mid + 1 + (size - mid - 1) // 2):
        free[mid, d] = True  # doorways in the horizontal wall
        free[d, mid] = True  # and in the vertical one
    return free


def rooms_mdp(size: int = 11, slip: float = 0.0, discount: float = 0.9) -> TabularMDP:
    """A four-room gridworld on a size x size grid (size 11: 104 free cells, as in Sutton, Precup
    and Singh's): actions up, down, left, right, stay; only free cells are states (row-major
    order, ``mdp.state_vectors`` their (row, col)); one-hot state features; a uniform initial
    state."""
    size = _int("size", size, 5)
    slip = _real("slip", slip, 0.0, 1.0)
    discount = _real("discount", discount, 0.0, 1.0, open_high=True)
    free = _rooms_free(size)
    return TabularMDP.from_dense(_grid_dense(free, slip), discount=discount, name=f"rooms{size}",
                                 state_vectors=np.argwhere(free).astype(np.float64))


def rooms(seed: int = 0, *, size: int = 11, num_skills: int = 5, num_trajectories: int = 60,
          min_length: int = 60, max_length: int = 140, num_heldout: int = 20,
          skills_per_trajectory: Sequence[int] = (2, 3), switch_prob: float = 0.04,
          inverse_temperature: float = 5.0, slip: float = 0.0, discount: float = 0.9) -> World:
    """The four-room kind: goal-seeking skills, each trajectory with its own few of them.

    Skill k's reward is 1 at its goal cell: the four outer corners, then the doorways (top,
    left, right, bottom), in that order. A trajectory draws how many skills it uses uniformly
    from ``skills_per_trajectory`` and then which, uniformly; it starts in a uniformly random
    cell with one of them, uniformly; at every step its skill switches with probability
    ``switch_prob`` to another of its own, uniformly. Lengths are uniform in
    min_length..max_length.

    Args:
        seed: the seed; size: grid side (at least 5); num_skills: 2..8.
        num_trajectories, min_length, max_length: training demonstrations.
        num_heldout: held-out trajectories.
        skills_per_trajectory: the possible sizes of a trajectory's skill set (each 1..num_skills).
        switch_prob: per-step switching probability, in [0, 1].
        inverse_temperature: the experts' beta; slip: random-move probability; discount: gamma.
    Returns:
        a :class:`World`.
    """
    rng = _seed(seed)
    mdp = rooms_mdp(size, slip=slip, discount=discount)
    num_skills = _int("num_skills", num_skills, 2)
    if num_skills > 8:
        raise ValueError(f"num_skills must be at most 8 (four corners and four doorways), got {num_skills}")
    num_trajectories = _int("num_trajectories", num_trajectories, 1)
    min_length = _int("min_length", min_length, 2)
    max_length = _int("max_length", max_length, min_length)
    num_heldout = _int("num_heldout", num_heldout, 1)
    try:
        sizes = sorted({int(n) for n in skills_per_trajectory})
    except (TypeError, ValueError):
        raise ValueError(f"skills_per_trajectory must be a sequence of integers, got {skills_per_trajectory!r}") \
            from None
    if not sizes or sizes[0] < 1 or sizes[-1] > num_skills:
        raise ValueError(f"skills_per_trajectory must hold sizes in 1..{num_skills}, got {skills_per_trajectory!r}")
    switch_prob = _real("switch_prob", switch_prob, 0.0, 1.0)
    beta = _real("inverse_temperature", inverse_temperature, 0.0, open_low=True)
    free = _rooms_free(size)
    index = -np.ones(free.shape, dtype=np.int64)
    index[free] = np.arange(free.sum())
    mid, last = size // 2, size - 1
    doors = (mid // 2, mid + 1 + (size - mid - 1) // 2)
    goals = [(0, 0), (0, last), (last, 0), (last, last), (doors[0], mid), (mid, doors[0]), (mid, doors[1]),
             (doors[1], mid)][:num_skills]
    names = ("top_left", "top_right", "bottom_left", "bottom_right", "top_door", "left_door", "right_door",
             "bottom_door")[:num_skills]
    K, S = num_skills, mdp.num_states
    weights = np.zeros((K, S))
    for k, (r, c) in enumerate(goals):
        weights[k, index[r, c]] = beta
    sets = [c for n in sizes for c in combinations(range(K), n)]
    set_probs = np.array([1.0 / (len(sizes) * math.comb(K, len(c))) for c in sets])
    member = np.zeros((len(sets), K), dtype=bool)
    for m, c in enumerate(sets):
        member[m, list(c)] = True
    n_in = member.sum(-1, keepdims=True)
    initial = member / n_in
    others = np.where(n_in[:, :, None] > 1, member[:, None, :] / np.maximum(n_in[:, :, None] - 1, 1), 0.0)
    others = others * (1.0 - np.eye(K))[None]  # (M, K, K): uniform over the set's other skills
    stay = np.where(n_in[:, :, None] > 1, 1.0 - switch_prob, 1.0)
    trans = stay * np.eye(K)[None] + (1.0 - stay) * others
    parts = {"skill_sets": member, "skill_set_probs": set_probs, "initial_skill": initial,
             "transitions": trans[:, None]}
    params = dict(seed=int(seed), size=size, num_skills=K, num_trajectories=num_trajectories,
                  min_length=min_length, max_length=max_length, num_heldout=num_heldout,
                  skills_per_trajectory=tuple(sizes), switch_prob=switch_prob, inverse_temperature=beta,
                  slip=float(slip), discount=float(discount), goals=goals)
    train = _lengths(rng, num_trajectories, min_length, max_length)
    held = _lengths(rng, num_heldout, min_length, max_length)
    cells = np.argwhere(free)
    return _world("rooms", rng, mdp, names, weights, parts, train, held, params,
                  describe_state=lambda s: {"row": int(cells[s][0]), "col": int(cells[s][1])})


WORLDS = {"tabular_grid": tabular_grid, "labyrinth": labyrinth, "rooms": rooms}


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
