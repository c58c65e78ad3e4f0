"""Progress shown while a fit runs, and warnings that name the user's own call."""

from __future__ import annotations

import os
import sys
import time
from typing import Optional

import numpy as np

__all__ = ["Progress", "latest_log_joint", "interactive", "user_stacklevel"]


def user_stacklevel() -> int:
    """``warnings.warn``'s stacklevel, called where the warning is raised, that names the first
    frame outside npbrs: the user's own call of ``fit`` (however many of npbrs's functions and
    wrappers lie between), not a line of npbrs's."""
    import npbrs.domains
    import npbrs.inference
    import npbrs.models

    roots = tuple(os.path.dirname(os.path.abspath(m.__file__)) + os.sep
                  for m in (npbrs.domains, npbrs.models, npbrs.inference))
    frame, level = sys._getframe(1), 1
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(roots):
        frame, level = frame.f_back, level + 1
    return level



class Progress:
    """Sweeps done, shown while a fit runs: one unit is a sweep of every chain.

    The clock runs from the start of the run; the first sweep compiles the sampler, so it is
    shown as "compiling" and left out of the rate: the time left comes from the sweeps after
    it. In a terminal or a notebook this is a tqdm bar; when the output is not a terminal (a
    log file, CI), a plain line every ``total / 10`` sweeps instead of carriage returns.

    Args:
        total: the sweeps (of each chain) to run; initial: those done already (a resumed run).
        enabled: show anything; stream: where (standard error); chains: the run's chains.
    """

    FORMAT = "{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} sweeps [{elapsed}{postfix}]"

    def __init__(self, total: int, initial: int, enabled: bool, stream=None, chains: int = 1):
        self.total, self.n, self.enabled, self.chains = int(total), int(initial), bool(enabled), int(chains)
        self.stream = sys.stderr if stream is None else stream
        self.phase, self.postfix = "compiling", ""
        self.timed_from = None  # (time, sweeps) after the first sweep
        self.bar = None
        self.plain = self.enabled and not interactive(self.stream)
        self.every = max(1, self.total // 10)
        of_each = f" of each of {self.chains} chains" if self.chains > 1 else ""
        if self.enabled and not self.plain:
            from tqdm.auto import tqdm

            self.bar = tqdm(total=total, initial=initial, dynamic_ncols=True, leave=True, smoothing=0,
                            file=self.stream, bar_format=self.FORMAT)
            self.bar.set_description("compiling the sampler", refresh=True)
        elif self.plain:
            self._line(f"compiling the sampler (the first sweep); {self.total - self.n} sweeps{of_each} to run")

    def _line(self, text):
        print(f"npbrs fit: {text}", file=self.stream, flush=True)

    def _left(self) -> str:
        """The time left, from the sweeps after the first ("" before them)."""
        if self.timed_from is None or self.n <= self.timed_from[1]:
            return ""
        t0, n0 = self.timed_from
        rate = (time.perf_counter() - t0) / (self.n - n0)
        return f"about {rate * (self.total - self.n):.0f} s left"

    def _refresh_postfix(self):
        if self.bar is not None:
            self.bar.set_postfix_str(", ".join(x for x in (self._left(), self.postfix) if x), refresh=False)

    def set_phase(self, phase: str):
        self.phase = phase
        if self.bar is not None and self.timed_from is not None:
            self.bar.set_description(phase, refresh=False)

    def set_postfix(self, text: str):
        self.postfix = text
        self._refresh_postfix()

    def update(self, k: int = 1):
        self.n += k
        now = time.perf_counter()
        if self.timed_from is None:  # the first sweep: compiled; the rate is timed from here
            self.timed_from = (now, self.n)
            if self.bar is not None:
                self.bar.set_description(self.phase, refresh=False)
                self.bar.update(k)
            elif self.plain:
                self._line(f"compiled; sweep {self.n}/{self.total} ({self.phase})")
            return
        if self.bar is not None:
            self._refresh_postfix()
            self.bar.update(k)
        elif self.plain and (self.n % self.every == 0 or self.n >= self.total):
            t0, n0 = self.timed_from
            rate = (now - t0) / max(self.n - n0, 1)
            self._line(f"sweep {self.n}/{self.total} ({self.phase}), {rate:.2f} s per sweep, "
                       f"about {rate * (self.total - self.n):.0f} s left" + (f", {self.postfix}" if self.postfix else ""))

    def extend(self, total: int):
        """More sweeps to run than first planned (a run extended until convergence)."""
        self.total = int(total)
        self.every = max(1, self.total // 10)
        if self.bar is not None:
            self.bar.total = self.total
            self.bar.refresh()

    def close_done(self, sweeps: int, seconds: float):
        """Close with the sweeps each chain has run and the run's wall time."""
        each = f" of each of {self.chains} chains" if self.chains > 1 else ""
        self.close(f"done: {sweeps} sweeps{each} in {seconds:.1f} s")

    def close(self, message: str = ""):
        if self.bar is not None:
            self.bar.close()
        elif self.plain and message:
            self._line(message)
        self.enabled = self.plain = False
        self.bar = None


def latest_log_joint(records) -> Optional[float]:
    """The best chain's log joint after the sweep that gave ``records`` (a dict batched over
    chains, or a list of one chain's each), for the progress line; None where the records have
    none, or where their arrays live partly on other processes' devices (a multi-host run)."""
    values = [r.get("log_joint") for r in (records if isinstance(records, list) else [records])]
    if any(v is None or not getattr(v, "is_fully_addressable", True) for v in values):
        return None
    return float(max(np.max(np.asarray(v)) for v in values))


def interactive(stream) -> bool:
    """A terminal, or a notebook (where tqdm draws a widget)."""
    try:
        if stream.isatty():
            return True
    except (AttributeError, ValueError):
        pass
    ipython = sys.modules.get("IPython")  # a notebook kernel: IPython is loaded and runs a kernel app
    shell = getattr(ipython, "get_ipython", lambda: None)() if ipython is not None else None
    return shell is not None and "IPKernelApp" in getattr(shell, "config", {})

