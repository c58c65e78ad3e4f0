"""Execute the notebooks with their full settings and keep copies with their outputs.

The notebooks in this folder are committed without outputs (small diffs; the tests run them
with tiny settings). This script runs each one top to bottom, as a reader would, and writes the
executed copy, pictures and tables included, to ``notebooks/executed/NAME.ipynb`` (GitHub and
Jupyter show it as it is), with the wall time in its metadata:

    python notebooks/build.py                 # both notebooks
    python notebooks/build.py quickstart.ipynb
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

FOLDER = Path(__file__).resolve().parent
NOTEBOOKS = ("quickstart.ipynb", "bring_your_own_mdp.ipynb")


def build(name: str, out: Path, timeout: int = 3600) -> float:
    """Execute one notebook into ``out / name``; returns the seconds it took."""
    import nbformat
    from nbclient import NotebookClient

    nb = nbformat.read(FOLDER / name, as_version=4)
    work = Path(tempfile.mkdtemp(prefix="npbrs-notebook-"))
    env = {k: v for k, v in os.environ.items() if k != "NPBRS_NOTEBOOK_QUICK"}
    env["MPLBACKEND"] = "Agg"
    start = time.perf_counter()
    NotebookClient(nb, timeout=timeout, kernel_name="python3", resources={"metadata": {"path": str(work)}}).execute(
        env=env)
    wall = time.perf_counter() - start
    nb.metadata["npbrs_build"] = {"wall_time_s": round(wall, 1), "cores": os.cpu_count(),
                                  "built": time.strftime("%Y-%m-%d")}
    out.mkdir(parents=True, exist_ok=True)
    nbformat.write(nb, out / name)
    return wall


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    p.add_argument("notebooks", nargs="*", default=list(NOTEBOOKS), help="which notebooks (default: all)")
    p.add_argument("--out", default=str(FOLDER / "executed"), help="where the executed copies go")
    args = p.parse_args(argv)
    for name in args.notebooks:
        if name not in NOTEBOOKS:
            p.error(f"unknown notebook {name!r}; expected one of {', '.join(NOTEBOOKS)}")
        wall = build(name, Path(args.out))
        print(f"{name}: executed in {wall:.0f} s -> {Path(args.out) / name}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
