"""Emission models of the BP-HMM: what a skill says about each step of a demonstration.

The segmentation machinery only ever sees an (N, T, K) array of per-step log-likelihoods.
An emission model supplies everything that depends on what a skill *is*:

- ``sample_params(K)``: a NumPyro fragment that draws the K skills' parameters from the
  prior as sample sites and returns them as a dict ``{site name: array with leading axis K}``;
- ``log_prior(params) -> (K,)``: the same prior's log density per skill (tested equal to
  the sites' log-probabilities);
- ``log_likelihoods(params, data, cache) -> ((N, T, K), cache)``: per-step log-likelihoods
  (``cache`` is a speed-up only, e.g. the previous soft values to warm-start a solve; the
  answer must not depend on it beyond solver tolerance);
- ``update(key, params, cache, data, weights, adapt) -> (params, cache, info)``: a move that
  leaves the conditional posterior of every skill's parameters given its steps invariant
  (``weights`` (N, T, K) is the one-hot of the sampled skill sequence; ``adapt`` is True
  during warmup only, when the move may tune itself, e.g. step sizes kept in the cache);
  ``info`` is an :class:`EmissionInfo` (diagnostics only);
- ``propose(key, data, weights) -> (params_one, log_q)`` and
  ``log_proposal(params_one, data, weights) -> log_q``: a data-driven proposal of one new
  skill's parameters from weighted steps (a window of a trajectory, or one side of a split);
  used by the trans-dimensional moves;
- ``init_cache(K)`` and ``init_params(key, data, weights)``: the cache's initial value and a
  data-driven starting point for a chain.
- optionally ``tune(params, cache, data, weights) -> cache`` with an integer attribute
  ``tune_every``: expensive warmup-only tuning of the move (e.g. a preconditioner), which the
  sampler runs before ``update`` in the first warmup sweep and every ``tune_every`` warmup
  sweeps after it, never in the sampling sweeps. An emission that declares
  ``tunes_in_update`` has its ``update`` passed a keyword ``tune`` (a bool, shared by vectorised
  chains) instead, true in those sweeps, and tunes itself there (the reward emission: where its
  move's first pass has solved what the tuning needs).
- ``redraw_unused`` (an integer class attribute, 1 by default): the sweeps between the prior
  redraws of unused skills' parameters that ``fit`` asks the sampler for
  (``moves["redraw_unused"]``: in between they are kept, also an exact move); more than 1 where a
  new draw's likelihoods are expensive (a soft Bellman solve from a cold start).
- optionally ``solves_in_update`` (a bool, False by default): ``update`` then takes
  ``redraw_unused`` (whether the skills without steps get prior draws in this sweep, else keep
  their parameters; the sampler stops choosing for it) and returns a cache from which
  ``log_likelihoods(params, data, cache, solved=True)`` gives the likelihoods of the parameters it
  returned without evaluating them afresh (the reward emission: its move's values).
- optionally ``reports_solves`` (a bool, False by default): ``log_likelihoods(params, data,
  cache, with_ok=True)`` then returns ``(ll, cache, ok)``, ok (K,) True where the likelihoods of
  skill k are to be trusted (the reward emission: its soft solve converged to the solver's
  tolerance and the log-likelihoods are finite), the cache as without it. The trans-dimensional
  moves reject a proposal whose new skills are not ok (:func:`log_likelihoods_and_ok`); an
  emission without the flag is always ok.
- optionally ``init_window`` (an integer or None) and ``initial_skills(max_skills)`` (an integer
  or None): the initial segmentation's window length and number of skills where the user gives
  none (None: the kernel's defaults), and ``fixed_max_skills`` (an integer or None): a number of
  skill slots the emission needs (unsegmented IRL: 1), which ``fit`` then uses.

Every optional hook has its "absent" value on :class:`Emission`, so the sampler and ``fit`` read
them as attributes. What an emission's methods accept beyond the protocol is declared by the
capability flags of :class:`Emission`, never read from their signatures.

A new emission model implements this protocol and registers itself with
:func:`register_emission`; the sampler needs no change.

An emission is a pytree (:class:`npbrs.domains.util.pytree.Pytree`): the compiled sweep takes it as an
argument, its array attributes (and npbrs objects such as a solver) as traced inputs and its
other attributes as static options, so that another MDP or dataset of the same shapes reuses the
program. An attribute holding a closure or jitted function over its arrays must be named in
``_pytree_derived`` and rebuilt by ``_pytree_rebuild``. Its methods run in float64
(:mod:`npbrs.domains.util.precision`).
"""

from __future__ import annotations

from typing import Any, Callable, Dict, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from npbrs.domains.util.pytree import Pytree
from npbrs.domains.util.precision import float64_all

__all__ = ["HMMData", "Emission", "EmissionInfo", "register_emission", "get_emission_class", "make_emission", "EMISSIONS",
           "bucket_size", "log_likelihoods_and_ok"]


class EmissionInfo(NamedTuple):
    """Diagnostics of an emission's ``update``: ``accept`` (), the mean acceptance of its move
    over the skills with steps (1 for an exact draw from the conditional)."""

    accept: jax.Array


class HMMData(NamedTuple):
    """Padded demonstrations as arrays.

    states: (N, T) int32 state indices (0 where padded).
    actions: (N, T) int32 action indices (0 where padded).
    mask: (N, T) bool, True on real steps.
    """

    states: jax.Array
    actions: jax.Array
    mask: jax.Array

    @classmethod
    def from_demonstrations(cls, demos, bucket: bool = False) -> "HMMData":
        """The demonstrations padded to their longest trajectory; with ``bucket``, also padded
        to :func:`bucket_size` trajectories and steps (extra trajectories have no step), so that
        data sets of similar sizes share compiled programs."""
        states, actions, mask = demos.padded()
        if bucket:
            (N, T), (Nb, Tb) = states.shape, (bucket_size(states.shape[0]), bucket_size(states.shape[1]))
            pad = ((0, Nb - N), (0, Tb - T))
            states, actions, mask = np.pad(states, pad), np.pad(actions, pad), np.pad(mask, pad)
        return cls(jnp.asarray(states, jnp.int32), jnp.asarray(actions, jnp.int32), jnp.asarray(mask, bool))


def bucket_size(n: int) -> int:
    """The smallest bucket size >= n: every integer up to 8, then 4 sizes per doubling (10, 12,
    14, 16, 20, 24, 28, 32, 40, ...), so padding adds at most a quarter."""
    n = int(n)
    if n <= 8:
        return max(n, 1)
    step = 1 << (n.bit_length() - 3)  # a quarter of the power of two below n
    return -(-n // step) * step


class Emission(Pytree):
    """Base class of emission models (see the module docstring for the protocol).

    Capabilities, declared as class attributes (False here; an emission that has one sets it, and
    a test checks each registered emission's flags against its methods):

    - ``tunes_in_update``: ``update`` takes a keyword ``tune`` (a bool shared by vectorised
      chains) and does the work of ``tune`` itself where it is true; the sampler then passes it
      instead of calling ``tune`` before ``update``.
    - ``solves_in_update``: ``update`` takes ``redraw_unused`` and returns a cache from which
      ``log_likelihoods(..., solved=True)`` needs no fresh evaluation (below).
    - ``fits_without_evidence``: ``fit_evidence`` takes ``with_evidence`` (a bool, or a traced
      one): where false only the fits are needed and the evidences may be anything (NaN), so
      their cost can be skipped. Without it the greedy moves never pass ``with_evidence``.
    - ``fits_with_likelihoods``: ``fit_evidence`` takes ``with_likelihoods`` (a Python bool) and,
      when true, returns the fits' per-step log-likelihoods (N, T, M) third, cheaper than
      ``log_likelihoods`` would. Without it the greedy moves call ``log_likelihoods``.
    - ``reports_solves``: ``log_likelihoods`` takes ``with_ok`` (a Python bool) and, when true,
      returns ``(ll, cache, ok)`` with ok (K,) bool: skill k's likelihoods came from a converged
      solve and are finite. Without it every skill is taken as ok
      (:func:`log_likelihoods_and_ok`).
    """

    name: str = "emission"
    #: what the likelihood is a probability of: "actions" (of the actions given the states, as
    #: a policy) or "states" (a density of the states' vectors): only runs of the same kind can
    #: be ranked by their likelihoods (``npbrs compare``)
    likelihood_of: str = "actions"
    #: whether the scores of demonstrations include the learned names of equivalent actions
    #: (:mod:`npbrs.models.names`; the reward emission's ``action_names="learned"``); the
    #: sampler never reads it (the names' factor leaves the skills' posterior unchanged)
    learns_action_names: bool = False
    #: the sweeps between prior redraws of unused skills' parameters that ``fit`` asks for
    redraw_unused: int = 1
    #: whether ``update`` takes ``redraw_unused`` (a bool shared by vectorised chains: the skills
    #: without steps get prior draws, else keep their parameters) and returns a cache from which
    #: ``log_likelihoods(params, data, cache, solved=True)`` gives its parameters' likelihoods
    #: without the work of a fresh evaluation (the reward emission: the values its move solved)
    solves_in_update: bool = False
    #: the initial segmentation's window length (None: the kernel's ``DEFAULT_INIT_WINDOW``)
    init_window: Optional[int] = None
    #: the skill slots the emission needs, if a fixed number (None: ``fit``'s ``max_skills``)
    fixed_max_skills: Optional[int] = None
    #: warmup-only tuning of the move, ``tune(params, cache, data, weights) -> cache``, run every
    #: ``tune_every`` warmup sweeps (None: none)
    tune: Optional[Callable] = None
    tune_every: int = 1
    #: ``update`` takes ``tune`` (see the class docstring)
    tunes_in_update: bool = False
    #: ``fit_evidence`` takes ``with_evidence`` (see the class docstring)
    fits_without_evidence: bool = False
    #: ``fit_evidence`` takes ``with_likelihoods`` (see the class docstring)
    fits_with_likelihoods: bool = False
    #: ``log_likelihoods`` takes ``with_ok`` (see the class docstring)
    reports_solves: bool = False

    def initial_skills(self, max_skills: int) -> Optional[int]:
        """The initial segmentation's number of skills for ``max_skills`` slots (None: the
        kernel's half of the slots)."""
        return None

    def sample_params(self, K: int) -> Dict[str, jax.Array]:
        raise NotImplementedError

    def log_prior(self, params) -> jax.Array:
        raise NotImplementedError

    def init_cache(self, K: int) -> Any:
        return ()

    def log_likelihoods(self, params, data: HMMData, cache=()):
        raise NotImplementedError

    def update(self, key, params, cache, data: HMMData, weights, adapt):
        raise NotImplementedError

    def log_policies(self, params) -> jax.Array:
        """log pi_k(a | s) of every state and action under K skills' parameters, (K, S, A): what
        the skills do when used for control (options, transfer to another MDP). Emissions that
        model actions as a policy of the state implement it; ones that model no actions raise."""
        raise NotImplementedError(f"the {self.name!r} emission gives no policies over states and actions")

    def propose(self, key, data: HMMData, weights):
        raise NotImplementedError

    def log_proposal(self, params_one, data: HMMData, weights):
        raise NotImplementedError

    def propose_and_score(self, key, data: HMMData, weights, other_one, init=None):
        """``(new_one, log q(new_one), log q(other_one))`` under one data-driven proposal
        (a birth needs the first two, the matching death the last); override to share work.
        ``init``: optional parameters of one skill that an iterative fit may start from (the
        proposal must be a deterministic function of ``weights`` and ``init``)."""
        new, log_q = self.propose(key, data, weights)
        return new, log_q, self.log_proposal(other_one, data, weights)

    def fit_point(self, data: HMMData, weights, init=None):
        """Deterministic point estimates (M, ...) of M skills' parameters from weighted steps
        ``weights`` (N, T, M), e.g. a few IRL steps started at ``init`` (M, ...) or a posterior
        mean. Used by the split-merge move's sequential allocation; optional."""
        raise NotImplementedError(f"the {self.name!r} emission has no fit_point (needed by split-merge moves)")

    @classmethod
    def supports_split_merge(cls) -> bool:
        return cls.fit_point is not Emission.fit_point

    def fit_evidence(self, data: HMMData, weights, init=None):
        """Point estimates (M, ...) of M skills' parameters from weighted steps ``weights``
        (N, T, M) and the log evidence (M,) of each skill's steps, log of the integral of
        p(steps | params) p0(params) over the parameters (exact, or e.g. a Laplace
        approximation at the estimate); ``init`` (M, ...) may start an iterative fit. Used by
        the warmup's greedy merges and splits (a split's allocation fits by it too); optional.
        An implementation may also take ``with_evidence`` and ``with_likelihoods``, declared by
        ``fits_without_evidence`` and ``fits_with_likelihoods`` (see the class docstring); the
        greedy moves pass each only where it is declared."""
        raise NotImplementedError(f"the {self.name!r} emission has no fit_evidence (needed by greedy merges)")

    @classmethod
    def supports_greedy_merge(cls) -> bool:
        return cls.fit_evidence is not Emission.fit_evidence

    def sample_prior_one(self, key):
        """One skill's parameters drawn from the prior (the sites of ``sample_params(1)``)."""
        from numpyro import handlers

        with handlers.seed(rng_seed=key):
            params = self.sample_params(1)
        return jax.tree.map(lambda x: x[0], params)

    def for_search(self) -> "Emission":
        """This emission as the work that steers the sampler but enters no acceptance ratio
        uses it: a chain's starting parameters (:meth:`init_params`), the warmup's greedy merges
        and splits (their fits and evidences) and the warmup's tuning of the emission's move
        (``tune``: a preconditioner, any fixed one of which leaves the posterior invariant). An
        emission may trade accuracy for time there (the reward emission solves to
        ``search_tol``); the default is itself."""
        return self

    def init_params(self, key, data: HMMData, weights):
        """A starting point: the proposal applied to each skill's weighted steps. (K, ...)."""
        K = weights.shape[-1]
        keys = jax.random.split(key, K)
        params, _ = jax.vmap(lambda k, w: self.propose(k, data, w), in_axes=(0, 2))(keys, weights)
        return params

    def describe(self) -> dict:
        """Plain-data options of this emission (for saved runs)."""
        return {"name": self.name}

    @classmethod
    def from_mdp(cls, mdp, **options) -> "Emission":
        """This emission for a TabularMDP, with its keyword options."""
        return cls(mdp, **options)


def log_likelihoods_and_ok(emission: Emission, params, data: HMMData, cache=()):
    """Per-step log-likelihoods of K skills' parameters and whether each is to be trusted.

    Args:
        emission: the emission model.
        params: K skills' parameters (leading axis K).
        data: the demonstrations.
        cache: the emission's cache for K skills (e.g. ``emission.init_cache(K)``).
    Returns:
        (ll (N, T, K), cache, ok (K,) bool): ``log_likelihoods(..., with_ok=True)`` where the
        emission declares ``reports_solves``, else ok all True.
    """
    if emission.reports_solves:
        return emission.log_likelihoods(params, data, cache, with_ok=True)
    ll, cache = emission.log_likelihoods(params, data, cache)
    return ll, cache, jnp.ones(ll.shape[-1:], bool)


EMISSIONS: Dict[str, Callable[..., Emission]] = {}


def register_emission(name: str):
    """Class decorator: make an emission model available under ``name`` to ``fit`` and configs."""

    def deco(cls):
        if not isinstance(name, str) or not name:
            raise ValueError("emission name must be a non-empty string")
        EMISSIONS[name] = cls
        cls.name = name
        return cls

    return deco


def get_emission_class(name: str):
    if name not in EMISSIONS:
        raise ValueError(f"unknown emission {name!r}; known emissions: {sorted(EMISSIONS)}")
    return EMISSIONS[name]


def make_emission(emission, mdp, **options) -> Emission:
    """An emission model from a registered name or an instance.

    Args:
        emission: a registered name ("reward", "policy", ...) or an :class:`Emission` instance.
        mdp: the TabularMDP the emission's ``from_mdp`` builds it for.
        **options: keyword options of the emission's ``from_mdp`` (none with an instance).
    Returns:
        the Emission.
    """
    if isinstance(emission, Emission):
        if options:
            raise ValueError(f"emission options {sorted(options)} given with an emission instance")
        return emission
    if not isinstance(emission, str):
        raise ValueError(f"emission must be a registered name or an Emission, got {emission!r}")
    cls = get_emission_class(emission)
    try:
        return cls.from_mdp(mdp, **options)
    except TypeError as e:  # an unknown or missing option
        raise ValueError(f"emission.options: {emission!r} does not take these options ({e})") from None


@register_emission("policy")
class PolicyEmission(Emission):
    """Each skill is a tabular stochastic policy pi_k(a | s) with a Dirichlet(c) prior per state.

    Conjugate, so its update is an exact Gibbs draw: segmentation by behaviour rather than by
    reward (no MDP solve). Useful as a fast baseline and as the exactly tractable emission
    of the sampler's tests.

    Args:
        num_states, num_actions: sizes of the tabular MDP.
        concentration: the symmetric Dirichlet parameter c.
    """

    # ``fit_evidence`` takes ``with_evidence`` (and computes the exact evidences anyway: cheap)
    fits_without_evidence = True

    def __init__(self, num_states: int, num_actions: int, concentration: float = 0.5):
        if num_states < 1 or num_actions < 1:
            raise ValueError(f"num_states and num_actions must be >= 1, got {num_states}, {num_actions}")
        if not concentration > 0:
            raise ValueError(f"concentration must be positive, got {concentration}")
        self.num_states = int(num_states)
        self.num_actions = int(num_actions)
        self.concentration = float(concentration)

    @classmethod
    def from_mdp(cls, mdp, **options):
        return cls(mdp.num_states, mdp.num_actions, **options)

    def _prior(self, K):
        import numpyro.distributions as dist

        conc = jnp.full((K, self.num_states, self.num_actions), self.concentration)
        return dist.Dirichlet(conc).to_event(2)

    def sample_params(self, K):
        import numpyro

        return {"policy": numpyro.sample("policy", self._prior(K))}

    def log_prior(self, params):
        import numpyro.distributions as dist

        conc = jnp.full(params["policy"].shape, self.concentration)
        return jnp.sum(dist.Dirichlet(conc).log_prob(params["policy"]), axis=-1)

    def log_policies(self, params):
        return jnp.log(jnp.maximum(params["policy"], 1e-300))  # (K, S, A)

    def log_likelihoods(self, params, data, cache=()):
        ll = self.log_policies(params)[:, data.states, data.actions]  # (K, N, T)
        return jnp.where(data.mask[..., None], jnp.moveaxis(ll, 0, -1), 0.0), cache

    def counts(self, data, weights):
        """Weighted (state, action) counts of the real steps of ``data``, (..., S, A) for weights
        (N, T, ...) (e.g. one-hot skill assignments (N, T, K): one table per skill)."""
        S, A = self.num_states, self.num_actions
        flat = (data.states * A + data.actions).reshape(-1)
        w = (weights * data.mask.reshape(data.mask.shape + (1,) * (weights.ndim - 2))).reshape(flat.shape[0], -1)
        c = jax.ops.segment_sum(w, flat, num_segments=S * A)  # (S*A, ...)
        return jnp.moveaxis(c.reshape((S, A) + weights.shape[2:]), (0, 1), (-2, -1))

    def update(self, key, params, cache, data, weights, adapt):
        counts = self.counts(data, weights)  # (K, S, A)
        policy = jax.random.dirichlet(key, self.concentration + counts)
        return {"policy": jnp.maximum(policy, 1e-300)}, cache, EmissionInfo(jnp.ones(()))

    def propose(self, key, data, weights):
        conc = self.concentration + self.counts(data, weights)
        policy = jnp.maximum(jax.random.dirichlet(key, conc), 1e-300)
        return {"policy": policy}, self.log_proposal({"policy": policy}, data, weights)

    def log_proposal(self, params_one, data, weights):
        import numpyro.distributions as dist

        conc = self.concentration + self.counts(data, weights)
        return jnp.sum(dist.Dirichlet(conc).log_prob(params_one["policy"]))

    def fit_point(self, data, weights, init=None):
        conc = self.concentration + self.counts(data, weights)  # (M, S, A)
        return {"policy": conc / jnp.sum(conc, -1, keepdims=True)}

    def fit_evidence(self, data, weights, init=None, with_evidence=True):
        """Posterior means and the exact Dirichlet-multinomial log evidence of each skill
        (computed whatever ``with_evidence`` says: it costs little)."""
        from jax.scipy.special import gammaln

        n = self.counts(data, weights)  # (M, S, A)
        c = self.concentration
        A = self.num_actions
        log_ev = jnp.sum(gammaln(A * c) - gammaln(A * c + jnp.sum(n, -1))
                         + jnp.sum(gammaln(c + n) - gammaln(c), -1), -1)
        return self.fit_point(data, weights), log_ev

    def describe(self):
        return {"name": self.name, "concentration": self.concentration}


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
