# Five seeds (1 chain, 100 + 100 sweeps) of one small world per option; the results are in README.md here.
# python small_worlds_seeds.py OPTIONS_JSON ... (the rooms variant: w = rooms(seed=1, size=7, num_skills=3,
# num_trajectories=24, min_length=40, max_length=80, num_heldout=12))
import time, sys, json, numpy as np
from npbrs.domains.worlds import labyrinth
from npbrs.inference import fit
from npbrs.inference.analysis.metrics import hungarian_accuracy
w = labyrinth(seed=1, depth=4, num_trajectories=80, num_heldout=40)
print("oracle", w.oracle().heldout_ll, w.oracle().sticky_heldout_ll)
for spec in sys.argv[1:]:
    opts = json.loads(spec)
    acc, held, sk = [], [], []
    t = time.time()
    for seed in range(5):
        r = fit(w.mdp, w.demos, num_chains=1, num_warmup=100, num_samples=100, seed=seed, progress_bar=False, **opts)
        acc.append(hungarian_accuracy(w.demos.skills, r.segmentation)); sk.append(r.num_skills)
        held.append(r.log_predictive(w.mdp, w.heldout, num_samples=16).per_step)
    print(spec, "skills", sk, "acc %.3f" % np.mean(acc), np.round(acc, 2), "held %.4f" % np.mean(held), np.round(held, 3), "%.0f s" % (time.time() - t), flush=True)
