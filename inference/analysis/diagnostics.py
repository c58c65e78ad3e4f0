"""Convergence diagnostics that survive label switching, and per-skill summaries across chains.

Skill labels are arbitrary: two chains that found the same skills number them differently,
so R-hat of a per-skill parameter across chains means nothing until the chains' skills are
matched. Hence:

- :func:`convergence` — R-hat and ESS (ArviZ) of the label-invariant scalars only: the log
  joint, the number of skills, the number of switches;
- :func:`nested_rhat` and :func:`superchain_ids` — where chains share a start (a chain restarted
  from another's state at warmup's end, ``SamplerConfig.restart_margin``), the nested R-hat of
  Margossian et al. (Bayesian Analysis 2024) over superchains of the chains that share one: what
  :attr:`FitResult.rhat`, :func:`unconverged`, :func:`convergence_warning` and :func:`summary`
  judge such a run by, beside ArviZ's rank-normalised R-hat;
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
from typing import Dict, Optional

import numpy as np
from scipy.optimize import linear_sum_assignment


__all__ = ["convergence", "nested_rhat", "superchain_ids", "shares_start", "shared_starts", "relabel",
           "relabelled_draws", "skill_summary", "LABEL_INVARIANT", "ConvergenceWarning", "label_invariant_diagnostic",
           "unconverged", "convergence_warning", "summary", "reward_prior_text", "shown_segmentation"]



class ConvergenceWarning(UserWarning):
    """``fit``'s draws fail the label-invariant diagnostics (an R-hat above 1.05 or an ESS below
    100: :meth:`FitResult.convergence_warning`). Silence it with
    ``warnings.filterwarnings("ignore", category=npbrs.inference.ConvergenceWarning)``."""

#: Scalars whose meaning does not depend on how skills are labelled: safe for R-hat and ESS
#: across chains (skill labels switch between chains).
LABEL_INVARIANT = ("log_joint", "num_skills", "num_switches")


def nested_rhat(draws, superchains) -> float:
    """Nested R-hat (Margossian, Hoffman, Sountsov, Riou-Durand, Vehtari and Gelman, "Nested
    R-hat: assessing the convergence of Markov chain Monte Carlo when running many short
    chains", Bayesian Analysis 2024) of one scalar: R-hat with superchains, groups of chains that
    share a start, in the place of chains.

    With chain means m_c, each superchain k's mean (the mean of its chains' means) and the
    overall mean (the mean of the superchains' means):

    - B: the variance of the superchains' means around the overall mean, 1/(K-1);
    - W: the mean over superchains of (the variance of its chains' means around the
      superchain's mean, 1/(M_k-1), 0 for a superchain of one chain) + (the mean of its chains'
      within-chain variances, 1/(N-1), 0 for chains of one draw);
    - nested R-hat = sqrt(1 + B / W).

    The paper's superchains are of equal size. Here a restart moves a chain into the best
    chain's superchain, so sizes differ (superchains of 2, 1 and 1 chains); every superchain
    weighs the same in the overall mean, in B and in W, as every superchain does in the paper
    (not every chain: a superchain of many chains that share one start is one piece of evidence
    about where the chains go from different starts, not many). With one chain per superchain
    it is the classic R-hat (Gelman and Rubin's, neither split nor rank-normalised) but for its
    (N-1)/N factor: nested R-hat^2 = R-hat^2 + 1/N, so never below 1.

    Args:
        draws: (chains, draws) array of the scalar.
        superchains: (chains,) the superchain of each chain (any hashable ids; e.g.
            :func:`superchain_ids`).
    Returns:
        the nested R-hat; NaN where undefined: a single superchain (no two starts to compare),
        W = 0 (every chain constant, at its superchain's value), a draw not finite.
    """
    x = np.asarray(draws, dtype=np.float64)
    if x.ndim != 2:
        raise ValueError(f"draws must be (chains, draws), got shape {x.shape}")
    ids = np.asarray(superchains).reshape(-1)
    if len(ids) != x.shape[0]:
        raise ValueError(f"{len(ids)} superchain ids for {x.shape[0]} chains")
    C, N = x.shape
    groups = [np.flatnonzero(ids == k) for k in np.unique(ids)]
    if len(groups) < 2 or N == 0 or not np.all(np.isfinite(x)):
        return float("nan")
    chain_means = x.mean(axis=1)
    chain_vars = x.var(axis=1, ddof=1) if N > 1 else np.zeros(C)
    super_means = np.array([chain_means[g].mean() for g in groups])
    within = np.array([(chain_means[g].var(ddof=1) if len(g) > 1 else 0.0) + chain_vars[g].mean()
                       for g in groups])
    B, W = super_means.var(ddof=1), within.mean()
    if not W > 0:
        return float("nan")
    return float(np.sqrt(1.0 + B / W))


def superchain_ids(restart: Optional[dict], num_chains: int) -> np.ndarray:
    """The superchain of each chain: the chains that share a start. A chain restarted at
    warmup's end (``restart["from"][i] != i``, :attr:`FitResult.restart`) continued from
    ``restart["from"][i]``'s state, so it joins that chain's superchain; without restarts
    (``restart`` None) every chain is its own superchain.

    Returns:
        (num_chains,) int: each chain's superchain, named by the chain of it that kept its own
        state (e.g. [0, 0, 2] for chain 1 restarted from chain 0's state).
    """
    if restart is None:
        return np.arange(num_chains)
    source = [int(c) for c in restart["from"]]
    if len(source) != num_chains:
        raise ValueError(f"restart['from'] names {len(source)} chains, the run has {num_chains}")
    parent = list(range(num_chains))

    def root(c):
        while parent[c] != c:
            c = parent[c]
        return c

    for i, c in enumerate(source):  # (union of i and the chain it continued from)
        a, b = root(i), root(c)
        if a != b:
            parent[max(a, b)] = min(a, b)
    groups: Dict[int, list] = {}
    for i in range(num_chains):
        groups.setdefault(root(i), []).append(i)
    out = np.empty(num_chains, dtype=np.int64)
    for members in groups.values():
        kept = [i for i in members if source[i] == i]
        out[members] = kept[0] if kept else min(members)
    return out


def shares_start(superchains) -> bool:
    """Whether two chains share a superchain (:func:`superchain_ids`): then R-hat across the
    chains alone does not show that they found the same region from different starts."""
    ids = np.asarray(superchains).reshape(-1)
    return len(np.unique(ids)) < len(ids)


def label_invariant_diagnostic(stats: Dict[str, np.ndarray], which: str = "rhat",
                               superchains=None) -> Dict[str, float]:
    """ArviZ's rank-normalised split R-hat (``which="rhat"``) or bulk ESS (``"ess"``) of each
    label-invariant scalar in ``stats`` ({name: (chains, draws)}): the numbers ``convergence``
    (``az.summary``) shows; or (``"nested_rhat"``) :func:`nested_rhat` over ``superchains``
    (each chain's superchain, :func:`superchain_ids`). NaN where undefined (a constant scalar,
    chains that are each constant at different values, fewer than 4 draws for ArviZ's, a single
    superchain for the nested R-hat)."""
    import logging
    import warnings

    from ..arviz_import import arviz

    if which == "nested_rhat":
        if superchains is None:
            raise ValueError("which='nested_rhat' needs each chain's superchain (superchains=)")
        return {name: nested_rhat(stats[name], superchains) for name in LABEL_INVARIANT}
    az = arviz()

    if which not in ("rhat", "ess"):
        raise ValueError(f"which must be 'rhat', 'ess' or 'nested_rhat', got {which!r}")
    fn = az.rhat if which == "rhat" else az.ess
    logger = logging.getLogger("arviz")
    level = logger.level
    logger.setLevel(logging.ERROR)  # one chain: "shape validation failed" is expected
    out = {}
    try:
        for name in LABEL_INVARIANT:
            x = np.asarray(stats[name], dtype=np.float64)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                value = float(fn(x)) if x.shape[1] >= 4 else float("nan")
            out[name] = value if np.isfinite(value) else float("nan")
    finally:
        logger.setLevel(level)
    return out
def unconverged(stats: Dict[str, np.ndarray], rhat: Dict[str, float], ess: Optional[Dict[str, float]] = None,
                target_rhat: float = 1.05, min_ess: float = 100.0, rank_rhat: Optional[Dict[str, float]] = None):
    """(failing, undefined): the label-invariant scalars in ``stats`` ({name: (chains, draws)})
    that have not converged, and those of them whose diagnostics are undefined although they
    vary (fewer than 4 draws a chain, chains each constant at a different value, every chain
    sharing one start). A scalar constant over every draw of every chain has converged; one that
    varies fails on an undefined diagnostic, an R-hat above ``target_rhat``, (where ``ess`` is
    given) an ESS below ``min_ess`` or (where ``rank_rhat`` is given) a rank-normalised R-hat
    above ``target_rhat``. ``rhat``: the R-hat a run is judged by (:attr:`FitResult.rhat`: the
    nested R-hat over superchains where chains share a start, else ArviZ's rank-normalised
    R-hat); ``rank_rhat``: where ``rhat`` is the nested one, ArviZ's, which must pass too (it
    sees a chain drifting within its draws, the nested R-hat does not); ``ess``:
    :func:`label_invariant_diagnostic`'s."""
    failing, undefined = [], []
    for name in LABEL_INVARIANT:
        x = np.asarray(stats[name], float)
        if x.size == 0 or np.ptp(x) == 0:
            continue
        rhats = [rhat[name]] + ([] if rank_rhat is None else [rank_rhat[name]])
        values = rhats + ([] if ess is None else [ess[name]])
        if not np.all(np.isfinite(values)):
            failing.append(name)
            undefined.append(name)
        elif max(rhats) > target_rhat or (ess is not None and ess[name] < min_ess):
            failing.append(name)
    return failing, undefined


def _and(items) -> str:
    items = [str(i) for i in items]
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


def shared_starts(result) -> str:
    """Which chains share a start, in words ("" when none does): per superchain of several
    chains (:func:`superchain_ids`), e.g. "chains 0 and 1 share a start (chain 1 continued from
    chain 0's state at warmup's end, 87 nats behind it; restart_margin 50)"."""
    restart = result.restart
    ids = superchain_ids(restart, result.num_chains)
    if not shares_start(ids):
        return ""
    source, scores = restart["from"], restart["scores"]
    parts = []
    for k in np.unique(ids):
        members = np.flatnonzero(ids == k).tolist()
        if len(members) < 2:
            continue
        moves = []
        for s in sorted({source[i] for i in members if source[i] != i}):
            moved = [i for i in members if source[i] == s and i != s]
            behind = _and(f"{scores[s] - scores[i]:.0f}" for i in moved)
            moves.append(f"chain{'s' if len(moved) > 1 else ''} {_and(moved)} continued from chain {s}'s state "
                         f"at warmup's end, {behind} nats behind it")
        parts.append(f"chains {_and(members)} share a start ({'; '.join(moves)}; restart_margin "
                     f"{restart['margin']:g})")
    return "; ".join(parts)


def _idata(result):
    return result.to_arviz() if hasattr(result, "to_arviz") else result


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


def _slot_params(result, chain: int) -> np.ndarray:
    """(K, P) each slot's parameters averaged over the chain's draws that use it (NaN if none)."""
    sites = sorted(result.skill_params)
    steps = np.asarray(result.samples["skill_steps"][chain])  # (D, K)
    used = steps > 0
    flat = np.concatenate([np.asarray(result.samples[s][chain]).reshape(steps.shape + (-1,)) for s in sites], -1)
    counts = used.sum(0)
    means = np.einsum("dk,dkp->kp", used.astype(float), flat) / np.maximum(counts, 1)[:, None]
    means[counts == 0] = np.nan
    return means


def relabel(result, by: str = "segmentation") -> np.ndarray:
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


def relabelled_draws(result, site: str, by: str = "segmentation") -> np.ndarray:
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


def skill_summary(result, site: Optional[str] = None, prob: float = 0.9, by: str = "segmentation",
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


def convergence_warning(result, rhat: Optional[Dict[str, float]] = None, ess: Optional[Dict[str, float]] = None,
                        rank_rhat: Optional[Dict[str, float]] = None) -> str:
    """Lines saying which label-invariant scalars have R-hat above 1.05 or ESS below 100, or
    diagnostics that are undefined although the scalar varies (:func:`unconverged`), how
    each chain's mean of them moved from the first to the second half of its draws (a
    chain still drifting, or chains holding different levels), and what to do; "" when
    none has. Where chains share a start (:func:`superchain_ids`), the R-hat is the nested one
    over the superchains and the rank-normalised one must pass too; where every chain shares
    one start the nested R-hat is undefined and the run has not shown that it converged, which
    the first line says with what to do (restart_margin off, or more chains). ``rhat``, ``ess``,
    ``rank_rhat``: the run's (:attr:`FitResult.rhat`, ``ess``, ``rank_rhat``), where the caller
    has them already."""
    rhat = result.rhat if rhat is None else rhat
    ess = result.ess if ess is None else ess
    ids = superchain_ids(result.restart, result.num_chains)
    shared = shares_start(ids)
    if shared and rank_rhat is None:
        rank_rhat = label_invariant_diagnostic(result.stats, "rhat")
    bad, undefined = unconverged(result.stats, rhat, ess, rank_rhat=rank_rhat if shared else None)
    if not bad:
        return ""
    halves = []
    for name in bad:
        x = np.asarray(result.stats[name], float)
        if x.ndim == 2 and x.shape[1] >= 2:
            h = x.shape[1] // 2
            fmt = ".1f" if name == "log_joint" else ".2f"
            per_chain = " | ".join(f"{a:{fmt}} -> {b:{fmt}}" for a, b in zip(x[:, :h].mean(1), x[:, h:].mean(1)))
            halves.append(f"{name} {per_chain}")
    moved = ("\n  each chain's mean over the first -> the second half of its draws: " + "; ".join(halves)
             if halves else "")
    one_start = shared and len(np.unique(ids)) == 1
    todo = "run more sweeps (samples, warmup) or more chains"
    if not shared:
        why = "R-hat above 1.05 or ESS below 100"
    elif one_start:  # (the nested R-hat is undefined for every scalar: the other reasons are ArviZ's)
        why = ("nested R-hat undefined: every chain shares one start (a restart at warmup's end), so no two "
               "chains that started apart can show that they reach the same region")
        plain_bad, undefined = unconverged(result.stats, rank_rhat, ess)
        if plain_bad:
            why += f"; rank-normalised R-hat above 1.05 or ESS below 100 for {', '.join(plain_bad)}"
        todo = ("run with restart_margin=0 (restarts off) or more chains, and more sweeps (samples, warmup) if "
                "need be,")
    else:
        why = ("nested R-hat over the chains that share a start, or rank-normalised R-hat, above 1.05, or ESS "
               "below 100")
    if undefined:
        why += (f"; undefined for {', '.join(undefined)}, which varies: fewer than 4 draws a chain, or chains "
                "each constant at a different value")
    starts = ("; chains that share a start count as one superchain (nested R-hat): restart_margin=0 keeps every "
              "chain's own start, and the run-length rule reads the rank-normalised R-hat only" if shared else "")
    return (f"not converged: {', '.join(bad)} ({why}); {todo} before trusting the skills found{moved}\n  (a chain "
            "whose halves differ is still moving: more warmup; chains steady at different levels sit in different "
            "regions: more chains or sampling sweeps; a config with max_samples and time_budget samples on "
            f"until every R-hat is at most 1.05{starts})")


def shown_segmentation(result):
    """The segmentation a run's figures and summaries show (``npbrs report``, ``npbrs segment``):
    each step's most probable skill over the draws (:meth:`FitResult.skill_probabilities`'
    labels) or, for a run saved without the per-step counts, the best draw's.

    Args:
        result: a FitResult.
    Returns:
        (per-trajectory labels, what they are in words).
    """
    if getattr(result, "step_skill_counts", None) is not None:  # (no MDP needed: counted over the draws)
        return result.skill_probabilities().labels, "per-step labels (most probable skill over the draws)"
    return list(result.segmentation), "the best draw's segmentation (the run kept no per-step counts)"


def reward_prior_text(emission: dict, num_features: int = 0) -> str:
    """The reward prior and start a run used, from its emission's description
    (``FitResult.emission``): the prior's family and scale, and where the skills' rewards start;
    ``prior_df``, ``prior_scale`` and ``start`` "auto" choose them from the number of reward
    weights (more than 16: a Student t and the starting skills' fits), which this says. "" for an
    emission without a reward prior.

    Args:
        emission: the run's emission description.
        num_features: the number of reward weights (``len(FitResult.feature_names)``; 0: unknown).
    Returns:
        one line of text, or "".
    """
    if "prior_scale" not in emission or "prior_df" not in emission:
        return ""
    df = emission["prior_df"]
    family = f"Student t ({df:g} degrees of freedom)" if df not in (False, None) else "Gaussian"
    start = emission.get("start")
    if start == "auto" and num_features:
        start = "fit" if num_features > 16 else "draw"
    starts = {"fit": "the IRL fit to each skill's starting steps", "draw": "a draw around that fit"}
    return (f"reward prior: {family} per weight, scale {emission['prior_scale']:g}"
            + (f"; the rewards start at {starts.get(start, start)}" if start else "")
            + (f" ({num_features} reward weights: the emission's \"auto\" options choose these by that number)"
               if num_features else ""))


def summary(result) -> str:
    """A run's text summary: skills, segment lengths, how the run went, label-invariant diagnostics.

    Args:
        result: a FitResult.
    Returns:
        the text, one line per item."""
    lengths = [len(s) for s in result.segmentation]
    shown, what = shown_segmentation(result)
    ids = superchain_ids(result.restart, result.num_chains)
    shared = shares_start(ids)

    def switches(labels):
        return np.mean([np.count_nonzero(np.diff(s)) for s in labels])

    counts = np.bincount(np.concatenate(shown), minlength=result.num_skills)
    used = np.flatnonzero(counts)
    lines = [f"{len(used)} skill{'' if len(used) == 1 else 's'} in {len(lengths)} trajectories ({sum(lengths)} "
             f"steps), {switches(shown):.2f} switches per trajectory: {what}",
             "steps per skill: " + ", ".join(f"{k}: {counts[k]}" for k in used)]
    if shown is not result.segmentation:
        best = np.bincount(np.concatenate(result.segmentation), minlength=result.num_skills)
        lines.append(f"the best draw (log joint {result.best_log_joint:.1f}, chain {result.best_chain}): "
                     f"{result.num_skills} skills, {switches(result.segmentation):.2f} switches per trajectory; "
                     "steps per skill: " + ", ".join(f"{k}: {c}" for k, c in enumerate(best)))
    else:
        lines.append(f"best log joint {result.best_log_joint:.1f} (chain {result.best_chain})")
    prior = reward_prior_text(result.emission, len(result.feature_names))
    if prior:
        sampler = (result.config or {}).get("sampler", {})
        if sampler.get("init_window") is not None and sampler.get("init_skills") is not None:
            # (the emission's init_window and initial_skills also follow the number of weights)
            prior += (f"; the initial segmentation: windows of {sampler['init_window']} steps among "
                      f"{sampler['init_skills']} skills")
        lines.append(prior)
    if getattr(result, "action_names", None):
        lines.append(result.action_names["text"])
    if "greedy_merges" in result.stats and "greedy_splits" in result.stats:
        kept = [np.asarray(result.stats[n])[:, -1].tolist() for n in ("greedy_merges", "greedy_splits")]
        if any(kept[0]) or any(kept[1]):
            lines.append(f"warmup's greedy moves kept per chain: merges {kept[0]}, splits {kept[1]}")
    if result.init_segmentation is not None:
        used = len(np.unique(np.concatenate(result.init_segmentation)))
        lines.append(f"started from a given segmentation ({used} skills)")
    if result.run_length is not None:
        r = result.run_length
        why = {"converged": f"every label-invariant R-hat at most {r['target_rhat']}" + (
                   ": the rank-normalised R-hat, which does not see chains that share a start" if shared else ""),
               "max_samples": f"max_samples reached before every R-hat was at most {r['target_rhat']}",
               "time_budget": f"the time budget ({r['time_budget']:g} s) spent before every R-hat was at most "
                              f"{r['target_rhat']}"}.get(r["stopped"], r["stopped"])
        lines.append(f"run length chosen by convergence: {r['samples']} sampling sweeps per chain ({why})")
    if shared:
        lines.append(shared_starts(result))
    if result.truncation is not None:
        t = result.truncation
        models = t.get("switching") or [None] * len(t["max_skills"])  # (a run saved before it was kept)
        both = len(set(models)) > 1
        steps = "; ".join(f"{k} slots{f' ({m})' if both else ''}: {n} skills, every slot in use in {p:.0%} of "
                          "the draws" for k, n, p, m in zip(t["max_skills"], t["skills"], t["saturated"], models))
        lines.append(f"skill slots grew ({steps})")
    if result.switching is not None:
        c = result.switching
        lines.append(f"switching chosen: {c['chosen']} (log Bayes factor of state-dependent ends over sticky "
                     f"switching, given the sticky fit's skill sequences: {c['log_bayes_factor']:+.1f} nats; "
                     f"state needs more than {c['margin']:g})")
    rhat, ess = result.rhat, result.ess
    rank_rhat = result.rank_rhat if shared else None

    def shown(value, fmt):
        return format(value, fmt) if np.isfinite(value) else "undefined"

    if not shared:
        lines.append("label-invariant diagnostics (ArviZ): " + "; ".join(
            f"{n} R-hat {shown(rhat[n], '.3f')} ESS {shown(ess[n], '.0f')}" for n in LABEL_INVARIANT))
    else:
        groups = [np.flatnonzero(ids == k).tolist() for k in np.unique(ids)]
        over = ("nested R-hat undefined: every chain shares one start" if len(groups) == 1 else
                "nested R-hat over the superchains " + _and("{" + ", ".join(map(str, g)) + "}" for g in groups))
        lines.append(f"label-invariant diagnostics ({over}; rank-normalised R-hat and ESS from ArviZ): " + "; ".join(
            f"{n} nested R-hat {shown(rhat[n], '.3f')} R-hat {shown(rank_rhat[n], '.3f')} ESS {shown(ess[n], '.0f')}"
            for n in LABEL_INVARIANT))
    warning = convergence_warning(result, rhat, ess, rank_rhat)
    if warning:
        lines.append(warning)
    return "\n".join(lines)
