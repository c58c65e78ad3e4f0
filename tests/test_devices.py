"""fit on several devices (``devices=``: a number of devices or a mesh): chains on separate devices, and each
chain's trajectories sharded over devices, give the one-device run's draws.

JAX reads ``XLA_FLAGS`` once, when its backend starts, so the runs on 4 CPU "devices"
(``--xla_force_host_platform_device_count=4``) happen in a child process that this test starts
with the flag set. The child fits one small data set (6 ragged trajectories of the cheap policy
emission, 4 chains, 3 + 3 sweeps, a greedy merge in each warmup sweep) three ways:

- on one device (no mesh);
- ``devices=4``: the 4 chains on 4 devices (mesh ("chains", "trajectories") of shape (4, 1));
- ``devices=Mesh(jax.devices(), ("trajectories",))``: every chain's trajectories sharded over the
  4 devices, the 6 trajectories padded to 8 with empty ones;
- and the one-device run's checkpoint after 3 sweeps resumed on that mesh (a checkpoint resumes
  on another layout);

and records what the compiled sweep was given: the devices its data and state span and their
shards' shapes. The test then asks for the same draws: every discrete draw (segmentations,
features, skills used, steps per skill, the greedy merges kept) bit for bit, and the policies
and the floating-point statistics to a relative 1e-12: sums over trajectories (the log joint)
are added in another order when the trajectories are split over devices (measured: 1e-13 in a
log joint of about -400), and XLA may round a mean or a Dirichlet draw's normalisation
differently in another program (measured: 2e-16 in 23 of the 576 policy entries of the chains
run, once the backward sampler drew its Gumbel noise before its scan; they had been equal).

(Checked by hand: with each device's chains given other keys (``devices.place_state`` folding the
device's index into the state's ``rng_key``) the chains run fails; with omega's Gammas drawn
after the trajectories' in the kernel's batch (their positions, and so their numbers, then
depend on how many trajectories there are) the padded trajectories run fails.)
"""

import json
import os
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest
from jax.sharding import Mesh

from npbrs.domains import Demonstrations, TabularMDP
from npbrs.inference import fit

CHILD = textwrap.dedent('''
    import importlib, json, shutil, sys, time
    import numpy as np
    import jax
    from jax.sharding import Mesh
    from npbrs.inference import fit

    F = importlib.import_module("npbrs.inference.driver.compiled")
    out_path = sys.argv[1]
    assert jax.device_count() == 4, jax.devices()

    from gridworld import ragged_policy_problem  # (the tests' folder is on PYTHONPATH)

    mdp, demos = ragged_policy_problem()
    # a greedy merge in every warmup sweep (it gathers one skill's steps over all trajectories);
    # greedy splits, birth/death and split-merge moves are left out to save their compilation
    # (the one-device run batches its chains, as the runs on devices do: "auto" would pick threads)
    config = {"emission": "policy", "max_skills": 4, "kappa": 5.0, "chain_method": "vectorized",
              "moves": {"greedy_merge": 1, "greedy_split": 0, "greedy_from": 0.0}}
    kw = dict(num_chains=4, num_warmup=3, num_samples=3, seed=1, progress_bar=False)
    seen = {}
    sweep = F.sweep_batched

    def shard(x):  # the shape of the array's block on its first device
        return list(x.addressable_shards[0].data.shape if isinstance(x, jax.Array) else np.shape(x))

    def spy(kernel, names, state, mesh=None):
        new, record = sweep(kernel, names, state, mesh=mesh)
        seen.setdefault(run, {
            "data_devices": len(kernel.data.states.sharding.device_set), "data_shard": shard(kernel.data.states),
            "z_devices": len(new.z.sharding.device_set), "z_shard": shard(new.z), "z_in_shard": shard(state.z),
            "policy_shard": shard(new.params["policy"])})
        return new, record

    F.sweep_batched = spy
    # the one-device run's checkpoint after its third sweep, kept to be resumed on 4 devices
    runs = importlib.import_module("npbrs.inference.driver.runs")
    write = runs.write_checkpoint

    def keep_third(path, *, state, draws, meta):
        write(path, state=state, draws=draws, meta=meta)
        if meta["sweeps_done"] == 3:
            shutil.copy(path, half)

    runs.write_checkpoint = keep_third
    half = out_path + ".half.npz"
    arrays, times = {}, {}
    traj_mesh = Mesh(np.array(jax.devices()), ("trajectories",))
    for run, options, extra in (("one", {"checkpoint_every": 3}, {"checkpoint_path": out_path + ".ckpt.npz"}),
                                ("chains", {}, {"devices": 4}), ("trajectories", {}, {"devices": traj_mesh}),
                                ("resumed", {}, {"devices": traj_mesh, "checkpoint_path": half, "resume": True})):
        t = time.perf_counter()
        result = fit(mdp, demos, {**config, **options}, **kw, **extra)
        times[run] = time.perf_counter() - t
        for k, v in {**result.stats, **result.samples}.items():
            arrays[f"{run}/{k}"] = v
        arrays[f"{run}/chain_best_z"] = result.chain_best_z
        arrays[f"{run}/segmentation"] = np.concatenate(result.segmentation)
    errors = {}
    chains_mesh = Mesh(np.array(jax.devices()), ("chains",))
    for name, options, extra in (("chains_not_dividing", {}, {"devices": chains_mesh, "num_chains": 6}),
                                 ("sequential_chains", {"chain_method": "sequential"}, {"devices": chains_mesh}),
                                 ("too_many", {}, {"devices": 5}),
                                 ("twice", {}, {"devices": [jax.devices()[0], jax.devices()[0]]})):
        try:
            fit(mdp, demos, {**config, **options}, **{**kw, **extra})
            errors[name] = None
        except ValueError as e:
            errors[name] = str(e)
    np.savez(out_path, **arrays)
    with open(out_path + ".json", "w") as f:
        json.dump({"seen": seen, "times": times, "errors": errors}, f)
''')

EXACT = ("num_skills", "features", "skill_steps", "greedy_merges", "chain_best_z", "segmentation")


@pytest.fixture(scope="module")
def four_devices(tmp_path_factory):
    out = str(tmp_path_factory.mktemp("devices") / "runs.npz")
    env = dict(os.environ)
    env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4").strip()
    env["NPBRS_CACHE_DIR"] = "off"
    tests = os.path.dirname(os.path.abspath(__file__))
    env["PYTHONPATH"] = os.pathsep.join([tests] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    cache = jax.config.jax_compilation_cache_dir  # the test session's: a second run compiles less
    if cache:
        env["JAX_COMPILATION_CACHE_DIR"] = os.path.join(cache, "devices4")
        env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0.5"
    done = subprocess.run([sys.executable, "-c", CHILD, out], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-4000:]
    with open(out + ".json") as f:
        info = json.load(f)
    print("fit times on 4 host devices:", info["times"])
    return dict(np.load(out)), info


def test_chains_and_trajectories_on_four_devices_give_the_one_device_draws(four_devices):
    arrays, info = four_devices
    seen = info["seen"]
    # the one-device run: one device, nothing padded
    assert seen["one"]["z_devices"] == 1 and seen["one"]["data_shard"] == [6, 30]
    # chains on 4 devices: a chain per device, the data replicated on each
    assert seen["chains"]["z_devices"] == 4 and seen["chains"]["z_shard"] == [1, 6, 30]
    assert seen["chains"]["data_devices"] == 4 and seen["chains"]["data_shard"] == [6, 30]
    # trajectories over 4 devices: 6 padded to 8, 2 per device, every chain on each; the state
    # stays sharded from sweep to sweep; the skills' parameters are replicated
    assert seen["trajectories"]["data_devices"] == 4 and seen["trajectories"]["data_shard"] == [2, 30]
    assert seen["trajectories"]["z_devices"] == 4
    assert seen["trajectories"]["z_shard"] == seen["trajectories"]["z_in_shard"] == [4, 2, 30]
    assert seen["trajectories"]["policy_shard"] == [4, 4, 4, 3]

    names = sorted(k.split("/", 1)[1] for k in arrays if k.startswith("one/"))
    assert {"log_joint", "num_skills", "features", "policy", "segmentation"} <= set(names)
    # (and the one-device run's checkpoint after 3 sweeps, resumed with the trajectories on 4
    # devices: its 6 trajectories' state padded to 8, the last 3 sweeps sharded)
    for run in ("chains", "trajectories", "resumed"):
        for name in names:
            a, b = arrays[f"one/{name}"], arrays[f"{run}/{name}"]
            assert a.shape == b.shape, (run, name)
            if name in EXACT or a.dtype.kind in "biu":
                np.testing.assert_array_equal(b, a, err_msg=f"{run}: {name}")
            else:
                np.testing.assert_allclose(b, a, rtol=1e-12, atol=0, err_msg=f"{run}: {name}")
    # the greedy moves ran (the check covers them), and the chains differ from each other
    assert arrays["one/greedy_merges"].max() >= 1
    assert not np.array_equal(arrays["one/log_joint"][0], arrays["one/log_joint"][1])


def test_bad_meshes_and_devices_are_refused_naming_the_problem(four_devices):
    errors = four_devices[1]["errors"]
    assert "'chains' axis has 4 devices, which does not divide num_chains = 6" in errors["chains_not_dividing"]
    assert "sequential" in errors["sequential_chains"]
    assert "devices=5: there are 4 devices" in errors["too_many"]
    assert "twice" in errors["twice"]
    # and in this one-device process, before anything is compiled
    rng = np.random.default_rng(0)
    mdp = TabularMDP.from_dense(rng.dirichlet(np.ones(3), (3, 2)))
    demos = Demonstrations([rng.integers(0, 3, 8)], [rng.integers(0, 2, 8)])
    kw = dict(num_chains=2, num_warmup=1, num_samples=1, progress_bar=False)
    one = np.array(jax.devices()[:1])
    for bad, match in (({"devices": len(jax.devices()) + 1}, "there are"),
                       ({"devices": Mesh(one, ("data",))}, "mesh axis 'data'"),
                       ({"devices": 2.5}, "devices must be a number of devices or a sequence of jax.Device, got float"),
                       ({"devices": "some"}, "devices must be a number, a list of jax.Device, 'all' or a Mesh")):
        with pytest.raises(ValueError, match=match):
            fit(mdp, demos, {"emission": "policy"}, **kw, **bad)
