"""Test-session settings: float64; JAX's persistent compilation cache in a folder of this run
so that the many samplers the tests build (identical programs around different objects)
compile once; and every compiled program released after each test module.

Why the release: a loaded CPU executable holds about 20 memory mappings (the LLVM JIT's code
and data sections), and the kernel allows a process 65530 (``vm.max_map_count``). The whole
suite in one process compiles about 3,000 programs, so without the release it ran out of
mappings near its end and XLA crashed (a segmentation fault or an abort inside
``put_executable_and_time``, whichever allocation failed first) at about 7 GB.

Compiling is most of the suite's time, so its processes (and the command-line runs and notebook
kernels they start) ask LLVM for its cheapest optimisation level (20% less wall time on two
cores, the same results; XLA's own graph optimisations still run) and XLA for its older CPU
fusion emitters where the installed jaxlib has that switch (a third less compile time; results
differ from the default emitters' in rounding only) and each program's machine code in one
piece (``OPTIONAL_FLAGS``), unless ``XLA_FLAGS`` already sets them. A test marked
``library_level`` compiles npbrs's programs at the library's own level instead (LLVM level 1,
``npbrs.domains.util.compiling``): for tests whose small programs run long (solves repeated to
convergence), which LLVM's level 0 runs several times slower.

The suite runs in two pytest-xdist worker processes (``addopts`` in pyproject.toml), each
test file in one of them: on two cores that is about a sixth faster than one process.

Under ``CI=true`` the cache must be a fresh, empty folder named by ``NPBRS_TEST_JAX_CACHE``
(``.ci/run`` makes one per run), so that CI compiles what a new machine compiles.
"""

import ctypes
import gc
import json
import os
import sys
import tempfile
import time


def _xla_accepts(*flags: str) -> bool:
    """Whether the installed jaxlib's XLA accepts these flags: an unknown flag in XLA_FLAGS aborts
    the process, and a flag's name can outlive the flag in jaxlib's binaries (jaxlib 0.12, on
    Python 3.12, still holds the string ``xla_cpu_use_fusion_emitters`` but aborts on it), so a
    short subprocess starts JAX's CPU backend with those not yet asked about. The answers are
    passed on to the test workers and the processes they start (``_ACCEPTS_ENV``), so only the
    first process asks. Several flags refused together are not recorded (ask one at a time)."""
    known = os.environ.get(_ACCEPTS_ENV, "").split()
    if any(f"-{flag}" in known for flag in flags):
        return False
    unknown = [flag for flag in flags if f"+{flag}" not in known]
    if not unknown:
        return True
    import subprocess

    try:
        probe = subprocess.run([sys.executable, "-c", "import jax; jax.devices('cpu')"], capture_output=True,
                               env={**os.environ, "XLA_FLAGS": " ".join(f"--{flag}" for flag in unknown),
                                    "JAX_PLATFORMS": "cpu"}, timeout=120)
        accepted = probe.returncode == 0
    except subprocess.TimeoutExpired:  # (not worth a test run that does not start)
        accepted = False
    if accepted or len(unknown) == 1:
        os.environ[_ACCEPTS_ENV] = " ".join(known + [f"{'+' if accepted else '-'}{flag}" for flag in unknown])
    return accepted


_ACCEPTS_ENV = "NPBRS_TEST_XLA_FLAGS_CHECKED"


#: optional flags, where the installed jaxlib has them: XLA's older CPU fusion emitters (a third
#: less compile time in the suite's programs; results differ from the default emitters' only in
#: rounding), and each program's machine code generated in one piece rather than split for
#: parallel compilation (both cores are busy with the two test workers: 11% less compiling in the
#: cold suite, 4% in one process's small fit; the same results)
OPTIONAL_FLAGS = ("xla_cpu_use_fusion_emitters=false", "xla_cpu_parallel_codegen_split_count=1")


def _fast_compile_flags(flags: str) -> str:
    """XLA_FLAGS with the test processes' cheaper compilation, unless the user set those flags:
    LLVM's lowest optimisation level, and ``OPTIONAL_FLAGS`` where XLA accepts them."""
    if "xla_backend_optimization_level" not in flags:
        flags += " --xla_backend_optimization_level=0"
    optional = [f for f in OPTIONAL_FLAGS if f.split("=")[0] not in flags]
    if optional and not _xla_accepts(*optional):  # (one at a time, then)
        optional = [f for f in optional if _xla_accepts(f)]
    return " ".join([flags.strip()] + [f"--{f}" for f in optional]).strip()


# whether the level in XLA_FLAGS is the suite's (not its runner's): said in the environment, for
# the pytest-xdist workers inherit XLA_FLAGS with the level in it
_LEVEL_ENV = "NPBRS_TEST_SUITE_SETS_LEVEL"
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ[_LEVEL_ENV] = "1"
_LEVEL_SET_HERE = os.environ.get(_LEVEL_ENV) == "1"
# (before JAX starts its backend, which reads XLA_FLAGS once)
os.environ["XLA_FLAGS"] = _fast_compile_flags(os.environ.get("XLA_FLAGS", ""))

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)
os.environ.setdefault("NPBRS_CACHE_DIR", "off")  # the command line, run in this process, keeps the cache below

CACHE_ENV = "NPBRS_TEST_JAX_CACHE"
_cache = os.environ.get(CACHE_ENV) or os.path.join(tempfile.gettempdir(), "npbrs-test-jax-cache")
# each pytest-xdist worker writes a folder of its own: JAX writes an entry in place, so a
# worker could otherwise read another's half-written file
_worker = os.environ.get("PYTEST_XDIST_WORKER")
jax.config.update("jax_compilation_cache_dir", os.path.join(_cache, _worker) if _worker else _cache)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)

# ArviZ 0.23 writes a once-a-day stamp file at import through a temporary file of a fixed name:
# on a day's first import (a fresh machine, CI) two workers collecting test files that import it
# race, and one worker's collection fails with FileNotFoundError. The controller imports it here,
# before it starts the workers (they then find today's stamp), and every process through npbrs's
# retrying import (npbrs.inference.arviz_import).
from npbrs.inference.arviz_import import arviz  # noqa: E402

arviz()


def check_fresh_cache(environ, cache_dir) -> str:
    """Why this test run may not start under CI, or "" if it may: CI must name its own
    compilation cache folder, and that folder must be empty (nothing from an earlier run)."""
    if environ.get("CI", "").lower() not in ("true", "1"):
        return ""
    if not environ.get(CACHE_ENV):
        return (f"CI=true but {CACHE_ENV} is not set: CI must compile into an empty cache folder of its own "
                "(see .ci/run), or it would reuse programs a new machine has to compile")
    if os.path.isdir(cache_dir) and os.listdir(cache_dir):
        return (f"CI=true but the compilation cache {cache_dir} already holds {len(os.listdir(cache_dir))} entries "
                "from an earlier run; CI must start from an empty folder (see .ci/run)")
    return ""


def pytest_configure(config):
    if hasattr(config, "workerinput"):  # a pytest-xdist worker: the controller has checked
        return
    problem = check_fresh_cache(os.environ, _cache)
    if problem:
        raise pytest.UsageError(problem)


# The test files that take longest from an empty compilation cache, longest first, with the
# seconds one worker spent in each (module fixtures included) in a cold run on this project's
# 2-core machine (``NPBRS_TEST_COMPILE_LOG`` and ``--durations``). The suite runs each
# file in one of two pytest-xdist workers, taking files in collection order
# (``--no-loadscope-reorder`` in ``addopts``: xdist would otherwise order them by their number of
# tests, which put the three-test file of default fits, the longest, near the end). Starting
# with the long ones balances the two workers. Files not named here follow in their usual order.
LONGEST_FIRST = ("test_worlds_recovery.py",  # 82
                 "test_greedy.py",  # 57
                 "test_termination.py",  # 53
                 "test_notebooks.py",  # 49 (its fixture: two notebook kernels at once)
                 "test_kernel.py",  # 39
                 "test_reward_emission.py",  # 37
                 "test_joint_distribution.py",  # 33
                 "test_cli.py",  # 31
                 "test_reward.py",  # 29
                 "test_solvers.py",  # 28
                 "test_reward_fit.py",  # 24
                 "test_posterior.py",  # 24
                 "test_split_merge.py",  # 23
                 "test_predictive.py",  # 22
                 "test_runs.py",  # 21
                 "test_hmm.py",  # 19
                 "test_reward_mala.py",  # 18
                 "test_devices.py",  # 18 (its fixture: a four-device subprocess)
                 "test_reproduce.py",  # 16
                 "test_subgoal.py",  # 15
                 "test_grow.py",  # 13
                 "test_autoregressive.py",  # 11
                 "test_config.py")  # 8


def pytest_collection_modifyitems(session, config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: the rest keep their order


def map_count() -> int:
    """Memory mappings this process holds (compiled programs hold most of them)."""
    try:
        with open("/proc/self/maps") as f:
            return sum(1 for _ in f)
    except OSError:  # not Linux
        return 0


def map_limit() -> int:
    try:
        with open("/proc/sys/vm/max_map_count") as f:
            return int(f.read())
    except (OSError, ValueError):
        return 65530


def _return_freed_memory():
    """Hand the C heap's free pages back to the system (glibc keeps them otherwise)."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc
        pass


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs(request):
    """After each module (its own fixtures are torn down first): forget npbrs's kernels and
    JAX's compiled programs, so that the process's memory mappings stay bounded; an error
    (on the module's last test) when a module leaves more than half the allowed mappings in
    use, or when they are not released: the crash would otherwise come back silently."""
    yield
    held = map_count()
    compiled = sys.modules.get("npbrs.inference.driver.compiled")
    if compiled is not None:
        compiled.clear_compiled()
    jax.clear_caches()
    gc.collect()
    _return_freed_memory()
    left, limit = map_count(), map_limit()
    if held > limit // 2 or left > limit // 4:
        raise RuntimeError(f"{request.module.__name__}: {held} memory mappings in use at its end and {left} after "
                           f"releasing the compiled programs, of {limit} allowed; compiled programs are not being "
                           "released (see tests/conftest.py)")


COMPILE_LOG_ENV = "NPBRS_TEST_COMPILE_LOG"


class _Usage:
    """Wall and CPU seconds since it was made: the process's (all its threads) and those of the
    subprocesses it waited for."""

    def __init__(self):
        self.start, self.cpu, self.children = time.perf_counter(), time.process_time(), self._children()

    @staticmethod
    def _children() -> float:
        t = os.times()
        return t.children_user + t.children_system

    def record(self, **fields) -> str:
        """A JSON line of ``fields``, the worker, and the seconds spent since."""
        return json.dumps({**fields, "worker": os.environ.get("PYTEST_XDIST_WORKER", ""), "end": round(time.time(), 1),
                           "wall": round(time.perf_counter() - self.start, 2),
                           "cpu": round(time.process_time() - self.cpu, 2),
                           "child_cpu": round(self._children() - self.children, 2)}) + "\n"


@pytest.fixture(autouse=True)
def _library_level(request, monkeypatch):
    """``@pytest.mark.library_level``: npbrs's programs compile at the library's LLVM level (1)
    rather than the suite's 0, which ``npbrs.domains.util.compiling`` reads from ``XLA_FLAGS`` at each
    call. (The level set in ``XLA_FLAGS`` by whoever runs the suite is left alone.) Measured on
    two cores, cold, one process: the four files with marked tests (reproduction, control, IRL,
    greedy) took 86.5 CPU-seconds instead of 103.5. Every program at level 1 is no choice: the
    whole suite took 504 s instead of 352 s so."""
    if _LEVEL_SET_HERE and request.node.get_closest_marker("library_level"):
        flags = " ".join(f for f in os.environ["XLA_FLAGS"].split() if "xla_backend_optimization_level" not in f)
        monkeypatch.setenv("XLA_FLAGS", flags)
    yield


@pytest.fixture(autouse=True)
def _compile_log(request):
    """With ``NPBRS_TEST_COMPILE_LOG=FILE``: append, per test, the seconds JAX spent tracing and
    compiling, the number of programs compiled (cache hits are not compiles), the name and
    seconds of each program that took at least half a second to compile, and the CPU-seconds
    of the process (all its threads) and of the subprocesses it waited for, as a JSON line, to
    find what makes the suite slow (its two workers share two cores, so CPU-seconds, not wall
    time, say what a test costs the suite)."""
    path = os.environ.get(COMPILE_LOG_ENV)
    if not path:
        yield
        return
    from jax._src.dispatch import BACKEND_COMPILE_EVENT, JAXPR_TRACE_EVENT

    seen = {"compile": 0.0, "trace": 0.0, "programs": 0}
    slow = []  # (name, seconds) of the programs that took at least half a second to compile

    def listen(event, duration, fun_name="", **_):
        if event == BACKEND_COMPILE_EVENT:
            seen["compile"] += duration
            seen["programs"] += 1
            if duration >= 0.5:
                slow.append((fun_name, round(duration, 2)))
        elif event == JAXPR_TRACE_EVENT:
            seen["trace"] += duration

    jax.monitoring.register_event_duration_secs_listener(listen)
    usage = _Usage()
    try:
        yield
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
        with open(path, "a") as f:
            f.write(usage.record(test=request.node.nodeid, **{k: round(v, 2) for k, v in seen.items()}, slow=slow))


@pytest.fixture(autouse=True, scope="module")
def _module_log(request):
    """With ``NPBRS_TEST_COMPILE_LOG``: a line per module with its wall and CPU seconds, its
    module fixtures (e.g. the notebooks' kernels, the four-device subprocess) included."""
    path = os.environ.get(COMPILE_LOG_ENV)
    if not path:
        yield
        return
    usage = _Usage()
    yield
    with open(path, "a") as f:
        f.write(usage.record(module=request.module.__name__))


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    try:
        import resource
    except ImportError:  # not Unix
        return
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2
    workers = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024 ** 2
    terminalreporter.write_line(f"npbrs: peak memory of the test process {own:.2f} GB, of its largest finished "
                                f"child process {workers:.2f} GB")


@pytest.fixture
def no_compilation(monkeypatch):
    """Fail if a fit gets as far as compiling the sampler: for checks that must come first."""
    from npbrs.inference.driver.compiled import Compiled

    def refuse(*args, **kwargs):
        raise AssertionError("compiled before checking the input")

    monkeypatch.setattr(Compiled, "init", refuse)
    monkeypatch.setattr(Compiled, "step", refuse)


def run_main(argv):
    """(exit code, stdout, stderr) of ``npbrs ARGV``, in this process (compiled kernels are shared)."""
    import contextlib
    import io

    from npbrs.inference.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main([str(a) for a in argv])
        except SystemExit as e:
            code = e.code
    return code, out.getvalue(), err.getvalue()
