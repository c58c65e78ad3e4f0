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
