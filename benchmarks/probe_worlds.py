"""One fit of one benchmark world with changed options: a quick probe of what a model change
might do, before it is built into the defaults and measured by ``bench_worlds.py``.

    python benchmarks/probe_worlds.py labyrinth 2 '{"emission_options": {"prior_scale": 1.0}}'

Arguments: the world (``tabular_grid``, ``labyrinth``, ``rooms``; seed 0, full size), the number
of chains, and ``fit``'s keyword overrides as JSON (everything else: ``fit``'s defaults). Prints
one JSON line: skills found (and true), one-to-one accuracy (and the oracle's), switches found
over true, held-out log-likelihood per step (20 Monte Carlo samples a draw; and the oracle's),
R-hat of the label-invariant scalars, wall seconds of the fit and peak memory (MB).

``{"init_segmentation": "truth"}`` starts every chain from the true segmentation (how far the
sampler then moves away from it, and what it scores, tell segmentation errors from the rest).
"""

import json
import resource
import sys
import time


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 3:
        raise SystemExit(__doc__)
    from npbrs.domains.worlds import WORLDS
    from npbrs.inference import fit
    from npbrs.inference.analysis.metrics import hungarian_accuracy, num_switches

    name, chains, overrides = argv[0], int(argv[1]), json.loads(argv[2])
    world = WORLDS[name](seed=0)
    oracle = world.oracle()
    if overrides.get("init_segmentation") == "truth":
        overrides = {**overrides, "init_segmentation": world.demos.skills}
    start = time.perf_counter()
    result = fit(world.mdp, world.demos, num_chains=chains, progress_bar=False, **overrides)
    wall = time.perf_counter() - start
    held = result.log_predictive(world.mdp, world.heldout, num_samples=20)
    print(json.dumps(dict(
        world=name, chains=chains, overrides=json.loads(argv[2]), skills=int(result.num_skills),
        true_skills=int(world.model.num_skills),
        hungarian=round(hungarian_accuracy(world.demos.skills, result.segmentation), 3),
        oracle_hungarian=round(hungarian_accuracy(world.demos.skills, oracle.viterbi), 3),
        switch_ratio=round(num_switches(result.segmentation) / num_switches(world.demos.skills), 2),
        heldout_ll=round(float(held.per_step), 4), oracle_heldout_ll=round(oracle.heldout_ll, 4),
        sticky_heldout_ll=round(oracle.sticky_heldout_ll, 4),
        rhat={k: round(float(v), 3) for k, v in result.rhat.items()}, wall_s=round(wall),
        peak_mb=round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024))), flush=True)


if __name__ == "__main__":
    main()
