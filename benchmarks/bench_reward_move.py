"""What solving only the skills with steps saves in the reward move (one MALA sweep of the
reward emission) and in a whole fit, against solving every slot, in the same process.

The reward move's solves cost about their batch size times one skill's on MDPs with many
(state, action) entries (``npbrs.models.reward.mala.BATCH_ENTRIES``): there the kernel
solves only the active skills, ``chunk_size`` at a time. The reference run sets
``BATCH_ENTRIES`` so high that every slot is solved at once: the same draws for the active
skills, up to the solver's tolerance.

For each domain (highway: 1080 states x 3 actions; quadcopter: 11664 x 4), it times

- ``update``: the reward emission's update (``mala_steps`` MALA steps after the start's
  solve) jitted, on 16 x 500 demonstrations with 3 active skills of ``max_skills`` 8, the median
  of 10 calls after the first (compiled) one;
- ``fit`` (``--fit``): a default 2-chain fit of 8 x 128 steps (20 + 20 sweeps), the seconds per
  sweep with compilation taken out (JAX's monitoring events).

Prints each figure for both settings and their ratio, and writes them, with the command and the
machine, to ``--json PATH`` (default ``benchmarks/results/bench_reward_move.json``).
Times are absolute seconds under whatever else runs on the machine; say what that was
(``--note``).

    python benchmarks/bench_reward_move.py [--fit] [--json PATH] [--note "..."]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from datetime import datetime, timezone

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from runinfo import run_info  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--json", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "bench_reward_move.json"),
                   help="write the figures here (JSON; default: benchmarks/results/bench_reward_move.json)")
    p.add_argument("--fit", action="store_true", help="also time a whole tiny highway fit per setting")
    p.add_argument("--domains", default="highway,quadcopter")
    p.add_argument("--note", default="", help="what else was running on the machine")
    args = p.parse_args(argv)
    os.environ["NPBRS_CACHE_DIR"] = "off"  # each setting compiles its own program

    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax._src.dispatch import BACKEND_COMPILE_EVENT, JAXPR_TO_MLIR_MODULE_EVENT, JAXPR_TRACE_EVENT

    from npbrs.domains import generate_demonstrations
    from npbrs.domains.registry import get_domain
    from npbrs.inference import fit
    from npbrs.models.reward import mala as reward_mala
    from npbrs.inference.sampler.kernel import skill_weights
    from npbrs.models.emissions import HMMData
    from npbrs.models.reward.emission import RewardEmission

    default_entries = reward_mala.BATCH_ENTRIES
    settings = {"active only": default_entries, "every slot": 10 ** 12}
    out = {"meta": {**run_info(), "date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "jax": jax.__version__,
                    "machine": platform.platform(), "cpus": os.cpu_count(), "note": args.note}}

    for name in [d for d in args.domains.split(",") if d]:
        domain = get_domain(name)
        demos = generate_demonstrations(domain, num_trajectories=16, length=500, seed=0)
        with jax.enable_x64(True):
            data = HMMData.from_demonstrations(demos)
            mask = data.mask
            K = 8
            z = jnp.where(mask, jnp.asarray(np.stack(_pad(demos.skills, mask.shape[1]))), -1)
            weights = skill_weights(z, mask, K)
            row = {"active_skills": int(jnp.sum(jnp.sum(weights, axis=(0, 1)) > 0)), "max_skills": K}
            for label, entries in settings.items():
                reward_mala.BATCH_ENTRIES = entries
                em = RewardEmission(domain.mdp)
                params = em.init_params(jax.random.PRNGKey(0), data, weights)
                cache = em.init_cache(K)
                update = jax.jit(lambda key, p, c: em.update(key, p, c, data, weights, False))
                jax.block_until_ready(update(jax.random.PRNGKey(1), params, cache))
                times = []
                for i in range(10):
                    t = time.perf_counter()
                    jax.block_until_ready(update(jax.random.PRNGKey(2 + i), params, cache))
                    times.append(time.perf_counter() - t)
                row[f"update_ms[{label}]"] = round(1000 * statistics.median(times), 2)
            reward_mala.BATCH_ENTRIES = default_entries
            row["update_ratio"] = round(row["update_ms[every slot]"] / row["update_ms[active only]"], 2)
        print(name, row, flush=True)
        out[name] = row

    if args.fit:
        compiling = [0.0]

        def listen(event, duration, **_):
            if event in (BACKEND_COMPILE_EVENT, JAXPR_TRACE_EVENT, JAXPR_TO_MLIR_MODULE_EVENT):
                compiling[0] += duration

        jax.monitoring.register_event_duration_secs_listener(listen)
        domain = get_domain("highway")
        demos = generate_demonstrations(domain, num_trajectories=8, length=128, seed=0)
        row = {}
        import importlib
        fit_module = importlib.import_module("npbrs.inference.driver.fit")
        for label, entries in settings.items():
            reward_mala.BATCH_ENTRIES = entries
            fit_module._COMPILED.clear()  # fit's programs of the other setting: compile this one anew
            jax.clear_caches()
            compiling[0] = 0.0
            t = time.perf_counter()
            result = fit(domain.mdp, demos, num_chains=2, num_warmup=20, num_samples=20, seed=0, progress_bar=False)
            total = time.perf_counter() - t
            row[f"fit_s[{label}]"] = round(total, 2)
            row[f"fit_compile_s[{label}]"] = round(compiling[0], 2)
            row[f"sweep_ms[{label}]"] = round(1000 * (total - compiling[0]) / 40, 1)
            row[f"skills[{label}]"] = int(result.num_skills)
        reward_mala.BATCH_ENTRIES = default_entries
        row["sweep_ratio"] = round(row["sweep_ms[every slot]"] / row["sweep_ms[active only]"], 2)
        print("tiny highway fit", row, flush=True)
        out["tiny_fit"] = row

    if args.json:
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
    return 0


def _pad(rows, T):
    import numpy as np
    return [np.pad(np.asarray(r), (0, T - len(r)), constant_values=-1) for r in rows]


if __name__ == "__main__":
    raise SystemExit(main())
