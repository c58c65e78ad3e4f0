"""The BP-HMM sampler: the jit-able sweep (``kernel``) and its moves (``birth_death``, ``split_merge``, ``greedy``)."""

from .options import MOVE_DEFAULTS, check_moves
from .kernel import BPHMMKernel, BPHMMState, skill_weights
from .birth_death import BirthDeathInfo, birth_death_log_ratio, window_weights
from .split_merge import SplitMergeInfo
from .greedy import GreedyInfo, merge_score
