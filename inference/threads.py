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
So with those jaxlibs, programs that call a library kernel (a ``custom_call`` in their lowered
text) run at most cores - 1 at once, which leaves a pool thread free; on 2 cores that is one at
a time. Programs without one run on every core: npbrs's own linear algebra is plain XLA code
for that reason (:mod:`npbrs.domains.util.linalg`), so a fit with the reward or policy emission and
fit's defaults runs its chains side by side with any jaxlib. jaxlib 0.11.2 and later run a
LAPACK batch on the calling thread. The rule counts npbrs's own threads: with an older jaxlib,
programs that your other threads run at the same time count against the same pool.
"""

from __future__ import annotations

import os
import re
from concurrent.futures import ThreadPoolExecutor

import jax
import jaxlib

__all__ = ["cores", "max_threads", "lapack_blocks_pool", "calls_library_kernel", "threads_for", "on_threads"]


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


def calls_library_kernel(program) -> bool:
    """Whether a lowered program (a ``jax.stages.Lowered`` or its text) calls a kernel outside
    XLA's own code generation (a ``custom_call``: LAPACK's, on the CPU)."""
    text = program if isinstance(program, str) else program.as_text()
    return "custom_call" in text


def max_threads(program=None) -> int:
    """How many copies of ``program`` npbrs runs side by side at most: the process's cores, one
    fewer where the LAPACK kernels block XLA's pool (:func:`lapack_blocks_pool`) and the program
    calls a library kernel (:func:`calls_library_kernel`); at least 1. ``program``: a lowered
    program, its text, or a function returning either (called only when the jaxlib has the
    hazard); None (not known) counts as one that calls a kernel."""
    n = cores()
    if n > 1 and lapack_blocks_pool():
        if program is not None and not isinstance(program, str) and not hasattr(program, "as_text"):
            program = program()
        if program is None or calls_library_kernel(program):
            n -= 1
    return max(1, n)


def threads_for(tasks: int, program=None) -> int:
    """How many threads to run ``tasks`` independent calls of ``program`` on (see
    :func:`max_threads`): up to :func:`max_threads` when JAX computes on the CPU, else 1 (an
    accelerator runs a batch in one program)."""
    if jax.default_backend() != "cpu" or int(tasks) <= 1:
        return 1
    return max(1, min(int(tasks), max_threads(program)))


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
