"""What each benchmark records about how its result was made: the command line and the machine.

    from runinfo import run_info  # (the scripts' own folder is on ``sys.path`` when they run)
    out = {"meta": {**run_info(), ...}}
"""

from __future__ import annotations

import os
import platform
import sys


def processor() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else what :mod:`platform` knows of it."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def run_info() -> dict:
    """``command`` (this process's command line), ``platform``, ``processor``, ``cores`` (CPUs the
    machine has) and ``cores_usable`` (those this process may run on), ``python``."""
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"command": " ".join(["python", *sys.argv]), "platform": platform.platform(), "processor": processor(),
            "cores": os.cpu_count(), "cores_usable": usable, "python": platform.python_version()}
