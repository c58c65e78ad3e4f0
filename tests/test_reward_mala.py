import jax
import jax.numpy as jnp
import numpy as np
import pytest
from numpyro.diagnostics import effective_sample_size

from scipy.optimize import brentq
from scipy.special import expit

from npbrs.domains import TabularMDP, make_soft_solver
from npbrs.models.reward.irl import irl_fit
from npbrs.models.reward.mala import RewardMALAInfo, RewardMALAState, build_kernel, init


def logistic_mdp(gamma=0.9):
    """One absorbing state, two actions, phi(s, a) = [a]: Q = r + gamma V, so
    log pi(1 | s) = theta - log(1 + e^theta), a logistic regression in theta."""
    return TabularMDP(successors=np.zeros((1, 2, 1), int), probs=np.ones((1, 2, 1)),
                      features=np.array([[[0.0], [1.0]]]), discount=gamma)


def exact_posterior(counts, sigma, tau=1.0, eps=0.0, df=None):
    """Mean and variance of theta given counts (n0, n1) by quadrature on a fine grid, for the
    policy pi(1) = (1 - eps) sigmoid(tau theta) + eps / 2 and a Normal(0, sigma^2) prior (or
    scipy's Student t of ``df`` degrees of freedom and scale sigma)."""
    from scipy import stats

    grid = np.linspace(-30, 30, 600001)
    n0, n1 = counts
    p1 = (1 - eps) * expit(tau * grid) + eps / 2
    prior = stats.norm(scale=sigma) if df is None else stats.t(df, scale=sigma)
    logp = n1 * np.log(p1) + n0 * np.log1p(-p1) + prior.logpdf(grid)
    w = np.exp(logp - logp.max())
    w /= w.sum()
    mean = (w * grid).sum()
    return mean, (w * (grid - mean) ** 2).sum()


@pytest.mark.parametrize("tau, eps, df", [(1.0, 0.0, None), (2.0, 0.1, None), (1.0, 0.0, 2.0)])
def test_mala_samples_the_exact_posterior_of_a_logistic_conditional(tau, eps, df):
    """Two skills at once, each with its own counts: chain means and variances agree with
    quadrature within Monte Carlo standard errors, at temperature 1 and at temperature 2 with a
    noisy expert (epsilon 0.1), and under a Student t prior of 2 degrees of freedom and scale
    0.5 (the default for one weight per state)."""
    sigma = 2.0 if df is None else 0.5
    counts = np.array([[3.0, 7.0], [10.0, 2.0]])
    truth = [exact_posterior(c, sigma, tau, eps, df) for c in counts]
    solver = make_soft_solver(logistic_mdp(), tol=1e-12)
    C = jnp.asarray(counts[:, None, :])  # (K, S=1, A=2)
    kernel = build_kernel(solver, prior_scale=sigma, temperature=tau, epsilon=eps, prior_df=df)
    step = jnp.asarray([1.1 * np.sqrt(v) for _, v in truth])
    state = init(solver, jnp.zeros((2, 1)), C, prior_scale=sigma, temperature=tau, epsilon=eps, prior_df=df)
    assert isinstance(state, RewardMALAState)

    @jax.jit
    def run(key, state):
        def one(st, k):
            st, info = kernel(k, st, C, step)
            return st, (st.theta[:, 0], info)

        return jax.lax.scan(one, state, jax.random.split(key, 4000))

    last, (theta, info) = run(jax.random.PRNGKey(0), state)
    assert isinstance(info, RewardMALAInfo)
    theta = np.asarray(theta)[500:]
    acc = np.asarray(info.is_accepted).mean(0)
    assert np.all((acc > 0.5) & (acc < 0.99)), acc
    assert not np.asarray(info.solver_failed).any()
    for k, (mean, var) in enumerate(truth):
        x = theta[:, k]
        ess = float(effective_sample_size(x[None]))
        assert ess > 300
        assert abs(x.mean() - mean) < 4 * x.std() / np.sqrt(ess), (k, x.mean(), mean, ess)
        dev = (x - x.mean()) ** 2
        ess_var = float(effective_sample_size(dev[None]))
        assert abs(dev.mean() - var) < 4 * dev.std() / np.sqrt(ess_var), (k, dev.mean(), var, ess_var)
    # the state carried along the chain is the density and gradient at its theta
    fresh = init(solver, last.theta, C, prior_scale=sigma, v0=last.V, temperature=tau, epsilon=eps, prior_df=df)
    np.testing.assert_allclose(last.log_density, fresh.log_density, rtol=1e-10)
    np.testing.assert_allclose(last.grad, fresh.grad, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("tau", [0.5, 1.0, 2.0])
def test_the_irl_fit_finds_the_analytic_mode_at_any_temperature(tau):
    """30 steps of action 0 and 70 of action 1 with prior N(0, 1): the mode of
    70 tau theta - 100 log(1 + exp(tau theta)) - theta^2 / 2 is the root of
    70 tau - 100 tau sigmoid(tau theta) - theta (0.4187 at tau = 2; a prior applied to tau theta
    instead of theta gives 0.4045 there). The temperature is traced: one program for all three."""
    mode = brentq(lambda t: 70 * tau - 100 * tau * expit(tau * t) - t, -10, 10)
    fit = irl_fit(make_soft_solver(logistic_mdp(), tol=1e-12), np.array([[30.0, 70.0]]), prior_scale=1.0,
                  num_steps=40, temperature=tau)
    np.testing.assert_allclose(float(fit.theta[0]), mode, atol=1e-5)
    if tau == 2.0:
        assert abs(mode - 0.4187) < 1e-4
    # under a Student t prior (3 degrees of freedom, scale 0.3): the root of
    # 70 tau - 100 tau sigmoid(tau theta) - 4 theta / (3 * 0.09 + theta^2)
    mode_t = brentq(lambda t: 70 * tau - 100 * tau * expit(tau * t) - 4 * t / (0.27 + t ** 2), -10, 10)
    fit_t = irl_fit(make_soft_solver(logistic_mdp(), tol=1e-12), np.array([[30.0, 70.0]]), prior_scale=0.3,
                    num_steps=40, temperature=tau, prior_df=3.0)
    np.testing.assert_allclose(float(fit_t.theta[0]), mode_t, atol=1e-5)
    assert abs(mode_t - mode) > 0.02  # (a different prior: a different mode)


def test_a_proposal_whose_solve_failed_is_rejected():
    """A solver capped at one value-iteration sweep never reaches its tolerance: every proposal
    is rejected, the state stays as it was, and the info says why."""
    solver = make_soft_solver(logistic_mdp(gamma=0.99), tol=1e-12, method="vi", max_iter=1)
    C = jnp.asarray([[[3.0, 7.0]], [[10.0, 2.0]]])
    state = init(solver, jnp.ones((2, 1)), C, prior_scale=2.0)
    kernel = jax.jit(build_kernel(solver, prior_scale=2.0))
    for seed in range(5):
        new, info = kernel(jax.random.PRNGKey(seed), state, C, 0.5)
        assert np.asarray(info.solver_failed).all() and not np.asarray(info.is_accepted).any()
        assert np.all(np.asarray(info.acceptance_rate) == 0.0)
        for a, b in zip(new, state):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # the same proposals with a solver that converges are accepted now and then
    good = make_soft_solver(logistic_mdp(gamma=0.99), tol=1e-12)
    state = init(good, jnp.ones((2, 1)), C, prior_scale=2.0)
    accepted = [np.asarray(jax.jit(build_kernel(good, prior_scale=2.0))(jax.random.PRNGKey(s), state, C, 0.5)[1]
                           .is_accepted) for s in range(5)]
    assert np.any(accepted)


def test_bad_shapes_are_reported():
    solver = make_soft_solver(logistic_mdp(), tol=1e-12)
    C = jnp.asarray([[[4.0, 1.0]]])
    kernel = build_kernel(solver, prior_scale=3.0)
    state = RewardMALAState(jnp.zeros((1, 1)), jnp.zeros(1), jnp.zeros((1, 1)), jnp.zeros((1, 1)))
    with pytest.raises(ValueError, match="counts"):
        kernel(jax.random.PRNGKey(1), state, jnp.zeros((2, 1, 2)), 0.3)
    with pytest.raises(ValueError, match="theta"):
        init(solver, jnp.zeros((1, 2)), C)
    with pytest.raises(ValueError, match="counts"):
        init(solver, jnp.zeros((1, 1)), jnp.zeros((2, 1, 2)))
    with pytest.raises(ValueError, match="temperature"):
        build_kernel(solver, temperature=0.0)
    with pytest.raises(ValueError, match="epsilon"):
        init(solver, jnp.zeros((1, 1)), C, epsilon=1.0)
    with pytest.raises(ValueError, match="prior_scale"):
        build_kernel(solver, prior_scale=-1.0)


def test_the_value_only_likelihood_is_the_posteriors_and_flags_a_failed_solve():
    """``count_log_likelihood_and_values`` (the magnitude move's density, no adjoint solve) is
    :func:`log_posterior`'s log-likelihood and values at any temperature and noise rate, and is
    not ok where the solve missed its tolerance."""
    from npbrs.models.reward.likelihood import count_log_likelihood_and_values, log_posterior

    C = jnp.asarray([[[3.0, 7.0]], [[10.0, 2.0]]])
    theta = jnp.asarray([[0.3], [-1.2]])
    for solver, converges in ((make_soft_solver(logistic_mdp(), tol=1e-12), True),
                              (make_soft_solver(logistic_mdp(gamma=0.99), tol=1e-12, method="vi", max_iter=1), False)):
        ll, V, ok = jax.jit(lambda t: count_log_likelihood_and_values(solver, t, C, None, 2.0, 0.1))(theta)
        post = jax.jit(lambda t: log_posterior(solver, t, C, None, 1.0, 2.0, 0.1))(theta)
        np.testing.assert_allclose(np.asarray(ll), np.asarray(post.log_lik), rtol=1e-12)
        np.testing.assert_allclose(np.asarray(V), np.asarray(post.V), rtol=1e-12)
        assert np.asarray(ok).tolist() == [converges, converges]
        if converges:  # the logistic policy's own value: pi(1) = (1 - eps) sigmoid(tau theta) + eps / 2
            p1 = 0.9 * expit(2.0 * np.asarray(theta)[:, 0]) + 0.05
            n0, n1 = np.asarray(C)[:, 0, 0], np.asarray(C)[:, 0, 1]
            np.testing.assert_allclose(np.asarray(ll), n1 * np.log(p1) + n0 * np.log1p(-p1), rtol=1e-10)


@pytest.mark.parametrize("chunk", [pytest.param(1, marks=pytest.mark.slow), 2, 4])  # (1: the gather of 2, smaller)
def test_only_the_active_skills_move_each_as_in_a_step_of_all(chunk, monkeypatch):
    """With ``active`` the kernel solves only the active skills (``chunk`` at a time: the
    module's batching threshold is set so; 2 puts an inactive skill in a chunk's tail, 4 pads
    past K) and each takes the same step as in a step of all K skills with the same key; the
    inactive skills keep their state. Under vmap two chains with 3 and 1 active skills."""
    from npbrs.models.reward import mala

    rng = np.random.default_rng(0)
    S, A, D, K = 6, 3, 4, 5
    mdp = TabularMDP(successors=rng.integers(S, size=(S, A, 2)), probs=np.full((S, A, 2), 0.5),
                     features=rng.normal(size=(S, A, D)), discount=0.9)
    solver = make_soft_solver(mdp, tol=1e-12)
    monkeypatch.setattr(mala, "BATCH_ENTRIES", chunk * S * A)
    assert mala.chunk_size(solver, K) == chunk
    scale = jnp.asarray([1.0, 2.0, 3.0, 1.5, 0.7])  # per skill: gathered with them
    theta = jnp.asarray(rng.normal(size=(2, K, D)))
    counts = jnp.asarray(rng.poisson(2.0, size=(2, K, S, A)).astype(float))
    active = jnp.asarray([[True, False, True, True, False], [False, False, False, True, False]])
    kernel = build_kernel(solver, prior_scale=scale, temperature=1.5, epsilon=0.05)

    def both(key, th, c, act):
        full = init(solver, th, c, prior_scale=scale, temperature=1.5, epsilon=0.05)
        part = init(solver, th, c, prior_scale=scale, temperature=1.5, epsilon=0.05, active=act)
        return full, part, kernel(key, full, c, 0.4)[0:2], kernel(key, part, c, 0.4, None, act)[0:2]

    keys = jax.random.split(jax.random.PRNGKey(3), 2)
    full0, part0, (full, full_info), (part, info) = jax.jit(jax.vmap(both))(keys, theta, counts, active)
    act = np.asarray(active)
    for a, b in zip(full0, part0):  # the start: solved where active
        np.testing.assert_allclose(np.asarray(a)[act], np.asarray(b)[act], rtol=1e-9, atol=1e-10)
    for a, b, b0 in zip(full, part, part0):
        np.testing.assert_allclose(np.asarray(a)[act], np.asarray(b)[act], rtol=1e-9, atol=1e-10)
        np.testing.assert_array_equal(np.asarray(b)[~act], np.asarray(b0)[~act])  # kept
    np.testing.assert_array_equal(np.asarray(info.is_accepted)[act], np.asarray(full_info.is_accepted)[act])
    assert np.asarray(info.is_accepted)[act].any() and not np.asarray(info.is_accepted)[~act].any()
    assert np.all(np.asarray(info.acceptance_rate)[~act] == 0.0)
    assert not np.asarray(info.solver_failed).any()


def test_the_emissions_one_loop_is_init_then_the_kernels_steps(monkeypatch):
    """The reward emission runs a chain's start and its MALA steps in one loop (the start is the
    kernel's ``evaluate`` pass, so the sweep's program holds one copy of the solve): it equals
    ``init`` followed by ``mala_steps`` kernel steps with the keys split from the update's,
    step sizes adapted after each real step only; its start solves every skill (so that the
    values it returns are all its weights'), the steps the active ones; ``init`` with ``active``
    is ``log_posterior`` at theta for the active skills and the given values for the others.
    Temperature 1.5, epsilon 0.05, one skill inactive (never moved), skills solved one at a
    time."""
    from npbrs.models.reward import mala
    from npbrs.models.reward.emission import RewardEmission
    from npbrs.models.reward.likelihood import log_posterior

    rng = np.random.default_rng(1)
    S, A, D, K = 6, 3, 4, 3
    mdp = TabularMDP(successors=rng.integers(S, size=(S, A, 2)), probs=np.full((S, A, 2), 0.5),
                     features=rng.normal(size=(S, A, D)), discount=0.9)
    em = RewardEmission(mdp, prior_scale=2.0, temperature=1.5, epsilon=0.05, mala_steps=3,
                        solver_options={"tol": 1e-12})
    monkeypatch.setattr(mala, "BATCH_ENTRIES", S * A)
    assert mala.chunk_size(em.solver, K) == 1
    theta = jnp.asarray(rng.normal(size=(K, D)))
    counts = jnp.asarray(rng.poisson(2.0, size=(K, S, A)).astype(float)).at[1].set(0.0)
    active = jnp.sum(counts, axis=(1, 2)) > 0
    cache = dict(em.init_cache(K), V=jnp.asarray(rng.normal(size=(K, S))))
    key = jax.random.PRNGKey(7)

    def by_hand(key):
        # (the emission's start solves every skill: the values of all the weights it returns)
        state = init(em.solver, theta, counts, 2.0, cache["V"], temperature=1.5, epsilon=0.05)
        kernel = build_kernel(em.solver, 2.0, temperature=1.5, epsilon=0.05)
        log_step, acc = cache["log_step"], jnp.zeros(K)
        for k in jax.random.split(key, 3):
            state, info = kernel(k, state, counts, jnp.exp(log_step), cache["scale"] ** 2, active)
            log_step = jnp.where(active, log_step + 0.3 * (info.acceptance_rate - em.target_accept), log_step)
            acc = acc + info.acceptance_rate
        return state, log_step, acc / 3

    start = jax.jit(lambda: init(em.solver, theta, counts, 2.0, cache["V"], temperature=1.5, epsilon=0.05,
                                 active=active))()
    post = log_posterior(em.solver, theta, counts, cache["V"], 2.0, 1.5, 0.05)
    for got, want in ((start.log_density, post.log_density), (start.grad, post.grad), (start.V, post.V)):
        np.testing.assert_allclose(np.asarray(got)[[0, 2]], np.asarray(want)[[0, 2]], rtol=1e-10)
    assert float(start.log_density[1]) == 0.0 and np.all(np.asarray(start.V[1]) == np.asarray(cache["V"][1]))
    want_state, want_step, want_acc = jax.jit(by_hand)(key)
    theta_new, new_cache, acc, log_density = jax.jit(
        lambda key: em.mala(key, theta, counts, cache, True, 2.0, active))(key)
    np.testing.assert_allclose(np.asarray(theta_new), np.asarray(want_state.theta), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(log_density), np.asarray(want_state.log_density), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(new_cache["log_step"]), np.asarray(want_step), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(acc), np.asarray(want_acc), rtol=1e-12, atol=1e-14)
    assert np.any(np.asarray(theta_new) != np.asarray(theta))  # (it moved)
    np.testing.assert_array_equal(np.asarray(theta_new)[1], np.asarray(theta)[1])  # (the inactive skill did not)
    np.testing.assert_allclose(np.asarray(new_cache["V"])[1], np.asarray(post.V)[1], rtol=1e-10)
