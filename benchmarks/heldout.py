"""Held-out log-likelihood and ArviZ model comparison of emission variants on highway-500.

24 highway demonstrations of 500 steps (seed = run) are drawn; 16 are fitted by each emission
(``reward``: npbrs; ``single``: one reward for all steps; ``subgoal``: BNIRL-style goals among
the visited states; ``policy``: a tabular Dirichlet policy per skill) and the other 8 are
scored by ``FitResult.log_predictive`` (nats per step, with its Monte Carlo standard error).
Each run's pointwise log-likelihood (``add_log_likelihood``) feeds ``az.compare`` (PSIS-LOO
over the 16 fitted trajectories).

    python benchmarks/heldout.py --runs 1 --out benchmarks/results/heldout
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import numpy as np

EMISSIONS = ("reward", "single", "subgoal", "policy")
SETTINGS = {"reward": {"num_chains": 4, "num_warmup": 20, "num_samples": 20},
            "single": {"num_chains": 2, "num_warmup": 25, "num_samples": 25},
            "subgoal": {"num_chains": 2, "num_warmup": 50, "num_samples": 50},
            "policy": {"num_chains": 2, "num_warmup": 50, "num_samples": 50}}
MAX_SKILLS = {"reward": 8, "single": 1, "subgoal": 8, "policy": 8}


def one_run(run, args):
    import arviz as az

    from npbrs.domains.demos import Demonstrations, generate_demonstrations
    from npbrs.domains.registry import get_domain
    from npbrs.inference.driver.fit import fit
    from npbrs.inference.analysis.metrics import hungarian_accuracy
    from npbrs.models.subgoal import SubgoalEmission, visited_states

    domain = get_domain("highway")
    mdp = domain.mdp
    demos = generate_demonstrations(domain, num_trajectories=args.train + args.test, length=args.length, seed=run)

    def part(idx):
        return Demonstrations([demos.states[i] for i in idx], [demos.actions[i] for i in idx],
                              [demos.skills[i] for i in idx], mdp_fingerprint=demos.mdp_fingerprint)

    train, test = part(range(args.train)), part(range(args.train, args.train + args.test))
    rows, idatas = {}, {}
    for name in EMISSIONS:
        emission = SubgoalEmission(mdp, candidates=visited_states(train)) if name == "subgoal" else name
        start = time.perf_counter()
        result = fit(mdp, train, {"emission": emission, "max_skills": MAX_SKILLS[name]}, seed=run, progress_bar=False,
                     **SETTINGS[name])
        wall = time.perf_counter() - start
        em = emission if name == "subgoal" else None
        start = time.perf_counter()
        held = result.log_predictive(mdp, test, emission=em, num_samples=args.mc)
        result.add_log_likelihood(mdp, emission=em)
        idatas[name] = result.to_arviz()
        loo = az.loo(idatas[name], pointwise=True)
        rows[name] = {"heldout_ll": held.per_step, "heldout_se": held.per_step_se, "skills": int(result.num_skills),
                      "accuracy": float(hungarian_accuracy(train.skills, result.segmentation)),
                      "elpd_loo": float(loo.elpd_loo), "pareto_k_max": float(np.max(loo.pareto_k.values)),
                      "fit_s": wall, "score_s": time.perf_counter() - start}
        print(f"  run {run} {name:>8}: held-out {held.per_step:.4f} ± {held.per_step_se:.4f} nats/step, "
              f"{result.num_skills} skills, fit {wall:.0f} s, scoring {rows[name]['score_s']:.0f} s", flush=True)
    table = az.compare(idatas)
    return {"run": run, "emissions": rows, "compare": json.loads(table.to_json(orient="index")),
            "compare_text": table.to_string()}


def markdown(results) -> str:
    lines = ["# Held-out log-likelihood and ArviZ comparison, highway-500", "", results["description"], ""]
    for r in results["runs"]:
        lines += [f"## Run {r['run']}", "", "| emission | held-out nats/step | skills | accuracy (Hungarian) | "
                  "elpd_loo | max Pareto k | fit (s) |", "|---|---:|---:|---:|---:|---:|---:|"]
        for name, row in r["emissions"].items():
            lines.append(f"| {name} | {row['heldout_ll']:.4f} ± {row['heldout_se']:.4f} | {row['skills']} | "
                         f"{row['accuracy']:.3f} | {row['elpd_loo']:.1f} | {row['pareto_k_max']:.2f} | "
                         f"{row['fit_s']:.0f} |")
        lines += ["", "`az.compare` (PSIS-LOO over the fitted trajectories):", "", "```", r["compare_text"], "```", ""]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    p.add_argument("--runs", type=int, default=1)
    p.add_argument("--train", type=int, default=16)
    p.add_argument("--test", type=int, default=8)
    p.add_argument("--length", type=int, default=500)
    p.add_argument("--mc", type=int, default=64, help="Monte Carlo samples per draw of log_predictive")
    p.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "heldout"))
    args = p.parse_args(argv)
    results = {"description": f"{args.train} highway demonstrations of {args.length} steps fitted, {args.test} held "
                              f"out; uniform actions score {-np.log(3):.4f} nats per step. Sampler settings: "
                              + "; ".join(f"{k}: {v['num_chains']} chains x ({v['num_warmup']} + {v['num_samples']})"
                                          for k, v in SETTINGS.items())
                              + f". Machine: {platform.machine()}, {os.cpu_count()} cores, shared with other jobs.",
               "settings": vars(args), "runs": []}
    os.makedirs(args.out, exist_ok=True)
    for run in range(args.runs):
        results["runs"].append(one_run(run, args))
        with open(os.path.join(args.out, "heldout.json"), "w") as f:
            json.dump(results, f, indent=1)
        with open(os.path.join(args.out, "heldout.md"), "w") as f:
            f.write(markdown(results))
    print(markdown(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
