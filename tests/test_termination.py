"""State-dependent skill ends (``switching="state"``): the counts, the conditionals of the ends
and their means against a direct computation or quadrature, the kernel's log joint against the
NumPyro model's, the features' conditional and eta's, and the fit's use of them."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from numpyro.infer.util import log_density
from scipy import stats
from scipy.special import betaln

from npbrs.inference.sampler.kernel import BPHMMKernel
from npbrs.models.bphmm import (Termination, end_counts, end_gate, hmm_parameters, sample_end_means, sample_ends)
from npbrs.models.emissions import HMMData, PolicyEmission
from npbrs.models.hmm import forward_filter, path_log_prob

S, A = 5, 3


def ragged_data(seed=0, N=6, T=30, pad=True):
    rng = np.random.default_rng(seed)
    states = rng.integers(0, S, (N, T))
    actions = rng.integers(0, A, (N, T))
    mask = np.arange(T)[None, :] < rng.integers(T // 2, T + 1, N)[:, None]
    if pad:
        mask[-1] = False  # a padding trajectory
    return HMMData(jnp.asarray(states, jnp.int32), jnp.asarray(actions, jnp.int32), jnp.asarray(mask))


def test_end_counts_equal_a_loop_over_steps_leaving_out_one_skill_trajectories():
    data = ragged_data()
    rng = np.random.default_rng(1)
    N, T = data.mask.shape
    K = 4
    z = np.where(data.mask, rng.integers(0, K, (N, T)), -1)
    features = rng.integers(0, 2, (N, K)).astype(float)
    features[:, 0] = 1.0
    features[2] = [0, 1, 0, 0]  # one skill only: its steps say nothing of the ends
    z[2] = np.where(data.mask[2], 1, -1)
    ends, stays = (np.asarray(x) for x in end_counts(jnp.asarray(z), data.mask, data.states, jnp.asarray(features), S))
    e_ref, s_ref = np.zeros((K, S)), np.zeros((K, S))
    for i in range(N):
        if features[i].sum() < 2:
            continue
        for t in range(1, T):
            if data.mask[i, t]:
                k, s = z[i, t - 1], int(data.states[i, t])
                (s_ref if z[i, t] == k else e_ref)[k, s] += 1
    np.testing.assert_array_equal(ends, e_ref)
    np.testing.assert_array_equal(stays, s_ref)


def test_the_gate_reads_each_steps_state():
    data = ragged_data()
    ends = jnp.asarray(np.random.default_rng(2).uniform(size=(3, S)))
    gate = np.asarray(end_gate(ends, data.states, data.mask))
    i, t = 1, 4
    np.testing.assert_array_equal(gate[i, t], np.asarray(ends)[:, int(data.states[i, t])])
    assert np.all(gate[~np.asarray(data.mask)] == 1.0)


TERM = Termination(num_states=S, concentration=3.0, mean_prior=(2.0, 5.0))


def test_the_end_means_conditional_equals_quadrature():
    # counts of two skills over the states: one that ends often in state 0 only, one never seen
    ended = jnp.asarray([[6.0, 0, 1, 0, 0], [0, 0, 0, 0, 0]])
    stayed = jnp.asarray([[2.0, 9, 7, 0, 3], [0, 0, 0, 0, 0]])
    c, (a, b) = TERM.concentration, TERM.mean_prior
    grid = np.linspace(1e-6, 1 - 1e-6, 20001)

    def log_post(k):
        x, y = c * grid[:, None], c * (1 - grid[:, None])
        e, s = np.asarray(ended[k]), np.asarray(stayed[k])
        ll = np.sum(betaln(x + e, y + s) - betaln(x, y), -1)
        return ll + stats.beta.logpdf(grid, a, b)

    draws = jax.jit(jax.vmap(lambda key: sample_end_means(key, jnp.full(2, 0.3), (ended, stayed), TERM, steps=60)))(
        jax.random.split(jax.random.PRNGKey(0), 4000))
    draws = np.asarray(draws)
    for k in range(2):
        w = np.exp(log_post(k) - log_post(k).max())
        w /= w.sum()
        mean, sd = np.sum(w * grid), np.sqrt(np.sum(w * grid ** 2) - np.sum(w * grid) ** 2)
        # independent chains (60 steps from one start each): the mean within 4.5 standard errors
        assert abs(draws[:, k].mean() - mean) < 4.5 * sd / np.sqrt(len(draws)), (k, draws[:, k].mean(), mean)
        assert abs(draws[:, k].std() - sd) < 0.1 * sd
        cdf = np.cumsum(w)
        assert stats.kstest(draws[:, k], lambda x: np.interp(x, grid, cdf)).pvalue > 1e-3


def test_the_ends_conditional_is_their_beta():
    ended = jnp.asarray([[6.0, 0, 1, 0, 0]])
    stayed = jnp.asarray([[2.0, 9, 7, 0, 3]])
    mean = jnp.asarray([0.2])
    draws = np.asarray(jax.vmap(lambda k: sample_ends(k, mean, (ended, stayed), TERM))(
        jax.random.split(jax.random.PRNGKey(1), 20000)))[:, 0]
    c = TERM.concentration
    for s in range(S):
        ref = stats.beta(c * 0.2 + float(ended[0, s]), c * 0.8 + float(stayed[0, s]))
        assert stats.kstest(draws[:, s], ref.cdf).pvalue > 1e-3


def test_gated_parameters_keep_a_one_skill_trajectory_and_leave_the_diagonal_out():
    eta = jnp.asarray(np.random.default_rng(3).gamma(1.0, size=(2, 3, 3)))
    features = jnp.asarray([[1.0, 1.0, 1.0], [0.0, 1.0, 0.0]])
    log_init, log_trans, active = hmm_parameters(features, eta, gated=True)
    gate = jnp.full((4, 3), 0.4)
    lik = jnp.zeros((4, 3))
    # a one-skill trajectory never switches: its likelihood is 1 whatever the gate
    np.testing.assert_allclose(forward_filter(log_init[1], log_trans[1], lik, None, active[1], gate)[0], 0.0,
                               atol=1e-12)
    # in the other, staying costs 1 - gate and a switch gate * (the row without the diagonal)
    row = np.asarray(eta[0, 0, 1:]) / np.asarray(eta[0, 0, 1:]).sum()
    z = jnp.asarray([0, 0, 1, 1])
    lp = path_log_prob(log_init[0], log_trans[0], lik, z, None, active[0], gate)
    np.testing.assert_allclose(lp, np.log(1 / 3) + np.log(0.6) + np.log(0.4 * row[0]) + np.log(0.6), rtol=1e-12)


# ----------------------------------------------------------------------------------- the kernel
@pytest.fixture(scope="module")
def kernel_and_state():
    data = ragged_data(4, N=5, T=25, pad=False)  # (the model has no notion of padding trajectories)
    kernel = BPHMMKernel(PolicyEmission(S, A), data, max_skills=4, kappa=5.0,
                         termination=Termination(S, 2.0, (1.0, 4.0)))
    state = kernel.init(jax.random.PRNGKey(0), 0, None, (), {})
    return kernel, state


def model_log_density(kernel, state, **overrides):
    params = {"omega": state.omega, "features": state.features, "eta": state.eta, "ends": state.ends,
              "end_mean": state.end_mean, **state.params}
    params.update(overrides)
    return float(jax.jit(lambda p: log_density(kernel.model, (), {}, p)[0])(params))


def test_the_kernels_log_joint_with_ends_equals_the_numpyro_models(kernel_and_state):
    kernel, state = kernel_and_state
    sweep = jax.jit(kernel.sweep)
    for _ in range(3):
        np.testing.assert_allclose(float(state.log_joint), model_log_density(kernel, state), rtol=1e-10)
        state = sweep(state)
    assert state.ends.shape == (4, S) and state.end_mean.shape == (4,)


def test_the_feature_conditional_with_ends_equals_the_model_density_ratio(kernel_and_state):
    kernel, state = kernel_and_state
    F = np.asarray(state.features)
    logits = np.asarray(jax.jit(lambda st: kernel.feature_logits(st, st.features, 1))(state))
    for i in range(F.shape[0]):
        on_f, off_f = F.copy(), F.copy()
        on_f[i, 1], off_f[i, 1] = 1.0, 0.0
        if off_f[i].sum() == 0:
            continue
        on = model_log_density(kernel, state, features=jnp.asarray(on_f))
        off = model_log_density(kernel, state, features=jnp.asarray(off_f))
        np.testing.assert_allclose(logits[i], on - off, rtol=1e-8, atol=1e-8)


def test_eta_learns_from_the_switches_only(kernel_and_state):
    kernel, state = kernel_and_state
    K = kernel.max_skills
    features = state.features.at[0].set(jnp.ones(K))
    # trajectory 0 stays in skill 0 for long runs and always switches 0 -> 2
    T = state.z.shape[1]
    z = state.z.at[0].set(jnp.where(kernel.data.mask[0], jnp.where(jnp.arange(T) % 8 < 6, 0, 2), -1))
    draws = jax.jit(jax.vmap(lambda k: kernel.sample_eta(k, z, features, state.hyper)))(
        jax.random.split(jax.random.PRNGKey(5), 4000))
    eta = np.asarray(draws)[:, 0, 0]  # row 0 of trajectory 0
    off = eta[:, 1:] / eta[:, 1:].sum(-1, keepdims=True)  # the switch distribution without the diagonal
    from npbrs.models.hmm import transition_counts

    n02 = int(transition_counts(z, kernel.data.mask, K)[0, 0, 2])
    gamma = float(state.hyper.gamma)
    expected = (gamma + n02) / (3 * gamma + n02)  # Dirichlet(gamma + counts) over skills 1, 2, 3
    assert abs(off[:, 1].mean() - expected) < 4.5 * off[:, 1].std() / np.sqrt(len(off))
    # the diagonal is not counted (the stays say nothing of it): Dirichlet(gamma + kappa, gamma + counts)
    share = eta[:, 0] / eta.sum(-1)
    prior_share = (gamma + float(state.hyper.kappa)) / (K * gamma + float(state.hyper.kappa) + n02)
    assert abs(share.mean() - prior_share) < 4.5 * share.std() / np.sqrt(len(share))


@pytest.mark.parametrize("active", [(1, 1, 1), (1, 0, 1), (0, 1, 0)])
def test_the_collapsed_sequence_probability_with_ends_sums_to_one_and_matches_monte_carlo(active):
    import itertools

    from npbrs.models.bphmm import collapsed_sequence_log_prob

    K, T = 3, 5
    rng = np.random.default_rng(7)
    gate = jnp.asarray(rng.uniform(0.05, 0.95, (1, T, K)))
    f = jnp.asarray([active], jnp.float64)
    kappa, gamma = 4.0, 0.7
    zs = np.array([p for p in itertools.product(range(K), repeat=T) if all(np.asarray(active)[list(p)])])
    mask = jnp.ones((len(zs), T), bool)
    lp = np.asarray(collapsed_sequence_log_prob(jnp.asarray(zs), mask, jnp.repeat(f, len(zs), 0), kappa, gamma,
                                                jnp.repeat(gate, len(zs), 0)))
    np.testing.assert_allclose(np.exp(lp).sum(), 1.0, rtol=1e-10)
    # against the gated chain averaged over eta's prior (Monte Carlo), for a few sequences
    M = 100000
    eta = jnp.asarray(rng.gamma(gamma + kappa * np.eye(K), 1.0, (M, K, K)))
    log_init, log_trans, act = hmm_parameters(jnp.repeat(f, M, 0), eta, gated=True)
    for j in rng.choice(len(zs), size=min(4, len(zs)), replace=False):
        paths = jax.vmap(lambda li, lt, a: path_log_prob(li, lt, jnp.zeros((T, K)), jnp.asarray(zs[j]), None, a,
                                                         gate[0]))(log_init, log_trans, act)
        p = np.exp(np.asarray(paths))
        assert abs(p.mean() - np.exp(lp[j])) < 4.5 * p.std() / np.sqrt(M) + 1e-12, (zs[j], p.mean(), np.exp(lp[j]))


def test_the_switching_options_round_trip_and_bad_ones_are_named():
    from npbrs.inference.driver.config import ModelConfig, PriorConfig
    from npbrs.inference.driver.fit import resolve_config

    cfg = resolve_config({"prior": {"end_concentration": 0.5, "end_mean": [2, 3]}}, switching="state")
    assert cfg.prior.switching == "state" and cfg.prior.end_concentration == 0.5 and cfg.prior.end_mean == (2.0, 3.0)
    assert ModelConfig.from_toml_string(cfg.to_toml()) == cfg
    assert "switching" not in ModelConfig().to_dict()["prior"]  # the sticky default's description is unchanged
    for bad, what in [({"switching": "sometimes"}, "prior.switching"), ({"end_concentration": 0}, "end_concentration"),
                      ({"end_mean": [1.0]}, "prior.end_mean")]:
        with pytest.raises(ValueError, match=what):
            PriorConfig.from_dict(bad)


def test_a_fit_with_state_dependent_ends_finds_where_the_planted_skills_end(tmp_path):
    """A small labyrinth (31 nodes): the water skill ends at the port with probability 0.6 and
    elsewhere with 0.02, the home skill likewise at the entrance. The fit's ends show both: a
    skill that ends at the port far more often than elsewhere, and one at the entrance. The
    run saves and loads with its ends, and scores held-out trajectories."""
    from npbrs.domains.worlds import labyrinth
    from npbrs.inference import fit, load, resolve_config

    world = labyrinth(seed=1, depth=4, num_trajectories=80, num_heldout=4)
    # c = 2: the default c = 8 shrinks each state's end towards the skill's mean more (it scored
    # held-out trajectories better on the full-size worlds), and with 80 short trajectories the
    # entrance's end then stays near 0.2
    # (no greedy moves: they are most of a fit's compile time, and the ends do not need them here;
    # 50 + 50 sweeps: the ratios below were 3.8 and 8.4 with 50 + 50 sweeps, 3.5 and 6.7 with 100 + 100)
    config = resolve_config({"prior": {"end_concentration": 2.0}}, switching="state",
                            moves={"greedy_merge": 0, "greedy_split": 0})
    result = fit(world.mdp, world.demos, config, num_chains=1, num_warmup=50, num_samples=50, seed=0,
                 progress_bar=False)
    K, S = result.config["max_skills"], world.mdp.num_states
    assert np.shape(result.samples["ends"]) == (1, 50, K, S)
    ends = np.asarray(result.samples["ends"])[0].mean(0)  # (K, S) posterior means
    used = np.asarray(result.samples["skill_steps"])[0].mean(0) > 20
    typical = np.median(ends, axis=1)
    # (the entrance's end is about 0.28 at a ratio of 4.6 with the Student t reward prior, above
    # 0.3 with a Gaussian one: 0.25 is the floor)
    for goal in (world.params["water_port"], 0):  # the port, the entrance
        ratio = np.where(used, ends[:, goal] / typical, 0.0)
        assert ratio.max() > 2.5 and ends[np.argmax(ratio), goal] > 0.25, (goal, ends[:, goal], typical)
    result.save(tmp_path / "run.nc")
    again = load(tmp_path / "run.nc")
    np.testing.assert_array_equal(np.asarray(again.samples["ends"]), np.asarray(result.samples["ends"]))
    assert again.model_config.prior.switching == "state"
    assert again.model_config.sampler.moves["sticky_phase"] == 0.5  # fit's default with state ends
    held = again.log_predictive(world.mdp, world.heldout, num_samples=4, num_draws=4)
    assert np.isfinite(held.per_step)
    # the skills as options terminate as the run's ends say (their posterior mean per skill)
    from npbrs.inference.analysis.diagnostics import relabelled_draws

    options = again.options(world.mdp)
    draws = relabelled_draws(again, "ends").reshape((-1, again.num_skills, S))
    for k, option in enumerate(options):
        np.testing.assert_allclose(option.termination, np.nanmean(draws[:, k], axis=0), rtol=1e-12)
    # and the report's plots show them
    from npbrs.inference.cli.main import save_plots

    (tmp_path / "plots").mkdir()
    paths = save_plots(again, tmp_path / "plots")
    assert os.path.getsize(paths["skill ends"]) > 1000
    from npbrs.inference.analysis.plots import plot_skill_ends

    with pytest.raises(ValueError, match="probabilities"):
        plot_skill_ends(np.full((2, 3), 1.5), tmp_path / "bad.png")


def test_a_state_ends_fit_too_large_to_keep_its_draws_is_refused_before_compiling():
    from npbrs.domains.gridworld import open_gridworld
    from npbrs.inference import fit

    mdp = open_gridworld(400)  # 160,000 states
    from npbrs.domains import Demonstrations

    demos = Demonstrations([np.array([0, 1, 2])], [np.array([1, 1, 1])])  # (moves this MDP can make)
    with pytest.raises(ValueError, match="switching='state' keeps each draw's end probabilities"):
        fit(mdp, demos, {"switching": "state"}, num_samples=200, progress_bar=False)


# ------------------------------------------------------------------- the whole sweep: getting it right
@pytest.mark.slow  # (50 s of a cold suite; its documented power is covered by the faster tests above)
def test_state_ends_sweeps_alternated_with_simulated_data_sample_the_prior():
    """Geweke's joint-distribution test (see ``test_joint_distribution.py``, whose setting this
    reuses: 3 ragged trajectories, 6 slots, policy skills, sampled alpha, kappa and gamma, birth/death
    and split-merge moves) with state-dependent ends: chains that alternate a sweep with redrawing
    the skill sequences, states and actions from the model given the sweep's parameters have the
    prior as their parameters' law; their means of label-invariant statistics (the ends' means
    over the slots among them) are compared with direct NumPy draws of the prior (t-tests over 48
    independent chains, Bonferroni).

    Power, checked: without the logit's Jacobian in mu's Metropolis ratio it fails (p 8e-5, skills
    used and switches); ends counted in the state left instead of the one entered it does not
    see (a few steps per state and slot here; the counts test and the planted test catch that).

    In ``-m slow`` only: each conditional the sweep with ends composes is checked exactly by a
    faster test above (mu's Metropolis move against quadrature, which a missing Jacobian fails;
    the ends' Beta; the features' ratio against the NumPyro model's density; eta from the
    switches only; the log joint), and the sweep without ends by ``test_joint_distribution``."""
    import test_joint_distribution as J

    from npbrs.models.bphmm import Hyper

    K, S_, A_ = J.K, J.S, J.A
    term = Termination(S_, 3.0, (2.0, 3.0))
    a, b = term.mean_prior
    c = term.concentration
    msk = J.mask()
    N, T = msk.shape
    P = J.mdp()
    # "entered": the end probability of the first step's skill in the state the first trajectory
    # enters next (a statistic that knows which state an end is counted in)
    names = ("skills_used", "features", "switches", "emission", "end_mean", "ends", "entered")

    def prior_draws(rng, m):
        alpha, kappa, gamma, omega, F, eta, params = J.prior_parameters(rng, m, N, J.POLICY)
        n = len(alpha)
        mu = rng.beta(a, b, (n, K))
        ends = rng.beta(c * mu[..., None], c * (1 - mu[..., None]), (n, K, S_))
        return alpha, kappa, gamma, omega, F, eta, params, mu, ends

    def simulate(rng, M):
        out = {k: [] for k in names}
        got = 0
        while got < M:
            alpha, kappa, gamma, omega, F, eta, params, mu, ends = prior_draws(rng, 2 * (M - got) + 100)
            m = len(alpha)
            pol = params["policy"]  # (m, K, S, A)
            several = F.sum(-1) >= 2  # (m, N)
            off = np.where(np.eye(K, dtype=bool), 0.0, eta * F[:, :, None, :])
            pi = np.where(several[..., None, None], off, np.eye(K) * F[:, :, :, None])
            pi = pi / np.maximum(pi.sum(-1, keepdims=True), 1e-300)
            z = np.empty((m, N, T), int)
            z[..., 0] = (rng.random((m, N, 1)) > np.cumsum(F / F.sum(-1, keepdims=True), -1)).sum(-1)
            s = rng.integers(0, S_, (m, N))
            mi, ni = np.arange(m)[:, None], np.arange(N)[None, :]
            entered = None
            for t in range(1, T):
                zt = np.minimum(z[..., t - 1], K - 1)
                act = (rng.random((m, N, 1)) > np.cumsum(pol[mi, zt, s], -1)).sum(-1)
                s = (rng.random((m, N, 1)) > np.cumsum(P[s, np.minimum(act, A_ - 1)], -1)).sum(-1)
                s = np.minimum(s, S_ - 1)
                if entered is None:
                    entered = ends[np.arange(m), zt[:, 0], s[:, 0]]
                end = several & (rng.random((m, N)) < ends[mi, zt, s])
                nxt = (rng.random((m, N, 1)) > np.cumsum(pi[mi, ni, zt], -1)).sum(-1)
                z[..., t] = np.where(end, nxt, zt)
            z = np.minimum(z, K - 1)
            out["skills_used"].append(np.stack([np.any((z == k) & msk, axis=(1, 2)) for k in range(K)], -1).sum(-1))
            out["features"].append(F.sum((1, 2)))
            out["switches"].append(np.mean(np.sum((z[..., 1:] != z[..., :-1]) & msk[:, 1:], -1), -1))
            out["emission"].append(J.POLICY.coordinate_prior(rng, m))
            out["end_mean"].append(mu.mean(-1))
            out["ends"].append(ends.mean((1, 2)))
            out["entered"].append(entered)
            got += m
        return {k: np.concatenate(v)[:M].astype(float) for k, v in out.items()}

    data = HMMData(jnp.zeros(msk.shape, jnp.int32), jnp.zeros(msk.shape, jnp.int32), jnp.asarray(msk))
    kernel = BPHMMKernel(J.POLICY.make(P), data, max_skills=K, hyperpriors=J.HYPERPRIORS, init_skills=1,
                         moves=J.MOVES, termination=term)
    Pj = jnp.asarray(P)

    def regenerate(key, state):
        active = state.features > 0
        several = jnp.sum(active, -1) >= 2
        log_pol = kernel.emission.log_policies(state.params)
        log_init, log_trans, act = hmm_parameters(state.features, state.eta, gated=True)
        log_pi = jnp.where(act[:, None, :], log_trans, -jnp.inf)
        k0, k1, key = jax.random.split(key, 3)
        z1 = jax.random.categorical(k0, jnp.where(active, 0.0, -jnp.inf))
        s1 = jax.random.randint(k1, (N,), 0, S_)

        def step(carry, key):
            z, s = carry
            ka, ks, ke, kz = jax.random.split(key, 4)
            a_ = jax.random.categorical(ka, log_pol[z, s])
            s_next = jax.random.categorical(ks, jnp.log(Pj[s, a_]))
            ends = several & jax.random.bernoulli(ke, state.ends[z, s_next])
            z_next = jnp.where(ends, jax.random.categorical(kz, log_pi[jnp.arange(N), z]), z)
            return (z_next, s_next), (z, s, a_)

        _, (z, s, a_) = jax.lax.scan(step, (z1, s1), jax.random.split(key, T))
        z, s, a_ = z.T, s.T, a_.T
        new = HMMData(jnp.where(msk, s, 0).astype(jnp.int32), jnp.where(msk, a_, 0).astype(jnp.int32), jnp.asarray(msk))
        return jnp.where(msk, z, -1).astype(jnp.int32), new

    def statistics(state, data):
        users = jnp.sum(state.features, 0)
        return jnp.stack([state.num_skills.astype(jnp.float64), jnp.sum(users), state.num_switches,
                          J.POLICY.coordinate(state.params, state.z[0, 0]), jnp.mean(state.end_mean),
                          jnp.mean(state.ends), state.ends[state.z[0, 0], data.states[0, 1]]])

    @jax.jit
    def run(key, start):
        template = jax.eval_shape(kernel.initial_state, jax.random.PRNGKey(0))

        def one(key, alpha, kappa, gamma, omega, F, eta, params, mu, ends):
            state = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), template)
            state = state._replace(hyper=Hyper(alpha, kappa, gamma), omega=omega, features=F, eta=eta, params=params,
                                   cache=kernel.emission.init_cache(K), end_mean=mu, ends=ends)

            def body(state, key):
                k_gen, k_sweep = jax.random.split(key)
                z, new = regenerate(k_gen, state)
                on_data = J.with_data(kernel, new)
                state = on_data.sweep(on_data._finish(state._replace(z=z, rng_key=k_sweep)))
                return state, statistics(state, new)

            return jax.lax.scan(body, state, jax.random.split(key, 100))[1]

        return jax.vmap(one)(jax.random.split(key, start[0].shape[0]), *start)

    chains = 48
    rng = np.random.default_rng(0)
    draws = prior_draws(rng, 8 * chains)
    start = jax.tree.map(lambda x: jnp.asarray(x[:chains]), draws)
    out = np.asarray(run(jax.random.PRNGKey(0), start))
    prior = simulate(rng, 50000)
    means = out.mean(1)
    lines, worst = [], 1.0
    for j, name in enumerate(names):
        x = prior[name]
        se = np.sqrt(means[:, j].var(ddof=1) / chains + x.var(ddof=1) / len(x))
        t = (means[:, j].mean() - x.mean()) / se
        p = 2 * stats.t.sf(abs(t), chains - 1)
        worst = min(worst, p)
        lines.append(f"{name}: chains {means[:, j].mean():.4f}, prior {x.mean():.4f}, t {t:+.2f}, p {p:.2g}")
    assert worst > 1e-3 / len(names), "\n".join(lines)


@pytest.mark.parametrize("bad", [1.0, -0.1, True, "half"])
def test_a_bad_sticky_phase_is_named(bad):
    with pytest.raises(ValueError, match="moves.sticky_phase must be a fraction of warmup"):
        BPHMMKernel(PolicyEmission(S, A), ragged_data(), max_skills=3, termination=Termination(S),
                    moves={"sticky_phase": bad})


def test_the_sticky_phase_is_a_sticky_sweep_and_ends_after_it():
    """moves["sticky_phase"] = 0.5 with 10 warmup sweeps: sweeps 0-4 of the state-ends kernel
    are sweeps of the sticky BP-HMM's kernel from the same state (the same features, skill
    sequences, eta, omega and parameters, with a greedy split move on: it moves the sticky model
    too), while the ends are drawn from the skill sequences as in every sweep; sweep 5 on is the
    model's own sweep (it differs from the sticky kernel's), and the log joint is always the
    model's. (Checked to fail: the diagonal left out of eta's
    counts in the phase; the gate not replaced by ones in the phase; the moves given the
    model's gate in the phase.) Every move reads its gate from one MoveState, so one move shows
    which gate they see: the greedy split, accepted often enough in these 7 sweeps to show it
    (split-merge or birth-death moves alone do not catch that third change; with both on as
    well, the test would compile twice as long: 60-70 s against 33 s)."""
    data = ragged_data(7, N=5, T=25, pad=False)
    # (no greedy merges: on these data they merge every skill into one, and the sweeps after the
    # phase would then not differ from the sticky kernel's)
    moves = {"greedy_split": 1, "greedy_from": 0.0, "split_merge": 0, "birth_death": 0}
    term = Termination(S, 2.0, (1.0, 4.0))
    state_k = BPHMMKernel(PolicyEmission(S, A), data, max_skills=4, kappa=5.0, termination=term,
                          moves={**moves, "sticky_phase": 0.5})
    sticky_k = BPHMMKernel(PolicyEmission(S, A), data, max_skills=4, kappa=5.0, moves=moves)
    plain_k = BPHMMKernel(PolicyEmission(S, A), data, max_skills=4, kappa=5.0, termination=term, moves=moves)
    state = state_k.init(jax.random.PRNGKey(3), 10, None, (), {})
    sweeps = {name: jax.jit(k.sweep) for name, k in (("state", state_k), ("sticky", sticky_k), ("plain", plain_k))}
    same = ("features", "z", "eta", "omega")
    for step in range(7):
        s = state._replace(step=jnp.int32(step))
        new = sweeps["state"](s)
        as_sticky = s._replace(ends=None, end_mean=None)
        as_sticky = sticky_k._finish(as_sticky)  # (its own log marginals: the sticky model's)
        other = sweeps["sticky"](as_sticky)
        plain = sweeps["plain"](s)
        if step < 5:
            for name in same:
                np.testing.assert_array_equal(np.asarray(getattr(new, name)), np.asarray(getattr(other, name)), f"{name} {step}")
            np.testing.assert_array_equal(np.asarray(new.params["policy"]), np.asarray(other.params["policy"]))
        else:
            np.testing.assert_array_equal(np.asarray(new.z), np.asarray(plain.z))
            np.testing.assert_array_equal(np.asarray(new.eta), np.asarray(plain.eta))
            assert not np.array_equal(np.asarray(new.eta), np.asarray(other.eta))  # (the stays inform only the sticky eta)
        np.testing.assert_allclose(float(new.log_joint), model_log_density(state_k, new), rtol=1e-10)
        state = new


# ------------------------------------------------------------------ switching="auto": the evidence
def _evidence_reference(z, lengths, states, K, S, kappa_prior, term, gamma=1.0):
    """The two log evidences of switching_log_evidence written out with NumPy/SciPy: each
    trajectory's skills those it uses, eta's rows as Dirichlet-multinomials, kappa and each
    skill's mean end integrated by adaptive quadrature (scipy.integrate.quad)."""
    from scipy import integrate
    from scipy.special import gammaln

    def dm(c, a):
        return gammaln(a.sum()) - gammaln(a.sum() + c.sum()) + np.sum(gammaln(a + c) - gammaln(a))

    seqs = [np.asarray(z[i, :n]) for i, n in enumerate(lengths)]

    def sticky_given(kappa):
        total = 0.0
        for zi in seqs:
            act = list(np.unique(zi))
            total -= np.log(len(act))
            C = np.zeros((K, K))
            for a, b in zip(zi[:-1], zi[1:]):
                C[a, b] += 1
            for r in act:
                a = np.full(len(act), gamma)
                a[act.index(r)] += kappa
                total += dm(C[r, act], a)
        return total

    shape, rate = kappa_prior
    sticky = np.log(integrate.quad(lambda k: np.exp(sticky_given(k)) * stats.gamma.pdf(k, shape, scale=1 / rate),
                                   0, np.inf, limit=200)[0])
    state, E, Nn = 0.0, np.zeros((K, S)), np.zeros((K, S))
    for i, zi in enumerate(seqs):
        act = list(np.unique(zi))
        state -= np.log(len(act))
        if len(act) < 2:
            continue
        C = np.zeros((K, K))
        for t in range(1, len(zi)):
            a, b = zi[t - 1], zi[t]
            if a != b:
                C[a, b] += 1
                E[a, states[i, t]] += 1
            else:
                Nn[a, states[i, t]] += 1
        for r in act:
            others = [k for k in act if k != r]
            state += dm(C[r, others], np.full(len(others), gamma))
    c, (a0, b0) = term.concentration, term.mean_prior
    for k in range(K):
        seen = E[k] + Nn[k] > 0
        if not seen.any():
            continue

        def given(mu):
            return np.exp(np.sum(betaln(c * mu + E[k][seen], c * (1 - mu) + Nn[k][seen]) - betaln(c * mu, c * (1 - mu))))

        state += np.log(integrate.quad(lambda mu: given(mu) * stats.beta.pdf(mu, a0, b0), 0, 1, limit=200)[0])
    return sticky, state


def test_the_switching_evidence_matches_quadrature_on_ragged_trajectories():
    """switching_log_evidence (64 prior quantiles for kappa and each mu_k) against the NumPy
    reference with adaptive quadrature: ragged lengths, a one-skill trajectory, kappa and ends
    priors other than the defaults. (Checked to fail: the stays left in eta's counts under
    state ends; the ends' Beta-binomial over the one-skill trajectory too.)"""
    from npbrs.models.bphmm import switching_log_evidence

    rng = np.random.default_rng(4)
    K, S, lengths = 3, 4, [14, 7, 9, 6]
    T = max(lengths)
    mask = np.arange(T)[None] < np.array(lengths)[:, None]
    z = np.zeros((4, T), np.int64)
    for i, n in enumerate(lengths):  # runs of a few steps each
        z[i, :n] = np.repeat(rng.integers(0, K, n), rng.integers(2, 5, n))[:n]
    z[3] = 2  # one skill only
    states = rng.integers(0, S, (4, T))
    term = Termination(S, 3.0, (1.0, 4.0))
    got = switching_log_evidence(z, mask, states, S, term, 1.0, (2.0, 0.1))
    want = _evidence_reference(z, lengths, states, K, S, (2.0, 0.1), term)
    np.testing.assert_allclose(got, want, atol=0.05)


def test_the_switching_evidence_sums_to_one_over_every_skill_sequence():
    """Given the features (every skill on) and the states, both evidences are distributions
    over the skill sequences: they sum to one over all of them (two ragged trajectories, two
    skills; one trajectory, three skills). (Checked to fail: the first skill's uniform term left
    out; the diagonal kept under state ends.)"""
    import itertools

    from scipy.special import logsumexp

    from npbrs.models.bphmm import switching_log_evidence

    term = Termination(3, 2.0, (2.0, 3.0))
    rng = np.random.default_rng(0)
    for lengths, K in (([4, 3], 2), ([4], 3)):
        N, T = len(lengths), max(lengths)
        mask = np.arange(T)[None] < np.array(lengths)[:, None]
        states = rng.integers(0, 3, (N, T))
        totals = []
        for flat in itertools.product(range(K), repeat=sum(lengths)):
            z = np.zeros((N, T), np.int64)
            z[mask] = flat
            totals.append(switching_log_evidence(z, mask, states, 3, term, 1.5, (2.0, 0.3), np.ones((N, K))))
        np.testing.assert_allclose(logsumexp(np.array(totals), axis=0), 0.0, atol=1e-9)



def test_the_greedy_moves_score_the_ends_integrated_out():
    """Under state-dependent ends the greedy moves score skill sequences with the ends
    integrated out given their means (collapsed_end_log_prob): each (skill, state) a
    Beta-binomial, against one-dimensional quadrature over beta; and the greedy score's
    structure term is the switches' collapsed probability plus that, whatever ends the chain
    holds. (Checked to fail: the stays and ends swapped in the Beta-binomial.)"""
    from scipy import integrate

    from npbrs.inference.sampler.greedy import structure_log_prob
    from npbrs.models.bphmm import Hyper, collapsed_end_log_prob, collapsed_transition_log_prob, eta_counts

    rng = np.random.default_rng(2)
    N, T, K = 4, 9, 3
    mask = np.arange(T)[None] < np.array([9, 6, 8, 5])[:, None]
    z = np.repeat(rng.integers(0, K, (N, 3)), 3, axis=1)
    states = rng.integers(0, S, (N, T))
    features = np.ones((N, K))
    features[3] = [1.0, 0.0, 0.0]
    z[3] = 0
    mean, c = np.array([0.2, 0.5, 0.05]), 3.0
    got = np.asarray(collapsed_end_log_prob(jnp.asarray(z), jnp.asarray(mask), jnp.asarray(states),
                                            jnp.asarray(features), jnp.asarray(mean), c, S))
    ended, stayed = (np.asarray(x) for x in end_counts(z, mask, states, features, S))
    for k in range(K):
        want = 0.0
        for s in range(S):
            e, n = ended[k, s], stayed[k, s]
            if e + n:
                want += np.log(integrate.quad(lambda b: b ** e * (1 - b) ** n * stats.beta.pdf(b, c * mean[k],
                                                                                               c * (1 - mean[k])),
                                              0, 1)[0])
        np.testing.assert_allclose(got[k], want, rtol=1e-6)
    hyper = Hyper(jnp.float64(1.0), jnp.float64(5.0), jnp.float64(1.0))
    lp = {}
    for seed in (0, 1):  # two different ends held by the chain: the score does not see them
        ends = jax.random.uniform(jax.random.PRNGKey(seed), (K, S))
        model = (ends, jnp.asarray(mean), jnp.float64(c))
        lp[seed] = float(structure_log_prob(hyper, jnp.asarray(mask), jnp.asarray(z), jnp.asarray(features),
                                            end_gate(ends, jnp.asarray(states), jnp.asarray(mask)), None, model,
                                            jnp.asarray(states)))
    assert lp[0] == lp[1]
    from npbrs.models.bphmm import collapsed_feature_log_prob, sequence_counts

    counts = eta_counts(jnp.asarray(z), jnp.asarray(mask), K, True)
    _, rest = sequence_counts(jnp.asarray(z), jnp.asarray(mask), jnp.asarray(features))
    want = (float(jnp.sum(collapsed_transition_log_prob(counts, jnp.asarray(features), 5.0, 1.0, True) + rest))
            + got.sum() + float(collapsed_feature_log_prob(jnp.asarray(features), 1.0, jnp.ones(N, bool))))
    np.testing.assert_allclose(lp[0], want, rtol=1e-10)
