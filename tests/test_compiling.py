"""npbrs compiles its own programs with LLVM's optimisation level 1 on the CPU, those a fit runs
once with XLA's older fusion emitters too (:mod:`npbrs.domains.util.compiling`), as per-program
compile options: the user's ``XLA_FLAGS`` win, other backends are left alone, and the wrapped
functions work where ``jax.jit`` does, inside other traces too (JAX refuses compile options on a
nested jit)."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from npbrs.domains.util import compiling
from npbrs.domains.util.compiling import compiler_options, jit


def _record_jits(monkeypatch):
    """``jax.jit`` as npbrs's wrapper calls it, recording each call's ``compiler_options``:
    (the list of them, the real ``jax.jit``)."""
    made, real = [], jax.jit

    def recording_jit(fn, **kwargs):
        made.append(kwargs.get("compiler_options"))
        return real(fn, **kwargs)

    monkeypatch.setattr(compiling.jax, "jit", recording_jit)
    return made, real


def test_the_level_is_set_on_the_cpu_unless_xla_flags_choose_one():
    assert compiler_options("cpu", {}) == {"xla_backend_optimization_level": 1}
    assert compiler_options("cpu", {"XLA_FLAGS": "--xla_force_host_platform_device_count=4"}) == \
        {"xla_backend_optimization_level": 1}
    assert compiler_options("cpu", {"XLA_FLAGS": "--xla_backend_optimization_level=3"}) == {}
    assert compiler_options("gpu", {}) == {} and compiler_options("tpu", {}) == {}
    assert compiler_options("gpu", {}, once=True) == {}


def test_a_program_run_once_also_gets_the_older_emitters_where_xla_takes_them(monkeypatch):
    """The initial state compiles with XLA's older fusion emitters (it compiles faster), where
    the installed XLA accepts the option (asked once, by compiling a tiny program) and
    ``XLA_FLAGS`` does not name it; an option XLA does not know is left out, not an error."""
    takes = compiling.accepted("xla_cpu_use_fusion_emitters", False)
    emitters = {"xla_cpu_use_fusion_emitters": False} if takes else {}
    assert compiler_options("cpu", {}, once=True) == {"xla_backend_optimization_level": 1, **emitters}
    assert compiler_options("cpu", {"XLA_FLAGS": "--xla_backend_optimization_level=0"}, once=True) == emitters
    assert compiler_options("cpu", {"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=true"}, once=True) == \
        {"xla_backend_optimization_level": 1}
    monkeypatch.setattr(compiling, "ONCE_OPTIONS", {**compiling.ONCE_OPTIONS, "xla_cpu_no_such_option": True})
    monkeypatch.setattr(compiling, "ACCEPTED", {})
    options = compiler_options("cpu", {}, once=True)
    assert "xla_cpu_no_such_option" not in options and compiling.ACCEPTED[("xla_cpu_no_such_option", True)] is False
    # the options kept compile and run a program, with the same numbers to rounding
    x = jnp.linspace(0.0, 3.0, 50)
    f = lambda x: jnp.cumsum(jnp.exp(jnp.sin(x) * 2.0)) / jnp.sum(x ** 2)  # noqa: E731
    np.testing.assert_allclose(jax.jit(f, compiler_options=options)(x), jax.jit(f)(x), rtol=1e-12)


def test_a_wrapped_function_gets_the_options_at_the_top_and_none_when_nested(monkeypatch):
    made, real = _record_jits(monkeypatch)
    monkeypatch.setattr(compiling, "compiler_options", lambda once=False: {"xla_backend_optimization_level": 1})

    def f(x, n):
        return jnp.sin(x) * n

    g = jit(f, static_argnums=1)
    x = jnp.linspace(0.0, 1.0, 5)
    np.testing.assert_allclose(g(x, 3), jnp.sin(x) * 3, rtol=1e-12)  # compiled alone: with the option
    assert made == [{"xla_backend_optimization_level": 1}]
    # inside another jit, a vmap and a scan: a plain nested jit (the option would be an error there)
    outer = real(lambda x: jax.vmap(lambda y: g(y, 2))(x[:, None]).sum() + jax.lax.scan(
        lambda c, y: (c + g(y, 1), None), 0.0, x)[0])
    np.testing.assert_allclose(outer(x), 3 * jnp.sum(jnp.sin(x)), rtol=1e-12)
    assert made[1:] == [None]  # one nested jit, made once
    # inside a jit with constant arguments only (no tracer to see): JAX refuses the option, so nested
    np.testing.assert_allclose(real(lambda: g(x, 4))(), jnp.sin(x) * 4, rtol=1e-12)
    assert made[1:] == [None]
    assert g.__name__ == "f" and g.lower(x, 3) is not None  # the jitted function's attributes


def test_fit_and_the_solvers_compile_through_it():
    from npbrs.domains.solvers import common as solvers
    from npbrs.inference.analysis import predictive
    from npbrs.inference.driver import compiled
    from npbrs.inference.sampler import kernel
    from npbrs.models.reward import irl, likelihood

    for fn in (compiled.sweep_batched, compiled.sweep_one, compiled.init_chains, kernel._init_state, solvers._solve_batch,
               predictive._one_draw, predictive._one_draw_marginals, irl._FIT_JIT, likelihood._LL_AND_GRAD):
        assert isinstance(fn, compiling._Jit), fn
    # the initial state is the fit's program run once; the sweeps are run hundreds of times
    assert compiled.init_chains._once and kernel._init_state._once
    assert not (compiled.sweep_one._once or compiled.sweep_batched._once or solvers._solve_batch._once)


def test_the_options_follow_xla_flags_at_each_call_and_each_set_compiles_once(monkeypatch):
    """A test marked ``library_level`` (tests/conftest.py) drops the suite's level from
    ``XLA_FLAGS`` for its duration: the wrapper then compiles with the library's level, and
    after the test with none again, reusing each set's jitted function."""
    made, real = _record_jits(monkeypatch)
    monkeypatch.setattr(compiling.jax, "default_backend", lambda: "cpu")
    g = jit(lambda x: x + 1.0)
    x = jnp.zeros(3)
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=0")
    g(x), g(x)
    monkeypatch.setenv("XLA_FLAGS", "")
    g(x), g(x)
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=0")
    np.testing.assert_allclose(g(x), 1.0)
    assert made == [None, {"xla_backend_optimization_level": 1}]
    # a program run once: with the older emitters too, unless XLA_FLAGS names them (the suite's do)
    h = jit(lambda x: x * 2.0, once=True)
    monkeypatch.setenv("XLA_FLAGS", "")
    np.testing.assert_allclose(h(x), 0.0)
    assert made[2:] == [compiler_options("cpu", {}, once=True)]
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false")
    h(x)
    assert made[3:] == [None]


@pytest.mark.library_level
def test_a_test_marked_library_level_compiles_at_the_librarys_level():
    from conftest import _LEVEL_SET_HERE

    # (.ci/run sets no level: there the suite sets it, and every worker must know that)
    assert _LEVEL_SET_HERE or os.environ.get("CI") != "true"
    if not _LEVEL_SET_HERE:
        pytest.skip("the level was set in XLA_FLAGS by whoever runs the suite")
    assert compiler_options("cpu") == {"xla_backend_optimization_level": 1}


def test_an_unmarked_test_compiles_at_the_suites_level():
    from conftest import _LEVEL_SET_HERE

    assert "xla_backend_optimization_level=0" in os.environ["XLA_FLAGS"] or not _LEVEL_SET_HERE
    assert compiler_options("cpu") == {}  # the level in XLA_FLAGS (the suite's, or whoever runs it) is left to XLA
