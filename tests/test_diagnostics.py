"""Diagnostics survive label switching: chains that number the same skills differently are
matched back to one labelling before per-skill summaries; convergence uses label-invariant scalars."""

import warnings

import numpy as np
import pytest

from npbrs.inference import FitResult, convergence, fit, relabel, skill_summary
from npbrs.inference.analysis.diagnostics import relabelled_draws

from gridworld import ragged_policy_problem

MEANS = np.array([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0]])  # three skills' reward weights


def switched_chains(C=3, D=40, N=2, T=30, seed=0):
    """A result whose chains found the same three skills in different slots (slot 3 unused)."""
    rng = np.random.default_rng(seed)
    perms = [np.array([0, 1, 2, 3]), np.array([2, 0, 3, 1]), np.array([3, 2, 1, 0])]  # slot -> skill (3: none)
    truth = np.stack([np.repeat([0, 1, 2], T // 3), np.repeat([2, 0, 1], T // 3)])  # (N, T) skills
    theta = np.zeros((C, D, 4, 2))
    steps = np.zeros((C, D, 4), np.int64)
    chain_z = np.zeros((C, N, T), np.int64)
    for c, perm in enumerate(perms):
        slot_of = {int(k): s for s, k in enumerate(perm)}
        for s, k in enumerate(perm):
            if k < 3:
                theta[c, :, s] = MEANS[k] + 0.1 * rng.normal(size=(D, 2))
                steps[c, :, s] = np.sum(truth == k)
            else:
                theta[c, :, s] = 100.0 + rng.normal(size=(D, 2))  # an unused slot's prior draws
        flip = rng.random((N, T)) < 0.05  # each chain's best segmentation is slightly different
        chain_z[c] = np.vectorize(slot_of.get)(np.where(flip, (truth + 1) % 3, truth))
    segmentation = [chain_z[0, i] for i in range(N)]  # chain 0 is the best; its slots 0..2 are skills 0..2
    stats = {"log_joint": rng.normal(size=(C, D)), "num_skills": np.full((C, D), 3),
             "num_switches": rng.integers(1, 3, (C, D)).astype(float)}
    return FitResult(segmentation=segmentation, num_skills=3, skill_params={"theta": MEANS.copy()},
                     skill_slots=np.arange(3), best_chain=0, best_log_joint=0.0, stats=stats,
                     samples={"theta": theta, "skill_steps": steps}, feature_names=("right", "up"),
                     chain_best_z=chain_z), perms


@pytest.mark.parametrize("by", ["segmentation", "params"])
def test_chains_are_relabelled_to_the_best_chains_skills(by):
    result, perms = switched_chains()
    expected = np.stack([np.where(p < 3, p, -1) for p in perms])
    np.testing.assert_array_equal(relabel(result, by=by), expected)


def test_per_skill_rewards_pool_the_relabelled_chains():
    result, _ = switched_chains()
    draws = relabelled_draws(result, "theta")
    assert draws.shape == (3, 40, 3, 2) and not np.isnan(draws).any()
    table = skill_summary(result, prob=0.9)
    assert list(table.index.get_level_values("entry")[:2]) == ["right", "up"]
    assert set(table["draws"]) == {120}
    for (skill, entry), row in table.iterrows():
        truth = MEANS[skill, ["right", "up"].index(entry)]
        assert abs(row["mean"] - truth) < 0.05
        assert row["lower"] < truth < row["upper"] and row["upper"] - row["lower"] < 0.5


def test_the_summary_is_each_entrys_mean_sd_and_quantiles_of_the_draws_that_hold_the_skill():
    result, _ = switched_chains()
    result.samples["skill_steps"][1, :10, :] = 0  # a chain without the skills in 10 draws
    draws = relabelled_draws(result, "theta").reshape(-1, 3, 2)
    table = skill_summary(result, prob=0.8)
    for j in range(3):
        held = draws[~np.isnan(draws[:, j]).any(-1), j]
        for p, entry in enumerate(["right", "up"]):
            row, v = table.loc[(j, entry)], held[:, p]
            np.testing.assert_allclose([row["mean"], row["sd"], row["lower"], row["upper"]],
                                       [np.mean(v), np.std(v, ddof=1), np.quantile(v, 0.1), np.quantile(v, 0.9)],
                                       rtol=1e-12)
            assert row["draws"] == len(v) == 110


def test_top_keeps_each_skills_largest_weights_first():
    """(``npbrs report`` prints these for a reward per state.)"""
    result, _ = switched_chains()
    full = skill_summary(result)
    top = skill_summary(result, top=1)
    assert list(top.index) == [(0, top.index[0][1]), (1, "right"), (2, "up")]  # skill 1's 5 is "right", 2's "up"
    for key, row in top.iterrows():
        np.testing.assert_array_equal(row.to_numpy(), full.loc[key].to_numpy())
        others = full.loc[key[0]]["mean"].abs()
        assert abs(row["mean"]) == others.max()
    assert skill_summary(result, top=5).equals(full)
    with pytest.raises(ValueError, match="top must be a positive number"):
        skill_summary(result, top=0)


def test_the_report_of_a_reward_per_state_prints_each_skills_largest_weights(tmp_path, capsys):
    from npbrs.inference.analysis.plots import BARS as REPORT_FEATURES  # (all weights up to the plot's bars)
    from npbrs.inference.cli.main import REPORT_TOP, main

    result, _ = switched_chains()
    C, D = result.samples["theta"].shape[:2]
    extra = REPORT_FEATURES + 6 - 2  # small weights on more features than the report lists
    result.samples["theta"] = np.concatenate([result.samples["theta"],
                                              np.random.default_rng(1).normal(size=(C, D, 4, extra))], -1)
    result.skill_params["theta"] = np.concatenate([result.skill_params["theta"], np.zeros((3, extra))], -1)
    result.feature_names = tuple(f"s{d}" for d in range(2 + extra))
    result.save(tmp_path / "run.nc")
    assert main(["report", str(tmp_path / "run.nc")]) == 0
    out = capsys.readouterr().out
    assert f"the {REPORT_TOP} largest in magnitude of {2 + extra}" in out
    table = out.split("largest in magnitude")[1]
    rows = [line.split() for line in table.splitlines() if line.strip().startswith(("0 ", "1 ", "2 ", "s"))
            and not line.startswith("skill")]
    assert len(rows) == 3 * REPORT_TOP
    assert ["1", "s0"] == rows[REPORT_TOP][:2] and ["2", "s1"] == rows[2 * REPORT_TOP][:2]  # 5.0 heads the list


def test_a_skill_missing_from_a_draw_does_not_enter_its_summary():
    result, _ = switched_chains()
    result.samples["skill_steps"][1, :10] = 0  # chain 1 uses no skill in its first 10 draws
    table = skill_summary(result)
    assert set(table["draws"]) == {110}
    assert np.isnan(relabelled_draws(result, "theta")[1, :10]).all()


def test_bad_requests_are_value_errors():
    result, _ = switched_chains()
    with pytest.raises(ValueError, match="by must be"):
        relabel(result, by="colour")
    with pytest.raises(ValueError, match="no per-skill site 'eta'"):
        skill_summary(result, "eta")
    with pytest.raises(ValueError, match="prob must lie in"):
        skill_summary(result, prob=1.5)


# ------------------------------------------------------------------------- a real run
@pytest.fixture(scope="module")
def run():
    # (the problem and settings of test_restart.py and test_skill_probabilities.py, so that the
    # test session's compilation cache holds the sampler already, where a worker ran those first)
    mdp, demos = ragged_policy_problem(correct=0.8)
    return fit(mdp, demos, {"emission": "policy", "max_skills": 3, "moves": {"greedy_merge": 0, "greedy_split": 0}},
               num_chains=2, num_warmup=6, num_samples=30, seed=5, progress_bar=False)


def test_convergence_reports_rhat_and_ess_of_the_label_invariant_scalars(run):
    table = convergence(run)
    assert list(table.index) == ["log_joint", "num_skills", "num_switches"]
    assert {"r_hat", "ess_bulk", "ess_tail", "mean"} <= set(table.columns)
    assert np.isfinite(table.loc["log_joint", "r_hat"]) and table.loc["log_joint", "ess_bulk"] > 1


def test_a_real_run_relabels_its_best_chain_to_itself_and_summarises_every_skill(run):
    mapping = relabel(run)
    np.testing.assert_array_equal(mapping[run.best_chain][run.skill_slots], np.arange(run.num_skills))
    table = skill_summary(run, "policy")
    assert len(table) == run.num_skills * 4 * 3
    assert ((table["lower"] <= table["mean"]) & (table["mean"] <= table["upper"])).all()


def _stats_result(log_joint, num_skills, num_switches):
    from npbrs.inference.driver.results import FitResult

    return FitResult(segmentation=[np.array([0, 0, 1])], num_skills=2, skill_params={}, skill_slots=np.arange(2),
                     best_chain=0, best_log_joint=0.0,
                     stats={"log_joint": log_joint, "num_skills": num_skills, "num_switches": num_switches},
                     samples={})


def test_the_summary_shows_arviz_diagnostics_and_says_when_a_run_has_not_converged():
    import arviz as az

    rng = np.random.default_rng(0)
    mixed = _stats_result(rng.normal(size=(4, 200)), rng.integers(2, 5, (4, 200)).astype(float),
                          rng.normal(size=(4, 200)))
    # the summary's numbers are ArviZ's, as in the convergence table
    x = mixed.stats["log_joint"]
    assert mixed.rhat["log_joint"] == pytest.approx(float(az.rhat(x))) and mixed.ess["log_joint"] == pytest.approx(
        float(az.ess(x)))
    assert "not converged" not in mixed.summary()
    stuck = _stats_result(rng.normal(size=(2, 200)) + np.array([[0.0], [3.0]]), mixed.stats["num_skills"][:2],
                          mixed.stats["num_switches"][:2])
    assert stuck.rhat["log_joint"] > 1.05
    text = stuck.summary()
    assert "not converged: log_joint" in text and "more chains" in text
    # each chain's mean over its halves, where the warning names what to do about each pattern
    lj = stuck.stats["log_joint"]
    means = [(lj[c, :100].mean(), lj[c, 100:].mean()) for c in range(2)]
    assert f"log_joint {means[0][0]:.1f} -> {means[0][1]:.1f} | {means[1][0]:.1f} -> {means[1][1]:.1f}" in text
    assert "num_skills" not in stuck.convergence_warning() and "max_samples" in text
    drifting = _stats_result(rng.normal(size=(2, 200)) + np.linspace(0.0, 6.0, 200), mixed.stats["num_skills"][:2],
                             mixed.stats["num_switches"][:2])
    assert "log_joint" in drifting.convergence_warning() and " -> " in drifting.convergence_warning()
    # fit warns (ConvergenceWarning, at the user's line) exactly when the summary says so
    from npbrs.inference import ConvergenceWarning
    from npbrs.inference.driver.fit import warn_if_unconverged

    with pytest.warns(ConvergenceWarning, match="npbrs.fit: not converged: log_joint .*result.summary") as seen:
        warn_if_unconverged(stuck)
    assert [w.filename for w in seen] == [__file__]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_if_unconverged(mixed)
    # too short to split, and constant: undefined, never an overflowed number
    short = _stats_result(np.array([[1.0, 2.0, 3.0]]), np.full((1, 3), 3.0), np.array([[1.0, 1.0, 2.0]]))
    text = short.summary()
    assert "R-hat undefined ESS undefined" in text and "-1801" not in text
    assert "not converged: log_joint, num_switches (R-hat above 1.05 or ESS below 100; undefined for log_joint, " \
        "num_switches, which varies: fewer than 4 draws a chain" in text  # (num_skills is constant: converged)
    constant = _stats_result(rng.normal(size=(2, 50)), np.full((2, 50), 3.0), rng.normal(size=(2, 50)))
    assert np.isnan(constant.rhat["num_skills"]) and "num_skills R-hat undefined" in constant.summary()
    assert "num_skills" not in constant.convergence_warning()  # the same in every draw of every chain
    # two chains each constant at a different value: not converged, however ArviZ's R-hat comes out
    # (infinite, or huge, by the draws' number)
    apart = _stats_result(mixed.stats["log_joint"][:2], np.repeat([[3.0], [4.0]], 200, axis=1),
                          mixed.stats["num_switches"][:2])
    assert "not converged: num_skills (" in apart.convergence_warning()
    assert "num_skills 3.00 -> 3.00 | 4.00 -> 4.00" in apart.convergence_warning()


# ------------------------------------------------ chains that share a start: nested R-hat
def _nested_by_hand(x, superchains):
    """Margossian et al.'s nested R-hat, written out loop by loop (superchains weighed equally)."""
    labels = sorted(set(superchains))
    K = len(labels)
    super_means, within = [], []
    for k in labels:
        chains = [c for c in range(len(x)) if superchains[c] == k]
        means, variances = [], []
        for c in chains:
            total = 0.0
            for value in x[c]:
                total += value
            mean = total / len(x[c])
            squares = 0.0
            for value in x[c]:
                squares += (value - mean) ** 2
            means.append(mean)
            variances.append(squares / (len(x[c]) - 1))
        super_mean = sum(means) / len(means)
        between = (sum((m - super_mean) ** 2 for m in means) / (len(means) - 1)) if len(means) > 1 else 0.0
        super_means.append(super_mean)
        within.append(between + sum(variances) / len(variances))
    overall = sum(super_means) / K
    B = sum((m - overall) ** 2 for m in super_means) / (K - 1)
    W = sum(within) / K
    return (1.0 + B / W) ** 0.5


def test_nested_rhat_is_the_papers_formula_with_superchains_weighed_equally():
    from npbrs.inference.analysis.diagnostics import nested_rhat

    rng = np.random.default_rng(3)
    x = rng.normal(size=(5, 7)) + rng.normal(size=(5, 1))
    for superchains in ([0, 0, 1, 1, 2], [4, 4, 4, 9, 9], [0, 1, 0, 1, 0], list("aabbb")):
        assert nested_rhat(x, superchains) == pytest.approx(_nested_by_hand(x, superchains), rel=1e-12)
    # one chain per superchain: the classic (neither split nor rank-normalised) R-hat but for its
    # (N - 1)/N factor: nested R-hat^2 = R-hat^2 + 1/N
    C, N = x.shape
    means = x.mean(1)
    B = N / (C - 1) * np.sum((means - means.mean()) ** 2)
    W = np.mean(x.var(1, ddof=1))
    classic = np.sqrt(((N - 1) / N * W + B / N) / W)
    assert nested_rhat(x, np.arange(C)) ** 2 == pytest.approx(classic ** 2 + 1 / N, rel=1e-12)
    # superchains at different levels: far above 1; superchains that agree: near 1 (and never below)
    mixed = rng.normal(size=(4, 2000))
    assert 1.0 <= nested_rhat(mixed, [0, 0, 1, 1]) < 1.01
    apart = mixed + np.array([[0.0], [0.0], [3.0], [3.0]])
    assert nested_rhat(apart, [0, 0, 1, 1]) > 1.5
    # (the same chains, grouped across the levels: each superchain holds both, so they agree)
    assert nested_rhat(apart, [0, 1, 0, 1]) < 1.01
    # undefined: a single superchain, no spread at all, a draw not finite
    assert np.isnan(nested_rhat(mixed, [0, 0, 0, 0]))
    assert np.isnan(nested_rhat(np.repeat([[1.0], [1.0], [2.0]], 5, axis=1), [0, 1, 2]))
    bad = mixed.copy()
    bad[1, 3] = np.nan
    assert np.isnan(nested_rhat(bad, [0, 0, 1, 1]))
    with pytest.raises(ValueError, match="3 superchain ids for 4 chains"):
        nested_rhat(mixed, [0, 0, 1])


def test_chains_that_continued_from_anothers_state_share_its_superchain():
    from npbrs.inference.analysis.diagnostics import shares_start, superchain_ids

    np.testing.assert_array_equal(superchain_ids(None, 3), [0, 1, 2])
    record = {"margin": 50.0, "scores": [-100.0, -130.0, -200.0], "from": [0, 1, 0]}  # restart_lagging's record
    np.testing.assert_array_equal(superchain_ids(record, 3), [0, 1, 0])
    np.testing.assert_array_equal(superchain_ids(dict(record, **{"from": [2, 2, 2, 3]}), 4), [2, 2, 2, 3])
    np.testing.assert_array_equal(superchain_ids(dict(record, **{"from": [0, 1, 2]}), 3), [0, 1, 2])
    assert shares_start([0, 1, 0]) and not shares_start([0, 1, 2])
    with pytest.raises(ValueError, match="names 3 chains, the run has 2"):
        superchain_ids(record, 2)


def _restarted(source, offsets=None, D=300, seed=4):
    """A hand-built run of len(source) well-mixed chains, chain i having continued from chain
    source[i]'s state at warmup's end; ``offsets``: each chain's level of the log joint."""
    rng = np.random.default_rng(seed)
    C = len(source)
    result = _stats_result(rng.normal(size=(C, D)) + (0.0 if offsets is None else np.asarray(offsets)[:, None]),
                           rng.integers(2, 5, (C, D)).astype(float), rng.normal(size=(C, D)))
    result.restart = {"margin": 50.0, "scores": [-100.0 - 40.0 * i for i in range(C)], "from": list(source)}
    return result


def test_a_run_whose_chains_all_share_one_start_has_not_shown_that_it_converged():
    import arviz as az
    from npbrs.inference import ConvergenceWarning
    from npbrs.inference.driver.fit import warn_if_unconverged

    run = _restarted([0, 0])  # chain 1 continued from chain 0's state: one superchain
    free = _restarted([0, 1])  # the same draws, each chain from its own start
    np.testing.assert_array_equal(run.superchains, [0, 0])
    assert all(np.isnan(v) for v in run.rhat.values())
    for name in ("log_joint", "num_skills", "num_switches"):  # ArviZ's figures beside it, unchanged
        x = run.stats[name]
        assert run.rank_rhat[name] == pytest.approx(float(az.rhat(x))) == pytest.approx(free.rhat[name])
        assert run.rank_rhat[name] < 1.05 and run.ess[name] > 100
    text = run.summary()
    assert ("chains 0 and 1 share a start (chain 1 continued from chain 0's state at warmup's end, 40 nats behind "
            "it; restart_margin 50)") in text
    assert "label-invariant diagnostics (nested R-hat undefined: every chain shares one start;" in text
    assert f"log_joint nested R-hat undefined R-hat {run.rank_rhat['log_joint']:.3f}" in text
    first = run.convergence_warning().splitlines()[0]
    assert first.startswith("not converged: log_joint, num_skills, num_switches (nested R-hat undefined: every "
                            "chain shares one start")
    assert "restart_margin=0" in first and "more chains" in first
    assert "fewer than 4 draws" not in first and "R-hat above 1.05" not in first  # (ArviZ's figures pass)
    with pytest.warns(ConvergenceWarning, match="every chain shares one start.*restart_margin=0"):
        warn_if_unconverged(run)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warn_if_unconverged(free)  # the same draws from two starts have converged
    assert "share a start" not in free.summary() and "not converged" not in free.summary()


def test_superchains_at_different_levels_fail_and_agreeing_ones_pass():
    from npbrs.inference.analysis.diagnostics import nested_rhat

    # chains 0 and 2 share chain 0's start; chain 1 kept its own: superchains {0, 2} and {1}
    agree = _restarted([0, 1, 0])
    np.testing.assert_array_equal(agree.superchains, [0, 1, 0])
    for name, v in agree.rhat.items():
        assert v == pytest.approx(nested_rhat(agree.stats[name], [0, 1, 0]), rel=1e-12) and v < 1.05
    text = agree.summary()
    assert "chains 0 and 2 share a start (chain 2 continued from chain 0's state at warmup's end" in text
    assert "nested R-hat over the superchains {0, 2} and {1}" in text and "not converged" not in text
    # three chains continue from chain 0's state; chain 3's own start found another level: the
    # chains' rank-normalised R-hat passes (three of four agree), the superchains' does not
    apart = _restarted([0, 0, 0, 3], offsets=[0.0, 0.0, 0.0, 0.55], D=600)
    assert apart.rank_rhat["log_joint"] < 1.05 < apart.rhat["log_joint"] and apart.ess["log_joint"] > 100
    text = apart.summary()
    assert "chains 0, 1 and 2 share a start (chains 1 and 2 continued from chain 0's state" in text
    assert "nested R-hat over the superchains {0, 1, 2} and {3}" in text
    assert "not converged: log_joint (nested R-hat over the chains that share a start" in text
    apart.restart = None  # the same draws, read as four independent starts, pass
    assert apart.convergence_warning() == ""
    # the rank-normalised R-hat must pass too: it sees chains of different spread (its folded
    # R-hat), which the nested R-hat of means does not
    spread = _restarted([0, 0, 2, 0], D=600)
    spread.stats["log_joint"] = spread.stats["log_joint"] * np.array([[1.0], [2.5], [1.0], [1.0]])
    assert spread.rhat["log_joint"] < 1.05 < spread.rank_rhat["log_joint"] and spread.ess["log_joint"] > 100
    assert spread.convergence_warning().startswith("not converged: log_joint (")


def test_without_restarts_the_figures_are_arviz_rank_normalised_rhat_as_before():
    import arviz as az

    moved_none = _restarted([0, 1, 2])  # a restart record in which no chain moved
    none = _restarted([0, 1, 2])
    none.restart = None
    for run in (moved_none, none):
        np.testing.assert_array_equal(run.superchains, [0, 1, 2])
        for name in ("log_joint", "num_skills", "num_switches"):
            assert run.rhat[name] == float(az.rhat(run.stats[name])) == run.rank_rhat[name]
    assert moved_none.summary() == none.summary()
    assert "label-invariant diagnostics (ArviZ): log_joint R-hat" in none.summary() and "nested" not in none.summary()


def test_the_arviz_form_records_each_chains_superchain(tmp_path):
    from npbrs.inference import load
    from npbrs.inference.analysis.diagnostics import nested_rhat

    run = _restarted([0, 1, 0, 0])
    idata = run.to_arviz()
    for group in ("posterior", "sample_stats"):
        np.testing.assert_array_equal(idata[group]["superchain"].values, [0, 1, 0, 0])
        assert idata[group]["superchain"].dims == ("chain",)
    assert nested_rhat(idata.posterior["log_joint"].values, idata.posterior["superchain"].values) == \
        run.rhat["log_joint"]
    means = idata.posterior["log_joint"].groupby("superchain").mean()
    np.testing.assert_allclose(means.sel(superchain=1).values, run.stats["log_joint"][1])
    run.save(tmp_path / "run.nc")
    again = load(tmp_path / "run.nc")
    assert again.equals(run) and again.summary() == run.summary()
    np.testing.assert_array_equal(again.to_arviz().sample_stats["superchain"].values, [0, 1, 0, 0])
    np.testing.assert_array_equal(_restarted([0, 1]).to_arviz().posterior["superchain"].values, [0, 1])
