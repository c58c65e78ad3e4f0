"""The ``npbrs`` command line: every command has --help; the demo runs end to end; ``fit`` on the
demo's files reproduces the demo's run; ``report`` prints R-hat and ESS and writes plots."""

import os
import subprocess
import sys
import warnings

import numpy as np
import pytest

from npbrs.domains.mdp import TabularMDP
from npbrs.inference import ConvergenceWarning, ModelConfig, load, save_mdp
from conftest import run_main
from npbrs.inference.cli import compilation_cache_dir


@pytest.mark.parametrize("command", ["generate", "fit", "report", "demo", "segment", "score", "compare"])
def test_every_command_has_help(command):
    code, out, _ = run_main([command, "--help"])
    assert code == 0
    assert out.startswith(f"usage: npbrs {command}")


def test_the_console_entry_point_lists_the_commands():
    out = subprocess.run([sys.executable, "-m", "npbrs.inference.cli", "--help"], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0
    for command in ("generate", "fit", "report", "demo"):
        assert command in out.stdout


def test_the_command_line_keeps_compiled_sweeps_in_a_cache_folder(tmp_path):
    assert compilation_cache_dir({"NPBRS_CACHE_DIR": "/x/c"}) == "/x/c"
    assert compilation_cache_dir({"XDG_CACHE_HOME": "/x"}) == os.path.join("/x", "npbrs", "jax")
    assert compilation_cache_dir({}) == os.path.join(os.path.expanduser("~"), ".cache", "npbrs", "jax")
    for off in ({"NPBRS_CACHE_DIR": ""}, {"NPBRS_CACHE_DIR": "off"}, {"JAX_COMPILATION_CACHE_DIR": "/j"},
                {"JAX_COMPILATION_CACHE_DIR": "/j", "NPBRS_CACHE_DIR": "/x"}):
        assert compilation_cache_dir(off) is None, off
    # `npbrs fit` points JAX at it (in a fresh process: this one has its own cache), and what JAX
    # compiles then lands there
    cache = tmp_path / "cache"
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    env.update(NPBRS_CACHE_DIR=str(cache), JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0", JAX_PLATFORMS="cpu")
    script = ("import jax, jax.numpy as jnp\n"
              "from npbrs.inference.cli import main\n"
              "main(['fit', 'missing.npz', '--domain', 'highway', '-o', 'x.nc'])\n"
              "print(jax.config.jax_compilation_cache_dir)\n"
              "jax.jit(lambda x: jnp.sin(x) * 2)(jnp.ones(3)).block_until_ready()\n")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, cwd=tmp_path,
                         timeout=120)
    assert out.stdout.splitlines() == [str(cache)], out.stderr
    assert "missing.npz" in out.stderr  # the fit itself failed: no such file
    assert any(cache.iterdir())


_CACHE_SCRIPT = """
import jax, jax.numpy as jnp
{before}
from npbrs.inference import fit
try:
    fit(None, None)  # refused (no demonstrations), after the cache is on
except ValueError:
    pass
print(jax.config.jax_compilation_cache_dir)
print(float(jax.jit(lambda x: jnp.sin(x).sum() * 2)(jnp.ones(3))))
"""


def test_fit_keeps_compiled_programs_in_a_cache_that_survives_corrupt_entries(tmp_path):
    """``fit`` in Python turns JAX's persistent cache on in npbrs's folder (unless the process
    chose one: it is left alone); an entry that cannot be read (corrupt, half-written by another
    process) is recompiled with a warning, never an error."""
    cache = tmp_path / "cache"
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    env.update(NPBRS_CACHE_DIR=str(cache), JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0", JAX_PLATFORMS="cpu")

    def run(before=""):
        out = subprocess.run([sys.executable, "-c", _CACHE_SCRIPT.format(before=before)], capture_output=True,
                             text=True, env=env, cwd=tmp_path, timeout=120)
        assert out.returncode == 0, out.stderr
        return out

    first = run()
    folder, value = first.stdout.split()
    assert folder == str(cache) and abs(float(value) - 6 * np.sin(1.0)) < 1e-5, first.stdout
    entries = [f for f in cache.rglob("*") if f.is_file()]
    assert entries, "nothing was written to the cache"
    for f in entries:  # corrupt every entry: truncated garbage
        f.write_bytes(b"not an executable")
    second = run()
    assert second.stdout == first.stdout
    assert "Error reading persistent compilation cache entry" in second.stderr
    # a process that chose its own folder keeps it
    own = tmp_path / "own"
    third = run(before=f"jax.config.update('jax_compilation_cache_dir', {str(own)!r})")
    assert third.stdout.split()[0] == str(own)
    # and NPBRS_CACHE_DIR=off leaves the process without one
    env["NPBRS_CACHE_DIR"] = "off"
    assert run().stdout.split()[0] == "None"


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    code, stdout, stderr = run_main(["demo", "--quick", "--emission", "policy", "--out", out, "--no-progress"])
    assert code == 0, stderr
    return out, stdout


def test_the_quick_demo_segments_scores_and_plots(demo):
    out, stdout = demo
    assert {"demos.npz", "config.toml", "run.nc", "segmentation.png"} <= set(os.listdir(out))
    assert "accuracy" in stdout and "one-to-one" in stdout
    assert "expert" in stdout and "npbrs" in stdout  # the control table
    assert ModelConfig.from_toml(out / "config.toml").emission.name == "policy"


def test_fit_on_the_demos_files_reproduces_the_demos_run(demo):
    out, _ = demo
    code, stdout, stderr = run_main(["fit", out / "demos.npz", "--domain", "highway", "--config", out / "config.toml",
                                     "-o", out / "again.nc", "--checkpoint-every", "3", "--no-progress"])
    assert code == 0, stderr
    assert " in 3 trajectories (" in stdout
    assert not (out / "again.nc.checkpoint.npz").exists()  # removed once the run is saved
    assert load(out / "again.nc").equals(load(out / "run.nc"))
    # options override the config
    code, _, stderr = run_main(["fit", out / "demos.npz", "--domain", "highway", "--config", out / "config.toml",
                                "--samples", "2", "--seed", "5", "--devices", "1", "-o", out / "short.nc",
                                "--no-progress"])
    assert code == 0, stderr
    short = load(out / "short.nc")
    assert short.num_draws == 2 and short.model_config.sampler.seed == 5
    # (--devices passes fit's devices=; the runs on several devices are test_devices.py's)
    # --init-from starts from a saved run's segmentation, as fit(init_segmentation=...) does
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        code, stdout, stderr = run_main(["fit", out / "demos.npz", "--domain", "highway", "--config",
                                         out / "config.toml", "--samples", "6", "--init-from", out / "run.nc", "-o",
                                         out / "init.nc", "--no-progress"])
    assert code == 0, stderr
    # six draws have not converged: the printed summary says so, and fit's warning is not repeated
    assert "not converged" in stdout and not [w for w in seen if issubclass(w.category, ConvergenceWarning)]
    from npbrs.domains import Demonstrations, get_domain
    from npbrs.inference import fit

    with pytest.warns(ConvergenceWarning, match="npbrs.fit: not converged: .* result.summary") as seen:
        api = fit(get_domain("highway").mdp, Demonstrations.load(out / "demos.npz"), out / "config.toml",
                  num_samples=6, init_segmentation=load(out / "run.nc"), progress_bar=False)
    assert [w.filename for w in seen if w.category is ConvergenceWarning] == [__file__]  # the user's call
    assert load(out / "init.nc").equals(api)


def test_report_prints_label_invariant_convergence_and_writes_plots(demo):
    out, _ = demo
    code, stdout, stderr = run_main(["report", out / "run.nc", "--plots", out / "plots"])
    assert code == 0, stderr
    assert "r_hat" in stdout and "ess_bulk" in stdout and "num_switches" in stdout
    for name in ("trace.png", "segmentation.png"):
        assert (out / "plots" / name).stat().st_size > 1000


def test_fit_errors_name_what_is_wrong(demo, tmp_path):
    out, _ = demo
    (tmp_path / "bad.toml").write_text('[sampler]\nchainz = 2\n')
    code, _, err = run_main(["fit", out / "demos.npz", "--domain", "highway", "--config", tmp_path / "bad.toml",
                             "-o", tmp_path / "x.nc"])
    assert code == 2 and "sampler.chainz: unknown key" in err
    (tmp_path / "typo.toml").write_text('[emission]\nname = "reward"\n[emission.options]\nprior_scal = 2.0\n')
    code, _, err = run_main(["fit", out / "demos.npz", "--domain", "highway", "--config", tmp_path / "typo.toml",
                             "-o", tmp_path / "x.nc"])
    assert code == 2 and "typo.toml" in err and "prior_scal" in err and len(err.splitlines()) == 1
    tiny = TabularMDP.from_dense(np.full((2, 3, 2), 0.5))
    save_mdp(tiny, tmp_path / "tiny.npz")
    code, _, err = run_main(["fit", out / "demos.npz", "--mdp", tmp_path / "tiny.npz", "-o", tmp_path / "x.nc"])
    assert code == 2 and "recorded in another MDP" in err  # the demo's file records the highway's
    from npbrs.domains import Demonstrations

    recorded = Demonstrations.load(out / "demos.npz")
    Demonstrations(recorded.states, recorded.actions).save(tmp_path / "plain.npz")
    code, _, err = run_main(["fit", tmp_path / "plain.npz", "--mdp", tmp_path / "tiny.npz", "-o", tmp_path / "x.nc"])
    assert code == 2 and "trajectory 0, step 0: state" in err
    code, _, err = run_main(["fit", tmp_path / "missing.npz", "--domain", "highway", "-o", tmp_path / "x.nc"])
    assert code == 2 and "missing.npz" in err
    code, _, err = run_main(["fit", out / "demos.npz", "--domain", "highway", "--init-from", tmp_path / "none.nc",
                             "-o", tmp_path / "x.nc"])
    assert code == 2 and "none.nc" in err
    for devices, says in (("0", "at least 1 device"), ("two", "a number of devices or 'all'"),
                          ("64", "devices=64: there are")):
        code, _, err = run_main(["fit", out / "demos.npz", "--domain", "highway", "--devices", devices,
                                 "-o", tmp_path / "x.nc"])
        assert code == 2 and says in err, (devices, err)
    # --max-samples reaches fit (the demo's quick configuration has one chain: no R-hat across chains)
    code, _, err = run_main(["fit", out / "demos.npz", "--domain", "highway", "--config", out / "config.toml",
                             "--max-samples", "8", "-o", tmp_path / "x.nc"])
    assert code == 2 and "sampler.max_samples" in err and "at least 2 chains" in err, err
    # --switching reaches fit's configuration (a bad prior of the ends is named there)
    (tmp_path / "ends.toml").write_text('[prior]\nend_concentration = -1.0\n')
    code, _, err = run_main(["fit", out / "demos.npz", "--domain", "highway", "--config", tmp_path / "ends.toml",
                             "--switching", "state", "-o", tmp_path / "x.nc"])
    assert code == 2 and "prior.end_concentration" in err, err
    # --restart-margin reaches fit's configuration (a negative margin is named there)
    code, _, err = run_main(["fit", out / "demos.npz", "--domain", "highway", "--restart-margin", "-5",
                             "-o", tmp_path / "x.nc"])
    assert code == 2 and "sampler.restart_margin" in err, err
    code, _, err = run_main(["report", tmp_path / "missing.nc"])
    assert code == 2 and "missing.nc" in err
    assert not (tmp_path / "x.nc").exists()


def test_score_and_compare_held_out_demonstrations(demo, tmp_path):
    import shutil

    out, _ = demo
    code, _, stderr = run_main(["generate", "highway", "--trajectories", "2", "--length", "30", "--seed", "9",
                                "-o", tmp_path / "held.npz"])
    assert code == 0, stderr
    code, stdout, stderr = run_main(["score", out / "run.nc", tmp_path / "held.npz", "--domain", "highway",
                                     "--samples", "8", "--draws", "4"])
    assert code == 0, stderr
    per_step = float(stdout.split("held-out log-likelihood: ")[1].split()[0])
    assert -np.log(3) - 1.0 < per_step < 0  # 3 actions: uniform is -1.10 nats per step
    shutil.copy(out / "run.nc", tmp_path / "copy.nc")  # (one run twice: refused, before any computation)
    code, _, stderr = run_main(["compare", out / "run.nc", tmp_path / "copy.nc", "--domain", "highway"])
    assert code == 2 and "hold the same run" in stderr
    code, _, stderr = run_main(["fit", out / "demos.npz", "--domain", "highway", "--config", out / "config.toml",
                                "--seed", "7", "-o", tmp_path / "again.nc", "--checkpoint-every", "0", "--no-progress"])
    assert code == 0, stderr
    code, stdout, stderr = run_main(["compare", out / "run.nc", tmp_path / "again.nc", "--domain", "highway",
                                     "--samples", "8"])
    assert code == 0, stderr
    assert "elpd_loo" in stdout and "again" in stdout
    code, _, stderr = run_main(["score", out / "run.nc", tmp_path / "nothere.npz", "--domain", "highway"])
    assert code == 2 and "nothere.npz" in stderr and "Traceback" not in stderr
    code, _, stderr = run_main(["compare", out / "run.nc", "--domain", "highway"])
    assert code == 2 and "at least two" in stderr


def _segment_new_demonstrations(out, tmp_path) -> str:
    """``npbrs segment`` of the demo's run on 3 new highway trajectories of 25 steps (new.npz),
    writing labels.npz and labels.png in ``tmp_path``; returns what it printed."""
    code, _, stderr = run_main(["generate", "highway", "--trajectories", "3", "--length", "25", "--seed", "8",
                                "-o", tmp_path / "new.npz"])
    assert code == 0, stderr
    code, stdout, stderr = run_main(["segment", out / "run.nc", tmp_path / "new.npz", "--domain", "highway",
                                     "--samples", "4", "--draws", "3", "-o", tmp_path / "labels.npz",
                                     "--plot", tmp_path / "labels.png"])
    assert code == 0, stderr
    return stdout


def test_segment_writes_the_skills_of_new_demonstrations(demo, tmp_path):
    out, _ = demo
    stdout = _segment_new_demonstrations(out, tmp_path)
    assert "segmented 3 trajectories (75 steps)" in stdout
    with np.load(tmp_path / "labels.npz") as f:
        labels, probs, lengths = f["labels"], f["probs"], f["lengths"]
    from npbrs.inference.driver.runs import load

    K = load(out / "run.nc").num_skills
    assert labels.shape == (3, 25) and probs.shape == (3, 25, K) and lengths.tolist() == [25, 25, 25]
    assert np.all(probs >= 0) and np.all(probs.sum(-1) <= 1 + 1e-9)
    np.testing.assert_array_equal(labels, probs.argmax(-1))
    assert (tmp_path / "labels.png").stat().st_size > 1000
    code, _, stderr = run_main(["segment", out / "run.nc", tmp_path / "new.npz", "--domain", "quadcopter",
                                "-o", tmp_path / "x.npz"])
    assert code == 2 and "another MDP" in stderr and "Traceback" not in stderr and len(stderr.splitlines()) == 1
    assert not (tmp_path / "x.npz").exists()


def test_bad_files_and_abbreviated_options_fail_with_one_line(demo, tmp_path):
    out, _ = demo
    fit = ["fit", out / "demos.npz", "--domain", "highway", "-o", tmp_path / "x.nc", "--no-progress"]
    code, _, stderr = run_main(fit + ["--config", tmp_path / "nothere.toml"])
    assert code == 2 and "nothere.toml" in stderr and "Traceback" not in stderr
    code, _, stderr = run_main(fit + ["--chain", "2"])  # not taken as --chains
    assert code == 2 and "--chain" in stderr
    junk = tmp_path / "junk.npz"
    junk.write_bytes(np.random.default_rng(0).bytes(4000))
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes((out / "demos.npz").read_bytes()[:300])
    for bad in (junk, truncated):
        code, _, stderr = run_main(["fit", bad, "--domain", "highway", "-o", tmp_path / "x.nc"])
        assert code == 2, stderr
        assert str(bad) in stderr and "not a demonstrations file" in stderr, stderr
        assert "allow_pickle" not in stderr and "Traceback" not in stderr and len(stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x.nc").exists()


def test_a_new_run_refuses_to_overwrite_another_runs_checkpoint(demo, tmp_path):
    out, _ = demo
    checkpoint = tmp_path / "y.nc.checkpoint.npz"
    checkpoint.write_bytes(b"an interrupted run")
    code, _, stderr = run_main(["fit", out / "demos.npz", "--domain", "highway", "-o", tmp_path / "y.nc",
                                "--config", out / "config.toml", "--no-progress"])
    assert code == 2 and "--resume" in stderr and str(checkpoint) in stderr
    assert checkpoint.read_bytes() == b"an interrupted run" and not (tmp_path / "y.nc").exists()


def _counted_run(path, theta=None, mdp=None):
    """A saved run without a fit: two trajectories of 16 steps with true skills; the best draw
    has 4 skills (skill 3: the last 8 steps of trajectory 1), but over the draws those steps
    are mostly skill 1, so the per-step labels use 3 skills. ``theta`` (4, D): a reward
    emission's weights (every draw's), with ``mdp`` the MDP it was fitted in."""
    from npbrs.domains import Demonstrations
    from npbrs.inference.driver.results import FitResult

    true = [np.repeat([0, 1], 8), np.repeat([2, 1], 8)]
    true[0][7] = 1  # (one step the skills do not follow)
    seg = [np.repeat([0, 1], 8), np.repeat([2, 3], 8)]
    C, D, K = 2, 4, 4
    counts = np.zeros((C, 2, 16, K), np.int64)
    for i, z in enumerate(seg):
        counts[:, i, np.arange(16), z] = D
    counts[:, 1, 8:, 3], counts[:, 1, 8:, 1] = 1, D - 1
    S = 16 if mdp is None else mdp.num_states
    demos = Demonstrations([np.arange(16) % S] * 2, [np.zeros(16, int)] * 2, true)
    stats = {"log_joint": np.arange(8.0).reshape(C, D), "num_skills": np.full((C, D), 4.0),
             "num_switches": np.arange(8.0).reshape(C, D) % 3}
    samples = {"skill_steps": np.ones((C, D, K), np.int64)}
    params, emission, names = {"pi": np.ones((K, 3)) / 3}, {"name": "policy"}, ()
    if theta is not None:
        theta = np.asarray(theta, dtype=float)
        params, emission = {"theta": theta}, {"name": "reward"}
        samples["theta"] = np.broadcast_to(theta, (C, D) + theta.shape).copy()
        names = tuple(mdp.feature_names) if mdp is not None else tuple(f"f{d}" for d in range(theta.shape[1]))
    result = FitResult(segmentation=seg, num_skills=K, skill_params=params, skill_slots=np.arange(K), best_chain=0,
                       best_log_joint=-1.0, stats=stats, samples=samples, config={"max_skills": K},
                       fingerprint=demos.fingerprint(), emission=emission, feature_names=names,
                       chain_best_z=np.stack([np.stack(seg)] * C), demos=demos, step_skill_counts=counts,
                       mdp_fingerprint=mdp.fingerprint() if mdp is not None else "")
    result.save(path)
    return result


def test_report_states_the_skills_its_figure_shows_and_the_accuracy_against_the_truth(tmp_path, monkeypatch):
    """The summary's first line counts the skills of the per-step labels the segmentation figure
    draws (3 skills), and a line after it the best draw's (4): the figure's title says the same,
    and report scores those labels against the run's true skills (both accuracies and switches)."""
    from npbrs.inference.analysis import plots
    from npbrs.inference.analysis.metrics import hungarian_accuracy, num_switches, paper_accuracy

    result = _counted_run(tmp_path / "run.nc")
    labels = result.skill_probabilities().labels
    assert len(np.unique(np.concatenate(labels))) == 3 and result.num_skills == 4
    drawn = []
    monkeypatch.setattr(plots, "plot_trace", lambda *a, **k: None)
    monkeypatch.setattr(plots, "plot_segmentation", lambda true, inferred, path, **k: drawn.append(
        (inferred["npbrs"], k.get("title"))) or {"npbrs": plots.skill_styles(true, inferred["npbrs"])})
    code, stdout, stderr = run_main(["report", tmp_path / "run.nc", "--plots", tmp_path / "plots"])
    assert code == 0, stderr
    first = stdout.splitlines()[0]
    assert first.startswith("3 skills in") and "most probable skill over the draws" in first, first
    best = next(s for s in stdout.splitlines() if s.startswith("the best draw ("))
    assert "4 skills" in best, best
    shown, title = drawn[-1]
    assert all(np.array_equal(a, b) for a, b in zip(shown, labels))
    assert "most probable skill over the draws" in title and "3 of the best draw's 4 skills" in title, title
    true = result.demos.skills
    scores = next(s for s in stdout.splitlines() if s.startswith("against the true skills"))
    for value in (paper_accuracy(true, labels), hungarian_accuracy(true, labels), num_switches(labels),
                  num_switches(true)):
        assert f"{value:.3f}" in scores or f"{value:.2f}" in scores, (value, scores)
    assert f"{hungarian_accuracy(true, labels):.3f} (one-to-one" in scores
    assert f"{paper_accuracy(true, labels):.3f} (paper's" in scores
    # without the true skills: no accuracy
    from npbrs.domains import Demonstrations

    result.demos = Demonstrations(result.demos.states, result.demos.actions)
    result.save(tmp_path / "unknown.nc")
    code, stdout, stderr = run_main(["report", tmp_path / "unknown.nc"])
    assert code == 0, stderr
    assert "per-step labels" in stdout and "against the true skills" not in stdout


def test_segment_scores_against_the_truth_and_colours_skills_as_report_does(demo, tmp_path, monkeypatch):
    """segment prints the accuracy of its labels when the segmented demonstrations hold their
    true skills, states how many of the run's skills its labels use (its plot's title too),
    and its plot draws each skill in the colour the report's segmentation figure gives it."""
    from npbrs.domains import Demonstrations
    from npbrs.inference.analysis import plots
    from npbrs.inference.analysis.metrics import hungarian_accuracy, num_switches, paper_accuracy
    from npbrs.inference.cli.main import save_plots

    out, _ = demo
    run = load(out / "run.nc")
    seen = {}
    draw_segmentation, draw_probabilities = plots.plot_segmentation, plots.plot_skill_probabilities
    monkeypatch.setattr(plots, "plot_trace", lambda *a, **k: None)
    monkeypatch.setattr(plots, "plot_segmentation", lambda *a, **k: seen.setdefault(
        "report", draw_segmentation(*a, **k)))
    monkeypatch.setattr(plots, "plot_skill_probabilities", lambda *a, **k: seen.setdefault(
        "segment", (a, k)) and draw_probabilities(*a, **k))
    save_plots(run, tmp_path)
    stdout = _segment_new_demonstrations(out, tmp_path)
    with np.load(tmp_path / "labels.npz") as f:
        labels = [z[:n] for z, n in zip(f["labels"], f["lengths"])]
    true = Demonstrations.load(tmp_path / "new.npz").skills
    scores = next(s for s in stdout.splitlines() if s.startswith("against the true skills"))
    assert f"{hungarian_accuracy(true, labels):.3f} (one-to-one" in scores, scores
    assert f"{paper_accuracy(true, labels):.3f} (paper's" in scores, scores
    assert f"{num_switches(labels):.2f}" in scores and f"{num_switches(true):.2f}" in scores, scores
    used, K = len(np.unique(np.concatenate(labels))), run.num_skills
    assert f"{used} of the run's {K} skill" in stdout, stdout  # (skills: K > 1)
    _, options = seen["segment"]
    assert f"{used} of its {K} skill" in options["title"], options["title"]
    styles = seen["report"]["npbrs"]
    colours = options["colours"]
    assert len(colours) == K and all(tuple(colours[k]) == styles[k].colour for k in styles)
    assert all(tuple(colours[k]) == plots.UNMATCHED for k in range(K) if k not in styles)


def test_report_draws_a_reward_per_state_on_the_grid_of_the_mdp_given(tmp_path, monkeypatch):
    """A gridworld's one-hot rewards: with the run's MDP (--mdp or --domain) report draws each
    skill's reward per state on the grid (the states' 2-D coordinates); another MDP is refused."""
    from npbrs.domains.worlds.grid_world import grid_mdp
    from npbrs.inference.analysis import plots

    mdp = grid_mdp(size=5)
    theta = np.zeros((4, 25))
    theta[0, 4], theta[1, 20], theta[2, 12], theta[3, 0] = 5.0, -5.0, 2.0, 1.0
    _counted_run(tmp_path / "run.nc", theta=theta, mdp=mdp)
    save_mdp(mdp, tmp_path / "grid.npz")
    drawn = {}
    monkeypatch.setattr(plots, "plot_trace", lambda *a, **k: None)
    monkeypatch.setattr(plots, "plot_skill_rewards", lambda mean, names, path, **k: drawn.update(k, mean=mean))
    code, stdout, stderr = run_main(["report", tmp_path / "run.nc", "--mdp", tmp_path / "grid.npz",
                                     "--plots", tmp_path / "plots"])
    assert code == 0, stderr
    np.testing.assert_array_equal(drawn["coordinates"], mdp.state_vectors)  # feature d: state d's cell
    np.testing.assert_allclose(drawn["mean"], theta)
    assert "skill rewards plot" in stdout
    drawn.clear()
    code, stdout, stderr = run_main(["report", tmp_path / "run.nc", "--plots", tmp_path / "plots"])
    assert code == 0, stderr
    assert drawn.get("coordinates") is None and "--domain or --mdp" in stdout  # no MDP: the heat map, and how
    save_mdp(grid_mdp(size=5, slip=0.2), tmp_path / "other.npz")
    code, _, stderr = run_main(["report", tmp_path / "run.nc", "--mdp", tmp_path / "other.npz"])
    assert code == 2 and "another MDP" in stderr, stderr
