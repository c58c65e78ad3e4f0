"""Saved runs, checkpoints and MDP files: a run killed mid-way and resumed gives exactly the
draws of an uninterrupted run; a saved run loads back equal; nothing half-written is left."""

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys

import numpy as np
import pytest

from npbrs.domains.demos import Demonstrations
from npbrs.domains.mdp import TabularMDP
from npbrs.inference import ModelConfig, fit, load, load_mdp, resolve_config, save_mdp
from npbrs.inference.driver.runs import atomic_write, read_checkpoint


CONFIG = """
max_skills = 3
[emission]
name = "policy"
[sampler]
chains = 2
warmup = 4
samples = 8
seed = 11
init_window = 6
"""

# The uninterrupted run (fit, save, load), then the command line with a pause after every
# checkpoint so that the test can stop it there. Both in one process: one compilation, which
# also fills JAX's persistent cache for the next processes.
CHILD = """
import sys, time
from npbrs.domains.demos import Demonstrations
from npbrs.inference import fit, load, load_mdp
import npbrs.inference.driver.runs as runs
pause, whole, argv = float(sys.argv[1]), sys.argv[2] == "whole", sys.argv[3:]
if whole:
    result = fit(load_mdp("mdp.npz"), Demonstrations.load("demos.npz"), "model.toml", progress_bar=False)
    result.save("whole.nc")
    print("round trip", load("whole.nc").equals(result, wall_time=True), flush=True)
write = runs.write_checkpoint
def paused(path, **kwargs):
    write(path, **kwargs)
    print("checkpoint", kwargs["meta"]["sweeps_done"], flush=True)
    time.sleep(pause)
runs.write_checkpoint = paused
from npbrs.inference.cli import main
sys.exit(main(argv))
"""


def small_problem(seed=0, N=3, T=24, S=5, A=3):
    rng = np.random.default_rng(seed)
    mdp = TabularMDP.from_dense(rng.dirichlet(np.ones(S), (S, A)), initial=np.full(S, 1.0 / S),
                                state_vectors=rng.normal(size=(S, 2)), name="toy")
    states = [rng.integers(0, S, T - i) for i in range(N)]
    actions = [(np.arange(T - i) // 8 + i) % A for i in range(N)]
    skills = [np.arange(T - i) // 8 % 3 for i in range(N)]
    return mdp, Demonstrations(states, actions, skills)


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    d = tmp_path_factory.mktemp("runs")
    mdp, demos = small_problem()
    save_mdp(mdp, d / "mdp.npz")
    demos.save(d / "demos.npz")
    (d / "model.toml").write_text(CONFIG)
    return d


def run_child(workdir, argv, stop_at=None, sig=None, pause=0.2, whole=False):
    """Run CHILD in ``workdir``; send ``sig`` once a checkpoint of ``stop_at`` sweeps is written."""
    env = dict(os.environ, PYTHONUNBUFFERED="1", JAX_PLATFORMS="cpu",
               JAX_COMPILATION_CACHE_DIR=str(workdir / "jax-cache"), JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")
    proc = subprocess.Popen([sys.executable, "-c", CHILD, str(pause), "whole" if whole else "-"] + argv,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=workdir)
    lines = []
    for line in proc.stdout:
        lines.append(line)
        if sig is not None and line.startswith("checkpoint") and int(line.split()[1]) >= stop_at:
            proc.send_signal(sig)
            break
    out, err = proc.communicate(timeout=300)
    return proc.returncode, "".join(lines) + out, err


FIT = ["fit", "demos.npz", "--mdp", "mdp.npz", "--config", "model.toml", "-o", "resumed.nc", "--checkpoint-every", "2",
       "--no-progress"]


@pytest.fixture(scope="module")
def killed(workdir):
    """The uninterrupted run, then a run killed without warning in the middle of sampling
    (warmup is 4 sweeps, 12 in all); returns the uninterrupted result and the checkpoint's meta."""
    code, out, err = run_child(workdir, FIT, stop_at=6, sig=signal.SIGKILL, whole=True)
    assert code == -signal.SIGKILL, err
    assert "round trip True" in out
    _, _, meta = read_checkpoint(workdir / "resumed.nc.checkpoint.npz")
    shutil.copy(workdir / "resumed.nc.checkpoint.npz", workdir / "killed.checkpoint.npz")
    return load(workdir / "whole.nc"), meta


def test_a_killed_run_resumed_equals_an_uninterrupted_run_bit_for_bit(workdir, killed):
    whole_run, meta = killed
    checkpoint = workdir / "resumed.nc.checkpoint.npz"
    assert 6 <= meta["sweeps_done"] < 12
    _, draws, _ = read_checkpoint(workdir / "killed.checkpoint.npz")
    assert draws["log_joint"].shape == (2, meta["sweeps_done"] - 4)
    # resumed, then stopped by Ctrl-C: a clean stop that leaves a resumable checkpoint
    code, out, err = run_child(workdir, FIT + ["--resume"], stop_at=meta["sweeps_done"] + 2, sig=signal.SIGINT)
    assert code == 130, err
    assert "--resume" in err
    _, draws, later = read_checkpoint(checkpoint)
    assert meta["sweeps_done"] < later["sweeps_done"] < 12
    assert draws["log_joint"].shape == (2, later["sweeps_done"] - 4)
    # resumed to the end
    code, out, err = run_child(workdir, FIT + ["--resume"], pause=0.0)
    assert code == 0, err
    assert not checkpoint.exists()
    resumed = load(workdir / "resumed.nc")
    assert resumed.equals(whole_run)
    np.testing.assert_array_equal(resumed.samples["policy"], whole_run.samples["policy"])
    assert resumed.wall_time > 0


def test_resume_refuses_a_checkpoint_of_other_demonstrations_config_or_start(workdir, killed, no_compilation):
    mdp, demos = load_mdp(workdir / "mdp.npz"), Demonstrations.load(workdir / "demos.npz")
    path = workdir / "killed.checkpoint.npz"
    with pytest.raises(ValueError, match="sampler.seed"):
        fit(mdp, demos, workdir / "model.toml", seed=12, checkpoint_path=path, resume=True, progress_bar=False)
    with pytest.raises(ValueError, match="prior.kappa"):
        fit(mdp, demos, resolve_config(workdir / "model.toml", kappa=3.0), checkpoint_path=path, resume=True, progress_bar=False)
    other = Demonstrations(demos.states, [np.zeros_like(a) for a in demos.actions])
    with pytest.raises(ValueError, match="other demonstrations"):
        fit(mdp, other, workdir / "model.toml", checkpoint_path=path, resume=True, progress_bar=False)
    # its chains started from random windows, not from a given segmentation
    with pytest.raises(ValueError, match="started from random windows, not from this init_segmentation"):
        fit(mdp, demos, workdir / "model.toml", checkpoint_path=path, resume=True, progress_bar=False,
            init_segmentation=[np.zeros(n, int) for n in demos.lengths])


def test_a_saved_run_holds_the_draws_segmentation_skills_and_description(workdir, killed):
    import arviz as az

    whole_run = killed[0]
    idata = az.from_netcdf(workdir / "whole.nc")
    assert set(idata.groups()) >= {"posterior", "sample_stats", "constant_data", "observed_data"}
    assert idata.posterior["log_joint"].shape == (2, 8)
    assert idata.posterior["policy"].dims == ("chain", "draw", "skill", "policy_dim_0", "policy_dim_1")
    attrs = idata.constant_data.attrs
    given = ModelConfig.from_toml(workdir / "model.toml")  # with fit's default greedy merges filled in,
    # and the starting skills (the policy emission's: half of the slots)
    ran = given.replace(sampler=dataclasses.replace(given.sampler, moves={**given.sampler.moves, "greedy_merge": 1,
                                                                            "greedy_split": 1, "greedy_from": 0.75},
                                                    init_skills=(given.max_skills + 1) // 2),
                        prior=dataclasses.replace(given.prior, switching="sticky"))  # (the model "auto" chose)
    assert whole_run.switching["chosen"] == "sticky"
    assert ModelConfig.from_dict(json.loads(attrs["config"])) == ran
    assert attrs["fingerprint"] == Demonstrations.load(workdir / "demos.npz").fingerprint()
    assert whole_run.demos == Demonstrations.load(workdir / "demos.npz")
    seg = idata.constant_data["segmentation"].values
    assert [list(s) for s in whole_run.segmentation] == [list(r[:n]) for r, n in
                                                          zip(seg, idata.constant_data["lengths"].values)]
    assert whole_run.skill_params["policy"].shape == (whole_run.num_skills, 5, 3)
    # and once more through a file: equal, wall time included
    whole_run.save(workdir / "again.nc")
    assert load(workdir / "again.nc").equals(whole_run, wall_time=True)


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "run.nc"
    target.write_bytes(b"old")

    def half_then_fail(tmp):
        with open(tmp, "wb") as f:
            f.write(b"half")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        atomic_write(target, half_then_fail)
    assert target.read_bytes() == b"old"
    assert os.listdir(tmp_path) == ["run.nc"]


def test_an_mdp_file_round_trips_and_bad_files_are_named(tmp_path):
    mdp, _ = small_problem()
    save_mdp(mdp, tmp_path / "mdp.npz")
    back = load_mdp(tmp_path / "mdp.npz")
    for name in ("successors", "features", "initial", "state_vectors"):
        np.testing.assert_array_equal(getattr(back, name), getattr(mdp, name))
    np.testing.assert_allclose(back.probs, mdp.probs, rtol=1e-15)  # TabularMDP renormalises the rows
    assert (back.feature_names, back.discount, back.name) == (mdp.feature_names, mdp.discount, "toy")
    np.savez(tmp_path / "bad.npz", successors=mdp.successors, features=mdp.features, discount=0.9)
    with pytest.raises(ValueError, match="bad.npz: missing array probs"):
        load_mdp(tmp_path / "bad.npz")
    np.savez(tmp_path / "worse.npz", successors=mdp.successors, probs=mdp.probs * 2, features=mdp.features,
             discount=0.9)
    with pytest.raises(ValueError, match="worse.npz: transition probabilities of state 0, action 0 sum to 2"):
        load_mdp(tmp_path / "worse.npz")
    with pytest.raises(ValueError, match="not an npbrs run"):
        (tmp_path / "x.nc").write_bytes(b"")
        import xarray as xr

        xr.Dataset({"a": ("x", [1.0])}).to_netcdf(tmp_path / "x.nc", engine="h5netcdf")
        load(tmp_path / "x.nc")
