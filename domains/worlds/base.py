"""What every world shares: the checks of a generator's arguments, the true generating model of
the skills (:class:`SkillProcess`) and what it achieves (:class:`Oracle`), the generated
:class:`World`, and how a world is built from its MDP, skill rewards and switching (see
:mod:`npbrs.domains.worlds`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, NamedTuple, Sequence

import numpy as np

from ..demos import Demonstrations
from ..domain import Domain
from ..mdp import TabularMDP, set_frozen
from ..util.precision import float64_all

__all__ = ["World", "SkillProcess", "Oracle"]


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
    from ..solvers import boltzmann_log_policy, soft_value_iteration

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


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
