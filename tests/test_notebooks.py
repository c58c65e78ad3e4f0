"""The notebooks run from top to bottom without an error, under their tiny settings
(``NPBRS_NOTEBOOK_QUICK=1``: a few short trajectories, one chain, a few sweeps).

Both notebooks run at once, each in its own kernel: nearly all of their time is the sampler's
compilation, which uses one core, so two kernels take the time of one. The kernels inherit the
test processes' cheaper compilation (``conftest.py``'s XLA flags: it only slows the few sweeps a
tiny run makes), and each kernel compiles into a folder
of its own in the test session's persistent compilation cache (``conftest.py``), so a second
run compiles nothing.
"""

import asyncio
import os
from pathlib import Path

import jax
import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = ("quickstart.ipynb", "bring_your_own_mdp.ipynb")
FOLDER = Path(__file__).resolve().parent.parent / "notebooks"
TIMEOUT = 300  # seconds for a whole notebook (and for any one cell)


def _kernel_env(tmp: Path, name: str) -> dict:
    # (XLA_FLAGS, with the test processes' compile flags, comes from conftest.py through os.environ)
    env = dict(os.environ, NPBRS_NOTEBOOK_QUICK="1", TMPDIR=str(tmp), MPLBACKEND="Agg")
    cache = jax.config.jax_compilation_cache_dir
    if cache:
        # a folder per notebook: the kernels run at once, and JAX writes an entry in place, so
        # one kernel could read the other's half-written program (a kernel died so, once)
        env.update(JAX_COMPILATION_CACHE_DIR=os.path.join(cache, name.removesuffix(".ipynb")),
                   JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0.5", JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0")
    return env


async def _execute(name: str, tmp: Path):
    """The executed notebook, or the exception that stopped it."""
    work = tmp / name.removesuffix(".ipynb")
    work.mkdir()
    nb = nbformat.read(FOLDER / name, as_version=4)
    client = NotebookClient(nb, timeout=TIMEOUT, kernel_name="python3", resources={"metadata": {"path": str(work)}})
    try:
        await asyncio.wait_for(client.async_execute(env=_kernel_env(work, name)), TIMEOUT)
    except asyncio.TimeoutError:
        return TimeoutError(f"{name} did not finish in {TIMEOUT} s")
    except Exception as e:  # a cell's error (CellExecutionError) or a kernel that died
        return e
    return nb


@pytest.fixture(scope="module")
def executed(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("notebooks")

    async def both():
        return await asyncio.gather(*(_execute(name, tmp) for name in NOTEBOOKS))

    return dict(zip(NOTEBOOKS, asyncio.run(both())))


def test_the_notebooks_are_committed_without_outputs():
    for name in NOTEBOOKS:
        nb = nbformat.read(FOLDER / name, as_version=4)
        nbformat.validate(nb)
        for cell in nb.cells:
            if cell.cell_type == "code":
                assert not cell.outputs and cell.execution_count is None, f"{name}: outputs not cleared"


@pytest.mark.parametrize("name", NOTEBOOKS)
def test_the_notebook_runs_without_error(executed, name):
    nb = executed[name]
    if isinstance(nb, BaseException):
        raise nb
    code = [cell for cell in nb.cells if cell.cell_type == "code"]
    errors = [out for cell in code for out in cell.outputs if out.output_type == "error"]
    assert not errors, f"{name}: {errors[0].ename}: {errors[0].evalue}"
    assert all(cell.execution_count is not None for cell in code)  # every cell ran


@pytest.mark.parametrize("name", NOTEBOOKS)
def test_the_executed_copies_are_current_and_show_their_results(name):
    """``notebooks/executed/`` (``python notebooks/build.py``) holds each notebook run with its
    full settings: the same cells as the source (rebuild after editing a notebook), every code
    cell ran in order without an error, and the pictures are there."""
    path = FOLDER / "executed" / name
    assert path.exists(), f"{path} is missing: run python notebooks/build.py"
    source = nbformat.read(FOLDER / name, as_version=4)
    built = nbformat.read(path, as_version=4)
    nbformat.validate(built)
    assert [(c.cell_type, c.source) for c in built.cells] == [(c.cell_type, c.source) for c in source.cells], \
        f"{path} is stale: its cells differ from notebooks/{name}; run python notebooks/build.py {name}"
    code = [cell for cell in built.cells if cell.cell_type == "code"]
    assert [cell.execution_count for cell in code] == list(range(1, len(code) + 1)), f"{path}: not run in order"
    errors = [out for cell in code for out in cell.outputs if out.output_type == "error"]
    assert not errors, f"{path}: {errors[0].ename}: {errors[0].evalue}"
    pictures = [out for cell in code for out in cell.outputs if "image/png" in out.get("data", {})]
    assert pictures, f"{path}: no picture in the outputs"
    assert "npbrs_build" in built.metadata, f"{path}: not written by notebooks/build.py"
