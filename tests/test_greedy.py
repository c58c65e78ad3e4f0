"""Greedy merges of warmup: a copy of a skill is merged into it, distinct skills are not, the
move changes nothing outside warmup, and it removes copies the Gibbs sweeps keep."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from npbrs.inference.sampler import BPHMMKernel, MoveState, greedy_merge, greedy_merge_at, merge_score
from npbrs.models.emissions import Emission, PolicyEmission
from test_kernel import planted_policy_data


def _tree_equal(a, b):
    return all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def _tree_close(a, b):
    """The same discrete state, and floats equal up to rounding."""
    def same(x, y):
        x, y = np.asarray(x), np.asarray(y)
        if np.issubdtype(x.dtype, np.floating):
            return np.allclose(x, y, rtol=1e-9, atol=1e-12, equal_nan=True)
        return np.array_equal(x, y)

    return all(same(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def _copy_start(moves=None, num_warmup=0, seed=1):
    """Planted data of 3 skills, started at the true segmentation except that skill 0's steps
    in the first trajectories that use it are labelled 3: a copy of skill 0."""
    data, z_true = planted_policy_data(seed=seed, N=6, T=40)
    mask = np.asarray(data.mask)
    uses0 = [i for i in range(z_true.shape[0]) if np.any((z_true[i] == 0) & mask[i])]
    z = z_true.copy()
    for i in uses0[:2]:
        z[i][z[i] == 0] = 3
    kernel = BPHMMKernel(PolicyEmission(4, 3), data, max_skills=5, moves=moves)
    state = kernel.init(jax.random.PRNGKey(1), num_warmup, {"z": jnp.asarray(z)}, (), {})
    return kernel, data, np.where(mask, z_true, -1), state


def test_a_copy_is_merged_into_its_skill_and_distinct_skills_are_not():
    kernel, data, z_true, s = _copy_start()
    em, hyper = kernel.emission, kernel.hyper0
    assert int(s.num_skills) == 4
    state = MoveState.of(s)
    args = (em, data, hyper)
    merge_at = jax.jit(greedy_merge_at, static_argnums=2)
    new, info = merge_at(jax.random.PRNGKey(0), state, *args, 3)
    f, z, params, log_lik = new.features, new.z, new.params, new.log_lik
    assert bool(info.possible) and bool(info.accepted) and int(info.k) == 0
    np.testing.assert_array_equal(np.asarray(z), z_true)  # the copy's steps are skill 0's again
    f0 = np.asarray(s.features)
    np.testing.assert_array_equal(np.asarray(f)[:, 0], np.maximum(f0[:, 0], f0[:, 3]))
    assert not np.any(np.asarray(f)[:, 3])
    # slot 3 holds a prior draw now; the likelihoods returned are those of the parameters of the
    # skills with steps, and slot 3 keeps its column (no trial reads an unused slot's, and the
    # sweep recomputes them all: the draw is not solved for)
    assert not np.allclose(np.asarray(params["policy"][3]), np.asarray(s.params["policy"][3]))
    log_lik = np.asarray(log_lik)
    np.testing.assert_allclose(log_lik[..., :3], np.asarray(jax.jit(em.log_likelihoods)(params, data)[0])[..., :3],
                               atol=1e-10)
    np.testing.assert_array_equal(log_lik[..., 3:], np.asarray(s.log_lik)[..., 3:])
    # the gain is the score's change, and it is positive (compiled: op by op it was 100 programs)
    score = jax.jit(merge_score)
    gain = float(score(em, data, hyper, f, z) - score(em, data, hyper, s.features, s.z))
    np.testing.assert_allclose(float(info.gain), gain, rtol=1e-10)
    assert gain > 0
    # merging a true skill into another lowers the score: the state is returned unchanged
    for j in (1, 2):
        out, out_info = merge_at(jax.random.PRNGKey(0), state, *args, j)
        assert bool(out_info.possible) and not bool(out_info.accepted) and float(out_info.gain) < 0, j
        assert _tree_equal(out, state)
    # an unused slot cannot be merged
    assert not bool(merge_at(jax.random.PRNGKey(0), state, *args, 4)[1].possible)
    # the random trial is reproducible
    merge = jax.jit(greedy_merge, static_argnums=2)
    assert _tree_equal(merge(jax.random.PRNGKey(5), state, *args), merge(jax.random.PRNGKey(5), state, *args))


def test_greedy_merges_run_only_in_warmup_and_remove_a_copy_gibbs_keeps():
    data3 = planted_policy_data()[0]
    for bad in ({"greedy_merge": -1}, {"greedy_merge": 1.5}, {"greedy_split": -2}, {"greedy_from": 1.0},
                {"greedy_from": "half"}, {"greedy_from": True}):
        with pytest.raises(ValueError, match="moves.greedy_"):
            BPHMMKernel(PolicyEmission(4, 3), data3, max_skills=3, moves=bad)

    class NoEvidence(PolicyEmission):
        fit_evidence = Emission.fit_evidence

    class NoPoint(PolicyEmission):
        fit_point = Emission.fit_point

    for emission, moves, missing in ((NoEvidence(4, 3), {"greedy_merge": 1}, "fit_evidence"),
                                     (NoEvidence(4, 3), {"greedy_split": 1}, "fit_evidence")):
        with pytest.raises(ValueError, match=missing):
            BPHMMKernel(emission, data3, max_skills=3, moves=moves)
    BPHMMKernel(NoPoint(4, 3), data3, max_skills=3, moves={"greedy_split": 1})  # (a split fits by fit_evidence)
    gibbs, data, z_true, s_gibbs = _copy_start(None, num_warmup=4)
    greedy, _, _, s_greedy = _copy_start({"greedy_merge": 2, "greedy_from": 0.25}, num_warmup=4)
    assert _tree_equal(s_gibbs, s_greedy)
    # two chains, vectorised as numpyro runs them (the warmup test is shared by the chains)
    two = lambda s: jax.tree.map(lambda x: jnp.stack([x, x]), s)  # noqa: E731
    stack = two(s_gibbs)
    # (a key under which plain Gibbs keeps the copy through warmup, as it does under most)
    stack = stack._replace(rng_key=jax.random.split(jax.random.PRNGKey(8), 2))
    run_gibbs = jax.jit(lambda s: gibbs.sample(s, (), {}))
    run_greedy = jax.jit(lambda s: greedy.sample(s, (), {}))
    a = b = stack
    skills_gibbs, skills_greedy = [], []
    for step in range(8):
        before = b
        a, b = run_gibbs(a), run_greedy(b)
        skills_gibbs.append(np.asarray(a.num_skills).tolist())
        skills_greedy.append(np.asarray(b.num_skills).tolist())
        # greedy_idle counts the greedy sweeps in a row that kept nothing (sweeps 1-3 here)
        kept = np.asarray(b.greedy_merges) > np.asarray(before.greedy_merges)
        idle = np.asarray(before.greedy_idle)
        np.testing.assert_array_equal(b.greedy_idle, np.where(kept, 0, idle + 1) if 1 <= step < 4 else idle)
        if step < 1:  # before greedy_from * warmup = sweep 1: the same sweeps (two programs, so
            # the floats may differ in rounding)
            assert _tree_close(a, b), step
    assert skills_gibbs[3] == [4, 4], skills_gibbs  # Gibbs keeps the copy through warmup
    assert skills_greedy[3] == [3, 3] and skills_greedy[-1] == [3, 3], skills_greedy
    # the state counts the moves kept (warmup's totals): a merge per chain, no splits (off)
    assert np.all(np.asarray(b.greedy_merges) >= 1) and not np.any(np.asarray(b.greedy_splits))
    assert not np.any(np.asarray(a.greedy_merges)) and not np.any(np.asarray(a.greedy_splits))
    # the greedy moves stop once every chain's last greedy_patience greedy sweeps kept nothing:
    # while one chain's have not, both chains try: each chain's count of idle greedy sweeps is
    # reset (it merged the copy) or grows by one (its trials kept nothing), the stopped chain's too ...
    patience = greedy.moves["greedy_patience"]
    mixed = stack._replace(step=jnp.full(2, 2, jnp.int32), greedy_idle=jnp.array([patience, patience - 1]))
    out = run_greedy(mixed)
    merged = np.asarray(out.greedy_merges) > 0
    assert merged.any() and np.all(np.asarray(out.num_skills)[merged] == 3)
    np.testing.assert_array_equal(out.greedy_idle, np.where(merged, 0, np.asarray(mixed.greedy_idle) + 1))
    # ... and fit's sequential driver, which sweeps one chain at a time, does the same
    from npbrs.inference.driver.chains import Chains
    from npbrs.inference.driver.compiled import Compiled
    chains = Chains(Compiled(greedy, ()), "sequential", mixed)
    chains.advance()
    assert _tree_close(chains.state(), out)
    # once all have stopped, a sweep is the Gibbs sweep
    stopped = mixed._replace(greedy_idle=jnp.full(2, patience))
    out = run_greedy(stopped)
    assert _tree_close(out, run_gibbs(stopped)) and np.all(np.asarray(out.greedy_idle) == patience)
    with pytest.raises(ValueError, match="greedy_patience"):
        BPHMMKernel(PolicyEmission(4, 3), data3, max_skills=3, moves={"greedy_patience": -1})
    # after warmup the greedy kernel's sweep is the Gibbs sweep, even from the copy (up to rounding)
    for seed in range(3):
        late = stack._replace(step=jnp.full(2, 4, jnp.int32), rng_key=jax.random.split(jax.random.PRNGKey(seed), 2))
        assert _tree_close(run_greedy(late), run_gibbs(late)), seed


@pytest.mark.library_level
def test_policy_evidence_is_the_prior_expectation_of_the_likelihood():
    """Exact Dirichlet-multinomial evidence against a Monte Carlo average over the prior."""
    data, _ = planted_policy_data(seed=3, N=2, T=6, S=2, A=3)
    em = PolicyEmission(2, 3, concentration=0.7)
    rng = np.random.default_rng(0)
    weights = jnp.asarray(rng.integers(0, 2, (2, 6, 2)).astype(float))
    _, log_ev = em.fit_evidence(data, weights)
    draws = jax.random.dirichlet(jax.random.PRNGKey(0), jnp.full((200000, 2, 3), 0.7))
    ll = em.log_likelihoods({"policy": draws}, data)[0]  # (N, T, draws)
    per_draw = jnp.einsum("ntd,ntm->dm", ll, weights)  # (draws, M)
    mc = np.asarray(jax.scipy.special.logsumexp(per_draw, axis=0) - np.log(draws.shape[0]))
    np.testing.assert_allclose(np.asarray(log_ev), mc, atol=0.03)


@pytest.mark.parametrize("scale_prior, prior_df", [(False, None), ((2.0, 4.0), None), (False, 2.0)])
def test_reward_laplace_evidence_is_close_to_importance_sampling(scale_prior, prior_df):
    """The reward emission's Laplace evidence against an importance-sampling estimate of
    log E_prior[p(steps | theta)] (proposal: a wide Gaussian around the fit), on a gridworld;
    with a sampled prior variance the prior is theta's marginal, a multivariate Student t; with
    ``prior_df`` a Student t per weight (scale 1: the Laplace precision holds the t's curvature
    at the fit)."""
    from gridworld import gridworld
    from jax.scipy.special import gammaln

    from npbrs.domains.demos import generate_demonstrations
    from npbrs.inference import make_emission
    from npbrs.models.emissions import HMMData

    dom = gridworld(size=3)
    demos = generate_demonstrations(dom, num_trajectories=2, length=30, switch_prob=0.05, seed=1)
    data = HMMData.from_demonstrations(demos)
    em = make_emission("reward", dom.mdp, prior_scale=3.0 if prior_df is None else 1.0, scale_prior=scale_prior,
                       prior_df=prior_df, t_evidence="calibrated")
    z = np.zeros(data.mask.shape, int)
    for i, s in enumerate(demos.skills):
        z[i, :len(s)] = s
    weights = jax.nn.one_hot(jnp.asarray(z), 3) * data.mask[..., None]
    fits, log_ev = jax.jit(em.fit_evidence)(data, weights)  # compiled, not run op by op
    # importance sampling: q = N(fit, (2 * Laplace sd)^2) per skill
    from npbrs.models.reward.likelihood import fisher_information

    from numpyro.distributions import MultivariateNormal

    def log_prior(theta):
        if not scale_prior:
            return em.log_prior({"theta": theta})
        a, b = scale_prior
        D = theta.shape[-1]
        return (gammaln(a + D / 2) - gammaln(a) - D / 2 * jnp.log(2 * jnp.pi * b)
                - (a + D / 2) * jnp.log1p(jnp.sum(theta ** 2, -1) / (2 * b)))

    @jax.jit  # one program for the three skills (op by op it was a hundred)
    def estimate(key, fit, w):
        count = em.counts(data, w[..., None])[0]
        F = fisher_information(em.solver, fit, count) + jnp.eye(3) / 3.0 ** 2
        q = MultivariateNormal(fit, 4.0 * jnp.linalg.inv(F))
        theta = q.sample(key, (4000,))
        ll = jnp.einsum("ntd,nt->d", em.log_likelihoods({"theta": theta}, data)[0], w)
        log_w = ll + log_prior(theta) - q.log_prob(theta)
        return jax.scipy.special.logsumexp(log_w) - np.log(theta.shape[0])

    estimates = [float(estimate(jax.random.PRNGKey(m), fits["theta"][m], weights[..., m])) for m in range(3)]
    np.testing.assert_allclose(np.asarray(log_ev), estimates, atol=0.3)
    if prior_df is not None:  # the default "laplace" evidence: the same fits, 0.6-0.9 nats low here
        plain = make_emission("reward", dom.mdp, prior_scale=1.0, prior_df=prior_df)
        assert plain.t_evidence == "laplace"
        plain_fits, plain_ev = jax.jit(plain.fit_evidence)(data, weights)
        np.testing.assert_allclose(np.asarray(plain_fits["theta"]), np.asarray(fits["theta"]), rtol=1e-12)
        low = np.asarray(estimates) - np.asarray(plain_ev)
        assert np.all((low > 0.4) & (low < 1.2)), low
    # a traced ``with_evidence`` (the greedy split's allocation fits by the same call): the same
    # fits either way, the evidences where it is true, NaN where it is false
    flagged = jax.jit(lambda flag: em.fit_evidence(data, weights, None, with_evidence=flag))
    for flag in (True, False):
        fits_f, log_ev_f = flagged(flag)
        np.testing.assert_allclose(np.asarray(fits_f["theta"]), np.asarray(fits["theta"]), rtol=1e-9, atol=1e-12)
        if flag:
            np.testing.assert_allclose(np.asarray(log_ev_f), np.asarray(log_ev), rtol=1e-9)
        else:
            assert np.all(np.isnan(np.asarray(log_ev_f)))
    if scale_prior:
        # with the prior's variance pinned (at the variance of the fit), the fixed-scale Laplace evidence
        pinned = make_emission("reward", dom.mdp, prior_scale=3.0, scale_prior=(1e6, 9e6))
        theta, log_lik, precision, _ = jax.jit(em.laplace)(em.counts(data, weights))
        fixed = make_emission("reward", dom.mdp, prior_scale=3.0, scale_prior=False)
        _, logdet = jnp.linalg.slogdet(precision)
        laplace = log_lik + fixed.log_prior({"theta": theta}) + 1.5 * np.log(2 * np.pi) - 0.5 * logdet
        mixed = pinned.scale_mixture_evidence(theta, log_lik, precision, jnp.full(3, 9.0))
        np.testing.assert_allclose(np.asarray(mixed), np.asarray(laplace), atol=2e-3)


def test_a_lumped_pair_is_split_and_a_true_skill_is_not():
    from npbrs.inference.sampler import greedy_split_at

    data, z_true = planted_policy_data(seed=1, N=6, T=40)
    mask = np.asarray(data.mask)
    z = np.where(z_true == 2, 1, z_true)  # skills 1 and 2 share slot 1
    kernel = BPHMMKernel(PolicyEmission(4, 3), data, max_skills=5, moves={"greedy_split": 1})
    s = kernel.init(jax.random.PRNGKey(1), 0, {"z": jnp.asarray(z)}, (), {})
    assert int(s.num_skills) == 2
    state = MoveState.of(s)
    args = (kernel.emission, data, kernel.hyper0)
    split_at = jax.jit(greedy_split_at, static_argnums=2)
    where = lambda k: [(i, t) for i in range(6) for t in range(40) if mask[i, t] and z_true[i, t] == k]  # noqa: E731
    a, b = where(1)[3], where(2)[5]
    new, info = split_at(jax.random.PRNGKey(0), state, *args, (*a, *b))
    f, zz, params, log_lik = new.features, new.z, new.params, new.log_lik
    assert bool(info.possible) and bool(info.accepted) and float(info.gain) > 0
    k2 = int(info.k)
    assert k2 not in (0, 1)
    zz = np.asarray(zz)
    # the split separates the two true skills (up to a few steps the actions do not tell apart)
    agree = np.mean(np.where(z_true == 2, zz == k2, zz == z_true)[mask])
    assert agree > 0.9, agree
    np.testing.assert_array_equal(np.asarray(f)[:, k2], np.any((zz == k2) & mask, axis=1))
    np.testing.assert_allclose(np.asarray(log_lik), np.asarray(kernel.emission.log_likelihoods(params, data)[0]),
                               atol=1e-10)
    gain = float(merge_score(kernel.emission, data, kernel.hyper0, f, jnp.asarray(zz))
                 - merge_score(kernel.emission, data, kernel.hyper0, s.features, s.z))
    np.testing.assert_allclose(float(info.gain), gain, rtol=1e-8)
    # splitting true skill 0 at two of its steps lowers the score: nothing changes
    c, d = where(0)[2], where(0)[-3]
    out, out_info = split_at(jax.random.PRNGKey(0), state, *args, (*c, *d))
    assert bool(out_info.possible) and not bool(out_info.accepted), float(out_info.gain)
    assert _tree_equal(out, state)

    class WithoutFlag(PolicyEmission):  # an emission whose fit_evidence does not take ``with_evidence``
        fits_without_evidence = False

        def fit_evidence(self, data, weights, init=None):
            return PolicyEmission.fit_evidence(self, data, weights, init)

    old_style = split_at(jax.random.PRNGKey(0), state, WithoutFlag(4, 3), data, kernel.hyper0, (*a, *b))
    assert _tree_equal(old_style, (new, info))
    # the random trial (anchors drawn towards badly explained steps) finds the split, reproducibly
    from npbrs.inference.sampler import greedy_split

    split = jax.jit(greedy_split, static_argnums=2)
    outs = [split(jax.random.PRNGKey(r), state, *args) for r in range(4)]
    assert any(bool(o[1].accepted) for o in outs), [float(o[1].gain) for o in outs]
    assert _tree_equal(split(jax.random.PRNGKey(0), state, *args), outs[0])
    # the kernel's loop (one compiled evidence for merges and splits) is the trials one by one
    from npbrs.inference.sampler import greedy_trials

    merge = jax.jit(greedy_merge, static_argnums=2)
    k_m, k_s = jax.random.PRNGKey(3), jax.random.PRNGKey(0)
    looped, merged, kept_splits = jax.jit(greedy_trials, static_argnums=(3, 6, 7))(k_m, k_s, state, *args, 2, 2)
    one, kept = state, []
    for key in jax.random.split(k_m, 2):
        one, info = merge(key, one, *args)
        kept.append(("merge", bool(info.accepted)))
    for key in jax.random.split(k_s, 2):
        one, info = split(key, one, *args)
        kept.append(("split", bool(info.accepted)))
    assert _tree_close(looped, one)
    assert (int(merged), int(kept_splits)) == tuple(sum(a for m, a in kept if m == w) for w in ("merge", "split"))
    assert int(kept_splits) >= 1, kept  # the lumped pair is split in the loop too


def test_fit_runs_greedy_merges_by_default_where_the_emission_supports_them():

    from gridworld import gridworld

    from npbrs.domains.demos import generate_demonstrations
    from npbrs.inference import ModelConfig, fit
    from npbrs.models.autoregressive import AutoregressiveEmission

    from npbrs.inference.driver import compiled as compiled_module
    dom = gridworld(size=3)
    demos = generate_demonstrations(dom, num_trajectories=2, length=12, seed=0)
    result = fit(dom.mdp, demos, {"emission": "policy", "max_skills": 3}, num_chains=1, num_warmup=2, num_samples=1,
                 progress_bar=False)
    # recorded in the run
    assert result.config["sampler"]["moves"] == {"greedy_merge": 1, "greedy_split": 1, "greedy_from": 0.75}
    policy = PolicyEmission(9, 5)
    moves = lambda cfg, em=policy: compiled_module.default_moves(cfg, em).sampler.moves  # noqa: E731
    assert moves(ModelConfig.from_dict({"sampler": {"moves": {"greedy_merge": 0}}})) == {
        "greedy_merge": 0, "greedy_split": 1, "greedy_from": 0.75}
    assert moves(ModelConfig.from_dict({"sampler": {"moves": {"birth_death": 1}}})) == {
        "birth_death": 1, "greedy_merge": 1, "greedy_split": 1, "greedy_from": 0.75}
    assert moves(ModelConfig.from_dict({"max_skills": 1})) == {}  # one slot: nothing to merge

    class NoPoint(PolicyEmission):
        fit_point = Emission.fit_point

    # (a split's allocation fits by fit_evidence too: splits need no fit_point)
    assert moves(ModelConfig(), NoPoint(9, 5)) == {"greedy_merge": 1, "greedy_split": 1, "greedy_from": 0.75}
    # (an emission without fit_evidence: no greedy moves; the windows and the starting skills are
    # the only defaults left open)
    cfg = ModelConfig.from_dict({"sampler": {"init_window": 25, "init_skills": 4}})
    assert compiled_module.default_moves(cfg, AutoregressiveEmission.__new__(AutoregressiveEmission)) is cfg


def test_the_search_solves_looser_and_only_the_search(monkeypatch):
    """``RewardEmission.for_search``: a copy whose solver has ``search_tol`` (itself when the
    solver is as loose already); warm-started as in the greedy moves, its Laplace evidences and
    fits are the exact solver's within 1e-5 nats and 1e-4. The kernel hands it to the starting
    fits, the greedy moves and the reward move's preconditioner (refreshed inside ``update``,
    ``_preconditioner``) only: the reward move and the likelihoods the sampler keeps see the
    solver's own tolerance. (Traced, not
    compiled: each method records the tolerance it ran with.) It failed with the greedy moves
    given the kernel's emission."""
    from gridworld import gridworld

    from npbrs.domains.demos import generate_demonstrations
    from npbrs.inference import make_emission
    from npbrs.models.emissions import HMMData
    from npbrs.models.reward.emission import RewardEmission

    dom = gridworld(size=3)
    demos = generate_demonstrations(dom, num_trajectories=2, length=30, switch_prob=0.05, seed=1)
    data = HMMData.from_demonstrations(demos)
    em = make_emission("reward", dom.mdp, prior_scale=3.0)
    search = em.for_search()
    assert (em.search_tol, em.solver.tol, search.solver.tol) == (1e-6, 1e-10, 1e-6) and search is not em
    assert search.solver.features is em.solver.features and em.describe()["search_tol"] == 1e-6
    assert make_emission("reward", dom.mdp, solver_options={"tol": 1e-5}).for_search().solver.tol == 1e-5
    assert make_emission("reward", dom.mdp, search_tol=1e-12).for_search().solver.tol == 1e-10
    with pytest.raises(ValueError, match="search_tol"):
        make_emission("reward", dom.mdp, search_tol=0.0)

    z = np.zeros(data.mask.shape, int)
    for i, s in enumerate(demos.skills):
        z[i, :len(s)] = s
    weights = jax.nn.one_hot(jnp.asarray(z), 3) * data.mask[..., None]
    # from theta = 0 (20 L-BFGS steps) the looser fits stop a little earlier; warm-started, as
    # the greedy moves fit (3 steps from the current rewards), they agree closely
    both = jax.jit(lambda w, init: (em.fit_evidence(data, w, init), search.fit_evidence(data, w, init)))
    (fits, log_ev), (loose_fits, loose_ev) = both(weights, None)
    np.testing.assert_allclose(np.asarray(loose_ev), np.asarray(log_ev), atol=0.02)
    np.testing.assert_allclose(np.asarray(loose_fits["theta"]), np.asarray(fits["theta"]), atol=0.1)
    (fits, log_ev), (loose_fits, loose_ev) = both(weights, fits)
    np.testing.assert_allclose(np.asarray(loose_ev), np.asarray(log_ev), atol=1e-5)
    np.testing.assert_allclose(np.asarray(loose_fits["theta"]), np.asarray(fits["theta"]), atol=1e-4)
    # the fits' likelihoods that the greedy moves ask for come from the fits' own values (no
    # solve): those of the fits, to the search's tolerance (checked to fail with the values of the
    # fits' starts)
    loose_fits, loose_ev, lik = jax.jit(lambda w, init: search.fit_evidence(data, w, init, with_likelihoods=True))(
        weights, fits)
    np.testing.assert_allclose(np.asarray(lik), np.asarray(search.log_likelihoods(loose_fits, data)[0]), atol=1e-5)

    seen = {}
    for name in ("update", "tune", "_preconditioner", "log_likelihoods", "fit_evidence", "fit_point", "init_params"):
        method = getattr(RewardEmission, name)

        @functools.wraps(method)  # (the sampler reads the keywords an emission's method takes)
        def recording(self, *args, _name=name, _method=method, **kwargs):
            seen.setdefault(_name, set()).add(self.solver.tol)
            return _method(self, *args, **kwargs)

        monkeypatch.setattr(RewardEmission, name, recording)
    kernel = BPHMMKernel(em, data, max_skills=3, moves={"greedy_merge": 1, "greedy_split": 1, "greedy_from": 0.0})
    state = jax.eval_shape(lambda k: kernel.initial_state(k, None, 4), jax.random.PRNGKey(0))
    jax.eval_shape(kernel.sweep, state)
    assert seen == {"init_params": {1e-6}, "fit_evidence": {1e-6}, "update": {1e-10}, "_preconditioner": {1e-6},
                    "log_likelihoods": {1e-10}}, seen
