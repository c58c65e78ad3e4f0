"""Independent programs side by side on a CPU's cores: threads, without touching the process.

JAX runs the programs that one thread dispatches to a device one after another; on the CPU, a
program mostly keeps one core busy. Calls made from several threads, each waiting for its own
results, run side by side. npbrs uses that for what is independent: a fit's chains
(``fit(chain_method="threads")``, the default "auto" on a multi-core CPU) and the draws of
different chains in the predictive functions (``log_predictive``, ``segment``,
``pointwise_log_likelihood``). Unlike ``--xla_force_host_platform_device_count`` it needs no
setting made before JAX starts.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import jax

__all__ = ["cores", "threads_for", "on_threads"]


def cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # (not on every platform)
        return os.cpu_count() or 1


def threads_for(tasks: int) -> int:
    """How many threads to run ``tasks`` independent programs on: up to the process's cores
    when JAX computes on the CPU, else 1 (an accelerator runs a batch in one program)."""
    if jax.default_backend() != "cpu":
        return 1
    return max(1, min(int(tasks), cores()))


def on_threads(fn, calls, threads: int) -> list:
    """[fn(*args) for args in calls], in that order; with ``threads`` > 1 the calls run on up to
    that many threads at once, each waiting for its results (so that they run side by side). A
    thread starts without the caller's JAX context, so each enters npbrs's float64 scope and the
    caller's default device. An exception in a call is raised here."""
    calls = list(calls)
    if threads <= 1 or len(calls) <= 1:
        return [fn(*args) for args in calls]
    device = jax.config.jax_default_device

    def call(args):
        with jax.enable_x64(True), jax.default_device(device):
            return jax.block_until_ready(fn(*args))

    with ThreadPoolExecutor(max_workers=min(threads, len(calls))) as pool:
        return list(pool.map(call, calls))
