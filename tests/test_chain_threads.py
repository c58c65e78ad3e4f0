"""``chain_method="threads"`` (and "auto", the default, which picks it on the CPU; with one
thread allowed it is the sequential chains): the sequential sweep with each chain's call on its
own thread, so the chains run side by side.
The draws are the sequential method's, bit for bit; the calls really overlap; each thread
computes in npbrs's float64 scope (threads start without the caller's JAX context)."""

import dataclasses
import re
import threading

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gridworld import ragged_policy_problem
from npbrs.inference import fit
from npbrs.inference.driver import chains as chains_module, compiled as compiled_module
from npbrs.inference.driver.chains import choose_chain_method
from npbrs.inference import threads as threads_module
from npbrs.inference.threads import on_threads

MDP, DEMOS = ragged_policy_problem(correct=0.8)
# test_skill_probabilities.py's settings (the greedy moves off: their compilation is not what this tests)
CONFIG = dict(emission="policy", max_skills=3, moves={"greedy_merge": 0, "greedy_split": 0})
KW = dict(num_chains=2, num_warmup=6, seed=5, progress_bar=False)


def two_cores(monkeypatch):
    # two threads even on one core (with a jaxlib whose LAPACK kernels block XLA's pool, too:
    # this model's programs call no library kernel, checked below)
    monkeypatch.setattr(chains_module, "cores", lambda: 2)
    monkeypatch.setattr(threads_module, "cores", lambda: 2)


def test_threads_give_the_sequential_draws_bit_for_bit(monkeypatch):
    two_cores(monkeypatch)
    calls = []
    monkeypatch.setattr(chains_module, "on_threads", lambda *a: calls.append(a[2]) or on_threads(*a))
    threads = fit(MDP, DEMOS, dict(CONFIG, chain_method="threads"), num_samples=4, **KW)
    assert calls and set(calls) == {2}  # every sweep on two threads
    sequential = fit(MDP, DEMOS, dict(CONFIG, chain_method="sequential"), num_samples=4, **KW)
    assert threads.config["sampler"]["chain_method"] == "threads"
    assert threads.equals(dataclasses.replace(sequential, config=threads.config))
    np.testing.assert_array_equal(threads.step_skill_counts, sequential.step_skill_counts)
    assert not np.array_equal(threads.stats["log_joint"][0], threads.stats["log_joint"][1])  # two chains
    # the default ("auto") is the threads on this CPU
    default = fit(MDP, DEMOS, CONFIG, num_samples=4, **KW)
    assert default.config["sampler"]["chain_method"] == "auto"
    assert default.equals(dataclasses.replace(threads, config=default.config))


def test_the_calls_run_at_the_same_time_in_float64_and_raise_their_errors():
    """Two calls that each wait for the other (a barrier of two) finish only if they are in
    flight together; each sees 64-bit types."""
    barrier = threading.Barrier(2, timeout=30)

    def call(x):
        barrier.wait()  # (a BrokenBarrierError after 30 s if the calls ran one after another)
        return jnp.asarray(x) * 2, jnp.ones(1).dtype, threading.get_ident()

    x64 = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", False)  # a user's process (the suite's is float64)
    try:
        out = on_threads(call, [(1.5,), (2.5,)], 2)
        assert jnp.ones(1).dtype == jnp.float32  # the caller's own setting is left alone
    finally:
        jax.config.update("jax_enable_x64", x64)
    assert [float(o[0]) for o in out] == [3.0, 5.0]  # in the calls' order
    assert all(o[1] == jnp.float64 for o in out)
    assert out[0][2] != out[1][2]

    def fails(x):
        raise ValueError(f"bad {x}")

    with pytest.raises(ValueError, match="bad 1"):
        on_threads(fails, [(1,), (2,)], 2)


def test_auto_picks_threads_on_the_cpu_else_vectorized(monkeypatch):
    monkeypatch.setattr(chains_module, "cores", lambda: 2)
    assert choose_chain_method("auto", 2, None, None) == ("sequential", None, 2)
    assert choose_chain_method("auto", 4, None, None) == ("sequential", None, 2)  # as many threads as cores
    assert choose_chain_method("threads", 4, None, None) == ("sequential", None, 2)
    assert choose_chain_method("auto", 1, None, None) == ("sequential", None, 1)
    assert choose_chain_method("vectorized", 4, None, None) == ("vectorized", None, 1)
    monkeypatch.setattr(chains_module, "cores", lambda: 8)
    assert choose_chain_method("auto", 4, None, None) == ("sequential", None, 4)
    monkeypatch.setattr(chains_module, "cores", lambda: 1)  # (one thread: the sequential chains)
    assert choose_chain_method("auto", 4, None, None) == ("sequential", None, 1)
    assert choose_chain_method("threads", 4, None, None) == ("sequential", None, 1)
    monkeypatch.setattr(chains_module, "cores", lambda: 2)
    monkeypatch.setattr(chains_module.jax, "default_backend", lambda: "gpu")  # an accelerator: one batched program
    assert choose_chain_method("auto", 4, None, None) == ("vectorized", None, 1)
    with pytest.raises(ValueError, match="chain_method='threads'.*mesh or devices"):
        choose_chain_method("threads", 4, None, 1)


def test_the_sweep_compiles_once_beside_the_initial_state(monkeypatch):
    """The first fit of a new shape compiles the sweep on a thread of its own while the initial
    state compiles and runs, for exactly the state the init returns: the sweep's first call
    then waits for that program instead of compiling another (one compile of it in all)."""
    from jax._src.dispatch import BACKEND_COMPILE_EVENT

    two_cores(monkeypatch)
    where = []

    def listen(event, duration, fun_name="", **_):
        if event == BACKEND_COMPILE_EVENT and "sweep_one" in fun_name:
            where.append(threading.current_thread().name)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        # (max_skills 2: shapes no other test's fit has, so this process has not compiled them)
        fit(MDP, DEMOS, dict(CONFIG, max_skills=2), num_samples=2, **KW)
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert where == ["npbrs-compile-sweep"]


def test_these_programs_call_no_lapack_kernel_and_the_version_rule(monkeypatch):
    """The tests above run two of this model's programs at once even where jaxlib's LAPACK
    kernels can hang XLA's pool; that is safe because the policy emission's init and sweep
    call no library kernel at all. And which jaxlibs have the hazard (before 0.11.2)."""
    import jax.numpy as jnp

    from npbrs.inference.driver.compiled import init_chains, sweep_one
    from npbrs.inference.threads import lapack_blocks_pool, max_threads

    texts = []
    real = compiled_module.Compiled.compile_sweep_beside_init

    def lowered(self, method, keys, num_warmup, z0=None):
        with jax.enable_x64(True):
            traced = init_chains.trace(self.kernel, keys[0], z0, jnp.int32(num_warmup))
            state = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype), traced.out_info)
            texts.append(traced.lower().as_text())
            texts.append(sweep_one.lower(self.kernel, self.hyper_names, state,
                                          jax.ShapeDtypeStruct((), jnp.bool_)).as_text())
        return real(self, method, keys, num_warmup, z0)

    monkeypatch.setattr(compiled_module.Compiled, "compile_sweep_beside_init", lowered)
    fit(MDP, DEMOS, dict(CONFIG, chain_method="sequential"), num_samples=1, **KW)
    assert len(texts) == 2 and all("func.func public @main" in t for t in texts)
    assert [re.findall(r"custom_call @(\w+)", t) for t in texts] == [[], []]
    for version, hazard in (("0.10.2", True), ("0.11.1", True), ("0.11.2", False), ("0.12.0.1", False),
                            ("0.10.2.dev20260101", True)):
        assert lapack_blocks_pool(version) is hazard, version
    assert max_threads() >= 1


class _Lowered(Exception):
    """Raised where a fit would start compiling: its init's and sweep's lowered text."""


def _program_texts(monkeypatch, mdp, demos, config, **kwargs) -> list:
    """The lowered text of a sequential fit's init and sweep (fit(mdp, demos, config with
    sequential chains, **kwargs)), without compiling either."""
    from npbrs.inference.driver.compiled import init_chains, sweep_one

    def lowered(self, method, keys, num_warmup, z0=None):
        with jax.enable_x64(True):
            traced = init_chains.trace(self.kernel, keys[0], z0, jnp.int32(num_warmup))
            state = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype), traced.out_info)
            raise _Lowered([traced.lower().as_text(), sweep_one.lower(
                self.kernel, self.hyper_names, state, jax.ShapeDtypeStruct((), jnp.bool_)).as_text()])

    monkeypatch.setattr(compiled_module.Compiled, "compile_sweep_beside_init", lowered)
    with pytest.raises(_Lowered) as got:
        fit(mdp, demos, dict(config, chain_method="sequential"), progress_bar=False, **kwargs)
    texts = got.value.args[0]
    assert len(texts) == 2 and all("func.func public @main" in t for t in texts)
    return texts


def test_the_reward_emissions_programs_call_no_library_kernel(monkeypatch):
    """fit's defaults with the reward emission (its greedy moves included), on a few reward
    features and on one per state: the init's and the sweep's programs call no library kernel
    (npbrs.domains.util.linalg's plain-XLA Cholesky and solves instead of LAPACK's), so with any
    jaxlib their chains run on every core. It failed with jnp.linalg.slogdet / cholesky / inv,
    numpyro's MultivariateNormal and jax.scipy's solve_triangular (GMRES) in them."""
    from gridworld import gridworld
    from npbrs.domains import Demonstrations, generate_demonstrations
    from npbrs.domains.worlds import labyrinth_mdp

    dom = gridworld()
    few = generate_demonstrations(dom, num_trajectories=4, length=20, switch_prob=0.05, seed=0)
    one_hot = labyrinth_mdp(depth=3)  # 15 states, a reward weight each
    rng = np.random.default_rng(0)
    states, actions = np.zeros((3, 10), int), rng.integers(0, 4, (3, 10))
    for i in range(3):  # (a random walk the MDP can make: fit checks the transitions)
        states[i, 0] = rng.integers(0, 15)
        for t in range(1, 10):
            s, a = states[i, t - 1], actions[i, t - 1]
            possible = one_hot.successors[s, a][one_hot.probs[s, a] > 0]
            states[i, t] = rng.choice(possible)
    per_state = Demonstrations(states, actions)
    for mdp, demos in ((dom.mdp, few), (one_hot, per_state)):
        texts = _program_texts(monkeypatch, mdp, demos, {"emission": "reward", "max_skills": 3}, num_chains=2,
                               num_warmup=4, num_samples=2)
        assert [re.findall(r"custom_call @(\w+)", t) for t in texts] == [[], []], mdp.name


def test_a_program_that_calls_a_library_kernel_runs_one_at_a_time_on_two_cores(monkeypatch):
    """The rule that keeps jaxlib < 0.11.2 from hanging (npbrs.inference.threads): on two
    cores, programs whose text calls a library kernel run one at a time, the others two at once;
    a fit asks about its init's and its sweep's programs. It failed with the threads taken
    from the core count alone."""
    from npbrs.inference.threads import calls_library_kernel, max_threads, threads_for

    two_cores(monkeypatch)
    monkeypatch.setattr(threads_module, "lapack_blocks_pool", lambda: True)
    kernel_text = 'stablehlo.custom_call @lapack_dgetrf_ffi(%0)'
    assert calls_library_kernel(kernel_text) and not calls_library_kernel("stablehlo.add %0, %1")
    assert max_threads(kernel_text) == 1 and max_threads("stablehlo.add") == 2 and max_threads() == 1
    assert threads_for(4, lambda: "stablehlo.add") == 2 and threads_for(4, lambda: kernel_text) == 1
    monkeypatch.setattr(threads_module, "lapack_blocks_pool", lambda: False)  # (a newer jaxlib)
    assert threads_for(4, lambda: pytest.fail("not needed")) == 2 and max_threads(kernel_text) == 2

    monkeypatch.setattr(threads_module, "lapack_blocks_pool", lambda: True)
    asked, used = [], []
    for module in (chains_module, compiled_module):  # (the chains' sweeps and their initial states)
        monkeypatch.setattr(module, "on_threads", lambda *a: used.append(a[2]) or on_threads(*a))
    for calls in (False, True):
        def check(program, calls=calls):
            asked.append(re.search(r"module @jit_(\w+)", program.as_text()).group(1))
            return calls

        monkeypatch.setattr(threads_module, "calls_library_kernel", check)
        asked.clear(), used.clear()
        fit(MDP, DEMOS, dict(CONFIG, chain_method="threads"), num_samples=2, **KW)
        assert asked == ["init_chains", "sweep_one"]  # each program asked about once
        assert used and set(used) == {1 if calls else 2}


@pytest.fixture(scope="module")
def run():
    return fit(MDP, DEMOS, CONFIG, num_samples=4, **KW)


def test_the_predictive_runs_the_chains_draws_side_by_side_with_the_same_results(run, monkeypatch):
    """``log_predictive``, ``segment`` and ``pointwise_log_likelihood`` give the chains' j-th
    draws to threads at once (each chain's solves warm-started from its own previous draw, as
    on one thread): the same numbers, bit for bit, on one thread or two."""
    from npbrs.inference.analysis import predictive

    used = []
    real = threads_module.on_threads
    monkeypatch.setattr(threads_module, "on_threads", lambda *a: used.append(a[2]) or real(*a))
    # (two at once is safe with any jaxlib: these programs call no library kernel, checked here)
    calls, seen = set(), set()
    for name in ("_one_draw", "_one_draw_marginals"):
        program = getattr(predictive, name)

        def lowered(*a, _program=program, _name=name, **k):
            seen.add(_name)
            with jax.enable_x64(True):
                calls.update(re.findall(r"custom_call @(\w+)", _program.lower(*a, **k).as_text()))
            return _program(*a, **k)

        monkeypatch.setattr(predictive, name, lowered)
    results = {}
    for n in (1, 2):
        monkeypatch.setattr(threads_module, "threads_for", lambda tasks, program=None, n=n: n)
        used.clear()
        results[n] = (predictive.log_predictive(run, MDP, DEMOS, num_samples=4, num_draws=3),
                      predictive.segment(run, MDP, num_samples=4, num_draws=3),
                      predictive.pointwise_log_likelihood(run, MDP, num_samples=4))
        assert used and set(used) == {n}
    one, two = results[1], results[2]
    assert one[0].per_step == two[0].per_step and np.array_equal(one[0].per_trajectory, two[0].per_trajectory)
    for a, b in zip(one[1].probs, two[1].probs):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(one[2], two[2])
    assert seen == {"_one_draw", "_one_draw_marginals"} and calls == set()
