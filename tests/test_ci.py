"""The test run itself: under CI it compiles into an empty cache of its own, as a new machine
does, and compiled programs are released so that the process's memory mappings stay bounded."""

import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp

from conftest import _ACCEPTS_ENV, CACHE_ENV, LONGEST_FIRST, _xla_accepts, check_fresh_cache, map_count

ROOT = Path(__file__).resolve().parents[1]


def test_ci_refuses_a_compilation_cache_shared_with_earlier_runs(tmp_path):
    empty, used = tmp_path / "empty", tmp_path / "used"
    empty.mkdir()
    used.mkdir()
    (used / "jit_sweep-0123-cache").write_bytes(b"x")
    assert check_fresh_cache({}, str(used)) == ""  # a developer's run may reuse its cache
    assert check_fresh_cache({"CI": "true", CACHE_ENV: str(empty)}, str(empty)) == ""
    assert "not set" in check_fresh_cache({"CI": "true"}, str(empty))
    assert "1 entries from an earlier run" in check_fresh_cache({"CI": "true", CACHE_ENV: str(used)}, str(used))


def test_the_suites_xla_flags_are_asked_of_xla_itself(monkeypatch):
    """A flag XLA does not know aborts the process (jaxlib 0.12 aborts on a flag whose name is
    still in its binaries), so the suite's optional flag is tried in a subprocess first; the
    answer is kept for the workers."""
    monkeypatch.setenv(_ACCEPTS_ENV, "+xla_backend_optimization_level=0")
    assert not _xla_accepts("xla_npbrs_no_such_flag=1")  # (the accepted case: every run of this suite)
    assert os.environ[_ACCEPTS_ENV] == "+xla_backend_optimization_level=0 -xla_npbrs_no_such_flag=1"
    # several at once: one subprocess; refused together, nothing is recorded (each is asked alone)
    assert not _xla_accepts("xla_backend_optimization_level=1", "xla_npbrs_other_flag=1")
    assert os.environ[_ACCEPTS_ENV] == "+xla_backend_optimization_level=0 -xla_npbrs_no_such_flag=1"
    monkeypatch.setattr("subprocess.run", None)  # from the record now, no subprocess
    assert not _xla_accepts("xla_npbrs_no_such_flag=1") and _xla_accepts("xla_backend_optimization_level=0")
    assert not _xla_accepts("xla_backend_optimization_level=0", "xla_npbrs_no_such_flag=1")


def test_a_ci_run_with_a_used_cache_stops_before_any_test(tmp_path):
    (tmp_path / "jit_sweep-0123-cache").write_bytes(b"x")
    env = {**os.environ, "CI": "true", CACHE_ENV: str(tmp_path)}
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-n", "0", "-p", "no:cacheprovider",
                           "tests/test_mdp.py"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 4, proc.stdout[-2000:] + proc.stderr[-2000:]  # pytest's usage error
    assert "earlier run" in proc.stdout + proc.stderr


def test_clearing_jax_caches_releases_the_memory_mappings_of_compiled_programs():
    # what tests/conftest.py relies on after each module: ~20 mappings per compiled program
    before = map_count()
    fns = [jax.jit(lambda x, i=i: jnp.cumsum(x) * i) for i in range(30)]
    for i, f in enumerate(fns):
        f(jnp.ones(i + 1)).block_until_ready()
    grown = map_count()
    jax.clear_caches()
    assert grown - before > 150, (before, grown)
    assert map_count() < before + 0.3 * (grown - before), (before, grown, map_count())


def test_the_code_passes_the_linter():
    """ruff with the project's rule set (pyproject.toml: pyflakes and syntax errors) finds
    nothing in the library, the tests and the benchmarks."""
    import shutil

    ruff = shutil.which("ruff") or os.path.join(os.path.dirname(sys.executable), "ruff")
    assert os.path.exists(ruff), "ruff is missing: it is in the test extras (pip install -e '.[test]')"
    proc = subprocess.run([ruff, "check", "--no-cache", "."], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]


def test_the_files_scheduled_first_exist_and_the_workers_keep_their_order():
    """conftest.py's LONGEST_FIRST names test files (a renamed file would silently lose its
    place), and pytest's options keep xdist from reordering the files by their test counts."""
    folder = Path(__file__).resolve().parent
    missing = [name for name in LONGEST_FIRST if not (folder / name).is_file()]
    assert not missing, f"conftest.LONGEST_FIRST names files that do not exist: {missing}"
    assert len(set(LONGEST_FIRST)) == len(LONGEST_FIRST)
    text = (folder.parent / "pyproject.toml").read_text()
    assert "--dist loadfile" in text and "--no-loadscope-reorder" in text
