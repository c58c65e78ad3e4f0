"""``fit``: segment demonstrations into skills with the BP-HMM sampler.

The model and the sampler are described by one :class:`~npbrs.inference.driver.config.ModelConfig`;
``fit`` takes it (or a dict of its options, or a TOML file) and what a run needs besides. The run
itself is :mod:`.loop` (sweeps, checkpoints, run length), around which :mod:`.strategies` chooses
the switching model and grows the skill slots; :mod:`.chains`, :mod:`.devices`, :mod:`.compiled`
and :mod:`.progress` hold the chain methods, device meshes, the compiled programs and the
progress bar (see ``docs/design.md``).
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from typing import Optional, Union

import jax
import numpy as np

from npbrs.domains.demos import Demonstrations
from npbrs.domains.util.precision import float64
from npbrs.models.emissions import Emission

from ..analysis.diagnostics import ConvergenceWarning
from .config import EmissionConfig, ModelConfig, PriorConfig, SamplerConfig
from .progress import user_stacklevel
from .results import FitResult
from .strategies import fit_auto, fit_grown

__all__ = ["fit", "resolve_config", "warn_if_unconverged", "OPTIONS"]

#: Keyword arguments of ``fit`` that stand for sampler fields.
_RUN_SIZES = {"num_chains": "chains", "num_samples": "samples", "num_warmup": "warmup"}
#: The options a flat dict (or :func:`resolve_config`'s keywords) may set: the emission, its
#: options, the truncation, every prior field and hyperpriors, and every sampler field.
OPTIONS = (("emission", "emission_options", "max_skills", "hyperpriors")
           + tuple(f.name for f in dataclasses.fields(PriorConfig))
           + tuple(f.name for f in dataclasses.fields(SamplerConfig)) + tuple(_RUN_SIZES))


def _base(config) -> tuple:
    """(ModelConfig, flat options) of ``config``: a dict's sections (``prior``, ``sampler``, an
    ``emission`` table) are read as the TOML file's, its other keys are options."""
    if config is None:
        return ModelConfig(), {}
    if isinstance(config, ModelConfig):
        return config, {}
    if isinstance(config, dict):
        nested = {k: v for k, v in config.items()
                  if k in ("prior", "sampler") or (k == "emission" and isinstance(v, dict))}
        return ModelConfig.from_dict(nested), {k: v for k, v in config.items() if k not in nested}
    if isinstance(config, (str, os.PathLike)):
        return ModelConfig.from_toml(config), {}
    raise ValueError(f"config must be a ModelConfig, a dict or a TOML path, got {type(config).__name__}")


def resolve_config(config=None, **options) -> ModelConfig:
    """The validated model and sampler configuration of a fit.

    Args:
        config: a :class:`ModelConfig`, a TOML path, None (the defaults), or a dict: its
            sections ``prior`` / ``sampler`` / an ``emission`` table as in the TOML file, and
            any flat option of :data:`OPTIONS` (e.g. ``{"emission": "policy", "alpha": 2.0,
            "max_skills": 4, "moves": {"birth_death": 2}}``; an Emission instance may stand for
            the emission).
        **options: more flat options, applied last (None: not given).
    Returns:
        the ModelConfig.
    Raises:
        ValueError: an unknown option or a value out of range, naming it.
    """
    cfg, flat = _base(config)
    flat = {k: v for k, v in {**flat, **options}.items() if v is not None}  # (None: not given)
    unknown = sorted(k for k in flat if k not in OPTIONS)
    if unknown:
        raise ValueError(f"config: unknown option{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))}; "
                         f"the options are {', '.join(OPTIONS)} and the sections prior, sampler, emission")
    data = cfg.to_dict()
    emission, emission_options = flat.pop("emission", None), flat.pop("emission_options", None)
    if isinstance(emission, Emission):
        description = dict(emission.describe())
        data["emission"] = {"name": description.pop("name", emission.name), "options": description}
        if emission_options:
            raise ValueError(f"emission options {sorted(emission_options)} given with an emission instance")
    elif emission is not None:
        if isinstance(emission, type):
            emission = EmissionConfig(emission).name
        same = emission == data["emission"]["name"]
        data["emission"] = {"name": emission, "options": data["emission"]["options"] if same else {}}
    if emission_options is not None:
        data["emission"]["options"] = dict(emission_options)
    if "max_skills" in flat:
        data["max_skills"] = flat.pop("max_skills")
    hyperpriors = flat.pop("hyperpriors", None)
    for name in PriorConfig.NAMES:
        if name in flat:
            value, current = flat.pop(name), data["prior"][name]
            data["prior"][name] = {**current, "value": value} if isinstance(current, dict) else value
    if hyperpriors is not None:
        if not isinstance(hyperpriors, dict):
            raise ValueError(f"hyperpriors must be a dict {{name: (shape, rate)}}, got {hyperpriors!r}")
        for name, prior in hyperpriors.items():
            if name not in PriorConfig.NAMES:
                raise ValueError(f"prior.{name}: unknown hyperparameter; expected alpha, kappa or gamma")
            try:
                shape, rate = prior
            except (TypeError, ValueError):
                raise ValueError(f"prior.{name}: a hyperprior is (shape, rate), got {prior!r}") from None
            current = data["prior"][name]
            value = current["value"] if isinstance(current, dict) else current
            data["prior"][name] = {"value": value, "shape": shape, "rate": rate}
    prior_fields = {f.name for f in dataclasses.fields(PriorConfig)}
    for key, value in flat.items():
        if key in prior_fields:
            data["prior"][key] = list(value) if key == "end_mean" else value
        else:
            data["sampler"][_RUN_SIZES.get(key, key)] = value
    return ModelConfig.from_dict(data)


def _emission_instance(config) -> Optional[Emission]:
    """The Emission instance a dict config names, if any."""
    emission = config.get("emission") if isinstance(config, dict) else None
    return emission if isinstance(emission, Emission) else None


def fit(mdp, demos: Demonstrations, config: Union[ModelConfig, dict, str, os.PathLike, None] = None, *,
        num_chains: Optional[int] = None, num_samples: Optional[int] = None, num_warmup: Optional[int] = None,
        seed: Optional[int] = None, init_segmentation=None, progress_bar: bool = True, checkpoint_path=None,
        resume: bool = False, devices=None) -> FitResult:
    """Segment demonstrations into skills.

    Args:
        mdp: the TabularMDP the demonstrations live in.
        demos: :class:`~npbrs.domains.Demonstrations`.
        config: the model and sampler (see :func:`resolve_config`): a
            :class:`~npbrs.inference.driver.config.ModelConfig`, a TOML file, or a dict of
            options such as ``{"emission": "policy", "max_skills": 4, "switching": "sticky"}``.
            Defaults: the reward emission, 8 skill slots, ``switching="auto"``, 4 chains of 200
            warmup and 200 sampling sweeps (``docs/fitting.md``).
        num_chains, num_samples, num_warmup: MCMC sizes (sweeps per chain), over the config's.
        seed: the random seed, over the config's; the same seed gives the same draws, bit for bit.
        init_segmentation: start every chain from this segmentation instead of random windows:
            per trajectory an integer label per step, or a FitResult.
        progress_bar: show progress (a bar in a terminal or notebook, a line every tenth of the
            sweeps otherwise).
        checkpoint_path: write a checkpoint (``.npz``) there every ``checkpoint_every`` sweeps
            (config), at the end, and on Ctrl-C (then KeyboardInterrupt is re-raised).
        resume: continue from ``checkpoint_path`` when it exists (without it an existing
            checkpoint is refused, never overwritten); the result equals an uninterrupted run's.
        devices: run on several devices: a number of devices, a list of ``jax.Device``, "all",
            or a ``jax.sharding.Mesh`` with axes "chains" and/or "trajectories"
            (``docs/speed.md``); the draws are those of the one-device run with the same seed.
    Returns:
        a :class:`~npbrs.inference.driver.results.FitResult`.
    Warns:
        ConvergenceWarning: the draws fail the label-invariant diagnostics (an R-hat above 1.05
            or an ESS below 100; ``result.summary()`` says how each chain moved).
        UserWarning: every skill slot was in use in most of the draws (without ``grow``).
    Raises:
        ValueError: bad demonstrations, configuration, devices or checkpoint, before anything is
            compiled.
    """
    with jax.threefry_partitionable(True):  # (each draw numbered by its position: devices and padding do not matter)
        cfg = resolve_config(config, num_chains=num_chains, num_samples=num_samples, num_warmup=num_warmup, seed=seed)
        if cfg.sampler.grow and checkpoint_path is not None:
            raise ValueError("grow=True refits with more skill slots, which a checkpoint of one run cannot hold; "
                             "give either grow or checkpoint_path")
        run = dict(init_segmentation=init_segmentation, progress_bar=progress_bar, checkpoint_path=checkpoint_path,
                   resume=resume, devices=devices)
        strategy = fit_auto if cfg.prior.switching == "auto" else fit_grown
        result = strategy(mdp, demos, cfg, _emission_instance(config), **run)
    result = with_action_names(result, mdp, demos, _emission_instance(config))
    warn_if_unconverged(result)
    return result


def with_action_names(result: FitResult, mdp, demos, emission: Optional[Emission] = None) -> FitResult:
    """``result`` with its ``action_names`` set where its emission learns which of several
    equivalent actions the demonstrator names (:mod:`npbrs.models.names`)."""
    from npbrs.models.names import ActionNames

    learns = (emission.learns_action_names if emission is not None
              else result.emission.get("action_names") == "learned")
    if not learns:
        return result
    names = ActionNames.fit(mdp, demos)
    if not len(names.counts.sets):  # (no state the demonstrations visit has equivalent actions)
        return result
    return dataclasses.replace(result, action_names={
        "sets": [np.flatnonzero(s).tolist() for s in names.counts.sets],
        "log_bayes_factor": names.log_bayes_factor, "text": names.describe()})


def warn_if_unconverged(result: FitResult) -> None:
    """A :class:`ConvergenceWarning` naming the user's call when ``result`` fails the
    label-invariant diagnostics (what its summary says, in one line)."""
    text = result.convergence_warning()
    if text:
        warnings.warn(f"npbrs.fit: {text.splitlines()[0]}; result.summary() shows how each chain moved",
                      ConvergenceWarning, stacklevel=user_stacklevel())


# float64 inside, the user's setting outside (npbrs.domains.util.precision)
fit, resolve_config = float64(fit), float64(resolve_config)
