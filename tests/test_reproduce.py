"""The reproduction of the paper's Figures 7 and 10: every cell of the table is filled, the
expert's score is what a method gets back with the true skills, the JSON round trips, the
plots are written, a stopped reproduction resumes, and the command line writes its files.

The fast tests replace ``fit`` by an oracle that returns the true segmentation and rewards
(compiling four samplers per run takes minutes on two cores); the slow test runs the real
samplers of ``--quick``."""

import argparse
import importlib.util
import json
import os
import sys
from types import SimpleNamespace

import numpy as np
import pytest

from npbrs.domains.registry import get_domain
from npbrs.inference.cli import reproduce as rep
from npbrs.inference.cli.reproduce import (COLUMNS, METHODS, ROWS, format_markdown, load_json, reproduce,
                                       save_json)

# (the expert's and the methods' solves on the highway run many times: level 0 runs them slowly)
pytestmark = pytest.mark.library_level

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture
def oracle_fit(monkeypatch):
    """``fit`` replaced by the truth: the true segmentation and skill rewards ("single": one
    skill with skill A's reward; "subgoal": every skill aims at the first candidate goal). The
    truth is the run's per-step most probable skills (``segment``); its best draw
    (``segmentation``) mislabels every trajectory's first step."""
    calls = []
    domain = get_domain("highway")

    def fake(mdp, demos, config=None, *, seed=None, **kwargs):
        emission, max_skills = config["emission"], config["max_skills"]
        name = emission if isinstance(emission, str) else emission.name
        calls.append((name, seed, max_skills))
        true = [np.asarray(z) for z in demos.skills]
        if name == "single":
            seg, params = [np.zeros_like(z) for z in true], {"theta": domain.skill_weights[:1]}
        elif name == "subgoal":
            seg, params = true, {"goal": np.repeat(np.asarray(emission.candidates[:1]), domain.num_skills)}
        elif name == "reward":
            seg, params = true, {"theta": np.array(domain.skill_weights)}
        else:
            seg, params = true, {}
        K = len(np.unique(np.concatenate(seg)))
        best = [np.where(np.arange(len(z)) == 0, (z + 1) % K, z) for z in seg]
        return SimpleNamespace(segmentation=best, num_skills=K, skill_params=params, best_log_joint=0.0,
                               wall_time=0.0, segment=lambda mdp, emission=None: SimpleNamespace(labels=seg))

    monkeypatch.setattr(sys.modules["npbrs.inference.driver.fit"], "fit", fake)
    return calls


def check_table(result, runs):
    columns = ["expert", *METHODS]
    assert set(result["table"]) == {row for row, _ in ROWS}
    for row, _ in ROWS:
        assert list(result["table"][row]) == columns
        for col in columns:
            cell = result["table"][row][col]
            if (row == "reward" and col == "lds") or (row == "wall_time" and col == "expert"):
                assert cell is None  # LDS has no policy; the expert is not fitted
                continue
            assert cell["n"] == runs and np.isfinite(cell["mean"])
            assert (cell["sd"] is None) == (runs == 1)
    assert result["runs_done"] == runs and len(result["per_run"]) == runs
    assert [t["met"] is not None for t in result["targets"]] == [True] * 5


def check_targets_met(result):
    """The true skills meet every target: the expert's reward and switches, at most 4 skills,
    accuracy 1, ahead of the subgoal and unsegmented baselines (which the markdown says)."""
    targets = result["targets"]
    assert [t["met"] for t in targets] == [True] * 5, targets
    assert targets[0]["value"] == "100.0%" and targets[2]["value"].endswith("(+0%)") and targets[3]["value"] == "1.000"
    text = format_markdown(result)
    assert "NOT met" not in text and sum(f"- {t['target']}: met" in text for t in targets) == 5


def test_a_reproduction_with_the_true_skills_scores_as_the_expert(oracle_fit, tmp_path):
    result = reproduce("highway", 40, runs=2, num_trajectories=2, quick=True, plots_dir=tmp_path, progress=False)
    check_table(result, runs=2)
    check_targets_met(result)
    table = result["table"]
    # common random numbers: the true segmentation with the true rewards replays the expert exactly
    assert table["reward"]["npbrs"]["mean"] == table["reward"]["expert"]["mean"]
    for run in result["per_run"]:
        assert run["methods"]["npbrs"]["rewards"] == run["expert"]["rewards"]
    assert table["paper_accuracy"]["npbrs"]["mean"] == table["hungarian_accuracy"]["npbrs"]["mean"] == 1.0
    assert table["switches"]["irl"]["mean"] == 0 and table["skills"]["irl"]["mean"] == 1
    assert table["switches"]["npbrs"]["mean"] == table["switches"]["expert"]["mean"]
    # run r uses seed r for the demonstrations and the sampler; every method and run is fitted once
    assert [r["seed"] for r in result["per_run"]] == [0, 1]
    assert sorted(oracle_fit) == sorted((rep.EMISSIONS[m], r, result["settings"][m]["max_skills"])
                                        for r in (0, 1) for m in METHODS)
    assert sorted(os.listdir(tmp_path)) == ["highway-40-run0.png", "highway-40-run1.png"]

    path = tmp_path / "result.json"
    save_json(result, path)
    assert load_json(path) == result
    text = format_markdown(result)
    for _, label in ROWS:
        assert f"| {label} |" in text
    assert "| | Expert | NPBRS | Subgoal | IRL | LDS |" in text
    assert "2 of 2 runs" in text and "Targets:" in text


def targets_table(reward=98.0, skills=4.0, switches=12.5, accuracy=0.90, irl=0.0, expert_switches=10.0):
    """A table of one run's means (expert reward 100) for ``_targets``."""
    means = {"reward": {"expert": 100.0, "npbrs": reward, "subgoal": -50.0, "irl": irl, "lds": None},
             "skills": {"expert": 3.0, "npbrs": skills}, "switches": {"expert": expert_switches, "npbrs": switches},
             "paper_accuracy": {"npbrs": accuracy}}
    return {row: {col: None if v is None else {"mean": v, "sd": None, "n": 1} for col, v in cells.items()}
            for row, cells in means.items()}


def test_the_targets_are_met_at_their_bounds_and_not_past_them():
    """``_targets`` on constructed tables: every target met exactly at its bound (98% of the
    expert's reward, 4 skills, switches 25% off the expert's, accuracy 0.90, any margin over
    the baselines); each one moved past its bound alone is NOT met, the others still are; one
    that cannot be measured is None."""
    met = lambda table, methods=METHODS: [t["met"] for t in rep._targets(table, list(methods))]  # noqa: E731
    assert met(targets_table()) == [True] * 5
    assert met(targets_table(switches=7.5)) == [True] * 5
    past = [("reward", 97.9, 0), ("skills", 4.1, 1), ("switches", 12.6, 2), ("switches", 7.4, 2),
            ("accuracy", 0.899, 3), ("irl", 98.0, 4)]
    for name, value, which in past:
        assert met(targets_table(**{name: value})) == [i != which for i in range(5)], (name, value)
    assert met(targets_table(expert_switches=0.0))[2] is None  # (no relative error to the expert's 0)
    assert met(targets_table(), ("npbrs", "lds"))[4] is None  # (no baseline to be ahead of)
    assert rep._targets(targets_table(), ["irl"]) == []


def test_a_stopped_reproduction_resumes_with_its_finished_runs(oracle_fit):
    first = reproduce("highway", 30, runs=1, num_trajectories=2, quick=True, progress=False,
                      methods=("npbrs", "lds"))
    oracle_fit.clear()
    seen = []
    both = reproduce("highway", 30, runs=2, num_trajectories=2, quick=True, progress=False, methods=("npbrs", "lds"),
                     previous=json.loads(json.dumps(first)), on_run=seen.append)
    assert [seed for _, seed, _ in oracle_fit] == [1, 1]  # only run 1 is fitted
    assert both["per_run"][0] == first["per_run"][0] and both["runs_done"] == 2
    assert [r["runs_done"] for r in seen] == [2]
    with pytest.raises(ValueError, match="differs in settings"):
        reproduce("highway", 30, runs=2, num_trajectories=2, progress=False, methods=("npbrs", "lds"), previous=first)


def test_a_reproduction_scores_the_posterior_marginals_and_keeps_the_best_draws_scores(oracle_fit):
    """By default every method is scored by its run's per-step most probable skills (here the
    truth); the best draw's segmentation (here off at every first step) is scored beside it,
    and is what ``segmentation="best"`` scores."""
    options = dict(runs=1, num_trajectories=2, quick=True, progress=False, methods=("npbrs", "lds"))
    marginal = reproduce("highway", 30, **options)
    best = reproduce("highway", 30, segmentation="best", **options)
    assert marginal["segmentation"] == "marginal" and best["segmentation"] == "best"
    for method in ("npbrs", "lds"):
        m, b = marginal["per_run"][0]["methods"][method], best["per_run"][0]["methods"][method]
        assert m["hungarian_accuracy"] == 1.0 > b["hungarian_accuracy"]
        assert m["best_draw"] == {k: b[k] for k in ("reward", "switches", "paper_accuracy", "hungarian_accuracy")}
        assert "best_draw" not in b
    run = marginal["per_run"][0]
    assert run["methods"]["npbrs"]["rewards"] == run["expert"]["rewards"]
    assert best["per_run"][0]["methods"]["npbrs"]["reward"] != run["expert"]["reward"]
    assert "best draw's segmentation instead" in format_markdown(marginal)
    assert "best draw's segmentation instead" not in format_markdown(best)
    with pytest.raises(ValueError, match="segmentation must be one of marginal, best"):
        reproduce("highway", 30, segmentation="mode", **options)
    with pytest.raises(ValueError, match="differs in segmentation"):
        reproduce("highway", 30, previous=best, **options)
    # a result made before the setting existed scored the best draw's, and resumes as such
    older = {k: v for k, v in best.items() if k != "segmentation"}
    assert reproduce("highway", 30, previous=older, segmentation="best", **options)["per_run"] == best["per_run"]


def test_bad_methods_and_settings_are_refused():
    with pytest.raises(ValueError, match="methods must be distinct names"):
        reproduce("highway", 30, methods=("npbrs", "hmm"))
    with pytest.raises(ValueError, match="settings.npbrs.sweeps: unknown setting"):
        reproduce("highway", 30, settings={"npbrs": {"sweeps": 3}})


def test_a_methods_switching_setting_reaches_its_fit_and_the_record(oracle_fit, monkeypatch):
    """``settings={"npbrs": {"switching": "state"}}`` (a reproduction with state-dependent ends)
    is passed to ``fit`` and kept in the result."""
    module = sys.modules["npbrs.inference.driver.fit"]
    inner, seen = module.fit, []

    def spy(mdp, demos, config=None, **kwargs):
        seen.append(config)
        return inner(mdp, demos, config, **kwargs)

    monkeypatch.setattr(module, "fit", spy)
    result = reproduce("highway", 30, runs=1, methods=["npbrs"], settings={"npbrs": {"switching": "state"}},
                       progress=False)
    assert [config.get("switching") for config in seen] == ["state"]
    assert result["settings"]["npbrs"]["switching"] == "state"


def test_the_quadcopter_subgoal_baseline_bounds_its_candidates():
    assert rep.default_settings("quadcopter")["subgoal"]["emission_options"]["max_candidates"] >= 1
    assert "max_candidates" not in rep.default_settings("highway")["subgoal"]["emission_options"]


def parse(argv):
    parser = argparse.ArgumentParser(prog="npbrs")
    rep.add_parser(parser.add_subparsers(dest="command", required=True))
    return parser.parse_args(argv)


def test_the_reproduce_command_writes_json_markdown_and_plots(oracle_fit, tmp_path, capsys):
    args = parse(["reproduce", "--quick", "--json", str(tmp_path / "r.json"), "--markdown", str(tmp_path / "r.md"),
                  "--plots", str(tmp_path / "plots"), "--no-progress"])
    assert args.func(args) == 0
    result = load_json(tmp_path / "r.json")
    check_table(result, runs=1)
    check_targets_met(result)
    assert (result["length"], result["num_trajectories"]) == (40, 2)
    assert (tmp_path / "r.md").read_text() == format_markdown(result)
    assert os.listdir(tmp_path / "plots") == ["highway-40-run0.png"]
    assert "| Reward |" in capsys.readouterr().out


def test_the_benchmark_script_defaults_to_the_results_folder():
    spec = importlib.util.spec_from_file_location("bench_reproduce", os.path.join(ROOT, "benchmarks", "reproduce.py"))
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    assert script.RESULTS == os.path.join(ROOT, "benchmarks", "results")
    with pytest.raises(SystemExit) as e:
        script.main(["--help"])
    assert e.value.code == 0


@pytest.mark.slow
def test_the_quick_reproduction_runs_the_real_samplers(tmp_path):
    args = parse(["reproduce", "--quick", "--json", str(tmp_path / "r.json"), "--plots", str(tmp_path / "plots"),
                  "--no-progress"])
    assert args.func(args) == 0
    result = load_json(tmp_path / "r.json")
    check_table(result, runs=1)
    for method in METHODS:
        assert result["table"]["wall_time"][method]["mean"] > 0
    assert COLUMNS["lds"] in format_markdown(result)
    assert os.listdir(tmp_path / "plots") == ["highway-40-run0.png"]
    # the BP-HMM methods' fits chose their switching model ("auto"), and the table says which
    made = result["per_run"][0]["methods"]["npbrs"]["switching"]
    assert made["chosen"] in ("sticky", "state") and made["margin"] > 0
    assert f"NPBRS: {made['chosen']} in 1 of 1 runs" in format_markdown(result)


def test_the_table_says_which_switching_model_each_methods_fits_chose():
    """Runs whose fits chose their switching model ("auto") are counted by choice, with the
    range of log Bayes factors; runs that fixed the model add no line."""
    from npbrs.inference.cli.reproduce import switching_lines

    made = [{"chosen": c, "log_bayes_factor": f, "margin": 10.0, "sticky": 0.0, "state": f}
            for c, f in (("sticky", -12.5), ("state", 33.0), ("sticky", -4.0))]
    result = {"methods": ["npbrs", "irl"],
              "per_run": [{"methods": {"npbrs": {"switching": m}, "irl": {"switching": None}}} for m in made]}
    lines = switching_lines(result)
    assert lines[-1] == ("- NPBRS: sticky in 2, state in 1 of 3 runs (log Bayes factors of state ends over sticky "
                         "switching -12.5 to +33.0 nats; state needs more than 10)")
    assert not any("IRL" in line for line in lines)
    assert switching_lines({"methods": ["irl"], "per_run": result["per_run"]}) == []
