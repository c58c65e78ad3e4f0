"""The forward filter's cost against a log-space reference, alone and inside whole sweeps.

``npbrs.models.hmm.forward_filter`` runs in probability space: the likelihoods are
exponentiated for all steps at once and the loop holds no exponential, only each step's
normaliser's logarithm. The reference here is the same recursion written plainly in log space
(a baseline for timing, not a second implementation the library uses):

- ``--part filter``: N trajectories x T steps x K skills (default 400 x 500 x 8: the benchmark
  grid's 200 trajectories, 2 chains), the log marginal alone (what the feature Gibbs step and
  the log joint need) and with the filtered probabilities (what backward sampling needs);
  median of ``--repeats`` calls of each, interleaved, and the largest differences between the two;
- ``--part sweep``: ``fit``'s defaults (2 chains, ``--sweeps`` + ``--sweeps``) on a world of
  ``npbrs.domains.worlds`` (default ``tabular_grid``: 200 x 500 steps), once with the
  reference filter swapped into ``npbrs.models.hmm`` and once with the library's, twice each,
  in one process (caches cleared between); the median sweep of each kind (plain warmup, greedy,
  sampling), compilation left out.

Prints the times and the ratios library / reference, and writes them with the load average
before and after, the command and the machine to ``--json PATH`` (default
``benchmarks/results/bench_filter.json``).

    python benchmarks/bench_filter.py [--part filter,sweep] [--json PATH] [--note "what ran"]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from runinfo import processor, run_info  # noqa: E402

os.environ.setdefault("NPBRS_CACHE_DIR", "off")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402


def reference_filter(log_init, log_trans, log_lik, mask=None, active=None, gate=None):
    """A log-space forward filter, for timing: the prediction a matrix product in probability
    space, everything else in logs."""
    from npbrs.models.hmm import NEG_LOG, _prepare, _prepare_lik

    if gate is not None:
        raise ValueError("the reference filter has no gate")
    log_lik = jnp.asarray(log_lik)
    T, K = log_lik.shape
    mask = jnp.ones(T, dtype=bool) if mask is None else jnp.asarray(mask, dtype=bool)
    active, log_trans, log_init = _prepare(jnp.asarray(log_init), jnp.asarray(log_trans), active)
    log_lik = _prepare_lik(log_lik, active)
    shift = jnp.max(log_trans, axis=0)
    trans = jnp.exp(log_trans - shift)
    tiny = jnp.finfo(log_lik.dtype).tiny

    def step(carry, inputs):
        log_pred, last_filt, total = carry
        ll, real = inputs
        joint = log_pred + ll
        log_c = jax.nn.logsumexp(joint)
        filt = joint - log_c
        pred_next = jnp.where(active, jnp.log(jnp.maximum(jnp.exp(filt) @ trans, tiny)) + shift, NEG_LOG)
        return ((jnp.where(real, pred_next, log_pred), jnp.where(real, filt, last_filt),
                 total + jnp.where(real, log_c, 0.0)), jnp.where(real, filt, last_filt))

    (_, _, log_marginal), log_alpha = jax.lax.scan(step, (log_init, log_init, jnp.zeros((), log_lik.dtype)),
                                                   (log_lik, mask))
    return log_marginal, log_alpha


def _load():
    return round(os.getloadavg()[0], 2)


def part_filter(N: int, T: int, K: int, repeats: int) -> dict:
    from npbrs.models import hmm

    rng = np.random.default_rng(0)
    with jax.enable_x64(True):  # the library's precision, here for the inputs too
        ll = jnp.asarray(rng.normal(size=(N, T, K)) * 2 - 1.5)
        active = jnp.asarray(rng.random((N, K)) < 0.6).at[:, 0].set(True)
        log_trans = jnp.log(jnp.asarray(rng.gamma(1.0, size=(N, K, K)) + 10 * np.eye(K)))
        mask = jnp.ones((N, T), bool)

        def batched(filter_fn):
            return jax.vmap(lambda lt, l, a: filter_fn(jnp.zeros(K), lt, l, mask[0], a))

        fns = {}
        for name, fn in (("reference", reference_filter), ("library", hmm.forward_filter)):
            fns[f"{name}_marginal"] = jax.jit(lambda lt, l, a, f=batched(fn): f(lt, l, a)[0])
            fns[f"{name}_filtered"] = jax.jit(batched(fn))
        times = {k: [] for k in fns}
        for f in fns.values():
            jax.block_until_ready(f(log_trans, ll, active))
        load = _load()
        for _ in range(repeats):
            for k, f in fns.items():
                t = time.perf_counter()
                jax.block_until_ready(f(log_trans, ll, active))
                times[k].append(time.perf_counter() - t)
        ref, lib = fns["reference_filtered"](log_trans, ll, active), fns["library_filtered"](log_trans, ll, active)
        out = {"N": N, "T": T, "K": K, "repeats": repeats, "load_before": load, "load_after": _load()}
        for k, v in times.items():
            out[f"{k}_ms"] = round(1000 * float(np.median(v)), 2)
        out["marginal_ratio"] = round(out["library_marginal_ms"] / out["reference_marginal_ms"], 3)
        out["filtered_ratio"] = round(out["library_filtered_ms"] / out["reference_filtered_ms"], 3)
        out["max_abs_diff_log_marginal"] = float(jnp.max(jnp.abs(ref[0] - lib[0])))
        out["max_abs_diff_filtered_probs"] = float(jnp.max(jnp.abs(jnp.exp(ref[1]) - jnp.exp(lib[1]))))
    print(f"filter, {N} x {T} steps x {K} skills: marginal {out['reference_marginal_ms']} -> "
          f"{out['library_marginal_ms']} ms (x {out['marginal_ratio']}); with filtered probabilities "
          f"{out['reference_filtered_ms']} -> {out['library_filtered_ms']} ms (x {out['filtered_ratio']}); "
          f"largest differences {out['max_abs_diff_log_marginal']:.1e} (log marginal), "
          f"{out['max_abs_diff_filtered_probs']:.1e} (probabilities)", flush=True)
    return out


def part_sweep(world_name: str, sweeps: int, chains: int) -> dict:
    from bench_scale import timed_sweeps

    from npbrs.domains.worlds import WORLDS
    from npbrs.inference import fit
    from npbrs.inference.sampler.options import MOVE_DEFAULTS
    from npbrs.models import hmm

    world = WORLDS[world_name](seed=0)
    library_filter = hmm.forward_filter
    greedy_from = int(np.floor(MOVE_DEFAULTS["greedy_from"] * sweeps))
    runs = {"reference": [], "library": []}
    with timed_sweeps() as (times, _starts):
        try:
            for _ in range(2):
                for name, fn in (("reference", reference_filter), ("library", library_filter)):
                    hmm.forward_filter = fn  # batch_forward_filter looks it up in the module
                    jax.clear_caches()
                    times.clear()
                    load = _load()
                    t = time.perf_counter()
                    result = fit(world.mdp, world.demos, num_chains=chains, num_warmup=sweeps, num_samples=sweeps, seed=0,
                                 progress_bar=False)
                    wall = time.perf_counter() - t
                    p = np.asarray(times)
                    row = {"wall_s": round(wall, 1), "first_sweep_s": round(float(p[0]), 1),
                           "plain_sweep_s": round(float(np.median(p[1:greedy_from])), 3),
                           "greedy_sweep_s": round(float(np.median(p[greedy_from:sweeps])), 3),
                           "sample_sweep_s": round(float(np.median(p[sweeps:])), 3), "skills": int(result.num_skills),
                           "load_before": load, "load_after": _load()}
                    runs[name].append(row)
                    print(f"{world_name}, {name} filter: {row}", flush=True)
        finally:
            hmm.forward_filter = library_filter
    out = {"world": world_name, "chains": chains, "sweeps": 2 * sweeps, "runs": runs}
    for kind in ("plain", "greedy", "sample"):
        ref = np.median([r[f"{kind}_sweep_s"] for r in runs["reference"]])
        lib = np.median([r[f"{kind}_sweep_s"] for r in runs["library"]])
        out[f"{kind}_sweep_ratio"] = round(float(lib / ref), 3)
    print(f"{world_name}: sweep ratios library / reference: plain {out['plain_sweep_ratio']}, greedy "
          f"{out['greedy_sweep_ratio']}, sampling {out['sample_sweep_ratio']}", flush=True)
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--part", default="filter,sweep", help="comma-separated: filter, sweep")
    parser.add_argument("--json", metavar="PATH", help="write the figures here (default: benchmarks/results/bench_filter.json)",
                        default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "bench_filter.json"))
    parser.add_argument("--note", default="", help="what else was running on the machine")
    parser.add_argument("--size", default="400,500,8", help="N,T,K of --part filter")
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--world", default="tabular_grid")
    parser.add_argument("--sweeps", type=int, default=30, help="warmup and sampling sweeps of --part sweep")
    parser.add_argument("--chains", type=int, default=2)
    args = parser.parse_args(argv)
    out = {"benchmark": "bench_filter", "note": args.note, "started": time.strftime("%Y-%m-%d %H:%M:%S"),
           "command": run_info()["command"],
           "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "processor": processor(),
                       "jax": jax.__version__}}
    parts = [p.strip() for p in args.part.split(",") if p.strip()]
    if "filter" in parts:
        N, T, K = (int(x) for x in args.size.split(","))
        out["filter"] = part_filter(N, T, K, args.repeats)
    if "sweep" in parts:
        out["sweep"] = part_sweep(args.world, args.sweeps, args.chains)
    if args.json:
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
