"""How npbrs compiles its own programs: ``jax.jit`` with LLVM's optimisation level 1 on the CPU.

XLA compiles a CPU program's kernels with LLVM at optimisation level 2 by default. npbrs's
programs (a sampler sweep, an IRL fit, the predictive's draws) are large and are run a few
hundred times, so compiling them is a large part of a fit: at level 1 a fit compiles about a
sixth faster and samples no slower (``benchmarks/NOTES.md``, session 28; e.g. highway 16 x 500
with 4 chains, 20 + 20 sweeps: 55 s against 64 s, 27 s of compiling against 32 s; its sweeps
were no slower). Results agree with level 2's to rounding, not bit for bit (a log joint by about
1e-8 after 20 sweeps; the paper's tables' 40 fits found the same best draws).

The level is a per-program compile option (``jax.jit(..., compiler_options=...)``), so it
changes only npbrs's programs and leaves the user's process alone. It is not set

- where ``XLA_FLAGS`` sets ``--xla_backend_optimization_level`` (the user's choice wins; the
  test suite sets 0);
- on other backends than the CPU (GPU code generation has its own trade-offs).
"""

from __future__ import annotations

import functools
import os

import jax

__all__ = ["jit", "compiler_options", "OPTIMIZATION_LEVEL"]

OPTIMIZATION_LEVEL = 1
_FLAG = "xla_backend_optimization_level"


def compiler_options(backend: str | None = None, environ=None) -> dict:
    """The compile options npbrs gives its programs on ``backend`` (default: JAX's default
    backend): ``{"xla_backend_optimization_level": 1}`` on the CPU, unless ``XLA_FLAGS`` sets
    that level; otherwise none."""
    environ = os.environ if environ is None else environ
    if _FLAG in environ.get("XLA_FLAGS", ""):
        return {}
    if (backend or jax.default_backend()) != "cpu":
        return {}
    return {_FLAG: OPTIMIZATION_LEVEL}


class _Jit:
    """``jax.jit(fn, **options)`` with :func:`compiler_options` where it is compiled as a program
    of its own; called inside another trace (a tracer among its arguments, or JAX's refusal of
    the options when all of them are constants) it is a plain nested jit, whose code joins the
    enclosing program (JAX takes compile options at the top level only). The top-level function
    is made at the first call with each set of options (the backend is not chosen at import, and
    the options follow ``XLA_FLAGS`` as it is at the call); other attributes (``lower``,
    ``trace``, ...) are the top-level jitted function's."""

    def __init__(self, fn, options):
        functools.update_wrapper(self, fn)
        self._fn, self._options, self._tops, self._nested = fn, options, {}, None

    def _get(self):
        # one top-level jit per set of options, read at each call (``XLA_FLAGS`` may change)
        options = compiler_options()
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


def jit(fn=None, **options):
    """``jax.jit`` for npbrs's programs: the same arguments (``static_argnums``, ...), compiled
    with :func:`compiler_options`. Use as ``jit(fn, ...)``, ``@jit`` or
    ``@functools.partial(jit, static_argnums=...)``."""
    if fn is None:
        return functools.partial(jit, **options)
    return _Jit(fn, options)
