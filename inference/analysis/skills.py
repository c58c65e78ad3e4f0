"""The found skills for control: their policies in the MDP of the fit or in a changed one
(transfer), and the skills as options.

A reward skill's policy in an MDP is the emission's own: the soft (Boltzmann) policy of the
inferred reward solved in that MDP, with the run's temperature and epsilon; its greedy policy
is the optimal action of the reward (hard value iteration, lowest action on ties). Solving
the inferred rewards again in a changed MDP with the same reward features is the paper's
argument for rewards over policies (sections I and II-B): the policies adapt to the new
dynamics. Skills of an emission without rewards (``policy``, ``subgoal``) carry their
policies over as they are (same states and actions needed).
"""

from __future__ import annotations

from typing import List

import numpy as np
from npbrs.domains.util.precision import float64_all

__all__ = ["skill_policies", "skill_options", "skill_parameters", "skill_ends", "REWARDS"]


def _emission_in(result, mdp, emission):
    from npbrs.models.emissions import make_emission

    if emission is not None:
        return emission
    cfg = result.model_config
    return make_emission(cfg.emission.name, mdp, **cfg.emission.options)


def _check_world(result, mdp):
    """Raise ValueError unless the run's skills can act in ``mdp``."""
    params = result.skill_params
    if "theta" in params:
        D = np.shape(params["theta"])[-1]
        names, theirs = tuple(result.feature_names), tuple(getattr(mdp, "feature_names", ()))
        if mdp.num_features != D or (names and theirs and names != theirs):
            raise ValueError(f"the run's rewards are over {D} features {list(names)}, but this MDP "
                             f"({getattr(mdp, 'name', 'mdp')!r}) has {mdp.num_features} {list(theirs)}: its "
                             "rewards cannot be solved there")
    elif "policy" in params:
        K, S, A = np.shape(params["policy"])
        if (mdp.num_states, mdp.num_actions) != (S, A):
            raise ValueError(f"the run's skills are policies over {S} states and {A} actions; this MDP has "
                             f"{mdp.num_states} and {mdp.num_actions}")
    elif "goal" in params:
        goals = np.asarray(params["goal"])
        if goals.size and goals.max() >= mdp.num_states:
            raise ValueError(f"the run's subgoal states reach {int(goals.max())}; this MDP has {mdp.num_states} states")


REWARDS = ("mean", "best")


def skill_parameters(result, rewards: str = "mean") -> dict:
    """The found skills' parameters {site: (K, ...)}: the best draw's (``"best"``), or their
    posterior means over the draws, every chain's skills matched to the run's
    (:func:`~npbrs.inference.analysis.diagnostics.relabelled_draws`; ``"mean"``; a skill that no draw
    of a site holds keeps the best draw's value; integer sites such as subgoal states keep
    the best draw's)."""

    if rewards not in REWARDS:
        raise ValueError(f"unknown rewards {rewards!r}; expected one of {REWARDS}")
    params = {k: np.asarray(v) for k, v in result.skill_params.items()}
    if rewards == "best":
        return params
    out = {}
    for site, best in params.items():
        if best.dtype.kind != "f" or site not in result.samples:
            out[site] = best
            continue
        mean, seen = _relabelled_mean(result, site)
        out[site] = np.where(seen.reshape((-1,) + (1,) * (mean.ndim - 1)), mean, best)
    return out


def _relabelled_mean(result, site):
    """A site's posterior mean per found skill, (K, ...), every chain's skills matched to the
    run's (:func:`~npbrs.inference.analysis.diagnostics.relabelled_draws`), and (K,) whether any
    draw holds the skill (0 where none does)."""
    from .diagnostics import relabelled_draws

    draws = relabelled_draws(result, site)  # (C, D, K, ...), NaN where a draw lacks the skill
    flat = draws.reshape((-1,) + draws.shape[2:])
    seen = ~np.isnan(flat).reshape(flat.shape[0], flat.shape[1], -1).any(-1)  # (CD, K)
    total = np.where(seen.reshape(seen.shape + (1,) * (flat.ndim - 2)), flat, 0.0).sum(0)
    count = seen.sum(0).reshape((-1,) + (1,) * (flat.ndim - 2))
    return total / np.maximum(count, 1), seen.any(0)


def skill_policies(result, mdp, *, greedy: bool = False, rewards: str = "mean", emission=None) -> np.ndarray:
    """The found skills' policies in ``mdp``: (K, S, A) action probabilities, or with ``greedy``
    (K, S) optimal actions (see :meth:`~npbrs.inference.driver.results.FitResult.policies`)."""
    import jax.numpy as jnp

    from npbrs.domains.control import skill_policies as greedy_actions

    if result.num_skills < 1:
        raise ValueError("the run found no skills")
    _check_world(result, mdp)
    chosen = skill_parameters(result, rewards)
    params = {k: jnp.asarray(v) for k, v in chosen.items()}
    em = _emission_in(result, mdp, emission)
    if greedy and "theta" in params:
        world = getattr(em, "mdp", mdp)  # the emission's own discount
        return greedy_actions(world, world.reward(np.asarray(chosen["theta"], np.float64)))
    try:
        log_pi = np.asarray(em.log_policies(params), dtype=np.float64)
    except NotImplementedError as e:
        raise ValueError(f"{e}; its skills cannot act") from None
    if greedy:
        return np.argmax(log_pi, axis=-1).astype(np.int64)
    pi = np.exp(log_pi)
    return pi / pi.sum(-1, keepdims=True)


def skill_options(result, mdp, demos=None, *, prior_strength: float = 2.0, rewards: str = "mean",
                  emission=None) -> List:
    """The found skills as options (see :meth:`~npbrs.inference.driver.results.FitResult.options`)."""
    from npbrs.domains.options import estimate_options

    result.check_mdp(mdp)
    if demos is None:
        if result.demos is None:
            raise ValueError("the run does not hold its demonstrations; pass demonstrations to estimate options from")
        demos, labels = result.demos, result.segmentation
    else:
        if len(demos.lengths) == 0:
            raise ValueError("the demonstrations hold no trajectory")
        labels = result.segment(mdp, demos, emission=emission).labels
    demos.validate(mdp)
    em = _emission_in(result, mdp, emission)
    options = estimate_options(demos.states, labels, skill_policies(result, mdp, rewards=rewards, emission=em),
                               skill_policies(result, mdp, greedy=True, rewards=rewards, emission=em),
                               prior_strength=prior_strength)
    if "ends" in result.samples:  # a run with state-dependent ends: the model's own termination
        import dataclasses

        mean, seen = skill_ends(result)
        options = [dataclasses.replace(o, termination=mean[k]) if seen[k] else o for k, o in enumerate(options)]
    return options


def skill_ends(result):
    """A run with state-dependent ends (``switching="state"``): each found skill's posterior mean
    end probability per state, (K, S), every chain's skills matched to the run's
    (:func:`~npbrs.inference.analysis.diagnostics.relabelled_draws`), and (K,) whether any draw
    holds the skill (rows of skills that none holds are 0)."""
    if "ends" not in result.samples:
        raise ValueError("the run has no end probabilities (it was fitted with switching='sticky')")
    return _relabelled_mean(result, "ends")


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
