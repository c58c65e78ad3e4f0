"""The reward emission: protocol, valid MCMC moves on known posteriors, its proposals and fits
(the sampler's fits with it: test_reward_fit.py)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate
from scipy.special import expit

from emission_suite import check_emission
from gridworld import gridworld
from npbrs.domains import TabularMDP, generate_demonstrations
from npbrs.models.emissions import HMMData
from npbrs.models.reward.emission import RewardEmission
from npbrs.models.reward.likelihood import fisher_information


def test_reward_emission_follows_the_protocol():
    dom = gridworld(size=3)
    demos = generate_demonstrations(dom, num_trajectories=3, length=12, seed=1)
    # (the sampler's part, a compiled reward sweep, is left to the planted-skills fit below; the
    # log joint's emission term is log_prior, checked against the sites here)
    # the emission with sampled prior variances: the same code plus the sigma2 site, its
    # conditional in the proposals and its Gibbs step (so it covers the fixed-scale emission's
    # paths too; those run in every fit below)
    check_emission(RewardEmission(dom.mdp, scale_prior=(2.0, 8.0)), HMMData.from_demonstrations(demos), sampler=False)
    with pytest.raises(ValueError, match="scale_prior"):
        RewardEmission(dom.mdp, scale_prior=(2.0, -1.0))
    # the default fixes the prior's scale at prior_scale (as do False, None and "off"); (a, b)
    # samples its variance, and a saved configuration keeps the choice (TOML has no None)
    from npbrs.inference import ModelConfig, make_emission

    assert RewardEmission(dom.mdp).scale_prior is None
    for off in (False, None, "off"):
        assert RewardEmission(dom.mdp, scale_prior=off).scale_prior is None
    for em in (RewardEmission(dom.mdp, scale_prior=[1, 1]), RewardEmission(dom.mdp)):
        options = {k: v for k, v in em.describe().items() if k != "name"}
        cfg = ModelConfig.from_dict({"emission": {"name": "reward", "options": options}})
        back = ModelConfig.from_toml_string(cfg.to_toml()).emission.options
        assert make_emission("reward", dom.mdp, **back).scale_prior == em.scale_prior
    # the noisy expert's emission: its likelihoods are the mixture's (the rest of the protocol is
    # the same code as above; its likelihood's gradient is tested in test_reward.py, and a second
    # full protocol run here cost a minute of the test suite's compiling)
    data = HMMData.from_demonstrations(demos)
    noisy = RewardEmission(dom.mdp, epsilon=0.05)
    params = {"theta": jnp.asarray(np.random.default_rng(0).normal(size=(2, dom.mdp.num_features)) * 3)}
    plain_ll, _ = jax.jit(RewardEmission(dom.mdp).log_likelihoods)(params, data)
    noisy_ll, _ = jax.jit(noisy.log_likelihoods)(params, data)
    A = dom.mdp.num_actions
    expected = np.log(0.95 * np.exp(np.asarray(plain_ll)) + 0.05 / A)
    np.testing.assert_allclose(np.where(data.mask[..., None], noisy_ll, 0), np.where(data.mask[..., None], expected, 0),
                               rtol=1e-10)
    with pytest.raises(ValueError, match="epsilon"):
        RewardEmission(dom.mdp, epsilon=1.0)


def test_the_default_prior_scale_is_10_for_a_few_features_and_narrows_with_one_weight_per_state():
    from scipy import stats

    from npbrs.domains.highway import FEATURE_NAMES as HIGHWAY_FEATURES
    from npbrs.domains.quadcopter import FEATURE_NAMES as QUADCOPTER_FEATURES
    from npbrs.domains.worlds import labyrinth_mdp, rooms_mdp
    from npbrs.models.reward.prior import auto_prior_df, auto_prior_scale

    # the paper's domains (4 and 3 features) keep a Gaussian of sigma 10, so their tables' draws are unchanged
    assert len(HIGHWAY_FEATURES) == 4 and len(QUADCOPTER_FEATURES) == 3
    assert auto_prior_scale(3) == auto_prior_scale(4) == 10.0
    assert auto_prior_df(3) is None and auto_prior_df(16) is None and auto_prior_df(17) == 2.0
    small = RewardEmission(gridworld(size=3).mdp)
    assert small.prior_scale == 10.0 and small.prior_df is None and small.describe()["prior_df"] is False
    # one weight per state: a Student t of 2 degrees of freedom and scale 0.5 per weight; with
    # prior_df None the Gaussian's sigma^2 D held at 400 (the four rooms' 104 cells: 1.96)
    for mdp in (rooms_mdp(), labyrinth_mdp()):
        D = mdp.num_features
        assert D == mdp.num_states > 100
        em = RewardEmission(mdp)
        assert (em.prior_df, em.prior_scale) == (2.0, 0.5)
        assert em.describe()["prior_df"] == 2.0 and em.describe()["prior_scale"] == 0.5  # the run records them
        again = RewardEmission(mdp, **{k: v for k, v in em.describe().items() if k != "name"})
        assert again.describe() == em.describe()  # (a saved run's emission is rebuilt from its record)
        gauss = RewardEmission(mdp, prior_df=None)
        np.testing.assert_allclose(gauss.prior_scale, 20.0 / np.sqrt(D), rtol=1e-12)
        for off in (False, "off"):
            assert RewardEmission(mdp, prior_df=off).prior_df is None
        assert RewardEmission(mdp, prior_scale=10.0).prior_scale == 10.0  # a number is kept as given
        assert RewardEmission(mdp, prior_df=5).prior_df == 5.0
        # a sampled scale per skill is its own heavy-tailed prior: no t under "auto", an error when both are asked
        assert RewardEmission(mdp, scale_prior=(3.0, 3.0)).prior_df is None
        with pytest.raises(ValueError, match="cannot be combined"):
            RewardEmission(mdp, scale_prior=(3.0, 3.0), prior_df=2.0)
        # the prior the sampler uses is that density, and the model's (numpyro) prior the same
        theta = jnp.linspace(-3.0, 6.0, 2 * D).reshape(2, D)
        np.testing.assert_allclose(np.asarray(em.log_prior({"theta": theta})),
                                   stats.t(2.0, scale=0.5).logpdf(np.asarray(theta)).sum(1), rtol=1e-10)
        np.testing.assert_allclose(np.asarray(gauss.log_prior({"theta": theta})),
                                   stats.norm(scale=gauss.prior_scale).logpdf(np.asarray(theta)).sum(1), rtol=1e-10)
        from numpyro import handlers

        traced = handlers.trace(handlers.seed(lambda: em.sample_params(2), 0)).get_trace()
        np.testing.assert_allclose(float(traced["theta"]["fn"].log_prob(theta)),
                                   float(jnp.sum(em.log_prior({"theta": theta}))), rtol=1e-10)
    np.testing.assert_allclose(auto_prior_scale(104), 1.9612, atol=1e-4)
    for bad in ("wide", 0.0, -1.0):
        with pytest.raises(ValueError, match="prior_scale"):
            RewardEmission(rooms_mdp(), prior_scale=bad)
    for bad in ("t", 0.0, -2.0, True, float("nan")):
        with pytest.raises(ValueError, match="prior_df"):
            RewardEmission(rooms_mdp(), prior_df=bad)
    with pytest.raises(ValueError, match="t_evidence"):
        RewardEmission(rooms_mdp(), t_evidence="exact")


def test_the_student_t_priors_gradient_and_curvature_are_its_log_densitys_derivatives():
    """prior_grad and prior_curvature against central differences of log_prior (the curvature
    where the t's is above its floor, and the floor in its tails), for both priors."""
    from npbrs.models.reward.prior import log_prior, prior_curvature, prior_grad

    theta = jnp.array([[-4.0, -0.7, -0.1, 0.0, 0.3, 0.9, 2.5]])
    h = 1e-4
    for scale, df in ((0.5, 2.0), (1.3, 5.0), (2.0, None)):
        lp = lambda t: float(log_prior(jnp.asarray([[t]]), scale, df)[0])  # noqa: E731
        for t in np.asarray(theta[0]):
            d1 = (lp(t + h) - lp(t - h)) / (2 * h)
            d2 = -(lp(t + h) - 2 * lp(t) + lp(t - h)) / h ** 2
            np.testing.assert_allclose(float(prior_grad(jnp.asarray(t), scale, df)), d1, rtol=1e-6, atol=1e-8)
            c = float(prior_curvature(jnp.asarray(t), scale, df))
            floor = 0.0 if df is None else 0.01 * (df + 1) / (df * scale ** 2)
            np.testing.assert_allclose(c, max(d2, floor), rtol=1e-4, atol=1e-6)
        assert prior_grad(theta, scale, df).shape == prior_curvature(theta, scale, df).shape == theta.shape


def one_state_mdp():
    # one state, two actions, phi(s, a) = [a == 1]: pi(1) = sigmoid(theta), a logistic regression
    return TabularMDP.from_dense(np.ones((1, 2, 1)), features=np.array([[[0.0], [1.0]]]), discount=0.5)


def test_fisher_information_of_a_logistic_policy():
    em = RewardEmission(one_state_mdp())
    counts = jnp.array([[3.0, 5.0]])
    p = expit(0.7)
    F = fisher_information(em.solver, jnp.array([0.7]), counts)
    np.testing.assert_allclose(float(F[0, 0]), 8 * p * (1 - p), rtol=1e-8)


@pytest.mark.parametrize("scale_prior", [None, (2.0, 2.0)])
def test_mala_move_leaves_the_logistic_posterior_invariant(scale_prior):
    """The reward update (MALA with the preconditioner refreshed in warmup, as the sampler does)
    samples the exact posterior of a logistic conditional; with a sampled prior variance
    (sigma^2 ~ InvGamma(a, b), its Gibbs step after MALA) theta's marginal prior is a Student-t
    with 2a degrees of freedom and scale sqrt(b / a), and E[sigma^2 | data] =
    E[(b + theta^2 / 2) / (a - 1/2) | data]: both checked against quadrature."""
    from numpyro.diagnostics import effective_sample_size
    from scipy.stats import t as student_t

    n0, n1, sigma = 3, 9, 2.0
    em = RewardEmission(one_state_mdp(), prior_scale=sigma, mala_steps=2, scale_prior=scale_prior)
    T = n0 + n1
    data = HMMData(jnp.zeros((1, T), jnp.int32), jnp.asarray([[0] * n0 + [1] * n1], jnp.int32), jnp.ones((1, T), bool))
    weights = jnp.ones((1, T, 1))

    def log_post(t):
        if scale_prior is None:
            prior = -0.5 * t ** 2 / sigma ** 2
        else:
            a, b = scale_prior
            prior = student_t.logpdf(t, df=2 * a, scale=np.sqrt(b / a))
        return prior + n1 * np.log(expit(t)) + n0 * np.log(expit(-t))

    Z = integrate.quad(lambda t: np.exp(log_post(t)), -30, 30)[0]
    mean = integrate.quad(lambda t: t * np.exp(log_post(t)), -30, 30)[0] / Z
    var = integrate.quad(lambda t: (t - mean) ** 2 * np.exp(log_post(t)), -30, 30)[0] / Z

    chains, warmup, draws = 8, 100, 1500
    start = {"theta": jnp.zeros((1, 1))} if scale_prior is None else {"theta": jnp.zeros((1, 1)),
                                                                       "sigma2": jnp.ones(1)}

    def run(key):
        params, cache = start, em.init_cache(1)

        def body(carry, xs):
            params, cache = carry
            key, adapt = xs
            # as the sampler does: the preconditioner refreshed in warmup, then fixed
            cache = jax.lax.cond(adapt, lambda c: em.tune(params, c, data, weights), lambda c: c, cache)
            params, cache, info = em.update(key, params, cache, data, weights, adapt)
            return (params, cache), jax.tree.map(lambda x: x[0], params)

        adapt = jnp.arange(warmup + draws) < warmup
        _, trace = jax.lax.scan(body, (params, cache), (jax.random.split(key, warmup + draws), adapt))
        return jax.tree.map(lambda x: x[warmup:], trace)

    trace = jax.jit(jax.vmap(run))(jax.random.split(jax.random.PRNGKey(0), chains))
    thetas = np.asarray(trace["theta"])[..., 0]
    ess = float(effective_sample_size(thetas))
    assert ess > 500
    assert abs(thetas.mean() - mean) < 4 * np.sqrt(var / ess)
    # the variance's standard error: var * sqrt(2 / ess) for a near-Gaussian posterior
    assert abs(thetas.var() - var) < 4 * var * np.sqrt(2 / ess)
    if scale_prior is not None:
        a, b = scale_prior
        want = integrate.quad(lambda t: (b + t ** 2 / 2) / (a - 0.5) * np.exp(log_post(t)), -30, 30)[0] / Z
        s2 = np.asarray(trace["sigma2"])
        ess_s2 = float(effective_sample_size(s2))
        assert ess_s2 > 300
        assert abs(s2.mean() - want) < 4 * s2.std() / np.sqrt(ess_s2), (s2.mean(), want, ess_s2)


def test_data_driven_proposal_is_the_defensive_mixture_it_scores():
    """Draws of the proposal follow (1 - w) N(fit, C) + w N(fit, s^2 C), and the scored density
    is that mixture's (checked against the formula and against the draws' Mahalanobis radii)."""
    from scipy.stats import chi2 as chi2_dist, multivariate_normal

    dom = gridworld(size=3)
    demos = generate_demonstrations(dom, num_trajectories=2, length=15, seed=3)
    data = HMMData.from_demonstrations(demos)
    # (the fixed-scale emission: its proposal of theta is the whole proposal)
    em = RewardEmission(dom.mdp, proposal_broad_weight=0.2, proposal_broad_scale=5.0, scale_prior=False)
    weights = jnp.asarray(data.mask, jnp.float64)
    plain = RewardEmission(dom.mdp, proposal_broad_weight=0.0, scale_prior=False)  # w = 0: the single Gaussian

    @jax.jit  # one program: XLA shares the proposals' common IRL fit (four programs took twice as long)
    def run(keys, key):
        mean, chol = em.proposal(data, weights)
        other = {"theta": mean + 7.0 * jnp.diag(chol)}
        thetas, log_q, log_q_other = jax.vmap(lambda k: em.propose_and_score(k, data, weights, other))(keys)
        first = em.log_proposal({"theta": thetas["theta"][0]}, data, weights)
        return mean, chol, other, thetas, log_q, log_q_other, first, plain.propose_and_score(key, data, weights, other)

    mean, chol, other, thetas, log_q, log_q_other, first, (th, lq, _) = run(
        jax.random.split(jax.random.PRNGKey(0), 4000), jax.random.PRNGKey(1))
    mean, chol = np.asarray(mean), np.asarray(chol)
    D = mean.shape[0]
    thetas = np.asarray(thetas["theta"])
    cov = chol @ chol.T

    def mixture(x):
        return np.logaddexp(np.log(0.8) + multivariate_normal(mean, cov).logpdf(x),
                            np.log(0.2) + multivariate_normal(mean, 25.0 * cov).logpdf(x))

    np.testing.assert_allclose(np.asarray(log_q)[:20], mixture(thetas[:20]), rtol=1e-8)
    np.testing.assert_allclose(np.asarray(log_q_other)[0], mixture(np.asarray(other["theta"])), rtol=1e-8)
    np.testing.assert_allclose(float(first), mixture(thetas[0]), rtol=1e-8)
    r2 = np.sum(np.linalg.solve(chol, (thetas - mean).T) ** 2, axis=0)
    q = chi2_dist.ppf(0.99, D)
    expected = 0.8 * 0.01 + 0.2 * chi2_dist.sf(q / 25.0, D)
    assert abs(np.mean(r2 > q) - expected) < 4 * np.sqrt(expected * (1 - expected) / 4000)
    # w = 0 is the single Gaussian
    np.testing.assert_allclose(float(lq), multivariate_normal(mean, cov).logpdf(np.asarray(th["theta"])), rtol=1e-8)
    with pytest.raises(ValueError, match="proposal_broad_weight"):
        RewardEmission(dom.mdp, proposal_broad_weight=1.0)


@pytest.mark.parametrize("tau", [2.0, pytest.param(0.5, marks=pytest.mark.slow)])
def test_irl_fits_find_the_posterior_mode_at_any_temperature(tau):
    """One state, feature [a == 1], 30 steps of action 0 and 70 of action 1, prior N(0, 1): the
    mode of 70 tau theta - 100 log(1 + exp(tau theta)) - theta^2 / 2 solves
    70 tau - 100 tau sigmoid(tau theta) - theta = 0 (0.4187 at tau = 2). fit_point, the
    greedy moves' evidence fit and the "map" update must all land there."""
    from scipy.optimize import brentq

    mode = brentq(lambda t: 70 * tau - 100 * tau * expit(tau * t) - t, -10, 10)
    em = RewardEmission(one_state_mdp(), prior_scale=1.0, temperature=tau, refit_steps=20, fit_steps=40,
                        map_steps=40, update="map", scale_prior=False)
    data = HMMData(jnp.zeros((1, 100), jnp.int32), jnp.asarray([[0] * 30 + [1] * 70], jnp.int32),
                   jnp.ones((1, 100), bool))
    w = jnp.ones((1, 100, 1))
    np.testing.assert_allclose(float(em.fit_point(data, w)["theta"][0, 0]), mode, atol=1e-4)
    np.testing.assert_allclose(float(em.fit_evidence(data, w)[0]["theta"][0, 0]), mode, atol=1e-4)
    params, _, _ = em.update(jax.random.PRNGKey(0), {"theta": jnp.zeros((1, 1))}, em.init_cache(1), data, w, False)
    np.testing.assert_allclose(float(params["theta"][0, 0]), mode, atol=1e-4)
    if tau == 2.0:
        assert abs(mode - 0.4187) < 1e-4


def test_start_at_the_fit_is_each_skills_posterior_mode():
    """``start="fit"``: a chain's first rewards are each skill's IRL fit, where the gradient of
    its conditional log-posterior vanishes (up to the fit's 20 L-BFGS steps; the default draw
    around it has gradients of order 100 here). Bad values are refused; the choice is part of the
    emission's description."""
    from npbrs.models.reward.likelihood import log_posterior

    dom = gridworld(size=3)
    demos = generate_demonstrations(dom, num_trajectories=4, length=40, switch_prob=0.05, seed=2)
    data = HMMData.from_demonstrations(demos)
    z = np.zeros(data.mask.shape, int)
    for i, s in enumerate(demos.skills):
        z[i, :len(s)] = s
    weights = jax.nn.one_hot(jnp.asarray(z), 3) * data.mask[..., None]
    em = RewardEmission(dom.mdp, prior_scale=3.0, start="fit", epsilon=0.05, temperature=2.0)
    assert em.describe()["start"] == "fit" and em.starts_at_fit
    # the default, "auto": a draw around the fit for a handful of features, the fit for one-hot ones
    assert RewardEmission(dom.mdp).start == "auto" and not RewardEmission(dom.mdp).starts_at_fit
    from npbrs.domains.worlds import labyrinth_mdp
    one_hot = labyrinth_mdp(depth=4)  # 31 states, a weight each
    assert RewardEmission(one_hot).starts_at_fit and not RewardEmission(one_hot, start="draw").starts_at_fit

    @jax.jit
    def gradient_at_start(key):
        theta = em.init_params(key, data, weights)["theta"]
        return log_posterior(em.solver, theta, em.counts(data, weights), jnp.zeros((3, em.num_states)), 3.0,
                             temperature=2.0, epsilon=0.05).grad

    assert np.max(np.abs(np.asarray(gradient_at_start(jax.random.PRNGKey(0))))) < 1e-3
    with pytest.raises(ValueError, match="start"):
        RewardEmission(dom.mdp, start="mode")


def test_the_preconditioner_refreshed_inside_the_update_is_tunes():
    """``update(..., tune=True)`` (what the sampler passes in its tuning sweeps) refreshes the
    MALA preconditioner from the first pass's values, with no solve of its own: the same
    scales as :meth:`RewardEmission.tune` at the same weights, for every skill with steps (a
    skill without steps is not solved by the move, and is redrawn from the prior). Without
    ``tune`` the cache's scales are kept. (Checked to fail with the refresh at the values the
    cache held before the move.)"""
    dom = gridworld(size=3)
    demos = generate_demonstrations(dom, num_trajectories=3, length=20, seed=2)
    data = HMMData.from_demonstrations(demos)
    em = RewardEmission(dom.mdp, scale_prior=(2.0, 8.0), temperature=1.5)
    K = 3
    z = np.zeros(data.mask.shape, int)
    for i, s in enumerate(demos.skills):
        z[i, :len(s)] = np.minimum(s, 1)  # skills 0 and 1 have steps, skill 2 none
    weights = jax.nn.one_hot(jnp.asarray(z), K) * data.mask[..., None]
    params = {"theta": jnp.asarray(np.random.default_rng(0).normal(size=(K, dom.mdp.num_features))),
              "sigma2": jnp.full(K, 4.0)}
    cache = em.init_cache(K)  # (cold: values of zero, which the move's first pass solves from)
    key = jax.random.PRNGKey(3)
    refreshed = jax.jit(lambda p, c: em.update(key, p, c, data, weights, True, tune=True)[1]["scale"])(params, cache)
    kept = jax.jit(lambda p, c: em.update(key, p, c, data, weights, True)[1]["scale"])(params, cache)
    tuned = jax.jit(lambda p, c: em.for_search().tune(p, c, data, weights)["scale"])(params, cache)
    np.testing.assert_allclose(np.asarray(refreshed)[:2], np.asarray(tuned)[:2], rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(kept), np.asarray(cache["scale"]))
    assert not np.allclose(np.asarray(tuned)[:2], np.asarray(cache["scale"])[:2], rtol=1e-2)


@pytest.mark.parametrize("scale_prior", [None, (2.0, 8.0)])
def test_the_sweeps_likelihoods_are_backups_from_the_moves_values(scale_prior, monkeypatch):
    """With MALA (``solves_in_update``) the reward emission draws or keeps the unused skills'
    weights itself (``redraw_unused``: the sampler's schedule, here every 3 sweeps) before its
    move, whose first pass solves every skill, and the sweep's likelihoods are backups from the
    values it returns: after a sweep that keeps and one that redraws, the state's likelihoods and
    values are a fresh solve's of its weights, the unused skills' weights kept exactly or drawn
    anew, the used skills' moved. The fixed-variance case solves the skills in chunks of 2 (as a
    large MDP does; here too small to need it), the other all at once. (Checked to fail with the
    first pass solving only the skills with steps, and with the prior draws made after the
    move.)"""
    from npbrs.inference.sampler import BPHMMKernel
    from npbrs.models.reward import mala

    if scale_prior is None:
        monkeypatch.setattr(mala, "BATCH_ENTRIES", 2 * 9 * 5)  # (9 states, 5 actions: chunks of 2)

    dom = gridworld(size=3)
    demos = generate_demonstrations(dom, num_trajectories=3, length=20, seed=2)
    data = HMMData.from_demonstrations(demos)
    em = RewardEmission(dom.mdp, scale_prior=scale_prior, temperature=1.5)
    assert em.solves_in_update and not RewardEmission(dom.mdp, update="map").solves_in_update
    kernel = BPHMMKernel(em, data, max_skills=5, init_skills=2, moves={"redraw_unused": 3})
    state = kernel.init(jax.random.PRNGKey(1), 0, None, (), {})
    sweep = jax.jit(kernel.sweep)
    fresh = jax.jit(lambda p: em.log_likelihoods(p, data))
    for step, redraw in ((1, False), (3, True)):
        s = state._replace(step=jnp.int32(step))
        new = sweep(s)
        ll, cache = fresh(new.params)
        np.testing.assert_allclose(np.asarray(new.log_lik), np.asarray(ll), atol=1e-8)
        np.testing.assert_allclose(np.asarray(new.cache["V"]), np.asarray(cache["V"]), rtol=1e-8, atol=1e-8)
        used = np.asarray(jnp.any((new.z[..., None] == jnp.arange(5)) & data.mask[..., None], axis=(0, 1)))
        assert used.any() and (~used).any()
        old, theta = np.asarray(s.params["theta"]), np.asarray(new.params["theta"])
        assert not np.allclose(theta[used], old[used])
        if redraw:
            assert not np.any(np.isclose(theta[~used], old[~used]))
        else:
            np.testing.assert_array_equal(theta[~used], old[~used])


def test_the_likelihoods_report_whether_each_skills_solve_converged():
    """``log_likelihoods(..., with_ok=True)`` (``reports_solves``) adds ok (K,): each skill's soft
    solve converged to the solver's tolerance and its log-likelihoods are finite. A solver that
    stops after one Newton step reports False, the default solver True; the likelihoods and the
    cache (its structure too: it is carried in the sampler's state) are those without
    ``with_ok``."""
    dom = gridworld(size=3)
    data = HMMData.from_demonstrations(generate_demonstrations(dom, num_trajectories=2, length=10, seed=1))
    params = {"theta": jnp.asarray(dom.skill_weights[:2])}
    assert RewardEmission.reports_solves
    for options, converged in (({}, True), ({"max_iter": 1}, False)):
        em = RewardEmission(dom.mdp, solver_options=options)
        ll, cache, ok = em.log_likelihoods(params, data, em.init_cache(2), with_ok=True)
        assert ok.shape == (2,) and ok.dtype == bool
        np.testing.assert_array_equal(np.asarray(ok), converged)
        plain_ll, plain_cache = em.log_likelihoods(params, data, em.init_cache(2))
        np.testing.assert_array_equal(np.asarray(ll), np.asarray(plain_ll))
        assert sorted(cache) == sorted(plain_cache) == sorted(em.init_cache(2))
        np.testing.assert_array_equal(np.asarray(cache["V"]), np.asarray(plain_cache["V"]))
