"""The reward emission: protocol, a valid MCMC move on a known posterior, and the sampler
recovering planted reward skills."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate
from scipy.special import expit

from emission_suite import check_emission
from gridworld import gridworld
from npbrs.domains import Demonstrations, TabularMDP, generate_demonstrations
from npbrs.inference import fit
from npbrs.inference.metrics import paper_accuracy
from npbrs.models.emissions import HMMData
from npbrs.models.reward import fisher_information
from npbrs.models.reward_emission import RewardEmission


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


def test_the_sampler_recovers_planted_reward_skills_in_a_gridworld():
    dom = gridworld()
    demos = generate_demonstrations(dom, num_trajectories=10, length=64, switch_prob=0.05, seed=0)
    result = fit(dom.mdp, demos, emission="reward", num_chains=4, num_samples=40, num_warmup=40, max_skills=5,
                 progress_bar=False)
    assert result.num_skills == 3
    assert paper_accuracy(demos.skills, result.segmentation) >= 0.9
    assert result.rhat["log_joint"] < 1.1


def _compiling(fn, *args, **kwargs):
    """fn(*args, **kwargs) and the seconds of every program JAX compiled (or loaded from its
    persistent cache) meanwhile; a call served by programs already in memory compiles none."""
    from jax._src.dispatch import BACKEND_COMPILE_EVENT

    compiles = []

    def listen(event, duration, **_):
        if event == BACKEND_COMPILE_EVENT:
            compiles.append(duration)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        return fn(*args, **kwargs), compiles
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)


def test_a_new_dataset_and_mdp_of_the_same_shapes_reuse_the_compiled_sampler():
    """The demonstrations and the MDP's arrays are arguments of the compiled programs, not
    constants: a second fit of other demonstrations in another MDP of the same shapes compiles
    nothing (it failed, compiling the sweep again, when the kernel was closed over)."""
    kwargs = dict(emission="reward", num_chains=4, num_samples=3, num_warmup=3, max_skills=5, progress_bar=False)
    dom = gridworld()
    first = fit(dom.mdp, generate_demonstrations(dom, num_trajectories=10, length=64, switch_prob=0.05, seed=3),
                **kwargs)
    other = gridworld(slip=0.2)
    demos = generate_demonstrations(other, num_trajectories=10, length=64, switch_prob=0.05, seed=4)
    second, compiles = _compiling(fit, other.mdp, demos, **kwargs)
    assert compiles == [], f"the second fit compiled {len(compiles)} programs ({sum(compiles):.1f} s)"
    assert second.fingerprint != first.fingerprint and second.mdp_fingerprint != first.mdp_fingerprint
    assert second.equals(fit(other.mdp, demos, **kwargs))  # the reused program: the same seed, the same draws


def test_a_data_set_in_the_same_shape_bucket_reuses_the_compiled_sampler():
    """``fit(bucket=True)`` pads to bucket sizes: another data set of other sizes in the same
    bucket compiles nothing, and the result has the demonstrations' own shapes."""
    from npbrs.models.emissions import bucket_size

    sizes = [bucket_size(n) for n in range(1, 1025)]
    assert all(s >= n and (n <= 8 or s <= 1.25 * n) for n, s in zip(range(1, 1025), sizes))
    assert len(set(sizes)) <= 40 and sizes == sorted(sizes)
    # padded to 10 x 64, the planted-skills fit's shapes above: in this module it compiles nothing
    kwargs = dict(emission="reward", num_chains=4, num_samples=3, num_warmup=3, max_skills=5, progress_bar=False,
                  bucket=True)
    dom = gridworld()
    fit(dom.mdp, generate_demonstrations(dom, num_trajectories=9, length=58, seed=5), **kwargs)
    demos = generate_demonstrations(dom, num_trajectories=9, length=61, seed=6)  # the same bucket
    result, compiles = _compiling(fit, dom.mdp, demos, **kwargs)
    assert compiles == [], f"the second fit compiled {len(compiles)} programs ({sum(compiles):.1f} s)"
    assert [len(z) for z in result.segmentation] == list(demos.lengths)
    assert result.samples["features"].shape[2] == 9 and result.chain_best_z.shape[1:] == (9, 61)
    assert result.config["sampler"]["bucket"] is True
    assert result.equals(fit(dom.mdp, demos, **kwargs))


_X64_SCRIPT = """
import sys
import jax, jax.numpy as jnp, numpy as np
sys.path.insert(0, {tests!r})
import npbrs.domains, npbrs.models, npbrs.inference
from gridworld import gridworld
from npbrs.domains import generate_demonstrations, soft_value_iteration
from npbrs.models.emissions import HMMData
from npbrs.models.reward import count_table, irl_fit
assert not jax.config.jax_enable_x64 and jnp.ones(1).dtype == jnp.float32, "importing npbrs changed jax_enable_x64"
other = gridworld(slip=0.2)
demos = generate_demonstrations(other, num_trajectories=10, length=64, switch_prob=0.05, seed=4)
rewards = np.linspace(-1, 1, other.mdp.num_states * other.mdp.num_actions).reshape(other.mdp.num_states, -1)
solve = soft_value_iteration(other.mdp, rewards)
data = HMMData.from_demonstrations(demos)
theta = irl_fit(other.mdp, count_table(data.states, data.actions, None, *rewards.shape, data.mask)).theta
assert not jax.config.jax_enable_x64 and jnp.ones(1).dtype == jnp.float32, "a call left jax_enable_x64 on"
np.savez({arrays!r}, V=np.asarray(solve.V), theta=np.asarray(theta), V_dtype=str(solve.V.dtype))
"""


def test_npbrs_computes_in_float64_without_switching_the_process_to_it(tmp_path):
    """Importing npbrs leaves JAX in float32 (a fresh process); there the solver and the IRL fit
    still compute in float64 (they run inside JAX's scoped switch) and give what they give in a
    float64 process; and ``fit`` with x64 off gives the draws it gives with x64 on, bit for bit
    (the same compiled program), leaving x64 off. (The notebooks run whole in float32 kernels.)"""
    import os
    import subprocess
    import sys

    from npbrs.domains import soft_value_iteration
    from npbrs.models.reward import count_table, irl_fit

    kwargs = dict(emission="reward", num_chains=4, num_samples=3, num_warmup=3, max_skills=5, progress_bar=False)
    script = _X64_SCRIPT.format(tests=os.path.dirname(__file__), arrays=str(tmp_path / "arrays.npz"))
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    cache = jax.config.jax_compilation_cache_dir
    if cache:  # the test session's compilation cache: the float64 programs compiled here are reused there
        env.update(JAX_COMPILATION_CACHE_DIR=cache, JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0.5",
                   JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0")
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    other = gridworld(slip=0.2)
    demos = generate_demonstrations(other, num_trajectories=10, length=64, switch_prob=0.05, seed=4)
    here = fit(other.mdp, demos, **kwargs)
    with jax.enable_x64(False):
        assert jnp.ones(1).dtype == jnp.float32
        there = fit(other.mdp, demos, **kwargs)
        assert not jax.config.jax_enable_x64 and jnp.ones(1).dtype == jnp.float32, "fit left jax_enable_x64 on"
    assert there.num_skills == here.num_skills and all(np.array_equal(a, b) for a, b in zip(there.segmentation,
                                                                                             here.segmentation))
    for name in here.samples:
        np.testing.assert_array_equal(there.samples[name], here.samples[name], err_msg=name)
    np.testing.assert_array_equal(there.stats["log_joint"], here.stats["log_joint"])
    arrays = np.load(tmp_path / "arrays.npz")
    assert str(arrays["V_dtype"]) == "float64"
    rewards = np.linspace(-1, 1, other.mdp.num_states * other.mdp.num_actions).reshape(other.mdp.num_states, -1)
    np.testing.assert_allclose(arrays["V"], np.asarray(soft_value_iteration(other.mdp, rewards).V), rtol=1e-13)
    data = HMMData.from_demonstrations(demos)
    counts = count_table(data.states, data.actions, None, *rewards.shape, data.mask)
    np.testing.assert_allclose(arrays["theta"], np.asarray(irl_fit(other.mdp, counts).theta), rtol=1e-10)


def test_data_driven_proposal_is_the_defensive_mixture_it_scores():
    """Draws of the proposal follow (1 - w) N(fit, C) + w N(fit, s^2 C), and the scored density
    is that mixture's (checked against the formula and against the draws' Mahalanobis radii)."""
    from scipy.stats import chi2 as chi2_dist, multivariate_normal

    dom = gridworld(size=3)
    demos = generate_demonstrations(dom, num_trajectories=2, length=15, seed=3)
    data = HMMData.from_demonstrations(demos)
    em = RewardEmission(dom.mdp, proposal_broad_weight=0.2, proposal_broad_scale=5.0)
    weights = jnp.asarray(data.mask, jnp.float64)
    mean, chol = (np.asarray(x) for x in jax.jit(em._proposal)(data, weights))
    D = mean.shape[0]
    other = {"theta": jnp.asarray(mean + 7.0 * np.diag(chol))}
    draw = jax.jit(jax.vmap(lambda k: em.propose_and_score(k, data, weights, other)))
    thetas, log_q, log_q_other = draw(jax.random.split(jax.random.PRNGKey(0), 4000))
    thetas = np.asarray(thetas["theta"])
    cov = chol @ chol.T

    def mixture(x):
        return np.logaddexp(np.log(0.8) + multivariate_normal(mean, cov).logpdf(x),
                            np.log(0.2) + multivariate_normal(mean, 25.0 * cov).logpdf(x))

    np.testing.assert_allclose(np.asarray(log_q)[:20], mixture(thetas[:20]), rtol=1e-8)
    np.testing.assert_allclose(np.asarray(log_q_other)[0], mixture(np.asarray(other["theta"])), rtol=1e-8)
    np.testing.assert_allclose(float(jax.jit(em.log_proposal)({"theta": jnp.asarray(thetas[0])}, data, weights)),
                               mixture(thetas[0]), rtol=1e-8)
    r2 = np.sum(np.linalg.solve(chol, (thetas - mean).T) ** 2, axis=0)
    q = chi2_dist.ppf(0.99, D)
    expected = 0.8 * 0.01 + 0.2 * chi2_dist.sf(q / 25.0, D)
    assert abs(np.mean(r2 > q) - expected) < 4 * np.sqrt(expected * (1 - expected) / 4000)
    # w = 0 is the single Gaussian
    plain = RewardEmission(dom.mdp, proposal_broad_weight=0.0)
    _, lq, _ = plain.propose_and_score(jax.random.PRNGKey(1), data, weights, other)
    th, _, _ = plain.propose_and_score(jax.random.PRNGKey(1), data, weights, other)
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
                        map_steps=40, update="map")
    data = HMMData(jnp.zeros((1, 100), jnp.int32), jnp.asarray([[0] * 30 + [1] * 70], jnp.int32),
                   jnp.ones((1, 100), bool))
    w = jnp.ones((1, 100, 1))
    np.testing.assert_allclose(float(em.fit_point(data, w)["theta"][0, 0]), mode, atol=1e-4)
    np.testing.assert_allclose(float(em.fit_evidence(data, w)[0]["theta"][0, 0]), mode, atol=1e-4)
    params, _, _ = em.update(jax.random.PRNGKey(0), {"theta": jnp.zeros((1, 1))}, em.init_cache(1), data, w, False)
    np.testing.assert_allclose(float(params["theta"][0, 0]), mode, atol=1e-4)
    if tau == 2.0:
        assert abs(mode - 0.4187) < 1e-4
