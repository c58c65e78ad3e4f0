"""Fits with the reward emission: the sampler recovers planted reward skills, and a new data
set of the same shapes (or in the same shape bucket) reuses its compiled programs; float64
inside, the user's setting outside. The tests share one compiled 10 x 64, 2-chain sampler
(without the greedy moves: see NO_GREEDY)
(kept apart from test_reward_emission.py so that the two halves run in parallel)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gridworld import gridworld
from npbrs.domains import generate_demonstrations
from npbrs.inference import fit, paper_accuracy
from npbrs.models.emissions import HMMData


# The module's fits leave out the warmup's greedy merges and splits, which are 60% of the reward
# sampler's compiling (a 66 s program becomes 27 s); the planted fit with fit's defaults, greedy
# moves included, is the slow variant (the greedy moves have their own tests in test_greedy.py).
NO_GREEDY = {"greedy_merge": 0, "greedy_split": 0}


@pytest.mark.parametrize("moves", [NO_GREEDY, pytest.param(None, marks=pytest.mark.slow, id="defaults")])
def test_the_sampler_recovers_planted_reward_skills_in_a_gridworld(moves):
    dom = gridworld()
    demos = generate_demonstrations(dom, num_trajectories=10, length=64, switch_prob=0.05, seed=0)
    config = {"emission": "reward", "max_skills": 5, **({} if moves is None else {"moves": moves})}
    result = fit(dom.mdp, demos, config, num_chains=2, num_samples=40, num_warmup=40, progress_bar=False)
    assert result.num_skills == 3
    assert paper_accuracy(demos.skills, result.segmentation) >= 0.9
    assert result.rhat["log_joint"] < 1.1


def _compiling(fn, *args, **kwargs):
    """fn(*args, **kwargs) and the seconds of every program JAX compiled (or loaded from its
    persistent cache) meanwhile; a call served by programs already in memory compiles none."""
    from jax._src.dispatch import BACKEND_COMPILE_EVENT

    compiles = []

    def listen(event, duration, **_):
        if event == BACKEND_COMPILE_EVENT:
            compiles.append(duration)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        return fn(*args, **kwargs), compiles
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)


def test_a_new_dataset_and_mdp_of_the_same_shapes_reuse_the_compiled_sampler():
    """The demonstrations and the MDP's arrays are arguments of the compiled programs, not
    constants: a second fit of other demonstrations in another MDP of the same shapes compiles
    nothing (it failed, compiling the sweep again, when the kernel was closed over)."""
    config = {"emission": "reward", "max_skills": 5, "moves": NO_GREEDY}
    kwargs = dict(num_chains=2, num_samples=3, num_warmup=3, progress_bar=False)
    dom = gridworld()
    first = fit(dom.mdp, generate_demonstrations(dom, num_trajectories=10, length=64, switch_prob=0.05, seed=3),
                config, **kwargs)
    other = gridworld(slip=0.2)
    demos = generate_demonstrations(other, num_trajectories=10, length=64, switch_prob=0.05, seed=4)
    second, compiles = _compiling(fit, other.mdp, demos, config, **kwargs)
    assert compiles == [], f"the second fit compiled {len(compiles)} programs ({sum(compiles):.1f} s)"
    assert second.fingerprint != first.fingerprint and second.mdp_fingerprint != first.mdp_fingerprint
    assert second.equals(fit(other.mdp, demos, config, **kwargs))  # the reused program: the same seed, the same draws


def test_a_data_set_in_the_same_shape_bucket_reuses_the_compiled_sampler():
    """The config option ``bucket=True`` pads to bucket sizes: another data set of other sizes in the same
    bucket compiles nothing, and the result has the demonstrations' own shapes."""
    from npbrs.models.emissions import bucket_size

    sizes = [bucket_size(n) for n in range(1, 1025)]
    assert all(s >= n and (n <= 8 or s <= 1.25 * n) for n, s in zip(range(1, 1025), sizes))
    assert len(set(sizes)) <= 40 and sizes == sorted(sizes)
    # padded to 10 x 64, the planted-skills fit's shapes above: in this module it compiles nothing
    config = {"emission": "reward", "max_skills": 5, "moves": NO_GREEDY, "bucket": True}
    kwargs = dict(num_chains=2, num_samples=3, num_warmup=3, progress_bar=False)
    dom = gridworld()
    fit(dom.mdp, generate_demonstrations(dom, num_trajectories=9, length=58, seed=5), config, **kwargs)
    demos = generate_demonstrations(dom, num_trajectories=9, length=61, seed=6)  # the same bucket
    result, compiles = _compiling(fit, dom.mdp, demos, config, **kwargs)
    assert compiles == [], f"the second fit compiled {len(compiles)} programs ({sum(compiles):.1f} s)"
    assert [len(z) for z in result.segmentation] == list(demos.lengths)
    assert result.samples["features"].shape[2] == 9 and result.chain_best_z.shape[1:] == (9, 61)
    assert result.config["sampler"]["bucket"] is True
    # fit redraws the unused reward skills every fifth sweep (the emission's redraw_unused), and
    # the run records it
    assert result.config["sampler"]["moves"] == {**NO_GREEDY, "redraw_unused": 5}
    assert result.equals(fit(dom.mdp, demos, config, **kwargs))


_X64_SCRIPT = """
import sys
import jax, jax.numpy as jnp, numpy as np
sys.path.insert(0, {tests!r})
import npbrs.domains, npbrs.models, npbrs.inference
from gridworld import gridworld
from npbrs.domains import generate_demonstrations, soft_value_iteration
from npbrs.models.emissions import HMMData
from npbrs.models.reward.irl import irl_fit
from npbrs.models.reward.likelihood import count_table
assert not jax.config.jax_enable_x64 and jnp.ones(1).dtype == jnp.float32, "importing npbrs changed jax_enable_x64"
other = gridworld(slip=0.2)
demos = generate_demonstrations(other, num_trajectories=10, length=64, switch_prob=0.05, seed=4)
rewards = np.linspace(-1, 1, other.mdp.num_states * other.mdp.num_actions).reshape(other.mdp.num_states, -1)
solve = soft_value_iteration(other.mdp, rewards)
data = HMMData.from_demonstrations(demos)
theta = irl_fit(other.mdp, count_table(data.states, data.actions, None, *rewards.shape, data.mask)).theta
assert not jax.config.jax_enable_x64 and jnp.ones(1).dtype == jnp.float32, "a call left jax_enable_x64 on"
np.savez({arrays!r}, V=np.asarray(solve.V), theta=np.asarray(theta), V_dtype=str(solve.V.dtype))
"""


def test_npbrs_computes_in_float64_without_switching_the_process_to_it(tmp_path):
    """Importing npbrs leaves JAX in float32 (a fresh process); there the solver and the IRL fit
    still compute in float64 (they run inside JAX's scoped switch) and give what they give in a
    float64 process; and ``fit`` with x64 off gives the draws it gives with x64 on, bit for bit
    (the same compiled program), leaving x64 off. (The notebooks run whole in float32 kernels.)"""
    import os
    import subprocess
    import sys

    from npbrs.domains import soft_value_iteration
    from npbrs.models.reward.irl import irl_fit
    from npbrs.models.reward.likelihood import count_table

    config = {"emission": "reward", "max_skills": 5, "moves": NO_GREEDY}
    kwargs = dict(num_chains=2, num_samples=3, num_warmup=3, progress_bar=False)
    script = _X64_SCRIPT.format(tests=os.path.dirname(__file__), arrays=str(tmp_path / "arrays.npz"))
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    cache = jax.config.jax_compilation_cache_dir
    if cache:  # the test session's compilation cache: the float64 programs compiled here are reused there
        env.update(JAX_COMPILATION_CACHE_DIR=cache, JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0.5",
                   JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0")
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    other = gridworld(slip=0.2)
    demos = generate_demonstrations(other, num_trajectories=10, length=64, switch_prob=0.05, seed=4)
    here = fit(other.mdp, demos, config, **kwargs)
    with jax.enable_x64(False):
        assert jnp.ones(1).dtype == jnp.float32
        there = fit(other.mdp, demos, config, **kwargs)
        assert not jax.config.jax_enable_x64 and jnp.ones(1).dtype == jnp.float32, "fit left jax_enable_x64 on"
    assert there.num_skills == here.num_skills and all(np.array_equal(a, b) for a, b in zip(there.segmentation,
                                                                                             here.segmentation))
    for name in here.samples:
        np.testing.assert_array_equal(there.samples[name], here.samples[name], err_msg=name)
    np.testing.assert_array_equal(there.stats["log_joint"], here.stats["log_joint"])
    arrays = np.load(tmp_path / "arrays.npz")
    assert str(arrays["V_dtype"]) == "float64"
    rewards = np.linspace(-1, 1, other.mdp.num_states * other.mdp.num_actions).reshape(other.mdp.num_states, -1)
    np.testing.assert_allclose(arrays["V"], np.asarray(soft_value_iteration(other.mdp, rewards).V), rtol=1e-13)
    data = HMMData.from_demonstrations(demos)
    counts = count_table(data.states, data.actions, None, *rewards.shape, data.mask)
    np.testing.assert_allclose(arrays["theta"], np.asarray(irl_fit(other.mdp, counts).theta), rtol=1e-10)
