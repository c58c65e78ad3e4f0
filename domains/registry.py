"""Domains by name: the paper's highway and quadcopter, and any a user registers."""

from __future__ import annotations

import importlib
from typing import Callable, Dict, Union

__all__ = ["DOMAINS", "get_domain", "register_domain"]

# name -> constructor returning a Domain, or "module:function" imported on first use (building
# a domain's tables is slow, and importing every domain module up front would pay for all)
DOMAINS: Dict[str, Union[str, Callable]] = {
    "highway": "npbrs.domains.highway:highway",
    "quadcopter": "npbrs.domains.quadcopter:quadcopter",
}


def register_domain(name: str, constructor: Union[str, Callable]) -> None:
    """Make ``get_domain(name)`` call ``constructor`` (a callable or "module:function")."""
    DOMAINS[name] = constructor


def get_domain(name: str, **kwargs):
    """The Domain registered as ``name``, built with ``kwargs``."""
    if name not in DOMAINS:
        raise ValueError(f"unknown domain {name!r}; known domains: {', '.join(sorted(DOMAINS))}")
    constructor = DOMAINS[name]
    if isinstance(constructor, str):
        module, _, function = constructor.partition(":")
        constructor = getattr(importlib.import_module(module), function)
    return constructor(**kwargs)
