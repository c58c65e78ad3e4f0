"""Atomic file writes: a temporary file in the target's directory, then a rename."""

import os
import tempfile

import numpy as np

__all__ = ["atomic_write", "atomic_savez"]


def atomic_write(path, write, suffix: str = ".tmp") -> None:
    """Call ``write(temporary_path)``, then rename the temporary file to ``path``.

    The temporary file lives in ``path``'s directory (a rename across file systems is not
    atomic) and is removed if ``write`` fails or is interrupted.
    """
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(dir=directory, prefix="." + os.path.basename(path) + "-", suffix=suffix)
    os.close(fd)
    try:
        write(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def atomic_savez(path, arrays: dict) -> None:
    """Write ``arrays`` as an ``.npz`` file at exactly ``path`` (no ``.npz`` appended), atomically."""

    def write(tmp):
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)

    atomic_write(path, write, suffix=".npz.tmp")
