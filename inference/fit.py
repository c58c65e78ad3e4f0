"""``fit``: segment demonstrations into skills with the BP-HMM sampler under numpyro's MCMC."""

from __future__ import annotations

import time
from typing import Optional

import jax
import numpy as np
from numpyro.infer import MCMC

from npbrs.domains.demos import Demonstrations
from npbrs.models.emissions import Emission, HMMData, get_emission_class

from .kernel import BPHMMKernel
from .results import FitResult

jax.config.update("jax_enable_x64", True)

__all__ = ["fit", "make_emission"]

_CHAIN_METHODS = ("vectorized", "sequential", "parallel")


def make_emission(emission, mdp, **options) -> Emission:
    """An emission model from a registered name (``"reward"``, ``"policy"``, ...) or an instance."""
    if isinstance(emission, Emission):
        if options:
            raise ValueError(f"emission options {sorted(options)} given with an emission instance")
        return emission
    if not isinstance(emission, str):
        raise ValueError(f"emission must be a registered name or an Emission, got {emission!r}")
    cls = get_emission_class(emission)
    return cls.from_mdp(mdp, **options)


def _check_positive_int(name, value, minimum=1):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")


def fit(mdp, demos: Demonstrations, *, emission="reward", num_chains: int = 4, num_samples: int = 200,
        num_warmup: int = 200, max_skills: int = 8, seed: int = 0, progress_bar: bool = True,
        chain_method: str = "vectorized", alpha: float = 1.0, kappa: float = 10.0, gamma: float = 1.0,
        hyperpriors: Optional[dict] = None, init_skills: Optional[int] = None, init_window: int = 25,
        emission_options: Optional[dict] = None) -> FitResult:
    """Segment demonstrations into skills.

    Args:
        mdp: the TabularMDP the demonstrations live in.
        demos: :class:`~npbrs.domains.Demonstrations`.
        emission: a registered emission name ("reward", "policy", ...) or an Emission instance.
        num_chains, num_samples, num_warmup: MCMC sizes (sweeps per chain).
        max_skills: truncation K of the beta process (skill slots).
        seed: the random seed; the same seed gives the same answer.
        progress_bar: show numpyro's progress bar.
        chain_method: "vectorized" (one process, chains vmapped), "sequential" or "parallel".
        alpha, kappa, gamma: BP-HMM hyperparameters (IBP mass, stickiness, transition concentration).
        hyperpriors: optional {"alpha"|"kappa"|"gamma": (shape, rate)} to sample them.
        init_skills, init_window: the initial segmentation (see :class:`BPHMMKernel`).
        emission_options: keyword options of the emission (e.g. prior_scale).
    Returns:
        a :class:`~npbrs.inference.results.FitResult`.
    """
    if not isinstance(demos, Demonstrations):
        raise ValueError(f"demos must be npbrs.domains.Demonstrations, got {type(demos).__name__}")
    demos.validate(mdp)
    for name, value in [("num_chains", num_chains), ("num_samples", num_samples), ("max_skills", max_skills)]:
        _check_positive_int(name, value)
    _check_positive_int("num_warmup", num_warmup, 0)
    _check_positive_int("init_window", init_window)
    if init_skills is not None:
        _check_positive_int("init_skills", init_skills)
        if init_skills > max_skills:
            raise ValueError(f"init_skills ({init_skills}) exceeds max_skills ({max_skills})")
    if chain_method not in _CHAIN_METHODS:
        raise ValueError(f"unknown chain_method {chain_method!r}; expected one of {_CHAIN_METHODS}")
    for name, value in [("alpha", alpha), ("kappa", kappa), ("gamma", gamma)]:
        if not (np.isfinite(value) and value > 0 or (name == "kappa" and value == 0)):
            raise ValueError(f"{name} must be a positive number, got {value!r}")
    for name, prior in (hyperpriors or {}).items():
        if name not in ("alpha", "kappa", "gamma"):
            raise ValueError(f"unknown hyperprior {name!r}; expected 'alpha', 'kappa' or 'gamma'")
        if len(prior) != 2 or not all(np.isfinite(p) and p > 0 for p in prior):
            raise ValueError(f"hyperprior {name!r} must be (shape, rate) with positive entries, got {prior!r}")
    em = make_emission(emission, mdp, **(emission_options or {}))
    data = HMMData.from_demonstrations(demos)
    kernel = BPHMMKernel(em, data, max_skills, alpha=alpha, kappa=kappa, gamma=gamma, hyperpriors=hyperpriors,
                         init_skills=init_skills, init_window=init_window)
    mcmc = MCMC(kernel, num_warmup=num_warmup, num_samples=num_samples, num_chains=num_chains,
                chain_method=chain_method if num_chains > 1 else "sequential", progress_bar=progress_bar)
    start = time.perf_counter()
    mcmc.run(jax.random.PRNGKey(seed))
    wall = time.perf_counter() - start
    config = {"emission": em.describe(), "num_chains": num_chains, "num_samples": num_samples,
              "num_warmup": num_warmup, "max_skills": max_skills, "seed": seed, "chain_method": chain_method,
              "alpha": alpha, "kappa": kappa, "gamma": gamma, "hyperpriors": dict(hyperpriors or {}),
              "init_skills": kernel.init_skills, "init_window": init_window}
    return FitResult.from_mcmc(mcmc, demos, config=config, wall_time=wall)
