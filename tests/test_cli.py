"""The ``npbrs`` command line: every command has --help; the demo runs end to end; ``fit`` on the
demo's files reproduces the demo's run; ``report`` prints R-hat and ESS and writes plots."""

import contextlib
import io
import os
import subprocess
import sys
import warnings

import numpy as np
import pytest

from npbrs.domains.mdp import TabularMDP
from npbrs.inference import ConvergenceWarning, ModelConfig, load, save_mdp
from npbrs.inference.cli import compilation_cache_dir, main


def run_main(argv):
    """(exit code, stdout, stderr) of ``npbrs ARGV``, in this process (compiled kernels are shared)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main([str(a) for a in argv])
        except SystemExit as e:
            code = e.code
    return code, out.getvalue(), err.getvalue()


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
    assert "skills in 3 trajectories" in stdout
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


def test_segment_writes_the_skills_of_new_demonstrations(demo, tmp_path):
    out, _ = demo
    code, _, stderr = run_main(["generate", "highway", "--trajectories", "3", "--length", "25", "--seed", "8",
                                "-o", tmp_path / "new.npz"])
    assert code == 0, stderr
    code, stdout, stderr = run_main(["segment", out / "run.nc", tmp_path / "new.npz", "--domain", "highway",
                                     "--samples", "4", "--draws", "3", "-o", tmp_path / "labels.npz",
                                     "--plot", tmp_path / "labels.png"])
    assert code == 0, stderr
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
