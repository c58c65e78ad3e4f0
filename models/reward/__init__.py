"""The reward emission: each skill a linear reward r_k = phi . theta_k, each step an action of the
Boltzmann policy of its soft Bellman equation (maximum-entropy IRL).

- :mod:`.likelihood`: count tables, Boltzmann policies, log-likelihoods and their gradients, the
  Fisher information, and the one density of a skill's weights (:func:`log_posterior`);
- :mod:`.prior`: the prior of the weights (Gaussian, Student t, sampled scale) and its "auto" choice;
- :mod:`.irl`: maximum a posteriori IRL fits (L-BFGS), :func:`irl_fit`;
- :mod:`.mala`: the reward move's MALA kernel (``init`` / ``build_kernel``);
- :mod:`.moves`: the emission's update (MALA or MAP), its warmup tuning, the data-driven proposals;
- :mod:`.evidence`: the Laplace and scale-mixture evidences of the greedy moves;
- :mod:`.emission`: :class:`RewardEmission` and :class:`SingleRewardEmission`, assembled from them.
"""

from .prior import PRIOR_SCALE, auto_prior_df, auto_prior_scale, check_prior_df, log_prior, prior_curvature, prior_grad
from .likelihood import (Posterior, as_solver, count_log_likelihood, count_log_likelihood_and_grad,
                         count_log_likelihood_and_values, count_table, fisher_information, log_policy, log_posterior,
                         noisy_log_policy, step_log_likelihoods)
from .irl import IRLFit, fit_reward, irl_fit
from .mala import RewardMALAInfo, RewardMALAState
from .emission import RewardEmission, SingleRewardEmission
