"""float64 inside npbrs, the user's JAX settings outside it.

npbrs computes in float64 (soft Bellman solves to 1e-10, log-likelihoods of thousands of steps,
Metropolis ratios of nearly equal densities), but it never switches the whole process to it:
importing npbrs leaves ``jax_enable_x64`` as the user set it. Its entry points run inside JAX's
scoped switch instead, :func:`float64` below: ``fit``, the solvers, the IRL fits, the
predictive functions, and every method of npbrs's pytree objects (MDPs, solvers, emissions,
the sampler's kernel; see :mod:`npbrs.domains.util.pytree`). Programs compiled there are float64
programs (the switch is part of JAX's compilation key).

What they return is float64: NumPy arrays, or JAX arrays for the solvers and emissions (meant to
be used inside other npbrs calls or under ``jax.enable_x64``). Arithmetic on a returned JAX
array outside npbrs follows the process's setting, so in a float32 process convert it with
``np.asarray`` first.
"""

from __future__ import annotations

import functools

import jax

__all__ = ["float64", "float64_methods", "float64_all"]


def float64(fn):
    """``fn`` run with JAX's 64-bit types on for the duration of the call (and the user's
    setting restored afterwards)."""
    if getattr(fn, "_npbrs_float64", False):
        return fn

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with jax.enable_x64(True):
            return fn(*args, **kwargs)

    wrapper._npbrs_float64 = True
    return wrapper


def float64_methods(cls):
    """Wrap ``__init__``, ``__call__`` and the other methods defined in ``cls`` itself (class and
    static methods too) with :func:`float64`; returns ``cls``."""
    for name, value in list(vars(cls).items()):
        if isinstance(value, (classmethod, staticmethod)):
            setattr(cls, name, type(value)(float64(value.__func__)))
        elif callable(value) and not isinstance(value, type) and (not name.startswith("__")
                                                                 or name in ("__init__", "__call__")):
            setattr(cls, name, float64(value))
    return cls


def float64_all(namespace: dict) -> None:
    """At the end of a module: wrap the functions it exports (``__all__``) and the methods of
    the classes it exports (NamedTuples excepted) with :func:`float64`."""
    module = namespace["__name__"]
    for name in namespace.get("__all__", ()):
        value = namespace.get(name)
        if getattr(value, "__module__", None) != module:
            continue
        if isinstance(value, type):
            if not issubclass(value, tuple):
                float64_methods(value)
        elif callable(value) and not isinstance(value, functools.partial):
            namespace[name] = float64(value)
