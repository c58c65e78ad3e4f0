"""benchmarks/bench_real.py: the mice-in-a-labyrinth benchmark. Its data lives outside the
repository (``../shared/data/labyrinth``), so these tests skip where it is absent (a clean clone)."""

import importlib.util
import json
import os

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DATA = os.path.join(os.path.dirname(ROOT), "shared", "data", "labyrinth", "water_restricted.npz")
README = os.path.join(os.path.dirname(DATA), "README.md")

needs_data = pytest.mark.skipif(not (os.path.exists(DATA) and os.path.exists(README)),
                                reason=f"the labyrinth data is not here ({DATA}): it lives outside the repository")


def _script():
    spec = importlib.util.spec_from_file_location("bench_real", os.path.join(ROOT, "benchmarks", "bench_real.py"))
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    return script


@needs_data
def test_behaviour_cloning_reproduces_the_readmes_figures():
    """The tables of action frequencies (add-0.5 smoothing; a first step's previous action is a
    category "none" of its own) score the README's -0.218 and -0.630 on the full split, and the
    script reads those and the published table from the README."""
    script = _script()
    with open(README) as f:
        published = script.published_figures(f.read())
    assert published["behaviour_cloning"] == {"state_and_previous_action": -0.218, "state": -0.630}
    table = published["table"]
    assert len(table) == 7
    assert table["DIRL, 4 goal maps with time-varying weights (best)"] == -0.569
    assert table["uniform actions"] == -1.386
    arrays = script.load(DATA)
    assert round(script.behaviour_cloning(arrays), 3) == published["behaviour_cloning"]["state_and_previous_action"]
    assert round(script.behaviour_cloning(arrays, previous_action=False), 3) == published["behaviour_cloning"]["state"]
    assert script.repeated(arrays) == 31


def test_the_published_figures_that_do_not_parse_are_an_error():
    script = _script()
    with pytest.raises(ValueError, match="Published figures"):
        script.published_figures("# a README without the section\n")
    with pytest.raises(ValueError, match="did not parse"):
        script.published_figures("## Published figures\n\n| model | nats per step |\n|---|---:|\n")


@needs_data
@pytest.mark.filterwarnings("ignore:npbrs.fit. not converged")  # (3 + 3 sweeps)
def test_the_benchmark_runs_on_a_few_trajectories(tmp_path, capsys):
    """A tiny run (6 + 6 trajectories, 2 chains of 3 + 3 sweeps, no state-action fit) writes the
    JSON's keys and prints the table; nothing is written beside the data."""
    before = sorted(os.listdir(os.path.dirname(DATA)))
    path = tmp_path / "real.json"
    assert _script().main(["--data", DATA, "--json", str(path), "--trajectories", "6", "--no-references",
                           "--num-warmup", "3", "--num-samples", "3"]) == 0
    out = json.loads(path.read_text())
    assert {"heldout_ll", "heldout_ll_even_names", "heldout_se", "skills", "labelled_skills", "wall_s", "rhat_max", "published",
            "behaviour_cloning", "state_action_rewards", "meta"} <= set(out)
    assert out["heldout_ll"] < 0 and out["heldout_se"] >= 0 and out["skills"] >= 1 and out["wall_s"] > 0
    assert 1 <= out["labelled_skills"] <= out["skills"]
    assert out["state_action_rewards"] is None
    assert out["published"]["behaviour_cloning"]["state"] == -0.630
    assert {"command", "processor", "cores", "note"} <= set(out["meta"])
    assert out["meta"]["train_trajectories"] == out["meta"]["validation_trajectories"] == 6
    printed = capsys.readouterr().out
    assert "| npbrs, a reward per state (fit's defaults) |" in printed and "published: uniform actions" in printed
    assert sorted(os.listdir(os.path.dirname(DATA))) == before
