"""Independent programs side by side on a CPU's cores: threads, without touching the process.

JAX runs the programs that one thread dispatches to a device one after another; on the CPU, a
program mostly keeps one core busy. Calls made from several threads, each waiting for its own
results, run side by side. npbrs uses that for what is independent: a fit's chains
(``fit(chain_method="threads")``, the default "auto" on a multi-core CPU) and the draws of
different chains in the predictive functions (``log_predictive``, ``segment``,
``pointwise_log_likelihood``). Unlike ``--xla_force_host_platform_device_count`` it needs no
setting made before JAX starts.

One hazard bounds the threads. XLA runs a program's kernels on an intra-op pool of one thread
per core. In jaxlib before 0.11.2 the CPU LAPACK kernels (LU, Cholesky, eigh, ... of a batch
of matrices) fan the batch out over that same pool and block until it is done: when every
pool thread holds such a kernel, nothing runs their parts, and the process hangs (seen here:
two chains' sweeps on 2 cores, each in a batched LU of 127 x 127 matrices, waiting forever).
So with those jaxlibs at most cores - 1 programs run at once, which leaves a pool thread free;
on 2 cores that is one, and ``fit``'s "auto" then runs the chains one after another. jaxlib
0.11.2 and later run a LAPACK batch on the calling thread. The rule counts npbrs's own
threads: with such a jaxlib, programs that your other threads run at the same time count
against the same pool.
"""

from __future__ import annotations

import os
import re
from concurrent.futures import ThreadPoolExecutor

import jax
import jaxlib

__all__ = ["cores", "max_threads", "lapack_blocks_pool", "threads_for", "on_threads"]


def cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # (not on every platform)
        return os.cpu_count() or 1


def lapack_blocks_pool(version: str | None = None) -> bool:
    """Whether this jaxlib's (or ``version``'s) CPU LAPACK kernels fan a batch out over XLA's
    intra-op pool and block on it: jaxlib before 0.11.2 (see the module notes)."""
    version = jaxlib.__version__ if version is None else version
    parts = tuple(int(x) for x in re.findall(r"\d+", version)[:3])
    return parts < (0, 11, 2)


def max_threads() -> int:
    """How many programs npbrs runs side by side at most: the process's cores, one fewer where
    the LAPACK kernels block XLA's pool (:func:`lapack_blocks_pool`), at least 1."""
    return max(1, cores() - (1 if lapack_blocks_pool() else 0))


def threads_for(tasks: int) -> int:
    """How many threads to run ``tasks`` independent programs on: up to :func:`max_threads`
    when JAX computes on the CPU, else 1 (an accelerator runs a batch in one program)."""
    if jax.default_backend() != "cpu":
        return 1
    return max(1, min(int(tasks), max_threads()))


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
