"""Running the sampler: ``fit`` (chains, devices, checkpoints), its configuration, its results and their files."""

from .config import EmissionConfig, Hyperparameter, ModelConfig, PriorConfig, SamplerConfig
from .results import LABEL_INVARIANT, ConvergenceWarning, FitResult
from .runs import load, load_mdp, save_mdp
from .fit import device_mesh, make_emission, resolve_config
