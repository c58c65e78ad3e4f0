"""Nothing silent: what a command or ``fit`` cannot do is refused, by name, before any work
starts: output folders that do not exist, runs that would be overwritten, demonstrations the MDP
cannot make, runs of other data or of another kind of likelihood, a credible mass outside (0, 1);
and a held-out score of the fitted trajectories says so."""

import numpy as np
import pytest

from conftest import run_main
from gridworld import gridworld
from npbrs.domains import Demonstrations
from npbrs.inference import FitResult, fit
from npbrs.inference.analysis.predictive import fitted_trajectories, log_predictive


def test_fit_refuses_a_missing_output_folder_and_an_existing_run_before_any_work(tmp_path, no_compilation):
    # (the demonstrations file does not exist either: the output is checked first)
    code, _, err = run_main(["fit", tmp_path / "demos.npz", "--domain", "highway", "-o", tmp_path / "nodir" / "run.nc"])
    assert code == 2 and "nodir" in err and "does not exist" in err and "Traceback" not in err
    assert not (tmp_path / "nodir").exists()
    run = tmp_path / "run.nc"
    run.write_bytes(b"a run of 400 sweeps")
    code, _, err = run_main(["fit", tmp_path / "demos.npz", "--domain", "highway", "-o", run])
    assert code == 2 and "--overwrite" in err and str(run) in err
    assert run.read_bytes() == b"a run of 400 sweeps"
    code, _, err = run_main(["fit", tmp_path / "demos.npz", "--domain", "highway", "-o", run, "--overwrite"])
    assert code == 2 and "demos.npz" in err  # (past the output check: the missing demonstrations)
    code, _, err = run_main(["fit", tmp_path / "demos.npz", "--domain", "highway", "-o", tmp_path])
    assert code == 2 and "is a folder" in err


def test_segment_report_and_compare_check_their_arguments_first(tmp_path, no_compilation):
    missing = tmp_path / "run.nc"  # (no such run: each check comes before the run is read)
    code, _, err = run_main(["segment", missing, tmp_path / "d.npz", "--domain", "highway",
                             "-o", tmp_path / "nodir" / "labels.npz"])
    assert code == 2 and "nodir" in err and "Traceback" not in err
    (tmp_path / "labels.npz").write_bytes(b"mine")
    code, _, err = run_main(["segment", missing, tmp_path / "d.npz", "--domain", "highway", "-o", tmp_path / "labels.npz"])
    assert code == 2 and "--overwrite" in err and (tmp_path / "labels.npz").read_bytes() == b"mine"
    for prob in ("1.5", "0", "-0.1"):
        code, out, err = run_main(["report", missing, "--prob", prob])
        assert code == 2 and "--prob must be between 0 and 1" in err and "Traceback" not in err and out == ""
    code, _, err = run_main(["report", missing, "--plots", tmp_path / "nodir" / "deeper"])
    assert code == 2 and "nodir" in err and not (tmp_path / "nodir").exists()
    code, _, err = run_main(["compare", missing, tmp_path / "." / "run.nc", "--domain", "highway"])
    assert code == 2 and "given twice" in err


def _saved_run(path, fingerprint, emission, demos=None):
    """A small run file (no fit): two chains of four draws, two skills."""
    stats = {k: np.arange(8.0).reshape(2, 4) for k in ("log_joint", "num_skills", "num_switches")}
    result = FitResult(segmentation=[np.array([0, 0, 1, 1])], num_skills=2, skill_params={"pi": np.ones((2, 3))},
                       skill_slots=np.array([0, 1]), best_chain=0, best_log_joint=-1.0, stats=stats, samples={},
                       config={"max_skills": 2}, fingerprint=fingerprint, emission={"name": emission}, demos=demos)
    result.save(path)
    return result


def test_compare_refuses_other_data_other_kinds_and_one_run_twice_before_computing(tmp_path, monkeypatch):
    monkeypatch.setattr(FitResult, "add_log_likelihood", lambda *a, **k: pytest.fail("computed before the checks"))
    a, b, c, d = (tmp_path / f"{n}.nc" for n in "abcd")
    _saved_run(a, "f" * 64, "policy")
    _saved_run(b, "e" * 64, "policy")
    _saved_run(c, "f" * 64, "autoregressive")
    _saved_run(d, "f" * 64, "policy")
    code, _, err = run_main(["compare", a, b, "--domain", "highway"])
    assert code == 2 and "different demonstrations" in err and "MDP" not in err
    code, _, err = run_main(["compare", a, c, "--domain", "highway"])
    assert code == 2 and "probability of the actions" in err and "density of the states' vectors" in err
    code, _, err = run_main(["compare", a, d, "--domain", "highway"])
    assert code == 2 and "hold the same run" in err


def test_fit_refuses_demonstrations_the_mdp_cannot_make_before_compiling(no_compilation):
    mdp = gridworld(size=4).mdp
    # every index in range, but 0 -> 15 is a jump across the grid
    demos = Demonstrations([np.array([0, 1, 2, 3]), np.array([0, 15, 14, 13])], [np.zeros(4, int), np.zeros(4, int)])
    with pytest.raises(ValueError, match=r"trajectory 1, step 0: state 0 with action 0 cannot lead to state 15"):
        fit(mdp, demos, {"emission": "policy"}, progress_bar=False)


def test_a_held_out_score_of_fitted_trajectories_says_so(tmp_path):
    fitted = Demonstrations([np.array([0, 1, 2, 3]), np.array([4, 5, 6, 7])], [np.zeros(4, int), np.ones(4, int)])
    run = _saved_run(tmp_path / "r.nc", fitted.fingerprint(), "policy", demos=fitted)
    new = Demonstrations([np.array([0, 1, 2, 3]), np.array([8, 9, 10, 11])], [np.zeros(4, int), np.zeros(4, int)])
    assert fitted_trajectories(run, fitted) == 2 and fitted_trajectories(run, new) == 1
    assert fitted_trajectories(run, Demonstrations([np.array([9, 9])], [np.array([0, 0])])) == 0
    mdp = gridworld(size=4).mdp
    with pytest.warns(UserWarning, match="1 of the 2 trajectories are ones the run was fitted to"):
        with pytest.raises(Exception):  # (this run has no draws to score with: the warning comes first)
            log_predictive(run, mdp, new, num_draws=1, num_samples=1)


def test_the_options_helpers_are_where_the_domains_are():
    from npbrs.domains import Option, run_option
    from npbrs.domains.options import run_option as same

    assert run_option is same and Option.__module__ == "npbrs.domains.options"


def test_the_summary_says_which_reward_prior_the_number_of_features_chose(tmp_path):
    """Beyond 16 reward weights the emission's "auto" options take a Student t prior and start
    at the fits: a run's summary says which (checked to fail without the line)."""
    run = _saved_run(tmp_path / "r.nc", "f" * 64, "policy")
    assert "reward prior" not in run.summary()
    for D, family, start in ((17, "Student t (2 degrees of freedom)", "the IRL fit"), (16, "Gaussian", "a draw")):
        run.emission = {"name": "reward", "prior_scale": 0.5, "prior_df": 2.0 if D > 16 else False, "start": "auto"}
        run.feature_names = tuple(f"x{i}" for i in range(D))
        run.config = dict(run.config, sampler={"init_window": 5 if D > 16 else 25, "init_skills": 8 if D > 16 else 4})
        line = next(s for s in run.summary().splitlines() if s.startswith("reward prior"))
        assert family in line and start in line and f"{D} reward weights" in line
        assert f"windows of {5 if D > 16 else 25} steps among {8 if D > 16 else 4} skills" in line
