"""Running the sampler: ``fit`` and its configuration (:mod:`.config`), the run (:mod:`.loop`,
:mod:`.strategies`, :mod:`.chains`, :mod:`.devices`, :mod:`.compiled`, :mod:`.progress`), its
results (:mod:`.results`) and their files (:mod:`.runs`)."""

from .config import EmissionConfig, Hyperparameter, ModelConfig, PriorConfig, SamplerConfig
from .results import LABEL_INVARIANT, ConvergenceWarning, FitResult
from .runs import load, load_mdp, save_mdp
from .devices import device_mesh
from .fit import fit, resolve_config
