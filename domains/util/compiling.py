"""How npbrs compiles its own programs: ``jax.jit`` with LLVM's optimisation level 1 on the CPU.

XLA compiles a CPU program's kernels with LLVM at optimisation level 2 by default. npbrs's
programs (a sampler sweep, an IRL fit, the predictive's draws) are large and are run a few
hundred times, so compiling them is a large part of a fit: at level 1 a fit compiles about a
sixth faster and samples no slower (``docs/speed.md``; e.g. highway 16 x 500 with 4
chains, 20 + 20 sweeps: 55 s against 64 s, 27 s of compiling against 32 s; its sweeps were no
slower). Results agree with level 2's to rounding, not bit for bit (a log joint by about
1e-8 after 20 sweeps; the paper's tables' 40 fits found the same best draws).

The programs a fit runs once (its initial state: ``jit(..., once=True)``) also take XLA's older
CPU fusion emitters (:data:`ONCE_OPTIONS`, where the installed XLA has them), which compile them
faster (a default labyrinth fit, 2 chains: 5-9 s less of about 90); the sweeps keep the newer
emitters, under which the filters' loops run up to a third faster (``docs/speed.md``).

These are per-program compile options (``jax.jit(..., compiler_options=...)``), so they change
only npbrs's programs and leave the user's process alone. None is set

- where ``XLA_FLAGS`` names it (the user's choice wins; the test suite sets level 0 and the
  older emitters for every program);
- on other backends than the CPU (GPU code generation has its own trade-offs).
"""

from __future__ import annotations

import functools
import os

import jax

__all__ = ["jit", "compiler_options", "accepted", "OPTIMIZATION_LEVEL", "ONCE_OPTIONS", "ACCEPTED"]

OPTIMIZATION_LEVEL = 1
_FLAG = "xla_backend_optimization_level"
#: the CPU options of the programs a fit runs once (its initial state; ``jit(..., once=True)``):
#: XLA's older fusion emitters compile them faster. The programs run many times (the sweeps)
#: keep the newer ones, whose filter loops run up to a third faster (``docs/speed.md``).
ONCE_OPTIONS = {"xla_cpu_use_fusion_emitters": False}
#: whether this process's XLA takes each compile option asked about, {(name, value): bool}, filled
#: by :func:`accepted` (a name XLA does not know is an error at compile time, and a newer jaxlib
#: may drop one of :data:`ONCE_OPTIONS`); replace it with an empty dict to ask again
ACCEPTED: dict = {}


def accepted(name: str, value) -> bool:
    """Whether the installed XLA takes the CPU compile option ``name=value``: asked once per
    process, by compiling a tiny program with it, and remembered in :data:`ACCEPTED`.

    Args:
        name: an XLA compile option, e.g. ``"xla_cpu_use_fusion_emitters"``.
        value: its value.
    Returns:
        True if a program compiled with it, False if XLA refused it.
    """
    if (name, value) not in ACCEPTED:
        import numpy as np

        try:
            x = jax.device_put(np.float32(0), jax.devices("cpu")[0])
            jax.jit(lambda x: x + 1, compiler_options={name: value}).lower(x).compile()
            ACCEPTED[name, value] = True
        except Exception:  # (JaxRuntimeError "No such compile option", or a refused value)
            ACCEPTED[name, value] = False
    return ACCEPTED[name, value]


def compiler_options(backend: str | None = None, environ=None, once: bool = False) -> dict:
    """The compile options npbrs gives its programs on ``backend`` (default: JAX's default
    backend): on the CPU ``{"xla_backend_optimization_level": 1}``, and for a program run once
    (``once``) each of :data:`ONCE_OPTIONS` that the installed XLA accepts, each unless
    ``XLA_FLAGS`` names it (the user's choice wins); on other backends none."""
    environ = os.environ if environ is None else environ
    if (backend or jax.default_backend()) != "cpu":
        return {}
    flags = environ.get("XLA_FLAGS", "")
    options = {} if _FLAG in flags else {_FLAG: OPTIMIZATION_LEVEL}
    if once:
        options.update({name: value for name, value in ONCE_OPTIONS.items()
                        if name not in flags and accepted(name, value)})
    return options


class _Jit:
    """``jax.jit(fn, **options)`` with :func:`compiler_options` where it is compiled as a program
    of its own; called inside another trace (a tracer among its arguments, or JAX's refusal of
    the options when all of them are constants) it is a plain nested jit, whose code joins the
    enclosing program (JAX takes compile options at the top level only). The top-level function
    is made at the first call with each set of options (the backend is not chosen at import, and
    the options follow ``XLA_FLAGS`` as it is at the call); other attributes (``lower``,
    ``trace``, ...) are the top-level jitted function's."""

    def __init__(self, fn, options, once=False):
        functools.update_wrapper(self, fn)
        self._fn, self._options, self._once, self._tops, self._nested = fn, options, once, {}, None

    def _get(self):
        # one top-level jit per set of options, read at each call (``XLA_FLAGS`` may change)
        options = compiler_options(once=self._once)
        key = tuple(sorted(options.items()))
        top = self._tops.get(key)
        if top is None:
            top = self._tops[key] = jax.jit(self._fn, compiler_options=options or None, **self._options)
        return top

    def __call__(self, *args, **kwargs):
        if not any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((args, kwargs))):
            try:
                return self._get()(*args, **kwargs)
            except ValueError as e:  # inside a trace all the same (constant arguments): nested
                if "compiler_options" not in str(e):
                    raise
        if self._nested is None:
            self._nested = jax.jit(self._fn, **self._options)
        return self._nested(*args, **kwargs)

    def __getattr__(self, name):
        if name.startswith("__"):
            raise AttributeError(name)
        return getattr(self._get(), name)


def jit(fn=None, *, once: bool = False, **options):
    """``jax.jit`` for npbrs's programs: the same arguments (``static_argnums``, ...), compiled
    with :func:`compiler_options` (``once``: a program a fit runs once, such as its initial
    state). Use as ``jit(fn, ...)``, ``@jit`` or ``@functools.partial(jit, static_argnums=...)``."""
    if fn is None:
        return functools.partial(jit, once=once, **options)
    return _Jit(fn, options, once)
