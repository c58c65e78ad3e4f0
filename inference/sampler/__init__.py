"""The BP-HMM sampler: the jit-able exact sweep (``kernel``) of the chain's state (``state``),
its Gibbs conditionals (``conditionals``) and moves (``birth_death``, ``split_merge``), and the
warmup aids around it (``schedule``, whose greedy moves are ``greedy``)."""

from .options import MOVE_DEFAULTS, check_moves
from .state import BPHMMState, MoveState
from .kernel import BPHMMKernel, skill_weights
from .birth_death import BirthDeathInfo, birth_death_log_ratio, birth_death_proposal, window_weights
from .split_merge import SplitMergeInfo, SplitMergeProposal, propose_split_merge, split_merge_log_ratio
from .greedy import (GreedyInfo, greedy_merge, greedy_merge_at, greedy_split, greedy_split_at, greedy_trials, merge_score,
                     structure_log_prob)
from .schedule import WarmupSchedule
from .conditionals import (feature_conditional, sample_end_model, sample_eta_omega, sample_features,
                           sample_hyperparameters)
