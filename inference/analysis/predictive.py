"""Held-out demonstrations under a fitted model: the posterior predictive log-likelihood.

For a trajectory x that was not in the fit,

    p(x | fit) = E_s[ sum_{f != 0} p(f | F_s) integral p(x | f, eta, theta_s) p(eta) d eta ]
                 / E_s[ P(f != 0 | F_s) ],

the expectations over the run's posterior draws s. Given draw s, the new trajectory's skill set f
follows the weak-limit beta-Bernoulli predictive of the draw's features F_s, its transition
weights eta their Gamma prior, and the skill sequence is summed out by the forward filter
(``npbrs.models.bphmm.predictive_log_likelihoods``). An empty skill set emits no step (the
model gives it likelihood 0, so no fitted trajectory's set is ever empty), and the predictive
samples one with positive probability: the value is the predictive given that the new
trajectory has steps, the denominator being the probability under the predictive that its set
is not empty, exact (1 - prod_k (1 - P(f_k = 1)) per draw). Without it the value sat that
probability's log lower (0.1 nats on a two-skill case of ``tests/test_predictive.py``). In the
numerator f and eta are integrated by Monte Carlo,
``num_samples`` independent samples per draw (eta's self shares are importance-sampled around
each trajectory's own stays, ``npbrs.models.bphmm._guided_eta``: drawn from the prior alone they
rarely fit a long trajectory, and 64 samples fell several nats per 500-step trajectory below the
value; ``segment`` weights its skill probabilities by the same importance weights), so the
estimate of log p(x | fit), the average
over the run's draws, carries a Monte Carlo standard error: from the samples' variance within
each draw, by the delta method on the log. It is consistent, and biased low by about se^2 / 2
(Jensen). (The draws themselves are taken as given, as ``az.loo`` takes them; more draws
reduce the posterior's own sampling error, which this does not report.)
"""

from __future__ import annotations

import warnings
from functools import partial
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np
from scipy.special import logsumexp

from npbrs.models.bphmm import Hyper, end_gate, feature_predictive, predictive_log_likelihoods
from npbrs.models.emissions import Emission, HMMData
from npbrs.domains.util.compiling import jit
from npbrs.domains.util.precision import float64_all

__all__ = ["HeldOut", "SkillProbabilities", "log_predictive", "pointwise_log_likelihood", "segment", "fitted_trajectories",
           "skill_probabilities"]  # (draw_moments, public for tests, is called inside these)

_NOT_PARAMS = ("features", "skill_steps", "alpha", "kappa", "gamma", "ends", "end_mean")


class HeldOut(NamedTuple):
    """Held-out log-likelihood of new demonstrations under a fit (nats).

    per_trajectory: (n,) log p(x_i | fit); per_trajectory_se: (n,) their Monte Carlo standard
    errors; per_step: sum_i log p(x_i | fit) / total steps (the field's figure of merit);
    per_step_se: its standard error (trajectories' errors combined as independent);
    num_steps: total steps; num_draws: posterior draws used.
    """

    per_trajectory: np.ndarray
    per_trajectory_se: np.ndarray
    per_step: float
    per_step_se: float
    num_steps: int
    num_draws: int


class SkillProbabilities(NamedTuple):
    """Posterior skill probabilities of demonstrations under a fit.

    probs: per trajectory, (T_i, L) the probability of each of the run's L skills (labelled as
    in ``result.segmentation``) at every step; a row sums to the probability that the step
    belongs to one of them (below 1 where some draws put it in a skill the run's best draw
    does not have). labels: per trajectory, (T_i,) the most probable of them.
    """

    probs: list
    labels: list


def _draw_indices(num_chains: int, num_draws_run: int, num_draws: int) -> np.ndarray:
    """Evenly spaced draw indices, the same in every chain, about num_draws in all."""
    per_chain = max(1, min(num_draws_run, -(-num_draws // num_chains)))
    return np.unique(np.linspace(0, num_draws_run - 1, per_chain).round().astype(int))


def fitted_trajectories(result, demos) -> int:
    """How many of ``demos``' trajectories (states and actions) are among those ``result`` was
    fitted to (0 when the run does not hold its demonstrations)."""
    if result.demos is None:
        return 0
    key = lambda s, a: (np.asarray(s, np.int64).tobytes(), np.asarray(a, np.int64).tobytes())  # noqa: E731
    known = {key(s, a) for s, a in zip(result.demos.states, result.demos.actions)}
    return sum(key(s, a) in known for s, a in zip(demos.states, demos.actions))


def log_predictive(result, mdp, demos, *, num_samples: int = 64, num_draws: int = 100, seed: int = 0,
                   emission: Optional[Emission] = None) -> HeldOut:
    """The posterior predictive log-likelihood of demonstrations that were not in the fit.

    Args:
        result: a :class:`~npbrs.inference.driver.results.FitResult`.
        mdp: the TabularMDP the run was fitted in.
        demos: the held-out :class:`~npbrs.domains.demos.Demonstrations`.
        num_samples: Monte Carlo samples of a new trajectory's skill set and transition
            weights per posterior draw.
        num_draws: posterior draws used (evenly spaced in every chain).
        seed: seed of the Monte Carlo samples (the same seed gives the same answer).
        emission: the emission instance, for a run fitted with one (by default the run's
            configured emission is rebuilt in ``mdp``).
    Returns:
        :class:`HeldOut` (for a run that learns the names of equivalent actions,
        :mod:`npbrs.models.names`, with that factor's exact predictive term in each trajectory's).
    Raises:
        ValueError: demonstrations outside the MDP, an MDP unlike the run's, bad options.
    """
    _check_counts(num_samples=num_samples, num_draws=num_draws)
    fitted = fitted_trajectories(result, demos)
    if fitted:
        warnings.warn(f"log_predictive: {fitted} of the {len(demos.lengths)} trajectories are ones the run was fitted "
                      "to, so their score is an in-sample fit, above what new demonstrations would score; score "
                      "held-out demonstrations (FitResult.add_log_likelihood gives the fitted ones' leave-one-out "
                      "inputs)", UserWarning, stacklevel=3)
    C, D = np.shape(result.stats["log_joint"])
    moments = draw_moments(result, mdp, demos, _draw_indices(C, D, num_draws), num_samples, seed, emission,
                            leave_one_out=False)
    held = _summarise(moments.reshape(-1, 3, len(demos.lengths)), num_samples, demos)
    names = _action_names(result, mdp, emission)
    if names is None:
        return held
    log_p = held.per_trajectory + names.heldout_correction(mdp, demos)
    return held._replace(per_trajectory=log_p, per_step=float(log_p.sum() / held.num_steps))


def _action_names(result, mdp, emission):
    """The action-name factor fitted to the run's demonstrations (:mod:`npbrs.models.names`)
    where the run's emission learns it, else None."""
    from npbrs.models.names import ActionNames

    learns = (emission.learns_action_names if emission is not None
              else result.emission.get("action_names") == "learned")
    if not learns:
        return None
    if result.demos is None:
        raise ValueError("the run learns the names of equivalent actions from its demonstrations, which it does not "
                         "hold; score it with an emission of action_names='uniform'")
    return ActionNames.fit(mdp, result.demos)


def pointwise_log_likelihood(result, mdp, *, num_samples: int = 32, seed: int = 0,
                             emission: Optional[Emission] = None) -> np.ndarray:
    """Each fitted trajectory's log-likelihood under each posterior draw, (C, D, N): the
    ``log_likelihood`` group ArviZ's ``loo`` and ``compare`` read.

    Trajectory i's value under draw s is log p(x_i | theta_s, F_s without row i, x_i has steps):
    its own skill set (from the beta-Bernoulli predictive of the other trajectories' features,
    given that it is not empty: divided by that predictive's exact probability of a nonempty set)
    and transition weights (their prior) integrated out by Monte Carlo (``num_samples`` per
    draw), the skill sequence by the forward filter. ``az.loo``'s importance weighting of these
    values by the posterior draws then estimates log p(x_i | the other trajectories, x_i has
    steps), the quantity :func:`log_predictive` gives for new trajectories. For a run that learns
    the names of equivalent actions (:mod:`npbrs.models.names`) each value also holds that
    factor's exact leave-one-out term, the same under every draw.
    """
    _check_counts(num_samples=num_samples)
    if result.demos is None:
        raise ValueError("the run does not hold its demonstrations, which the pointwise log-likelihood needs")
    C, D = np.shape(result.stats["log_joint"])
    moments = draw_moments(result, mdp, result.demos, np.arange(D), num_samples, seed, emission, leave_one_out=True)
    out = moments[:, :, 0, :] - moments[:, :, 2, :]
    names = _action_names(result, mdp, emission)
    # (the names' factor is independent of the draws: its exact leave-one-out term is added to each)
    return out if names is None else out + names.loo_correction()


def segment(result, mdp, demos=None, *, num_samples: int = 32, num_draws: int = 100, seed: int = 0,
            emission: Optional[Emission] = None) -> SkillProbabilities:
    """Posterior probabilities of the run's skills at every step, averaged over its draws.

    For new demonstrations, a trajectory's skill set follows the beta-Bernoulli predictive of
    each draw's features and its transition weights their prior, and each draw is weighted by
    the trajectory's likelihood under it (p(z | x, fit) = sum_s p(x | s) p(z | x, s) / sum_s
    p(x | s)); for the fitted ones (``demos=None``), its skill set is the draw's own and the
    draws count equally (they are draws of the posterior given these trajectories already:
    p(z | x, fit) = mean_s p(z | x, s)). Demonstrations equal to the fitted ones (the same
    trajectories, states and actions, in the same order) are the fitted ones: a session observed
    once is not new evidence a second time. Either way the transition weights and
    (for new ones) the skill set are integrated by self-normalised importance sampling
    (``num_samples`` per draw, the self shares of the transition weights proposed around the
    trajectory's own stays as for :func:`log_predictive`, each sample weighted by the
    trajectory's likelihood and its importance weight), and the skill sequence's
    marginals come from the forward filter and smoother. Every chain's skill slots are mapped
    to the run's skills by :func:`npbrs.inference.analysis.diagnostics.relabel`.

    Returns:
        :class:`SkillProbabilities`.
    """
    from .diagnostics import relabel

    _check_counts(num_samples=num_samples, num_draws=num_draws)
    fitted = demos is None or (result.demos is not None and demos.same_trajectories(result.demos))
    if fitted:
        if result.demos is None:
            raise ValueError("the run does not hold its demonstrations; pass the demonstrations to segment")
        demos = result.demos
    if len(demos.lengths) == 0:
        raise ValueError("the demonstrations hold no trajectory")
    mapping = relabel(result)  # (C, K): the run's skill of every chain's slot, -1 for none
    C, D = np.shape(result.stats["log_joint"])
    idx = _draw_indices(C, D, num_draws)
    L = result.num_skills
    n, T = len(demos.lengths), int(np.max(demos.lengths))
    total = np.full(n, -np.inf)
    acc = np.full((n, T, L), -np.inf)
    for c, j, lm, post in draw_moments(result, mdp, demos, idx, num_samples, seed, emission,
                                        leave_one_out=False, marginals=True, own_features=fitted):
        if fitted:
            # the draws already condition on the fitted trajectories: each draw's own posterior
            # counts once (weighting it by p(x_i | draw) as well would count x_i twice)
            seen = np.isfinite(lm)
            post = np.where(seen[:, None, None], post - np.where(seen, lm, 0.0)[:, None, None], -np.inf)
            lm = np.where(seen, 0.0, -np.inf)
        total = np.logaddexp(total, lm)
        for k, skill in enumerate(mapping[c]):
            if skill >= 0:
                acc[..., skill] = np.logaddexp(acc[..., skill], post[..., k])
    if not np.all(np.isfinite(total)):
        bad = int(np.argmin(np.isfinite(total)))
        raise ValueError(f"trajectory {bad} has probability 0 under every posterior draw")
    probs = np.exp(acc - total[:, None, None])
    rows = [probs[i, :m] for i, m in enumerate(demos.lengths)]
    return SkillProbabilities(probs=rows, labels=[np.argmax(r, axis=-1) for r in rows])


def _check_counts(**values):
    for name, value in values.items():
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise ValueError(f"{name} must be an integer >= 1, got {value!r}")


def draw_moments(result, mdp, demos, idx, num_samples, seed, emission, leave_one_out, marginals=False,
                  own_features=False):
    """The Monte Carlo moments behind the held-out scores (what :func:`log_predictive`,
    :func:`pointwise_log_likelihood` and :func:`segment` reduce).

    Args:
        result, mdp, demos: the run, its MDP and the demonstrations scored.
        idx: the draws used, indices into each chain's draws.
        num_samples, seed: Monte Carlo samples of a trajectory's skill set and transition weights.
        emission: the emission instance, or None (the run's configured one).
        leave_one_out: each fitted trajectory's skill set from the predictive given the others.
        marginals: instead, a generator of (chain, draw, log sum_m p_m (n,), log sum_m p_m
            p(z_t = k | ...)_m (n, T, K)), p_m the trajectory's likelihood under sample m.
        own_features: the draw's own skill sets (fitted trajectories) instead of the predictive.
    Returns:
        (C, len(idx), 3, n): per chain and draw, the log first and second moments over the
        samples of every trajectory's likelihood (an empty skill set's 0 included), and the log
        probability of a nonempty skill set under the draw's predictive.
    """
    from npbrs.models.emissions import make_emission
    from ..threads import on_threads, threads_for

    result.check_mdp(mdp)
    demos.validate(mdp)
    cfg = result.model_config
    if emission is None:
        emission = make_emission(cfg.emission.name, mdp, **cfg.emission.options)
    samples = {k: np.asarray(v) for k, v in result.samples.items()}
    if "features" not in samples:
        raise ValueError("the run holds no feature draws ('features' in samples), which the predictive needs")
    params_all = {k: v for k, v in samples.items() if k not in _NOT_PARAMS}
    C, D, N, K = samples["features"].shape
    for name, value in params_all.items():
        if value.shape[:3] != (C, D, K):
            raise ValueError(f"samples[{name!r}] has shape {value.shape}; expected ({C}, {D}, {K}, ...)")
    features_known = getattr(mdp, "num_features", None)
    if "theta" in params_all and features_known is not None and params_all["theta"].shape[-1] != features_known:
        raise ValueError(f"the run's rewards have {params_all['theta'].shape[-1]} features, the MDP "
                         f"{features_known}: a run and an MDP that do not belong together")
    data = HMMData.from_demonstrations(demos)
    hyper_fixed = {n: float(getattr(cfg.prior, n).value) for n in ("alpha", "kappa", "gamma")}
    others = N - 1 if leave_one_out else N

    draw = _draw_at(samples, params_all, hyper_fixed, idx, seed, C)
    # each draw's likelihood solves start from the values of the chain's previous draw (the
    # emission's cache; a chain's consecutive draws are close): the same likelihoods to the
    # solver's tolerance. So the chains are independent: their j-th draws run side by side, on
    # the CPU's cores (npbrs.inference.threads)
    caches = [emission.init_cache(K)] * C

    def call(c, j):  # (program, its arguments, its options) of chain c's j-th draw
        key, params, f, hyper, ends = draw(c, j)
        if marginals:
            p_on = f if own_features else feature_predictive(f.sum(0), others, float(hyper.alpha))
            return (_one_draw_marginals, (emission, key, params, jnp.asarray(p_on, jnp.float64), hyper, data, ends,
                                          caches[c]), {"num_samples": num_samples})
        # a fitted trajectory's own row is left out of the popularity counts
        counts = jnp.asarray(f.sum(0) - f if leave_one_out else f.sum(0), jnp.float64)
        return _one_draw, (emission, key, params, counts, hyper, data, ends, caches[c]), \
            {"num_samples": num_samples, "others": others}

    def one(c, j):
        program, args, options = call(c, j)
        *out, caches[c] = program(*args, **options)
        return (c, j, *(np.asarray(o) for o in out))

    def lowered():  # (the program every draw runs; the calls reuse this lowering)
        program, args, options = call(0, 0)
        return program.lower(*args, **options)

    threads = threads_for(C, lowered)

    def by_draw():  # (every chain's first draw, then every chain's second, ...)
        for j in range(len(idx)):
            yield from on_threads(one, [(c, j) for c in range(C)], threads)

    if marginals:
        return by_draw()
    out = np.empty((C, len(idx), 3, len(demos.lengths)))
    for c, j, moments in by_draw():
        out[c, j] = moments
    return out


_lse = jax.scipy.special.logsumexp


# compiled per emission structure and shapes: the emission (its MDP's arrays), the draw and the
# demonstrations are arguments, so every draw, run and data set of the same shapes shares one
@partial(jit, static_argnames="num_samples")
def _one_draw(emission, key, params, counts, hyper, data, ends, cache, *, num_samples, others):
    log_lik, cache = emission.log_likelihoods(params, data, cache)
    p_on = feature_predictive(counts, others, hyper.alpha)
    gate = None if ends is None else end_gate(ends, data.states, data.mask)
    lm = predictive_log_likelihoods(key, log_lik, data.mask, p_on, hyper, num_samples, gate=gate,
                                    guided=True)  # (M, n): -inf where the sampled skill set is empty
    # log P(the skill set is not empty) under the draw's predictive, exactly: () or (n,)
    log_nonempty = jnp.log(-jnp.expm1(jnp.sum(jnp.log1p(-p_on), -1)))
    return jnp.stack([_lse(lm, axis=0) - jnp.log(num_samples), _lse(2 * lm, axis=0) - jnp.log(num_samples),
                      jnp.broadcast_to(log_nonempty, lm.shape[1:])]), cache


@partial(jit, static_argnames="num_samples")
def _one_draw_marginals(emission, key, params, p_on, hyper, data, ends, cache, *, num_samples):
    log_lik, cache = emission.log_likelihoods(params, data, cache)
    gate = None if ends is None else end_gate(ends, data.states, data.mask)
    lm, post = predictive_log_likelihoods(key, log_lik, data.mask, p_on, hyper, num_samples, marginals=True,
                                          gate=gate, guided=True)
    return _lse(lm, axis=0), _lse(lm[..., None, None] + post, axis=0), cache


def _draw_at(samples, params_all, hyper_fixed, idx, seed, C):
    """(chain c, index j in idx) -> (key, emission parameters, features (N, K), Hyper, ends (K, S)
    or None) of that chosen draw."""
    keys = jax.random.split(jax.random.PRNGKey(seed), C * len(idx)).reshape(C, len(idx), -1)

    def at(c, j):
        d = idx[j]
        params = {k: jnp.asarray(v[c, d]) for k, v in params_all.items()}
        hyper = Hyper(*(jnp.float64(samples[n][c, d] if n in samples else hyper_fixed[n])
                        for n in ("alpha", "kappa", "gamma")))
        ends = jnp.asarray(samples["ends"][c, d]) if "ends" in samples else None
        return keys[c, j], params, samples["features"][c, d], hyper, ends
    return at


def _summarise(moments: np.ndarray, num_samples: int, demos) -> HeldOut:
    """HeldOut from each draw's log first and second moments of the likelihood and log
    probability of a nonempty skill set (S, 3, n): log mean_s p_s(x) - log mean_s P_s(nonempty),
    the denominator exact (the standard error is the numerator's)."""
    S, _, n = moments.shape
    top = np.max(moments[:, 0], axis=0)
    if not np.all(np.isfinite(top)):
        bad = int(np.argmin(np.isfinite(top)))
        raise ValueError(f"held-out trajectory {bad} has probability 0 under every posterior draw")
    first = np.exp(moments[:, 0] - top)  # (S, n), scaled by exp(top)
    second = np.exp(moments[:, 1] - 2 * top)
    mean = first.mean(axis=0)
    # the variance of each draw's sample mean, then of the average over draws
    var_draw = np.maximum(second - first ** 2, 0.0) / max(num_samples - 1, 1)
    se = np.sqrt(var_draw.sum(axis=0)) / S / mean
    if num_samples < 2:
        se = np.full(n, np.inf)
    log_p = top + np.log(mean) - (logsumexp(moments[:, 2], axis=0) - np.log(S))
    steps = int(np.sum(demos.lengths))
    return HeldOut(per_trajectory=log_p, per_trajectory_se=se, per_step=float(log_p.sum() / steps),
                   per_step_se=float(np.sqrt(np.sum(se ** 2)) / steps), num_steps=steps, num_draws=S)


def skill_probabilities(result) -> SkillProbabilities:
    """Each fitted step's posterior skill probabilities from the sampler's own draws: the share
    of the sampling sweeps, over every chain, in which the step was in each of the run's skills
    (every chain's slots mapped to them by :func:`npbrs.inference.analysis.diagnostics.relabel`);
    no MDP and no computation beyond that count. The same quantity as ``segment(result, mdp)`` up
    to Monte Carlo error; ``segment`` recomputes it from a subset of the draws, averaging each
    draw's smoothed probabilities (the transition weights integrated out), which is the less
    noisy of the two when a run has few draws (``docs/design.md``), and costs a forward-backward
    pass per draw and importance sample.

    Args:
        result: a FitResult that kept its per-step counts (``step_skill_counts``).
    Returns:
        a :class:`SkillProbabilities`: ``probs`` per trajectory (T, L) (a row sums to below 1
        where some draws put the step in a slot matched to none of the run's skills) and
        ``labels``, each step's most probable skill, the segmentation that labels the most steps
        right in expectation.
    """
    from .diagnostics import relabel

    if result.step_skill_counts is None:
        raise ValueError("this run kept no per-step skill counts (saved before they were kept); use "
                         "segment(mdp) instead")
    counts = np.asarray(result.step_skill_counts)
    C, N, T, K = counts.shape
    mapping = relabel(result)
    probs = np.zeros((N, T, result.num_skills))
    for c in range(C):
        for k in range(K):
            if mapping[c, k] >= 0:
                probs[..., mapping[c, k]] += counts[c, ..., k]
    probs /= C * result.num_draws
    rows = [probs[i, :m] for i, m in enumerate(len(s) for s in result.segmentation)]
    return SkillProbabilities(probs=rows, labels=[np.argmax(r, axis=-1) for r in rows])


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
