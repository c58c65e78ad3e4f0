"""Objects that enter compiled programs as arguments, not as constants.

A jitted function that closes over an array bakes the array into its program as a constant: a
new dataset or a new MDP of the same shapes then compiles the whole program again. npbrs's
MDPs, solvers, emissions and its sampler's kernel are instead *pytrees*: a ``jax.jit``-ed
function takes them as arguments, their arrays become the program's inputs, and the program is
keyed by the arrays' shapes and dtypes and by the object's other (static) attributes only.

:class:`Pytree` makes a class (and every subclass) such a pytree without per-class code:

- its *data* are the instance attributes holding arrays (NumPy or JAX), other pytrees, or
  tuples, lists and dicts of those; under ``jit`` they are traced;
- everything else is *static* (sizes, options, names, functions): compared with ``==`` when
  ``jit`` looks up a compiled program, so static attributes must be plain values (containers of
  numbers and strings are compared by value; other objects by identity);
- attributes named in ``_pytree_derived`` (closures or jitted functions built from the data)
  are left out and rebuilt by ``_pytree_rebuild()`` after unflattening, so that they use the
  traced data rather than the arrays they were first built from.

A domain-supplied function (say an MDP's factored next-value operator) stays a static attribute:
it is called inside the program, and whatever arrays it closes over stay constants of it.
"""

from __future__ import annotations

from typing import Any, Tuple

import jax
import numpy as np

from .precision import float64_methods

__all__ = ["Pytree", "is_data"]


def is_data(value: Any) -> bool:
    """Whether an attribute's value is traced data: an array, a pytree of this kind, or a
    tuple/list/dict holding one."""
    if isinstance(value, (np.ndarray, jax.Array, Pytree)):
        return True
    if isinstance(value, (tuple, list)):
        return any(is_data(v) for v in value)
    if isinstance(value, dict):
        return any(is_data(v) for v in value.values())
    return False


def _freeze(value: Any):
    """A hashable stand-in for a static value compared by content (containers of plain values)."""
    if isinstance(value, dict):
        return ("dict",) + tuple(sorted((repr(k), _freeze(v)) for k, v in value.items()))
    if isinstance(value, (list, tuple)):
        return (type(value).__name__,) + tuple(_freeze(v) for v in value)
    if isinstance(value, (set, frozenset)):
        return ("set",) + tuple(sorted(repr(v) for v in value))
    if isinstance(value, float) and value != value:  # NaN equals itself here
        return ("nan",)
    try:
        hash(value)
    except TypeError:
        return ("id", id(value))
    return value


class _Static:
    """The static attributes of one instance: equal when their frozen forms are."""

    __slots__ = ("items", "_key")

    def __init__(self, items: Tuple[Tuple[str, Any], ...]):
        self.items = items
        self._key = tuple((name, _freeze(value)) for name, value in items)

    def __eq__(self, other):
        return isinstance(other, _Static) and self._key == other._key

    def __hash__(self):
        return hash(self._key)

    def __repr__(self):
        return f"_Static({', '.join(name for name, _ in self.items)})"


class Pytree:
    """Base class: instances are JAX pytrees of their array attributes (see the module)."""

    _pytree_derived: Tuple[str, ...] = ()

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        jax.tree_util.register_pytree_node(cls, cls._pytree_flatten, cls._pytree_unflatten)
        # every method of an npbrs object computes in float64, whatever the process's setting
        float64_methods(cls)

    def _pytree_flatten(self):
        skip = set(type(self)._pytree_all_derived())
        data, static = [], []
        for name, value in vars(self).items():
            if name in skip:
                continue
            (data if is_data(value) else static).append((name, value))
        names = tuple(name for name, _ in data)
        return tuple(value for _, value in data), (names, _Static(tuple(static)))

    @classmethod
    def _pytree_unflatten(cls, aux, children):
        names, static = aux
        obj = object.__new__(cls)
        attrs = vars(obj)
        attrs.update(static.items)
        attrs.update(zip(names, children))
        obj._pytree_rebuild()
        return obj

    @classmethod
    def _pytree_all_derived(cls) -> Tuple[str, ...]:
        out = []
        for klass in cls.__mro__:
            out.extend(getattr(klass, "__dict__", {}).get("_pytree_derived", ()))
        return tuple(out)

    def _pytree_rebuild(self) -> None:
        """Rebuild the attributes named in ``_pytree_derived`` (called after unflattening)."""
