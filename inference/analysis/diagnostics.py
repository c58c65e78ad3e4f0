"""Convergence diagnostics that survive label switching, and per-skill summaries across chains.

Skill labels are arbitrary: two chains that found the same skills number them differently,
so R-hat of a per-skill parameter across chains means nothing until the chains' skills are
matched. Hence:

- :func:`convergence` — R-hat and ESS (ArviZ) of the label-invariant scalars only: the log
  joint, the number of skills, the number of switches;
- :func:`relabel` — each chain's skill slots matched to the result's skills (those of the best
  draw) by Hungarian matching, on segmentation agreement (default) or parameter distance;
- :func:`skill_summary` — per skill and parameter entry (e.g. reward weight per feature): the
  posterior mean and a central credible interval, pooling every chain's draws after relabelling.

Trace plots of the label-invariant scalars: :func:`npbrs.inference.analysis.plots.plot_trace`.

A chain's slot is assumed to keep its meaning across that chain's draws (slots are persistent in
the sampler; a slot that dies and is reborn may change meaning, which the per-skill summary
then averages over).
"""

from __future__ import annotations

import warnings
from typing import Optional

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..driver.results import LABEL_INVARIANT, FitResult

__all__ = ["convergence", "relabel", "relabelled_draws", "skill_summary"]


def _idata(result):
    if isinstance(result, FitResult):
        return result.to_arviz()
    return result


def convergence(result, var_names=LABEL_INVARIANT):
    """ArviZ summary (mean, sd, HDI, MCSE, bulk and tail ESS, R-hat) of label-invariant scalars.

    Args:
        result: a FitResult or its InferenceData.
        var_names: the posterior variables to summarise (default: log_joint, num_skills, num_switches).
    Returns:
        a pandas DataFrame, one row per variable. R-hat is NaN for a scalar that never
        changed (e.g. a constant number of skills) and for runs too short to split.
    """
    import logging

    from ..arviz_import import arviz

    az = arviz()

    idata = _idata(result)
    logger = logging.getLogger("arviz")
    level = logger.level
    logger.setLevel(logging.ERROR)  # one chain or few draws: "shape validation failed" is expected
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # constant series: "invalid value" warnings
            return az.summary(idata, var_names=list(var_names), kind="all")
    finally:
        logger.setLevel(level)


def _slot_params(result: FitResult, chain: int) -> np.ndarray:
    """(K, P) each slot's parameters averaged over the chain's draws that use it (NaN if none)."""
    sites = sorted(result.skill_params)
    steps = np.asarray(result.samples["skill_steps"][chain])  # (D, K)
    used = steps > 0
    flat = np.concatenate([np.asarray(result.samples[s][chain]).reshape(steps.shape + (-1,)) for s in sites], -1)
    counts = used.sum(0)
    means = np.einsum("dk,dkp->kp", used.astype(float), flat) / np.maximum(counts, 1)[:, None]
    means[counts == 0] = np.nan
    return means


def relabel(result: FitResult, by: str = "segmentation") -> np.ndarray:
    """Match every chain's skill slots to the result's skills (0..num_skills-1).

    Args:
        result: a FitResult.
        by: "segmentation": maximise the steps on which the chain's best segmentation agrees
            with the result's (Hungarian matching on the confusion matrix); "params": minimise the
            distance between the slot's parameters (averaged over the chain's draws that use it)
            and the skill's parameters in the best draw.
    Returns:
        (C, K) int array: the skill of each chain's slot, -1 for slots matched to none.
    """
    if by not in ("segmentation", "params"):
        raise ValueError(f"by must be 'segmentation' or 'params', got {by!r}")
    C = result.num_chains
    K = np.shape(result.samples["skill_steps"])[-1]
    L = result.num_skills
    mapping = np.full((C, K), -1, dtype=np.int64)
    if by == "segmentation":
        if result.chain_best_z is None:
            raise ValueError("this result has no per-chain segmentations; use by='params'")
        reference = np.concatenate(result.segmentation)
        for c in range(C):
            z = np.concatenate([result.chain_best_z[c, i, :len(s)] for i, s in enumerate(result.segmentation)])
            agree = np.zeros((K, L))
            np.add.at(agree, (z, reference), 1)
            rows, cols = linear_sum_assignment(agree, maximize=True)
            for r, col in zip(rows, cols):
                if agree[r, col] > 0:
                    mapping[c, r] = col
    else:
        sites = sorted(result.skill_params)
        target = np.concatenate([np.asarray(result.skill_params[s]).reshape(L, -1) for s in sites], -1)
        for c in range(C):
            means = _slot_params(result, c)
            ok = np.flatnonzero(~np.isnan(means).any(-1))
            if ok.size == 0:
                continue
            cost = np.linalg.norm(means[ok, None, :] - target[None], axis=-1)
            rows, cols = linear_sum_assignment(cost)
            mapping[c, ok[rows]] = cols
    return mapping


def relabelled_draws(result: FitResult, site: str, by: str = "segmentation") -> np.ndarray:
    """Draws of a per-skill site in the result's skill labels, NaN where a chain's draw does not
    use that skill: (C, D, num_skills, ...)."""
    if site not in result.samples:
        raise ValueError(f"no site {site!r}; per-skill sites are {sorted(result.skill_params)}")
    mapping = relabel(result, by)
    draws = np.asarray(result.samples[site], dtype=np.float64)
    steps = np.asarray(result.samples["skill_steps"])
    C, D, K = steps.shape
    out = np.full((C, D, result.num_skills) + draws.shape[3:], np.nan)
    for c in range(C):
        for k in range(K):
            j = mapping[c, k]
            if j < 0:
                continue
            used = steps[c, :, k] > 0
            out[c, used, j] = draws[c, used, k]
    return out


def skill_summary(result: FitResult, site: Optional[str] = None, prob: float = 0.9, by: str = "segmentation",
                  names=None, top: Optional[int] = None):
    """Per-skill posterior summary of a parameter site, pooled over chains after relabelling.

    Args:
        result: a FitResult.
        site: the per-skill site ("theta" for reward weights; default: "theta" if present, else
            the first site).
        prob: mass of the central credible interval (0.9: the 5% and 95% quantiles).
        by: how chains are relabelled (see :func:`relabel`).
        names: names of the site's entries (default: the MDP's feature names when the site has
            one entry per feature, else their indices).
        top: keep only each skill's ``top`` entries of largest absolute mean, largest first (a
            reward weight per state: the states a skill seeks or avoids most); default all, in
            order.
    Returns:
        a pandas DataFrame indexed by (skill, entry) with columns mean, sd, lower, upper and draws
        (the number of draws that used the skill).
    """
    import pandas as pd

    if not 0 < prob < 1:
        raise ValueError(f"prob must lie in (0, 1), got {prob}")
    if top is not None and (isinstance(top, bool) or not isinstance(top, (int, np.integer)) or top < 1):
        raise ValueError(f"top must be a positive number of entries, got {top!r}")
    if site is None:
        site = "theta" if "theta" in result.skill_params else sorted(result.skill_params)[0]
    if site not in result.skill_params:
        raise ValueError(f"no per-skill site {site!r}; sites are {sorted(result.skill_params)}")
    draws = relabelled_draws(result, site, by)  # (C, D, L, ...)
    L = result.num_skills
    flat = draws.reshape(-1, L, int(np.prod(draws.shape[3:], dtype=int)))
    P = flat.shape[-1]
    if names is None:
        names = (list(result.feature_names) if len(result.feature_names) == P
                 else ["[" + ",".join(map(str, idx)) + "]" for idx in np.ndindex(*draws.shape[3:])])
    if len(names) != P:
        raise ValueError(f"{len(names)} names for {P} entries of {site!r}")
    lo, hi = (1 - prob) / 2, 1 - (1 - prob) / 2
    columns = {name: np.full((L, P), np.nan) for name in ("mean", "sd", "lower", "upper")}
    counts = np.zeros(L, dtype=int)
    for j in range(L):  # all entries at once (a reward per state: up to millions of them)
        x = flat[:, j]
        x = x[~np.isnan(x).any(-1)]
        counts[j] = len(x)
        if len(x):
            columns["mean"][j] = x.mean(0)
            if len(x) > 1:
                columns["sd"][j] = x.std(0, ddof=1)
            columns["lower"][j], columns["upper"][j] = np.quantile(x, [lo, hi], axis=0)
    index = pd.MultiIndex.from_arrays([np.repeat(np.arange(L), P), np.tile(np.asarray(names, dtype=object), L)],
                                      names=["skill", "entry"])
    frame = pd.DataFrame({**{k: v.reshape(-1) for k, v in columns.items()}, "draws": np.repeat(counts, P)},
                         index=index)
    if top is None or top >= P:
        return frame
    order = np.argsort(-np.nan_to_num(np.abs(columns["mean"]), nan=-1.0), axis=1, kind="stable")[:, :top]
    return frame.iloc[(np.arange(L)[:, None] * P + order).reshape(-1)]
