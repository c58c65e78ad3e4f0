"""The BP-HMM Gibbs kernel: its log joint is the NumPyro model's, its conditionals are exact."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from numpyro.infer.util import log_density

from npbrs.inference.sampler.kernel import BPHMMKernel
from npbrs.models.emissions import HMMData, PolicyEmission


def planted_policy_data(seed=0, N=5, T=40, S=4, A=3, switch=0.05, noise=0.1):
    """Steps of three skills that each prefer one action, with sticky switches."""
    rng = np.random.default_rng(seed)
    states = rng.integers(0, S, (N, T))
    z = np.zeros((N, T), int)
    actions = np.zeros((N, T), int)
    for i in range(N):
        k = rng.integers(3)
        for t in range(T):
            if rng.random() < switch:
                k = rng.integers(3)
            z[i, t] = k
            actions[i, t] = k if rng.random() > noise else rng.integers(A)
    mask = np.ones((N, T), bool)
    mask[-1, T - 7:] = False  # one ragged trajectory
    return HMMData(jnp.asarray(states, jnp.int32), jnp.asarray(actions, jnp.int32), jnp.asarray(mask)), z


@pytest.fixture(scope="module")
def kernel_and_state():
    data, _ = planted_policy_data()
    kernel = BPHMMKernel(PolicyEmission(4, 3), data, max_skills=4, kappa=5.0)
    state = kernel.init(jax.random.PRNGKey(0), 0, None, (), {})
    return kernel, state


def model_log_density(kernel, state, **overrides):
    params = {"omega": state.omega, "features": state.features, "eta": state.eta, **state.params}
    params.update(overrides)
    return float(_jitted_log_density(kernel)(params))


_CACHE = {}


def _jitted_log_density(kernel):
    if id(kernel) not in _CACHE:
        _CACHE[id(kernel)] = jax.jit(lambda params: log_density(kernel.model, (), {}, params)[0])
    return _CACHE[id(kernel)]


def test_kernel_log_joint_equals_the_numpyro_model_log_density(kernel_and_state):
    kernel, state = kernel_and_state
    sweep = jax.jit(kernel.sweep)
    for _ in range(3):
        np.testing.assert_allclose(float(state.log_joint), model_log_density(kernel, state), rtol=1e-10)
        state = sweep(state)


def test_feature_conditional_equals_the_model_density_ratio(kernel_and_state):
    kernel, state = kernel_and_state
    rng = np.random.default_rng(3)
    features = jnp.asarray(rng.integers(0, 2, state.features.shape), jnp.float64).at[:, 0].set(1.0)
    state = jax.jit(kernel._finish)(state._replace(features=features))
    # (compiled once, k traced: op by op, this test compiled some 250 small programs)
    logits_of = jax.jit(lambda st, k: kernel.feature_logits(st, st.features, k))
    carried_of = jax.jit(lambda st, k: kernel.feature_logits(st, st.features, k, st.log_marginals))
    F = np.asarray(state.features)
    for k in range(kernel.max_skills):
        logits = np.asarray(logits_of(state, k))
        # the sweep's path: the current features' marginals known, only the flipped one filtered
        carried = np.asarray(carried_of(state, k))
        np.testing.assert_allclose(carried, logits, rtol=1e-12, atol=1e-12)
        for i in range(F.shape[0]):
            on_features, off_features = F.copy(), F.copy()
            on_features[i, k], off_features[i, k] = 1.0, 0.0
            on = model_log_density(kernel, state, features=jnp.asarray(on_features))
            off = model_log_density(kernel, state, features=jnp.asarray(off_features)) \
                if off_features[i].sum() > 0 else -np.inf
            if np.isinf(off):
                assert np.isinf(logits[i]) and logits[i] > 0
            else:
                np.testing.assert_allclose(logits[i], on - off, rtol=1e-8, atol=1e-8)


def test_transition_weights_follow_the_gamma_dirichlet_conditional(kernel_and_state):
    kernel, state = kernel_and_state
    K = kernel.max_skills
    features = state.features.at[0].set(jnp.array([1.0, 1.0, 0.0, 1.0]))
    z = state.z.at[0].set(jnp.where(kernel.data.mask[0], jnp.arange(state.z.shape[1]) // 10 % 2, -1).astype(state.z.dtype))
    hyper = state.hyper
    draws = jax.jit(jax.vmap(lambda k: kernel.sample_eta(k, z, features, hyper)))(
        jax.random.split(jax.random.PRNGKey(1), 4000))
    from npbrs.models.hmm import transition_counts

    counts = np.asarray(transition_counts(z, kernel.data.mask, K))[0]
    conc = np.asarray(hyper.gamma + hyper.kappa * np.eye(K))
    active = np.array([True, True, False, True])
    for j in range(K):
        row = np.asarray(draws[:, 0, j])
        props = row[:, active] / row[:, active].sum(-1, keepdims=True)
        a = conc[j, active] + counts[j, active]
        mean, var = a / a.sum(), a * (a.sum() - a) / (a.sum() ** 2 * (a.sum() + 1))
        np.testing.assert_array_less(np.abs(props.mean(0) - mean), 5 * np.sqrt(var / len(row)))
        total = row[:, active].sum(-1)
        shape = conc[j, active].sum()
        assert abs(total.mean() - shape) < 5 * np.sqrt(shape / len(row))
        # an inactive skill's weight keeps its Gamma prior
        assert abs(row[:, 2].mean() - conc[j, 2]) < 5 * np.sqrt(conc[j, 2] / len(row))


def test_vectorized_and_sequential_chains_give_the_same_draws():
    from numpyro.infer import MCMC

    from npbrs.models.bphmm import Termination

    data, _ = planted_policy_data(seed=1, N=3, T=20)
    # (and with the warmup's greedy merges and splits, whose loops hold conds on per-chain values;
    # and with state-dependent ends, a sticky phase (a cond on the clock) and a sampled kappa)
    greedy = {"greedy_merge": 1, "greedy_split": 1, "greedy_from": 0.0}
    # (greedy moves without the ends would add 15-20 s and no case: their loops and conds are
    # those of the case with the ends)
    for moves, extra in ((None, {}),
                         ({**greedy, "sticky_phase": 0.5},
                          {"termination": Termination(4), "hyperpriors": {"kappa": (2.0, 0.2)}})):
        runs = []
        for method in ("vectorized", "sequential"):
            kernel = BPHMMKernel(PolicyEmission(4, 3), data, max_skills=3, moves=moves, **extra)
            mcmc = MCMC(kernel, num_warmup=4, num_samples=5, num_chains=2, chain_method=method, progress_bar=False)
            mcmc.run(jax.random.PRNGKey(7))
            runs.append(np.asarray(mcmc.get_extra_fields(group_by_chain=True)["log_joint"]))
        np.testing.assert_allclose(runs[0], runs[1], rtol=1e-9)
        assert not np.allclose(runs[0][0], runs[0][1])  # chains differ from each other


def test_fit_sweeps_a_single_chain_unbatched():
    """One chain runs the sequential (unbatched) sweep, whose draws the test above holds to the
    vectorised ones: a batch of one traced every batching rule for nothing (1.5-2.5 s a fit)."""
    from npbrs.inference.driver.chains import choose_chain_method

    assert choose_chain_method("vectorized", 1, None, None) == ("sequential", None, 1)
    assert choose_chain_method("parallel", 1, None, None)[0] == "sequential"
    assert choose_chain_method("vectorized", 2, None, None) == ("vectorized", None, 1)
    assert choose_chain_method("auto", 1, None, None) == ("sequential", None, 1)


def test_init_from_a_segmentation_starts_every_chain_there():
    data, z_true = planted_policy_data(seed=1)
    kernel = BPHMMKernel(PolicyEmission(4, 3), data, max_skills=5, kappa=5.0)
    lengths = np.asarray(data.mask).sum(1)
    z0 = kernel.check_segmentation([z_true[i, :n] for i, n in enumerate(lengths)])
    states = kernel.init(jax.random.split(jax.random.PRNGKey(0), 2), 0, {"z": z0}, (), {})
    mask = np.asarray(data.mask)
    for c in range(2):
        z = np.asarray(states.z[c])
        np.testing.assert_array_equal(z[mask], z_true[mask])
        assert np.all(z[~mask] == -1)
        used = np.stack([np.isin(np.arange(5), z_true[i][mask[i]]) for i in range(len(z))])
        np.testing.assert_array_equal(np.asarray(states.features[c]) > 0, used)
        # each skill's initial policy is fitted to its steps: skill k prefers action k
        probs = np.asarray(states.params["policy"][c])  # (K, S, A)
        assert np.all(probs[:3].argmax(-1) == np.arange(3)[:, None])
    # the chains differ in their other draws
    assert not np.array_equal(np.asarray(states.eta[0]), np.asarray(states.eta[1]))
    default = kernel.init(jax.random.split(jax.random.PRNGKey(0), 2), 0, None, (), {})
    assert np.all(np.asarray(states.log_joint) > np.asarray(default.log_joint))


@pytest.mark.parametrize("name", ["alpha", "kappa", "gamma"])
def test_hyperparameter_moves_sample_their_full_conditionals(name):
    """Each hyperparameter's Metropolis move, run alone with z and F fixed, has its full
    conditional with omega and eta integrated out as stationary law: Gamma hyperprior x the
    beta-Bernoulli marginal of F (alpha) or the rows' Dirichlet-multinomials of z's transition
    counts (kappa, gamma), written out here in NumPy and SciPy, by quadrature on a grid. The
    trajectories have different lengths and skill sets. (Checked to fail: with kappa's weight
    on the diagonal 1.5 times too large in ``collapsed_transition_log_prob``, the kappa and
    gamma cases fail; without the proposal's Jacobian, test_joint_distribution.py fails with
    p around 1e-30 for each hyperparameter.)"""
    from scipy import stats
    from scipy.special import betaln, gammaln

    data, _ = planted_policy_data(N=4, T=12)
    mask = np.ones((4, 12), bool)
    mask[1, 7:] = False
    mask[3, 3:] = False
    data = data._replace(mask=jnp.asarray(mask))
    prior = {"alpha": (2.0, 1.0), "kappa": (2.0, 0.2), "gamma": (3.0, 2.0)}[name]
    kernel = BPHMMKernel(PolicyEmission(4, 3), data, max_skills=3, alpha=1.5, kappa=4.0, gamma=0.7,
                         hyperpriors={name: prior})
    z = np.array([[0, 0, 0, 1, 1, 1, 1, 0, 0, 2, 2, 2], [1, 1, 2, 2, 2, 1, 1, 0, 0, 0, 0, 0],
                  [2] * 12, [0, 1, 1] + [0] * 9])
    F = np.array([[1, 1, 1], [1, 1, 0], [1, 0, 1], [1, 1, 0]], float)
    F[1, 2] = 1.0  # z[1] uses skill 2
    draws = 20000

    def body(h, key):
        h = kernel.sample_hyperparameters(key, jnp.asarray(z), jnp.asarray(F), h)
        return h, getattr(h, name)

    _, xs = jax.jit(lambda h, k: jax.lax.scan(body, h, jax.random.split(k, draws)))(kernel.hyper0, jax.random.PRNGKey(2))
    xs = np.asarray(xs)[500:]
    K = 3
    grid = np.linspace(1e-3, 60.0 if name == "kappa" else 12.0, 20000)
    h0 = {"alpha": 1.5, "kappa": 4.0, "gamma": 0.7}
    logp = stats.gamma.logpdf(grid, prior[0], scale=1.0 / prior[1])
    if name == "alpha":
        m = F.sum(0)
        a = grid[:, None] / K
        logp += np.sum(betaln(m + a, len(F) - m + 1.0) - betaln(a, 1.0), -1)
    else:
        kap = grid if name == "kappa" else np.full_like(grid, h0["kappa"])
        gam = grid if name == "gamma" else np.full_like(grid, h0["gamma"])
        for i in range(len(z)):
            zi = z[i][mask[i]]
            on = np.flatnonzero(F[i])
            for j in on:
                n = np.array([np.sum((zi[:-1] == j) & (zi[1:] == k)) for k in on], float)
                c = gam[:, None] + kap[:, None] * (on == j)[None]
                logp += (gammaln(c.sum(-1)) - gammaln(c.sum(-1) + n.sum())
                         + np.sum(gammaln(c + n) - gammaln(c), -1))
    w = np.exp(logp - logp.max())
    w /= w.sum()
    mean = np.sum(w * grid)
    sd = np.sqrt(np.sum(w * (grid - mean) ** 2))
    # a random walk on log scale, ten steps a call: allow an effective sample size of a fifth
    se = sd / np.sqrt(len(xs) / 5)
    assert abs(xs.mean() - mean) < 5 * se, (xs.mean(), mean, se)
    assert abs(xs.std() - sd) < 0.05 * sd, (xs.std(), sd)


def test_unused_skills_are_redrawn_from_the_prior_on_schedule_and_kept_in_between():
    """moves["redraw_unused"] = 3: a sweep whose clock is not a multiple of 3 keeps the
    parameters of the skills without steps exactly (their likelihoods then need no new
    solve), a sweep at a multiple of 3 redraws them as the default kernel does in every sweep
    (the same draws: the schedule only keeps); skills with steps move in every sweep. (The
    schedule's exactness: test_posterior.py, "redraw_every_3".)"""
    data, _ = planted_policy_data()
    plain = BPHMMKernel(PolicyEmission(4, 3), data, max_skills=6, kappa=5.0, init_skills=2)
    sched = BPHMMKernel(PolicyEmission(4, 3), data, max_skills=6, kappa=5.0, init_skills=2,
                        moves={"redraw_unused": 3})
    state = plain.init(jax.random.PRNGKey(1), 0, None, (), {})
    for step, redraw in ((1, False), (3, True), (4, False)):
        s = state._replace(step=jnp.int32(step))
        a, b = jax.jit(plain.sweep)(s), jax.jit(sched.sweep)(s)
        np.testing.assert_array_equal(a.z, b.z)
        used = np.asarray(jnp.any((a.z[..., None] == jnp.arange(6)) & data.mask[..., None], axis=(0, 1)))
        assert used.any() and (~used).any()
        old, new_a, new_b = (np.asarray(x.params["policy"]) for x in (s, a, b))
        np.testing.assert_array_equal(new_b[used], new_a[used])  # the update's own draws
        assert not np.allclose(new_a[~used], old[~used])  # the default: a prior draw every sweep
        np.testing.assert_array_equal(new_b[~used], new_a[~used] if redraw else old[~used])
    with pytest.raises(ValueError, match="redraw_unused"):
        BPHMMKernel(PolicyEmission(4, 3), data, max_skills=6, moves={"redraw_unused": 0})


def test_a_sticky_start_sweeps_with_a_scaled_kappa_in_early_warmup_only():
    """moves["sticky_start"] = 10: the first warmup sweep is a plain kernel's sweep with kappa x
    10 (the same draws), except that the state keeps the model's kappa and reports the log joint
    under it; at mid-warmup the factor has fallen to 1, and in the sampling sweeps the option
    changes nothing."""
    data, _ = planted_policy_data()
    sticky = BPHMMKernel(PolicyEmission(4, 3), data, max_skills=4, kappa=5.0, moves={"sticky_start": 10.0})
    plain = BPHMMKernel(PolicyEmission(4, 3), data, max_skills=4, kappa=5.0)
    scaled = BPHMMKernel(PolicyEmission(4, 3), data, max_skills=4, kappa=50.0)
    state = plain.init(jax.random.PRNGKey(3), 8, None, (), {})
    sweep = jax.jit(sticky.sweep)
    first, reference = sweep(state), jax.jit(scaled.sweep)(state._replace(hyper=state.hyper._replace(kappa=50.0)))
    for name in ("z", "eta", "features", "omega"):
        np.testing.assert_array_equal(getattr(first, name), getattr(reference, name))
    assert float(first.hyper.kappa) == 5.0
    np.testing.assert_allclose(first.log_joint, plain._finish(first).log_joint, rtol=1e-12)
    assert not np.allclose(first.log_joint, reference.log_joint)  # kappa 50's would differ
    # half-way (sweep 4 of 8 warmup sweeps) and in sampling (sweep 8): a plain sweep
    for step in (4, 8):
        s = state._replace(step=jnp.int32(step))
        a, b = sweep(s), jax.jit(plain.sweep)(s)
        for name in ("z", "eta", "log_joint"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    with pytest.raises(ValueError, match="sticky_start"):
        BPHMMKernel(PolicyEmission(4, 3), data, max_skills=4, moves={"sticky_start": 0.5})
