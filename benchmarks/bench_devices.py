"""A sweep's time on 4 devices against 1: the trajectories of one chain sharded over CPU host devices.

Each layout runs in a process of its own, since JAX reads ``XLA_FLAGS`` once:
``--xla_force_host_platform_device_count=4`` splits the machine's CPU into 4 "devices" that
share its cores (on a 2-core machine they can only take turns: expect no speed-up; the figure
says what the partitioning costs, collectives included). In each: highway, N = 1024 trajectories
of ``--length`` steps, 1 chain, the reward emission (``fit``'s default) with the greedy moves off
(plain Gibbs sweeps), ``fit`` twice in the process: the first compiles, the second (the same
shapes: nothing compiles) is timed, ``sweep_s`` = its wall time (its start included) / its sweeps. The 4-device run is
``fit(..., devices=4)``: 1 chain, so the 4 devices shard the trajectories (256 each).

    python benchmarks/bench_devices.py [--length 100] [--sweeps 8] [--json benchmarks/results/bench_devices.json]

Writes ``devices4_ratio`` = sweep_s on 4 devices / sweep_s on 1 (below 1: faster), each run's
figures, whether the two runs' draws agree (the same segmentation; the log joints' largest
relative difference), and the load average around each run.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from datetime import datetime, timezone

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from runinfo import run_info  # noqa: E402

CHILD = r"""
import json, os, sys, time
import numpy as np
devices, length, sweeps, out = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
import jax
from npbrs.domains import generate_demonstrations, highway
from npbrs.inference import fit

assert jax.device_count() == devices, jax.devices()
dom = highway()
demos = generate_demonstrations(dom, num_trajectories=1024, length=length, seed=0)
config = {"moves": {"greedy_merge": 0, "greedy_split": 0}}
kw = dict(num_chains=1, num_warmup=sweeps // 2, num_samples=sweeps - sweeps // 2, seed=0, progress_bar=False,
          **({"devices": devices} if devices > 1 else {}))
load = os.getloadavg()[0]
t = time.perf_counter()
fit(dom.mdp, demos, config, **kw)
first = time.perf_counter() - t
load_mid = os.getloadavg()[0]
t = time.perf_counter()
result = fit(dom.mdp, demos, config, **kw)
second = time.perf_counter() - t
np.savez(out, log_joint=result.stats["log_joint"], segmentation=np.concatenate(result.segmentation))
print(json.dumps({"devices": devices, "first_fit_s": round(first, 2), "timed_fit_s": round(second, 2),
                  "sweep_s": round(second / sweeps, 3), "skills": int(result.num_skills),
                  "load_before": round(load, 2), "load_mid": round(load_mid, 2),
                  "load_after": round(os.getloadavg()[0], 2)}))
"""


def run(devices: int, length: int, sweeps: int, out: str) -> dict:
    env = dict(os.environ, NPBRS_CACHE_DIR="off")
    flags = env.get("XLA_FLAGS", "")
    env["XLA_FLAGS"] = (flags + f" --xla_force_host_platform_device_count={devices}").strip()
    done = subprocess.run([sys.executable, "-c", CHILD, str(devices), str(length), str(sweeps), out], env=env,
                          capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"the {devices}-device run failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def compare(length: int, sweeps: int, base: str, log=print) -> dict:
    """Both runs (1 and 4 devices) with their draws written next to ``base``: each run's figures,
    ``devices4_ratio``, ``same_segmentation`` and ``log_joint_max_rel_diff``."""
    import numpy as np

    out = {}
    for devices in (1, 4):
        t = time.perf_counter()
        out[f"devices{devices}"] = run(devices, length, sweeps, f"{base}.draws{devices}.npz")
        log(f"{devices} device(s): {out[f'devices{devices}']} ({time.perf_counter() - t:.0f} s)")
    out["devices4_ratio"] = round(out["devices4"]["sweep_s"] / out["devices1"]["sweep_s"], 3)
    one, four = (np.load(f"{base}.draws{d}.npz") for d in (1, 4))
    out["same_segmentation"] = bool(np.array_equal(one["segmentation"], four["segmentation"]))
    out["log_joint_max_rel_diff"] = float(np.max(np.abs(one["log_joint"] - four["log_joint"])
                                                 / np.abs(one["log_joint"])))
    for d in (1, 4):
        os.remove(f"{base}.draws{d}.npz")
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--length", type=int, default=100, help="steps per trajectory (N = 1024)")
    p.add_argument("--sweeps", type=int, default=8, help="sweeps of the timed fit")
    p.add_argument("--json", default=os.path.join(os.path.dirname(__file__), "results", "bench_devices.json"))
    p.add_argument("--note", default="", help="what else was running on the machine")
    args = p.parse_args(argv)
    out = {"meta": {**run_info(), "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                    "machine": platform.platform(), "cpus": os.cpu_count(), "trajectories": 1024,
                    "length": args.length, "sweeps": args.sweeps, "note": args.note}}
    out.update(compare(args.length, args.sweeps, os.path.splitext(args.json)[0], lambda m: print(m, flush=True)))
    print(f"sweep time on 4 host devices / on 1: {out['devices4_ratio']}; same segmentation: "
          f"{out['same_segmentation']}, log joints within {out['log_joint_max_rel_diff']:.1e} (relative)")
    os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
    with open(args.json, "w") as f:
        json.dump(out, f, indent=2)
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
