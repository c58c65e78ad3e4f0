"""Model variants as plain data: the emission, the BP-HMM prior, the truncation and the sampler.

A :class:`ModelConfig` is the full description of a run. It converts to and from nested dicts
(:meth:`ModelConfig.to_dict`, :meth:`ModelConfig.from_dict`) and TOML files
(:meth:`ModelConfig.to_toml`, :meth:`ModelConfig.from_toml`); a bad key or value is a
``ValueError`` that names it, e.g. ``prior.kappa: expected a number, got 'abc'``.

A TOML variant (every key optional; these are the defaults)::

    max_skills = 8

    [emission]
    name = "reward"            # or "subgoal", "autoregressive", "single", "policy", a registered name

    [emission.options]         # keyword options of the emission's from_mdp
    # prior_scale = "auto"

    [prior]
    alpha = 1.0                # a fixed value ...
    gamma = 1.0
    [prior.kappa]              # ... or sampled: Gamma(shape, rate) hyperprior, value = initial value
    value = 10.0
    shape = 2.0
    rate = 0.2
    # switching = "auto"       # "sticky", "state" (skills end with a probability per state entered)
    #                          # or "auto": the sticky fit, then state ends if its skills favour them
    # end_concentration = 8.0  # ... beta_k(s) ~ Beta(c mu_k, c (1 - mu_k)), c this
    # end_mean = [1.0, 9.0]    # ... mu_k ~ Beta(a, b)

    [sampler]
    chains = 4
    samples = 200
    warmup = 200
    seed = 0
    chain_method = "auto"         # threads on a CPU (as many as safe), else vectorized; or "vectorized",
                                  # "sequential", "threads", "parallel" (chains over the local devices)
    # init_window = 25           # default: the emission's (rewards of one weight per state: 5), else 25
    # init_skills = 4             # default: the emission's (rewards of one weight per state: every slot),
                                  # else (max_skills + 1) // 2

    [sampler.moves]            # the kernel's trans-dimensional moves (BPHMMKernel's ``moves``), e.g.
    # birth_death = 2          # birth/death trials per sweep
    # split_merge = 1          # split-merge trials per sweep (emissions with fit_point)
    # blocks = 4               # refits of a split's sequential allocation
    # window = [5, 30]         # (min, max) steps of a birth's window
    # start = 20               # the sweep from which the moves run (plain Gibbs before it)
    # greedy_merge = 0         # greedy merge and split trials per sweep late in warmup
    # greedy_split = 0         # (0: off; fit turns them on for emissions with fit_evidence)
    # greedy_from = 0.5        # ... from this fraction of warmup on
    # greedy_patience = 10     # ... until every chain's last this many greedy sweeps kept nothing (0: never stop)
    # sticky_phase = 0.5       # with switching = "state": the fraction of warmup searched under sticky switching

The moves' defaults are in one table, ``npbrs.inference.sampler.options.MOVE_DEFAULTS`` (every
move off), which the kernel reads too; ``fit`` turns the warmup's greedy moves on where the
configuration does not set them (``npbrs.inference.driver.fit.default_moves``). This module is
plain data: it imports that table and its check, and the ends prior's defaults
(``npbrs.models.bphmm.Termination``), never the kernel.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Dict, Optional, Union

from npbrs.domains.util.files import atomic_write
from npbrs.models.bphmm import Termination

from ..sampler.options import check_moves

__all__ = ["ModelConfig", "EmissionConfig", "PriorConfig", "SamplerConfig", "Hyperparameter", "CHAIN_METHODS"]

CHAIN_METHODS = ("auto", "vectorized", "sequential", "threads", "parallel")


# ------------------------------------------------------------------------------------ checks
def _describe(value) -> str:
    return repr(value) if isinstance(value, str) else f"{value!r} ({type(value).__name__})"


def _number(key: str, value, *, minimum: Optional[float] = None, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or hasattr(value, "shape"):
        try:  # numpy scalars
            import numpy as np

            if isinstance(value, (np.integer, np.floating)) and not isinstance(value, np.bool_):
                value = float(value)
            else:
                raise TypeError
        except TypeError:
            raise ValueError(f"{key}: expected a number, got {_describe(value)}") from None
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{key}: expected a finite number, got {value}")
    if positive and not value > 0:
        raise ValueError(f"{key}: expected a positive number, got {value}")
    if minimum is not None and value < minimum:
        raise ValueError(f"{key}: expected a number >= {minimum}, got {value}")
    return value


def _integer(key: str, value, minimum: Optional[int] = None) -> int:
    try:
        import numpy as np

        if isinstance(value, np.integer):
            value = int(value)
    except ImportError:  # pragma: no cover
        pass
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{key}: expected an integer, got {_describe(value)}")
    if minimum is not None and value < minimum:
        raise ValueError(f"{key}: expected an integer >= {minimum}, got {value}")
    return int(value)


def _table(key: str, value) -> dict:
    if not isinstance(value, dict):
        raise ValueError(f"{key}: expected a table (dict), got {_describe(value)}")
    for k in value:
        if not isinstance(k, str):
            raise ValueError(f"{key}: keys must be strings, got {k!r}")
    return value


def _known(key: str, data: dict, allowed) -> None:
    for k in data:
        if k not in allowed:
            raise ValueError(f"{key + '.' if key else ''}{k}: unknown key; expected one of {', '.join(allowed)}")


def _plain(key: str, value):
    """A copy of ``value`` made of TOML-writable data (str, bool, int, float, lists, tables)."""
    if isinstance(value, (bool, str)):
        return value
    if isinstance(value, (int, float)):
        return value
    try:
        import numpy as np

        if isinstance(value, np.bool_):
            return bool(value)
        if isinstance(value, np.integer):
            return int(value)
        if isinstance(value, np.floating):
            return float(value)
        if isinstance(value, np.ndarray):
            return [_plain(f"{key}[{i}]", v) for i, v in enumerate(value.tolist())]
    except ImportError:  # pragma: no cover
        pass
    if isinstance(value, (list, tuple)):
        return [_plain(f"{key}[{i}]", v) for i, v in enumerate(value)]
    if isinstance(value, dict):
        return {k: _plain(f"{key}.{k}", v) for k, v in _table(key, value).items()}
    raise ValueError(f"{key}: expected plain data (a number, string, boolean, list or table), got {_describe(value)}")


def _check_moves(moves: dict) -> None:
    """The move options' check (the table the kernel reads), as a ValueError naming ``sampler.moves``."""
    try:
        check_moves(moves)
    except (ValueError, TypeError) as e:
        message = str(e)
        if message.startswith("moves."):
            message = "sampler." + message
        raise ValueError(message if message.startswith("sampler.") else f"sampler.moves: {message}") from None


# ----------------------------------------------------------------------------- the parts
@dataclass
class EmissionConfig:
    """The emission model: a registered name and the keyword options of its ``from_mdp``.

    ``name`` may also be a registered Emission class; it is stored as its registered name.
    """

    name: str = "reward"
    options: Dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        if isinstance(self.name, type):
            from npbrs.models.emissions import EMISSIONS

            registered = [n for n, c in EMISSIONS.items() if c is self.name]
            if not registered:
                raise ValueError(f"emission.name: class {self.name.__name__} is not registered; decorate it with "
                                 f"npbrs.models.emissions.register_emission(name)")
            self.name = registered[0]
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"emission.name: expected a non-empty string, got {_describe(self.name)}")
        self.options = _plain("emission.options", _table("emission.options", self.options))

    @classmethod
    def from_dict(cls, data) -> "EmissionConfig":
        if isinstance(data, str):
            return cls(data)
        data = _table("emission", data)
        _known("emission", data, ("name", "options"))
        return cls(**data)

    def to_dict(self) -> dict:
        return {"name": self.name, "options": _plain("emission.options", self.options)}


@dataclass
class Hyperparameter:
    """A BP-HMM hyperparameter: fixed at ``value``, or sampled under a Gamma(shape, rate)
    hyperprior starting from ``value`` (when ``shape`` and ``rate`` are given)."""

    value: float
    shape: Optional[float] = None
    rate: Optional[float] = None

    @property
    def sampled(self) -> bool:
        return self.shape is not None

    def _check(self, key: str, allow_zero: bool) -> "Hyperparameter":
        if (self.shape is None) != (self.rate is None):
            raise ValueError(f"{key}: a hyperprior needs both shape and rate")
        self.value = _number(f"{key}.value" if self.sampled else key, self.value, minimum=0.0)
        if self.sampled:
            self.shape = _number(f"{key}.shape", self.shape, positive=True)
            self.rate = _number(f"{key}.rate", self.rate, positive=True)
        if not (self.value > 0 or (allow_zero and not self.sampled)):
            raise ValueError(f"{key}{'.value' if self.sampled else ''}: expected a positive number, got {self.value}")
        return self

    @classmethod
    def parse(cls, key: str, data, allow_zero: bool = False) -> "Hyperparameter":
        """From a number (fixed), a {value, shape, rate} table, or a Hyperparameter."""
        if isinstance(data, Hyperparameter):
            return cls(data.value, data.shape, data.rate)._check(key, allow_zero)
        if isinstance(data, dict):
            _known(key, data, ("value", "shape", "rate"))
            if ("shape" in data) != ("rate" in data):
                raise ValueError(f"{key}: a hyperprior needs both shape and rate")
            if "value" not in data and "shape" in data and "rate" in data:
                shape = _number(f"{key}.shape", data["shape"], positive=True)
                rate = _number(f"{key}.rate", data["rate"], positive=True)
                data = {**data, "value": shape / rate}  # start at the hyperprior's mean
            if "value" not in data:
                raise ValueError(f"{key}.value: missing")
            return cls(data["value"], data.get("shape"), data.get("rate"))._check(key, allow_zero)
        return cls(_number(key, data))._check(key, allow_zero)

    def to_data(self):
        return self.value if not self.sampled else {"value": self.value, "shape": self.shape, "rate": self.rate}


@dataclass
class PriorConfig:
    """BP-HMM hyperparameters: IBP mass ``alpha``, stickiness ``kappa`` (0 allowed when fixed),
    transition concentration ``gamma``; each a number (fixed) or a :class:`Hyperparameter`.

    ``switching``: "sticky" (the paper's BP-HMM: a skill continues with a probability of its
    trajectory's, wherever the agent is), "state" (skills are options that end with a
    probability per state entered, beta_k(s) ~ Beta(c mu_k, c (1 - mu_k)), mu_k ~ Beta(a, b):
    ``end_concentration`` c, ``end_mean`` (a, b); see ``npbrs.models.bphmm``) or "auto" (the
    default: ``fit`` fits the sticky model and refits with state-dependent ends when the sticky
    fit's skill sequences favour them by a Bayes factor; a fit's recorded configuration says
    which it chose)."""

    alpha: Union[float, Hyperparameter] = 1.0
    kappa: Union[float, Hyperparameter] = 10.0
    gamma: Union[float, Hyperparameter] = 1.0
    switching: str = "auto"
    end_concentration: float = Termination._field_defaults["concentration"]
    end_mean: Any = Termination._field_defaults["mean_prior"]

    NAMES = ("alpha", "kappa", "gamma")
    SWITCHING = ("sticky", "state", "auto")
    KEYS = NAMES + ("switching", "end_concentration", "end_mean")

    def __post_init__(self):
        for name in self.NAMES:
            setattr(self, name, Hyperparameter.parse(f"prior.{name}", getattr(self, name), allow_zero=name == "kappa"))
        if self.switching not in self.SWITCHING:
            raise ValueError(f"prior.switching: expected one of {', '.join(map(repr, self.SWITCHING))}, "
                             f"got {_describe(self.switching)}")
        self.end_concentration = _number("prior.end_concentration", self.end_concentration, positive=True)
        mean = self.end_mean
        if not isinstance(mean, (list, tuple)) or len(mean) != 2:
            raise ValueError(f"prior.end_mean: expected (a, b), the Beta prior of each skill's mean end "
                             f"probability, got {_describe(mean)}")
        self.end_mean = tuple(_number(f"prior.end_mean[{i}]", v, positive=True) for i, v in enumerate(mean))

    @property
    def hyperpriors(self) -> Dict[str, tuple]:
        """{name: (shape, rate)} of the sampled hyperparameters."""
        return {n: (getattr(self, n).shape, getattr(self, n).rate) for n in self.NAMES if getattr(self, n).sampled}

    @classmethod
    def from_dict(cls, data) -> "PriorConfig":
        data = _table("prior", data)
        _known("prior", data, cls.KEYS)
        return cls(**data)

    def to_dict(self) -> dict:
        out = {n: getattr(self, n).to_data() for n in self.NAMES}
        keys = ("switching", "end_concentration", "end_mean")
        ends = {k: getattr(self, k) for k in keys}
        if ends != {k: getattr(PriorConfig, k) for k in keys}:
            out.update(ends, end_mean=list(self.end_mean))  # (the default description stays short)
        return out


#: ``SamplerConfig.restart_margin``'s default, in nats (``docs/design.md``)
RESTART_MARGIN = 50.0


@dataclass
class SamplerConfig:
    """MCMC settings.

    chains, samples, warmup: number of chains and of sweeps per chain kept / discarded;
    seed: the random seed; chain_method: "auto" (the default: "threads" when JAX computes on
    the CPU and the run has several chains, on up to
    ``npbrs.inference.threads.max_threads`` threads, one of them the sequential chains;
    else "vectorized"), "vectorized" (the
    chains batched in one program), "sequential" (one chain after another), "threads" (each
    chain's sweep its own program call, on up to ``max_threads`` threads at once: the same
    draws as "sequential") or "parallel"
    (the vectorized sweep with the chains spread over the local devices, ``jax.sharding``; see
    ``fit``'s ``devices``);
    init_skills, init_window: the initial segmentation (skills used, default the emission's
    ``initial_skills(max_skills)`` where it gives one (rewards of one weight per state: every
    slot), else (max_skills + 1) // 2; window length, default the emission's ``init_window`` where
    it has one, else 25: ``fit`` records the values it used);
    moves: options of the kernel's trans-dimensional moves, passed to ``BPHMMKernel(moves=...)``
    and checked against :mod:`npbrs.inference.sampler.options`, the table the kernel reads
    (defaults: ``MOVE_DEFAULTS`` there, every move off).
    bucket: pad the demonstrations to bucket sizes of trajectories and steps
    (:func:`npbrs.models.emissions.bucket_size`), so that a data set of similar size reuses the
    compiled sampler. The padding trajectories have no steps: the posterior of the real ones is
    the same, but the random streams have other shapes, so the draws differ from an unpadded
    run's (the same seed gives the same draws with the same setting).
    max_samples, target_rhat, time_budget: a run length chosen by convergence. With
    ``max_samples`` above ``samples`` (0, the default: off), the chains keep sampling after
    ``samples`` sweeps, ``max(samples // 2, 1)`` sweeps at a time, until the rank-normalised
    split R-hat of every label-invariant scalar (log joint, number of skills, number of switches)
    is at most ``target_rhat`` (a scalar constant over every draw of every chain counts as
    converged), or ``max_samples`` sweeps are drawn, or more than ``time_budget`` seconds
    (0: no budget) have passed since the run started. The first two rules depend on the draws
    only, so the same seed gives the same run; the time budget depends on the machine. The
    result's ``run_length`` says which rule stopped the run and the R-hat reached. Needs at
    least 2 chains.
    restart_margin: at the end of warmup, every chain is scored by its log joint (log p(x, z,
    F, parameters, eta, omega, hyperparameters), the draws' ``log_joint``) averaged over the last
    tenth of the warmup sweeps (at least the last one), and a chain more than this many nats
    below the best chain continues from the best chain's state with its own random key (50 by
    default; 0 is off). The warmup's draws are discarded, so this changes where the sampling
    sweeps start, not what they sample: a chain that far behind has stalled in a region the
    best chain has left behind, and its draws would only blur the estimates and hold R-hat up.
    Chains within the margin keep their own states, so modes of comparable probability stay
    visible to R-hat. The result's ``restart`` records the scores and which chains moved.
    Needs at least 2 chains and a warmup.
    checkpoint_every: sweeps between the checkpoints of a run given a checkpoint path (100).
    grow: when every skill slot was in use in more than half of the sampling draws (the
    truncation ``max_skills`` may be hiding skills), fit again with twice the slots, starting
    from the run's best segmentation, until it is not so or 64 slots; the result's
    ``truncation`` records each fit. Without it such a run warns. Not with checkpoints.
    """

    chains: int = 4
    samples: int = 200
    warmup: int = 200
    seed: int = 0
    chain_method: str = "auto"
    init_skills: Optional[int] = None
    init_window: Optional[int] = None
    moves: Dict[str, Any] = field(default_factory=dict)
    bucket: bool = False
    max_samples: int = 0
    target_rhat: float = 1.05
    time_budget: float = 0.0
    restart_margin: float = RESTART_MARGIN
    checkpoint_every: int = 100
    grow: bool = False

    def __post_init__(self):
        self.chains = _integer("sampler.chains", self.chains, 1)
        self.samples = _integer("sampler.samples", self.samples, 1)
        self.warmup = _integer("sampler.warmup", self.warmup, 0)
        self.seed = _integer("sampler.seed", self.seed, 0)
        if self.chain_method not in CHAIN_METHODS:
            raise ValueError(f"sampler.chain_method: expected one of {', '.join(CHAIN_METHODS)}, "
                             f"got {_describe(self.chain_method)}")
        if self.init_skills is not None:
            self.init_skills = _integer("sampler.init_skills", self.init_skills, 1)
        if self.init_window is not None:
            self.init_window = _integer("sampler.init_window", self.init_window, 1)
        self.moves = _plain("sampler.moves", _table("sampler.moves", self.moves))
        _check_moves(self.moves)
        if not isinstance(self.bucket, bool):
            raise ValueError(f"sampler.bucket: expected true or false, got {_describe(self.bucket)}")
        self.bucket = bool(self.bucket)
        self.max_samples = _integer("sampler.max_samples", self.max_samples, 0)
        if self.max_samples and self.max_samples < self.samples:
            raise ValueError(f"sampler.max_samples: {self.max_samples} is below sampler.samples ({self.samples}); "
                             "it is the most sweeps a run extended until convergence may draw (0: no extension)")
        if self.max_samples > self.samples and self.chains < 2:
            raise ValueError("sampler.max_samples: a run length chosen by convergence (R-hat across chains) needs "
                             f"at least 2 chains, got {self.chains}")
        self.target_rhat = _number("sampler.target_rhat", self.target_rhat)
        if not self.target_rhat > 1.0:
            raise ValueError(f"sampler.target_rhat: expected a number above 1 (R-hat is at least 1), got "
                             f"{self.target_rhat}")
        self.time_budget = _number("sampler.time_budget", self.time_budget, minimum=0.0)
        self.restart_margin = _number("sampler.restart_margin", self.restart_margin, minimum=0.0)
        self.checkpoint_every = _integer("sampler.checkpoint_every", self.checkpoint_every, 1)
        if not isinstance(self.grow, bool):
            raise ValueError(f"sampler.grow: expected true or false, got {_describe(self.grow)}")

    @classmethod
    def from_dict(cls, data) -> "SamplerConfig":
        data = _table("sampler", data)
        _known("sampler", data, [f.name for f in dataclasses.fields(cls)])
        return cls(**data)

    def to_dict(self) -> dict:
        return {f.name: (dict(self.moves) if f.name == "moves" else getattr(self, f.name))
                for f in dataclasses.fields(self)}


# ----------------------------------------------------------------------------- the whole
@dataclass
class ModelConfig:
    """A model variant and how to sample it.

    Args:
        emission: an :class:`EmissionConfig` (or a registered name, or a dict).
        prior: a :class:`PriorConfig` (or a dict).
        max_skills: truncation K of the beta process (skill slots), at least 1.
        sampler: a :class:`SamplerConfig` (or a dict).

    Example:
        >>> cfg = ModelConfig(emission=EmissionConfig("policy", {"concentration": 0.5}),
        ...                   prior=PriorConfig(kappa=Hyperparameter(10.0, shape=2.0, rate=0.2)),
        ...                   max_skills=6, sampler=SamplerConfig(chains=2, samples=100))
        >>> ModelConfig.from_dict(cfg.to_dict()) == cfg
        True
    """

    emission: EmissionConfig = field(default_factory=EmissionConfig)
    prior: PriorConfig = field(default_factory=PriorConfig)
    max_skills: int = 8
    sampler: SamplerConfig = field(default_factory=SamplerConfig)

    def __post_init__(self):
        if isinstance(self.emission, (str, type)):
            self.emission = EmissionConfig(self.emission)
        elif isinstance(self.emission, dict):
            self.emission = EmissionConfig.from_dict(self.emission)
        elif not isinstance(self.emission, EmissionConfig):
            raise ValueError(f"emission: expected an EmissionConfig, a name or a table, got {_describe(self.emission)}")
        for name, cls in (("prior", PriorConfig), ("sampler", SamplerConfig)):
            value = getattr(self, name)
            if isinstance(value, dict):
                setattr(self, name, cls.from_dict(value))
            elif not isinstance(value, cls):
                raise ValueError(f"{name}: expected a {cls.__name__} or a table, got {_describe(value)}")
        self.max_skills = _integer("max_skills", self.max_skills, 1)
        if self.sampler.init_skills is not None and self.sampler.init_skills > self.max_skills:
            raise ValueError(f"sampler.init_skills: {self.sampler.init_skills} exceeds max_skills ({self.max_skills})")

    # ------------------------------------------------------------------ dicts
    @classmethod
    def from_dict(cls, data: dict) -> "ModelConfig":
        """From nested plain data (as written by :meth:`to_dict` or read from TOML); keys may be omitted."""
        data = _table("", data) if isinstance(data, dict) else _table("config", data)
        _known("", data, ("emission", "prior", "max_skills", "sampler"))
        return cls(emission=EmissionConfig.from_dict(data.get("emission", {})),
                   prior=PriorConfig.from_dict(data.get("prior", {})),
                   max_skills=data.get("max_skills", 8),
                   sampler=SamplerConfig.from_dict(data.get("sampler", {})))

    def to_dict(self) -> dict:
        """Nested plain data (JSON-serialisable)."""
        return {"emission": self.emission.to_dict(), "prior": self.prior.to_dict(), "max_skills": self.max_skills,
                "sampler": self.sampler.to_dict()}

    def replace(self, **changes) -> "ModelConfig":
        """A copy with some parts replaced, e.g. ``cfg.replace(sampler=dataclasses.replace(cfg.sampler, seed=1))``."""
        return ModelConfig.from_dict({**self.to_dict(), **{k: (v.to_dict() if hasattr(v, "to_dict") else v)
                                                            for k, v in changes.items()}})

    # ------------------------------------------------------------------ TOML
    @classmethod
    def from_toml(cls, path) -> "ModelConfig":
        """Read a TOML file (see the module docstring for its keys)."""
        import tomllib
        try:
            with open(path, "rb") as f:
                data = tomllib.load(f)
        except tomllib.TOMLDecodeError as e:
            raise ValueError(f"{path}: not valid TOML: {e}") from None
        try:
            return cls.from_dict(data)
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from None

    @classmethod
    def from_toml_string(cls, text: str) -> "ModelConfig":
        import tomllib
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as e:
            raise ValueError(f"not valid TOML: {e}") from None
        return cls.from_dict(data)

    def to_toml(self, path=None) -> str:
        """This config as TOML text; also written (atomically) to ``path`` when given."""
        text = _toml_document(self.to_dict())
        if path is not None:
            def write(tmp):
                with open(tmp, "w", encoding="utf-8") as f:
                    f.write(text)

            atomic_write(path, write, suffix=".toml.tmp")
        return text


# ------------------------------------------------------------------------- a TOML writer
def _toml_key(key: str) -> str:
    if key and all(c.isalnum() or c in "-_" for c in key) and key.isascii():
        return key
    return _toml_string(key)


def _toml_string(s: str) -> str:
    out = ['"']
    for c in s:
        if c == '"':
            out.append('\\"')
        elif c == "\\":
            out.append("\\\\")
        elif c == "\n":
            out.append("\\n")
        elif c == "\t":
            out.append("\\t")
        elif ord(c) < 0x20 or ord(c) == 0x7F:
            out.append(f"\\u{ord(c):04x}")
        else:
            out.append(c)
    out.append('"')
    return "".join(out)


def _toml_value(key: str, value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)  # shortest round-tripping form, always with '.' or 'e'
    if isinstance(value, str):
        return _toml_string(value)
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(f"{key}[{i}]", v) for i, v in enumerate(value)) + "]"
    if isinstance(value, dict):  # a table inside a list: inline
        return "{" + ", ".join(f"{_toml_key(k)} = {_toml_value(f'{key}.{k}', v)}"
                               for k, v in value.items() if v is not None) + "}"
    raise ValueError(f"{key}: cannot be written as TOML: {_describe(value)}")


def _toml_document(data: dict) -> str:
    lines = []

    def table(prefix: str, d: dict):
        scalars = {k: v for k, v in d.items() if not isinstance(v, dict) and v is not None}
        tables = {k: v for k, v in d.items() if isinstance(v, dict)}
        if prefix and (scalars or not tables):
            if lines:
                lines.append("")
            lines.append(f"[{prefix}]")
        for k, v in scalars.items():
            lines.append(f"{_toml_key(k)} = {_toml_value(f'{prefix}.{k}' if prefix else k, v)}")
        for k, v in tables.items():
            table(f"{prefix}.{_toml_key(k)}" if prefix else _toml_key(k), v)

    table("", data)
    return "\n".join(lines) + "\n"

