"""Which of several equivalent actions a demonstrator names: the action-name factor of the likelihood.

Two actions of a state are *equivalent* when they lead to the same next-state distribution and
have the same reward features (:func:`npbrs.domains.mdp.TabularMDP.equivalent_actions`): every
reward gives them the same soft Q-value, so a Boltzmann policy splits their probability evenly,
and nothing a reward says can tell them apart. A real demonstrator need not: a mouse at a dead
end "stays" by one action, not by the three that all keep it there. This factor models the name
chosen within each set of equivalent actions, separately from the choice of a consequence:

    p(a | s, skill) = pi_skill(class of a | s) * q_C(a),  C the set of actions equivalent to a,

with q_C ~ Dirichlet(c / |C|, ..., c / |C|) per set C of equivalent actions (shared by every
state where that set occurs), and the concentration c either infinite (q_C uniform: the plain
Boltzmann policy) or on a log grid. The factor does not depend on the skills, the rewards or the
segmentation, so it leaves their posterior untouched: the sampler runs as before, and the
factor enters the scores of demonstrations (:func:`npbrs.inference.analysis.predictive.log_predictive`,
the pointwise log-likelihoods behind LOO). It is conjugate: the scores are exact
(Dirichlet-multinomial), averaged over c by its posterior given the fitted names, with prior
mass one half on uniform names (so the evidence decides whether names are learned at all).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.special import gammaln, logsumexp

__all__ = ["ActionNames", "NameCounts", "name_counts", "CONCENTRATIONS"]

# the concentrations c of the learned-names models (the uniform model, c infinite, is apart)
CONCENTRATIONS = np.logspace(-2, 3, 26)


class NameCounts(NamedTuple):
    """How often each action was named within each set of equivalent actions.

    ``sets`` (G, A) bool: the sets of two or more equivalent actions that occur;
    ``counts`` (n, G, A): per trajectory, the steps that named each action of each set."""

    sets: np.ndarray
    counts: np.ndarray


def name_counts(mdp, demos, sets=None) -> NameCounts:
    """Per-trajectory counts of the actions named within each set of equivalent actions.

    Args:
        mdp: the TabularMDP (its :meth:`equivalent_actions`).
        demos: Demonstrations in that MDP.
        sets: (G, A) bool, the sets to count (default: those the demonstrations visit).
    Returns:
        a :class:`NameCounts`; steps whose action has no equivalent are not counted.
    """
    members = mdp.equivalent_actions()  # (S, A, A): members[s, a] is the set of a at s
    rows = [members[np.asarray(s), np.asarray(a)] for s, a in zip(demos.states, demos.actions)]  # (T, A) each
    if sets is None:
        steps = np.concatenate(rows) if rows else np.zeros((0, mdp.num_actions), bool)
        steps = steps[steps.sum(-1) > 1]
        sets = np.unique(steps, axis=0) if len(steps) else np.zeros((0, mdp.num_actions), bool)
    sets = np.asarray(sets, dtype=bool)
    counts = np.zeros((len(rows), len(sets), mdp.num_actions))
    for i, (row, a) in enumerate(zip(rows, demos.actions)):
        if not len(sets):
            break
        match = np.all(row[:, None, :] == sets[None], axis=-1)  # (T, G)
        t, g = np.nonzero(match)
        np.add.at(counts[i], (g, np.asarray(a)[t]), 1.0)
    return NameCounts(sets, counts)


def _evidence(counts, sets, c) -> np.ndarray:
    """log p(the names | c) of count tables (..., G, A) under Dirichlet(c / |C|) names per set;
    c = inf: uniform names. Returns (...)."""
    size = sets.sum(-1)  # (G,)
    n = counts.sum(-1)  # (..., G)
    if np.isinf(c):
        return -np.sum(n * np.log(size), axis=-1)
    a = c / size
    per_set = gammaln(c) - gammaln(c + n) + np.sum(np.where(sets, gammaln(a[:, None] + counts) - gammaln(a)[:, None],
                                                           0.0), axis=-1)
    return np.sum(per_set, axis=-1)


class ActionNames:
    """The action-name factor fitted to demonstrations: its posterior over the concentration.

    Args:
        counts: the fitted demonstrations' :class:`NameCounts`.
    """

    def __init__(self, counts: NameCounts):
        self.counts = counts
        self.concentrations = np.concatenate([CONCENTRATIONS, [np.inf]])
        # prior: one half on uniform names, one half spread evenly over the grid
        G = len(CONCENTRATIONS)
        self.log_prior = np.concatenate([np.full(G, np.log(0.5 / G)), [np.log(0.5)]])

    @classmethod
    def fit(cls, mdp, demos) -> "ActionNames":
        """The factor fitted to ``demos`` in ``mdp``.

        Args:
            mdp: a TabularMDP; demos: its Demonstrations.
        Returns:
            an :class:`ActionNames`.
        """
        return cls(name_counts(mdp, demos))

    def _log_posterior(self, total) -> np.ndarray:
        lp = self.log_prior + np.array([_evidence(total, self.counts.sets, c) for c in self.concentrations])
        return lp - logsumexp(lp)

    @property
    def log_bayes_factor(self) -> float:
        """log p(names | learned) - log p(names | uniform) of the fitted names (nats)."""
        total = self.counts.counts.sum(0)
        ev = np.array([_evidence(total, self.counts.sets, c) for c in self.concentrations])
        G = len(CONCENTRATIONS)
        return float(logsumexp(ev[:G]) - np.log(G) - ev[G])

    def _uniform(self, counts) -> np.ndarray:
        return _evidence(counts, self.counts.sets, np.inf)

    def _predictive(self, given, new) -> np.ndarray:
        """log p(new names | given names), per row of ``new`` (n, G, A); ``given`` (G, A) or
        (n, G, A)."""
        log_w = self._log_posterior(given) if np.ndim(given) == 2 else np.stack(
            [self._log_posterior(g) for g in given], -1)
        terms = np.stack([_evidence(given + new, self.counts.sets, c) - _evidence(given, self.counts.sets, c)
                          for c in self.concentrations])  # (G + 1, n)
        return logsumexp(log_w.reshape(len(self.concentrations), -1) + terms, axis=0)

    def heldout_correction(self, mdp, demos) -> np.ndarray:
        """Per trajectory of new demonstrations, log p(its names | the fitted names) minus the
        uniform names the Boltzmann policy gives them: what to add to a score computed with
        the plain policy.

        Args:
            mdp: the TabularMDP; demos: Demonstrations not among the fitted ones.
        Returns:
            (n,) nats.
        """
        new = name_counts(mdp, demos, self.counts.sets).counts
        return self._predictive(self.counts.counts.sum(0), new) - self._uniform(new)

    def loo_correction(self) -> np.ndarray:
        """Per fitted trajectory, log p(its names | the other trajectories' names) minus the
        uniform names: what to add to its leave-one-out score under the plain policy.

        Returns:
            (n,) nats.
        """
        own = self.counts.counts
        return self._predictive(own.sum(0)[None] - own, own) - self._uniform(own)

    def describe(self) -> str:
        """One line: the sets of equivalent actions and how strongly the names are learned."""
        if not len(self.counts.sets):
            return "action names: no state of the demonstrations has equivalent actions"
        sets = "; ".join("{" + ", ".join(map(str, np.flatnonzero(s))) + "}" for s in self.counts.sets)
        total = self.counts.counts.sum(0)
        shares = "; ".join(", ".join(f"{a}: {total[g, a] / max(total[g].sum(), 1):.2f}" for a in np.flatnonzero(s))
                           for g, s in enumerate(self.counts.sets))
        p_uniform = float(np.exp(self._log_posterior(total)[-1]))
        return (f"action names within sets of equivalent actions ({sets}): named {shares}; "
                f"log Bayes factor of learned over uniform names {self.log_bayes_factor:+.1f} nats "
                f"(posterior probability of uniform names {p_uniform:.2g})")
