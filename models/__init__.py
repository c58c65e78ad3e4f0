"""Probability: HMM inference on arrays, emission models, and the BP-HMM NumPyro model."""

from .hmm import (batch_backward_sample, batch_forward_filter, batch_viterbi, backward_sample, forward_filter,
                  initial_counts, transition_counts, viterbi)
from .emissions import EMISSIONS, Emission, HMMData, PolicyEmission, get_emission_class, register_emission
from .bphmm import Hyper, bphmm_model
from .subgoal import SubgoalEmission, visited_states
from .autoregressive import AutoregressiveEmission
from .reward.emission import RewardEmission, SingleRewardEmission
from .reward.prior import PRIOR_SCALE, log_prior
from .reward.likelihood import (count_log_likelihood, count_log_likelihood_and_grad, count_log_likelihood_and_values,
                                count_table, fisher_information, log_policy, log_posterior, step_log_likelihoods)
from .reward.irl import IRLFit, fit_reward, irl_fit
from .names import ActionNames
from . import mcmc
from .reward import mala as reward_mala  # reward_mala.init / reward_mala.build_kernel: the reward move
from .reward.mala import RewardMALAInfo, RewardMALAState
