"""ArviZ, imported where npbrs needs it (never at npbrs's own import).

ArviZ 0.23 writes a once-a-day stamp file in the user's cache folder when it is imported, through
a temporary file of a fixed name: two processes that import it at the same moment on the day's
first import (parallel test workers, several ``npbrs`` runs finishing together, a fresh machine)
race, and the loser's import fails with ``FileNotFoundError`` from the rename. The winner has then
written the stamp, so importing again succeeds: :func:`arviz` does that.

The same import warns, once a day, that ArviZ 1 will change its interface (a ``FutureWarning``
printed in the middle of ``npbrs demo``'s report). npbrs keeps ArviZ below 1, so that warning
is not its user's concern: it is silenced for npbrs's import only (``warnings.catch_warnings``
restores the filters); a user who imports ArviZ first still sees it.
"""

from __future__ import annotations

import sys
import time
import warnings

__all__ = ["arviz"]


def arviz(attempts: int = 5):
    """The ``arviz`` module, its import retried (after a short pause) when another process's
    concurrent import of the same day made it fail on the stamp file."""
    for attempt in range(attempts):
        try:
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", message=r"\s*ArviZ is undergoing a major refactor",
                                        category=FutureWarning)
                import arviz as az

            return az
        except FileNotFoundError:
            sys.modules.pop("arviz", None)
            if attempt == attempts - 1:
                raise
            time.sleep(0.05 * (attempt + 1))
