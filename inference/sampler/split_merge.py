"""Split-merge moves of the BP-HMM sampler (after Hughes, Fox and Sudderth 2012, "Effective
split-merge Monte Carlo methods for nonparametric models of sequential data"), for emissions
whose parameters have no conjugate update.

A trial first chooses a split or a merge and its anchor steps by skill (``_choose_anchors``:
a used skill and two of its steps, or two used skills and one step of each), so that small
skills are proposed for merging as often as large ones; the choice's probability, and that of
choosing the same anchors for the reverse move in the proposed state, enter the ratio.

The move acts on the features F, the emission parameters, the transition weights eta of the
trajectories that use either skill, and the skill sequences z jointly; the popularities omega
are integrated out (the sweep redraws them right after). Given two anchor steps (see above):
if their skills are equal (k1) the move proposes a *split* of k1 into k1 and a free slot k2
(drawn uniformly among the slots no trajectory uses); otherwise a *merge* of the anchors'
skills k1 and k2 into k1.

Split of the merged state M into S:

1. A deterministic sequential allocation of M's k1-steps between k1 and k2: two point fits
   (``emission.fit_point``), started at M's parameters of k1, fitted to the run of steps
   around each anchor; then the trajectories with f_ik1 = 1, in blocks (the anchors'
   trajectories first, then a random order: an auxiliary choice independent of the state),
   each allocated by Viterbi over {k1, k2} at its k1-steps (other steps and the anchors
   held), and the fits refitted to the allocation so far after each block.
2. Features: for each trajectory with f_ik1 = 1 a pair (f_ik1, f_ik2) != (0, 0); the pair
   that matches the allocation's use has probability 1 - 2 eps, the other two eps (the
   anchors' trajectories must keep the anchor's skill).
3. Parameters of k1 and k2 from the emission's data-driven proposal fitted to their
   allocations (started at the point fits).

Merge of S into M: f_k1 | f_k2 on k1, k2 off; k1's parameters from the data-driven proposal
fitted to the union of both skills' steps (started at their step-weighted mean), k2's from
the prior.

Transition weights, both directions: every trajectory that uses k1 or k2 gets a new eta_i
from its exact conditional given the move's allocation (the split's, or the merged labels
k2 -> k1), or with probability ``ETA_PRIOR_WEIGHT`` from its prior: per row,
Dirichlet(conc + counts) proportions over the active skills times a Gamma(sum conc) total,
inactive entries from their Gamma prior. Prior and proposal share the total, its Jacobian and
the inactive entries, so per row log p(eta) - log q(eta) is log Dir(D; conc) -
log Dir(D; conc + counts) of the proportions D.

Both directions then redraw z from its conditional given the proposed state *with the two
anchors clamped* to their skills (k1, k2 after a split; k1, k1 after a merge), by forward
filtering, backward sampling. With the reverse move computed from the proposed state's own z,
the skill sequences cancel from the acceptance ratio (the move is a Metropolis-Hastings step
on the joint, with an exact conditional as z's proposal), leaving

    log p(x, anchors clamped | S) + log p(S) - log p(x, anchors clamped | M) - log p(M)
    + log q(M | S) - log q(S | M)

for a split (and its negative for a merge), where p(x, clamped | .) is the forward filter's
marginal likelihood with the anchors' skills fixed, p(.) the prior of the features (omega
integrated out) and of the parameters, and q the proposal densities above. Nothing in it
counts allocations.

The reverse move's densities of the current rewards and transition weights can be tiny when
the deterministic allocation lands far from the current labelling, so both proposals are
defensive mixtures (eta: ``ETA_PRIOR_WEIGHT``; the reward emission: ``proposal_broad_weight``),
which bounds those densities from below. The move is exact (tested against enumeration, by
posterior invariance, and by split-merge reciprocity) and off by default; the copies of a skill
that the Gibbs sweeps leave are removed by the warmup's greedy moves
(:mod:`npbrs.inference.sampler.greedy`) instead. What was measured on the paper's domains, and
why eta is redrawn rather than kept: ``benchmarks/NOTES.md``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from npbrs.models.mcmc import metropolis_accept, select
from npbrs.models.bphmm import (collapsed_feature_log_prob, eta_counts, eta_from_gammas, eta_gamma_shapes,
                                hmm_parameters)
from npbrs.models.emissions import log_likelihoods_and_ok
from npbrs.models.hmm import NEG_LOG, batch_backward_sample, batch_forward_filter, viterbi
from npbrs.domains.util.precision import float64_all

from .state import MoveState

__all__ = ["SplitMergeInfo", "SplitMergeProposal", "split_merge", "propose_split_merge", "split_merge_log_ratio",
           "allocate", "Allocation", "allocation", "allocate_block", "allocated_steps", "skill_counts",
           "visiting_order"]

# probability of each feature pair other than the one that matches the allocation
PAIR_EPS = 0.1
# weight of the prior in each touched trajectory's eta proposal (a defensive mixture: a
# reverse move's density of the current eta is at least this weight times the prior's)
ETA_PRIOR_WEIGHT = 0.02


class SplitMergeInfo(NamedTuple):
    """Diagnostics of one split-merge trial: a split or a merge, whether it was possible and
    accepted, its log acceptance ratio (-inf when impossible), and the skills: k1 (split, or
    kept by the merge) and k2 (the split's free slot, or the skill merged into k1)."""

    is_split: jax.Array
    possible: jax.Array
    accepted: jax.Array
    log_ratio: jax.Array
    k1: jax.Array
    k2: jax.Array


class SplitMergeProposal(NamedTuple):
    """A split or merge proposed at given anchors (:func:`propose_split_merge`): the proposed
    state, its log acceptance ratio given the anchors (:func:`split_merge_log_ratio`), whether
    the move is possible, whether it is a split, its skills k1 and k2 (as in
    :class:`SplitMergeInfo`), and the allocation's visiting order of the trajectories (N,)."""

    state: MoveState
    log_ratio: jax.Array
    possible: jax.Array
    is_split: jax.Array
    k1: jax.Array
    k2: jax.Array
    order: jax.Array


def _two(params, k1, k2):
    return jax.tree.map(lambda p: jnp.stack([p[k1], p[k2]]), params)


def _set_two(params, k1, k2, two):
    return jax.tree.map(lambda p, t: p.at[k1].set(t[0]).at[k2].set(t[1]), params, two)


def _run_around(z_row, mask_row, t):
    """(T,) bool: the run of equal labels of ``z_row`` that contains step t."""
    change = jnp.concatenate([jnp.zeros(1, bool), z_row[1:] != z_row[:-1]])
    run = jnp.cumsum(change)
    return (run == run[t]) & mask_row


def visiting_order(key, mask, ia, ib):
    """(N,) a random order of the trajectories, anchor a's first and b's second, the
    trajectories without steps (padding) last: the real ones' order does not depend on how many
    padding trajectories there are (their uniform keys are numbered by position)."""
    N = mask.shape[0]
    priority = jax.random.uniform(key, (N,))
    priority = jnp.where(jnp.any(mask, axis=1), priority, 2.0).at[ib].set(-1.0).at[ia].set(-2.0)
    return jnp.argsort(priority).astype(jnp.int32)


def _blocks(order, num_real, num_blocks):
    """The allocation's blocks of ``order`` (padding trajectories last), (num_blocks, per_block)
    with -1 for no trajectory, and (num_blocks,) whether each block is in use.

    The real trajectories are split as if they were all there is: min(num_blocks, num_real)
    blocks of ceil(num_real / blocks) (``num_real`` traced), in blocks of the static size
    ceil(N / num_blocks) >= that; the blocks past them are not used, so padding the data with
    empty trajectories changes nothing (with num_real = N these are the plain blocks)."""
    N = order.shape[0]
    per_block = -(-N // num_blocks)
    used_blocks = jnp.minimum(num_blocks, jnp.maximum(num_real, 1))
    per_real = -(-num_real // used_blocks)
    b, j = jnp.arange(num_blocks)[:, None], jnp.arange(per_block)[None, :]
    pos = b * per_real + j
    take = (j < per_real) & (pos < num_real)
    return jnp.where(take, order[jnp.clip(pos, 0, N - 1)], -1), jnp.arange(num_blocks) < used_blocks


class Allocation(NamedTuple):
    """The sequential allocation of the k1-steps of (z, features) between k1 and k2
    (:func:`allocation`), before its fits: ``start`` (N, T, 2) the anchors' runs, the first
    fits' steps; ``rows`` (num_blocks + 1, per_block) the trajectories of each scan step's block
    (-1: none; the last step has none and fits the final allocation); ``fit_on``
    (num_blocks + 1,) whether each step refits (the first always, a later one when the block
    before it was in use). :func:`allocate_block` allocates one block given the fits'
    likelihoods, :func:`allocated_steps` gives the fits' step weights of an allocation."""

    z: jax.Array
    features: jax.Array
    k1: jax.Array
    k2: jax.Array
    anchors: tuple
    start: jax.Array
    rows: jax.Array
    fit_on: jax.Array


def allocation(data, z_m, f_m, k1, k2, anchors, order, num_blocks) -> Allocation:
    """The :class:`Allocation` of the k1-steps of (z_m, f_m) between k1 and k2, trajectories in
    ``order`` (:func:`visiting_order`: padding last) in ``num_blocks`` blocks."""
    N, T = data.mask.shape
    mask = data.mask
    anchors = tuple(jnp.asarray(a, jnp.int32) for a in anchors)
    ia, ta, ib, tb = anchors
    k1, k2 = jnp.asarray(k1, jnp.int32), jnp.asarray(k2, jnp.int32)
    blocks, in_use = _blocks(jnp.asarray(order, jnp.int32), jnp.sum(jnp.any(mask, axis=1)), num_blocks)
    start = jnp.zeros((N, T, 2)).at[ia, :, 0].set(_run_around(z_m[ia], mask[ia], ta).astype(jnp.float64))
    start = start.at[ib, :, 1].set(_run_around(z_m[ib], mask[ib], tb).astype(jnp.float64))
    # one point fit per scan step, then that step's block: the first step fits the anchors' runs,
    # each later one the steps allocated so far (kept where its block was in use), and a last
    # step with no block fits the final allocation (one call site of the fit in the program)
    fit_on = jnp.concatenate([jnp.ones(1, bool), in_use])  # (num_blocks + 1,)
    rows = jnp.concatenate([blocks, jnp.full((1,) + blocks.shape[1:], -1, blocks.dtype)])
    return Allocation(z_m, f_m, k1, k2, anchors, start, rows, fit_on)


def allocated_steps(plan: Allocation, data, z, done):
    """(N, T, 2) float: the steps of k1 and k2 in the trajectories allocated so far (``done``)."""
    w = jnp.stack([(z == plan.k1), (z == plan.k2)], -1) & (data.mask & done[:, None])[..., None]
    return w.astype(jnp.float64)


def allocate_block(plan: Allocation, data, z, done, lik_ab, rows):
    """Allocate the trajectories ``rows`` (-1: none) of the k1-steps of ``plan`` by Viterbi over
    {k1, k2} under the fits' log-likelihoods ``lik_ab`` (N, T, 2), the anchors and other steps
    held, a sticky chain between them: returns (z, done)."""
    N, T = data.mask.shape
    mask, z_m, f_m, k1, k2 = data.mask, plan.z, plan.features, plan.k1, plan.k2
    ia, ta, ib, tb = plan.anchors
    K = f_m.shape[1]
    t_idx = jnp.arange(T)
    cols = jnp.arange(K)
    log_trans = jnp.log(jnp.ones((K, K)) + 10.0 * jnp.eye(K))  # a sticky chain for the allocation

    def one_trajectory(i, valid):
        i = jnp.maximum(i, 0)
        zi, mi = z_m[i], mask[i]
        is_k = (zi == k1) & mi
        go = valid & (f_m[i, k1] > 0) & jnp.any(is_k)
        allow_a = is_k & ~((i == ib) & (t_idx == tb))
        allow_b = is_k & ~((i == ia) & (t_idx == ta))
        fixed = (cols[None, :] == zi[:, None]) & ~is_k[:, None]
        allowed = fixed | ((cols == k1)[None, :] & allow_a[:, None]) | ((cols == k2)[None, :] & allow_b[:, None])
        emit = jnp.where(cols[None, :] == k1, lik_ab[i, :, 0:1], jnp.where(cols[None, :] == k2, lik_ab[i, :, 1:2], 0.0))
        path, _ = viterbi(jnp.zeros(K), log_trans, jnp.where(allowed, emit, NEG_LOG), mi, (f_m[i] > 0) | (cols == k2))
        return jnp.where(go, path, zi)

    valid = rows >= 0
    zs = jax.vmap(one_trajectory)(rows, valid)
    safe = jnp.where(valid, rows, N)  # out of range: dropped by the scatter
    return z.at[safe].set(zs, mode="drop"), done.at[safe].set(True, mode="drop")


def allocate(emission, data, z_m, f_m, k1, k2, anchors, order, init_one, num_blocks):
    """Deterministic sequential allocation of the k1-steps of (z_m, f_m) between k1 and k2,
    trajectories in ``order`` (:func:`visiting_order`: padding last) in ``num_blocks`` blocks,
    the point fits (``emission.fit_point``, started at ``init_one``) refitted after each block.

    Returns (z (N, T) allocated, point fits (2, ...) of the final allocation)."""
    N = data.mask.shape[0]
    plan = allocation(data, z_m, f_m, k1, k2, anchors, order, num_blocks)
    init = jax.tree.map(lambda x: jnp.stack([x, x]), init_one)

    def block(carry, step):
        z, done, fits, weights = carry
        rows, fit_now = step
        refit = emission.fit_point(data, weights, fits)
        fits = jax.tree.map(lambda new, old: jnp.where(fit_now, new, old), refit, fits)
        lik_ab, _ = emission.log_likelihoods(fits, data, emission.init_cache(2))  # (N, T, 2)
        z, done = allocate_block(plan, data, z, done, lik_ab, rows)
        return (z, done, fits, allocated_steps(plan, data, z, done)), None

    (z, _, fits, _), _ = jax.lax.scan(block, (z_m, jnp.zeros(N, bool), init, plan.start), (plan.rows, plan.fit_on))
    return z, fits


def _eta_counts(z_alloc, f, mask, gated=False):
    """Transition counts (N, K, K) of an allocation in the active columns of F; ``gated``
    (state-dependent ends): the switches only, as in the kernel's conditional (a skill that
    continues says nothing of eta there)."""
    return jnp.where((f > 0)[:, None, :], eta_counts(z_alloc, mask, f.shape[1], gated), 0.0)


def _draw_eta(key, eta, counts, f, involved, hyper):
    """eta with the involved trajectories' matrices redrawn from the defensive mixture
    (1 - ETA_PRIOR_WEIGHT) p(eta_i | z_alloc) + ETA_PRIOR_WEIGHT p(eta_i), per trajectory
    (the kernel's conditional of eta, :func:`~npbrs.models.bphmm.eta_gamma_shapes`);
    counts: the allocation's :func:`_eta_counts`."""
    k_g, k_t, k_w = jax.random.split(key, 3)
    from_prior = jax.random.bernoulli(k_w, ETA_PRIOR_WEIGHT, (f.shape[0],))
    counts = jnp.where(from_prior[:, None, None], 0.0, counts)
    shape_g, shape_total, active = eta_gamma_shapes(counts, f, hyper)
    g = jnp.maximum(jax.random.gamma(k_g, shape_g), 1e-300)
    total = jnp.maximum(jax.random.gamma(k_t, shape_total[..., None]), 1e-300)
    return jnp.where(involved[:, None, None], eta_from_gammas(g, total, active), eta)


def _eta_log_p_over_q(eta, counts, f, involved, hyper):
    """log p(eta_i | F) - log q(eta_i | z_alloc, F) summed over the involved trajectories,
    q the defensive mixture of :func:`_draw_eta`; counts: the allocation's :func:`_eta_counts`.

    The conditional and the prior share the Gamma(sum conc) total, its Jacobian and the
    inactive entries, so per row log p - log p(. | z_alloc) is
    log Dir(D; conc) - log Dir(D; conc + counts) with D the row's proportions over the active
    columns; the mixture's weight on the prior bounds log p - log q by -log ETA_PRIOR_WEIGHT."""
    conc, c_row, active = eta_gamma_shapes(jnp.zeros_like(counts), f, hyper)  # the prior's shapes
    row = jnp.sum(jnp.where(active, eta, 0.0), -1, keepdims=True)
    log_d = jnp.where(active, jnp.log(jnp.where(active, eta, 1.0) / jnp.maximum(row, 1e-300)), 0.0)
    lg = lambda x: jnp.where(active, jax.scipy.special.gammaln(jnp.where(active, x, 1.0)), 0.0)  # noqa: E731
    n_row = jnp.sum(counts, -1)
    per_row = (jax.scipy.special.gammaln(c_row) - jnp.sum(lg(conc), -1)
               - jax.scipy.special.gammaln(c_row + n_row) + jnp.sum(lg(conc + counts), -1)
               - jnp.sum(counts * log_d, -1))
    per_row = jnp.where(c_row > 0, per_row, 0.0)
    delta = jnp.sum(per_row, -1)  # (N,) log p - log p(. | z_alloc)
    w = ETA_PRIOR_WEIGHT
    log_p_over_q = -jnp.logaddexp(jnp.log1p(-w) - delta, jnp.log(w))
    return jnp.sum(jnp.where(involved, log_p_over_q, 0.0))


def _pair_table(used_a, used_b, N, ia, ib):
    """log-probabilities (N, 3) of the pairs (1, 0), (0, 1), (1, 1)."""
    preferred = jnp.where(used_a & used_b, 2, jnp.where(used_b, 1, 0))
    probs = jnp.where(jnp.arange(3)[None, :] == preferred[:, None], 1.0 - 2 * PAIR_EPS, PAIR_EPS)
    rows = jnp.arange(N)
    # the anchors' trajectories keep their anchor's skill: a needs f_k1, b needs f_k2
    probs = jnp.where((rows == ia)[:, None] & (jnp.arange(3) == 1)[None, :], 0.0, probs)
    probs = jnp.where((rows == ib)[:, None] & (jnp.arange(3) == 0)[None, :], 0.0, probs)
    return jnp.log(probs / jnp.sum(probs, -1, keepdims=True))


def _pair_index(fa, fb):
    return jnp.where((fa > 0) & (fb > 0), 2, jnp.where(fb > 0, 1, 0))


def _clamp(log_lik, anchors, labels):
    """log_lik with the anchors' steps allowed only their given skills."""
    ia, ta, ib, tb = anchors
    K = log_lik.shape[-1]
    cols = jnp.arange(K)
    ll = log_lik.at[ia, ta].set(jnp.where(cols == labels[0], log_lik[ia, ta], NEG_LOG))
    return ll.at[ib, tb].set(jnp.where(cols == labels[1], ll[ib, tb], NEG_LOG))


def _proposals(emission, data, anchors, order, k1, k2, num_blocks, k_prop, k_prior):
    """The split's and the merge's proposals at ``anchors`` (k1 split into k1 and k2; k2 merged
    into k1), each drawing when given a key and otherwise scoring given values:

    - ``split_proposal(z_m, f_m, theta_m_k1, f_s, two_s, key)``: log q(S | M) of the split
      state's features f_s and parameters two_s of (k1, k2) (given), and, when key is not None,
      a draw of them: returns (f_s, two_s, log q, allocation);
    - ``merge_proposal(z_s, two_s, two_m, key)``: (two_m, log q(M | S)) of the merged
      parameters two_m (given) or of a draw of them.

    ``k_prop`` feeds the proposals' draws when scoring (their densities do not depend on it);
    ``k_prior`` draws the prior parameters of the slot a merge frees."""
    N = data.mask.shape[0]
    mask = data.mask
    ia, ta, ib, tb = anchors
    real = jnp.any(mask, axis=1)
    rows = jnp.arange(N)
    log_p0 = lambda one: emission.log_prior(jax.tree.map(lambda x: x[None], one))[0]  # noqa: E731

    def steps(zz, k):
        return ((zz == k) & mask).astype(jnp.float64)

    def weighted_mean(two, zz):
        n_a, n_b = jnp.sum(steps(zz, k1)), jnp.sum(steps(zz, k2))
        return jax.tree.map(lambda t: (n_a * t[0] + n_b * t[1]) / jnp.maximum(n_a + n_b, 1.0), two)

    def split_proposal(z_m, f_m, theta_m_k1, f_s, two_s, key):
        z_alloc, fits = allocate(emission, data, z_m, f_m, k1, k2, anchors, order, theta_m_k1, num_blocks)
        used_a = jnp.any((z_alloc == k1) & mask, axis=1)
        used_b = jnp.any((z_alloc == k2) & mask, axis=1)
        table = _pair_table(used_a, used_b, N, ia, ib)
        involved = (f_m[:, k1] > 0) & real
        if key is not None:
            k_pairs, k_two = jax.random.split(key)
            pick = jax.random.categorical(k_pairs, table)
            fa = jnp.where(pick != 1, 1.0, 0.0)
            fb = jnp.where(pick != 0, 1.0, 0.0)
            f_s = f_m.at[:, k1].set(jnp.where(involved, fa, 0.0)).at[:, k2].set(jnp.where(involved, fb, 0.0))
        lq_pairs = jnp.sum(jnp.where(involved, table[rows, _pair_index(f_s[:, k1], f_s[:, k2])], 0.0))
        others = two_s if two_s is not None else fits
        w = jnp.stack([steps(z_alloc, k1), steps(z_alloc, k2)])
        keys = jax.random.split(k_two if key is not None else k_prop, 2)
        new, lq_new, lq_other = jax.vmap(lambda kk, ww, o, i: emission.propose_and_score(kk, data, ww, o, i))(
            keys, w, others, fits)
        if two_s is None:
            two_s, lq_two = new, jnp.sum(lq_new)
        else:
            lq_two = jnp.sum(lq_other)
        n_free = jnp.sum(_users(f_m, real) == 0)
        return f_s, two_s, -jnp.log(jnp.maximum(n_free, 1).astype(jnp.float64)) + lq_pairs + lq_two, z_alloc

    def merge_proposal(z_s, two_s, two_m, key):
        init = weighted_mean(two_s, z_s)
        w_union = steps(z_s, k1) + steps(z_s, k2)
        other = jax.tree.map(lambda t: t[0], two_m) if two_m is not None else init
        new, lq_new, lq_other = emission.propose_and_score(key if key is not None else k_prop, data, w_union, other,
                                                           init)
        if two_m is None:
            prior = emission.sample_prior_one(k_prior)
            two_m = jax.tree.map(lambda a, b: jnp.stack([a, b]), new, prior)
            return two_m, lq_new + log_p0(prior)
        return two_m, lq_other + log_p0(jax.tree.map(lambda t: t[1], two_m))

    return split_proposal, merge_proposal


def _log_ratio(current: MoveState, proposed: MoveState, emission, data, hyper, anchors, k1, k2, is_split, proposals,
               lq_fwd, counts_fwd, lm_new=None):
    """The log acceptance ratio of a split (``is_split``) or merge at ``anchors`` from
    ``current`` to ``proposed``, given the forward proposal's density ``lq_fwd`` and its
    allocation's transition counts ``counts_fwd``; the reverse move's density is computed here,
    from the proposed state and its skill sequences. ``lm_new``: the proposed state's clamped log
    marginals (N,), when known."""
    features, eta, z, params, log_lik, gate = current[:6]
    new_f, new_eta, new_z, new_params, new_log_lik = proposed[:5]
    mask = data.mask
    real = jnp.any(mask, axis=1)
    split_proposal, merge_proposal = proposals
    current_two, new_two = _two(params, k1, k2), _two(new_params, k1, k2)
    old_labels = (k1, jnp.where(is_split, k1, k2))
    new_labels = (k1, jnp.where(is_split, k2, k1))
    # the trajectories whose transition weights the move redraws: those that use k1 or k2
    involved = ((features[:, k1] > 0) | (features[:, k2] > 0)) & real
    gated = current.is_gated  # the ends' gate is the same in both states
    li_o, lt_o, act_o = hmm_parameters(features, eta, gated)
    lm_old, _ = batch_forward_filter(li_o, lt_o, _clamp(log_lik, anchors, old_labels), mask, act_o, gate)
    if lm_new is None:
        li_n, lt_n, act_n = hmm_parameters(new_f, new_eta, gated)
        lm_new, _ = batch_forward_filter(li_n, lt_n, _clamp(new_log_lik, anchors, new_labels), mask, act_n, gate)

    # the reverse move, computed from the proposed state and its skill sequences
    def reverse_of_split(_):  # a merge of the proposed split state
        return merge_proposal(new_z, new_two, current_two, None)[1], jnp.where(new_z == k2, k1, new_z)

    def reverse_of_merge(_):  # a split of the proposed merged state
        out = split_proposal(new_z, new_f, jax.tree.map(lambda t: t[0], new_two), features, current_two, None)
        return out[2], out[3]

    lq_rev, alloc_rev = jax.lax.cond(is_split, reverse_of_split, reverse_of_merge, None)
    return (jnp.sum(lm_new) - jnp.sum(lm_old)
            + collapsed_feature_log_prob(new_f, hyper.alpha, real)
            - collapsed_feature_log_prob(features, hyper.alpha, real)
            + jnp.sum(emission.log_prior(new_two)) - jnp.sum(emission.log_prior(current_two))
            + lq_rev - lq_fwd
            + _eta_log_p_over_q(new_eta, counts_fwd, new_f, involved, hyper)
            - _eta_log_p_over_q(eta, _eta_counts(alloc_rev, features, mask, gated), features, involved, hyper))


def propose_split_merge(key, state: MoveState, emission, data, hyper, anchors, num_blocks: int = 2):
    """One split-merge proposal at given anchors ((i_a, t_a, i_b, t_b)): a split of their skill
    when they share one, else a merge of theirs. Returns a :class:`SplitMergeProposal`; its log
    ratio leaves out the anchors' choice (which :func:`split_merge` adds). It is not possible
    where the emission does not report the likelihoods of the skills it proposes ok (a split's
    two, a merge's merged one: :func:`npbrs.models.emissions.log_likelihoods_and_ok`, e.g. a soft
    solve that did not converge)."""
    K = state.features.shape[1]
    mask = data.mask
    features, eta, z, params, log_lik, gate = state[:6]
    gated = state.is_gated
    ia, ta, ib, tb = anchors
    k_slot, k_order, k_feat, k_prop, k_prior, k_z, k_eta = jax.random.split(key, 7)
    k1 = z[ia, ta]
    l2 = z[ib, tb]
    same_step = (ia == ib) & (ta == tb)
    is_split = k1 == l2
    # trajectories without steps (padding to a shape bucket or to a multiple of the devices)
    # are left out: their features count for no skill and the move does not touch them
    real = jnp.any(mask, axis=1)
    free = _users(features, real) == 0
    k2_free = jax.random.categorical(k_slot, jnp.where(free, 0.0, -jnp.inf))
    k2 = jnp.where(is_split, jnp.where(jnp.any(free), k2_free, (k1 + 1) % K), l2)
    order = visiting_order(k_order, mask, ia, ib)  # auxiliary visiting order, anchors first
    proposals = _proposals(emission, data, anchors, order, k1, k2, num_blocks, k_prop, k_prior)
    split_proposal, merge_proposal = proposals
    current = _two(params, k1, k2)
    f_merged = features.at[:, k1].set(jnp.maximum(features[:, k1], features[:, k2])).at[:, k2].set(0.0)

    # the proposal, forward
    def forward_split(_):
        return split_proposal(z, features, jax.tree.map(lambda t: t[0], current), None, None, k_feat)

    def forward_merge(_):
        two_m, lq = merge_proposal(z, current, None, k_feat)
        return f_merged, two_m, lq, jnp.where(z == k2, k1, z)

    new_f, new_two, lq_fwd, alloc_fwd = jax.lax.cond(is_split, forward_split, forward_merge, None)
    new_params = _set_two(params, k1, k2, new_two)
    new_cols, _, cols_ok = log_likelihoods_and_ok(emission, new_two, data, emission.init_cache(2))  # (N, T, 2)
    new_log_lik = log_lik.at[:, :, k1].set(new_cols[..., 0]).at[:, :, k2].set(new_cols[..., 1])

    # transition weights of the trajectories that use k1 or k2: redrawn from their
    # conditional given the move's allocation (the merged labels, or the split's)
    involved = ((features[:, k1] > 0) | (features[:, k2] > 0)) & real
    counts_fwd = _eta_counts(alloc_fwd, new_f, mask, gated)  # one count for the draw and its density
    new_eta = _draw_eta(k_eta, eta, counts_fwd, new_f, involved, hyper)
    # skill sequences: redrawn given the proposed state with the anchors clamped
    new_labels = (k1, jnp.where(is_split, k2, k1))
    li_n, lt_n, act_n = hmm_parameters(new_f, new_eta, gated)
    lm_new, alpha_new = batch_forward_filter(li_n, lt_n, _clamp(new_log_lik, anchors, new_labels), mask, act_n, gate)
    new_z = batch_backward_sample(k_z, lt_n, alpha_new, mask, act_n, gate)
    proposed = MoveState(new_f, new_eta, new_z, new_params, new_log_lik, gate, state.gated, state.end_model)

    log_ratio = _log_ratio(state, proposed, emission, data, hyper, anchors, k1, k2, is_split, proposals, lq_fwd,
                           counts_fwd, lm_new)
    # the proposed skills' likelihoods must be trusted (e.g. their solves converged): a split's
    # two; a merge's merged skill, its freed slot's prior draw entering no ratio
    new_ok = cols_ok[0] & (cols_ok[1] | ~is_split)
    possible = (~same_step & (~is_split | jnp.any(free)) & jnp.isfinite(log_ratio) & (log_ratio > 0.5 * NEG_LOG)
                & new_ok)
    return SplitMergeProposal(proposed, log_ratio, possible, is_split, k1, k2, order)


def split_merge_log_ratio(current: MoveState, proposed: MoveState, emission, data, hyper, anchors, order,
                          num_blocks: int = 2):
    """log acceptance ratio of the split or merge at ``anchors`` ((i_a, t_a, i_b, t_b)) from
    ``current`` to ``proposed``, the allocation visiting the trajectories in ``order``
    (:func:`visiting_order`; a proposal's ``order``): the ratio :func:`propose_split_merge`
    computes from its draws, here from the two states (the move back from ``proposed`` to
    ``current`` has its negative). A split when the anchors share a skill k1 in ``current``
    (into k1 and the anchor b's skill in ``proposed``), else a merge of anchor b's skill into
    anchor a's. The anchors' choice is left out (see :func:`split_merge`)."""
    ia, ta, ib, tb = anchors
    features, z, params = current.features, current.z, current.params
    k1 = z[ia, ta]
    l2 = z[ib, tb]
    is_split = k1 == l2
    k2 = jnp.where(is_split, proposed.z[ib, tb], l2)
    key = jax.random.PRNGKey(0)  # the proposals' draws are discarded: only their densities count
    proposals = _proposals(emission, data, anchors, order, k1, k2, num_blocks, key, key)
    split_proposal, merge_proposal = proposals
    current_two, new_two = _two(params, k1, k2), _two(proposed.params, k1, k2)

    def forward_split(_):
        out = split_proposal(z, features, jax.tree.map(lambda t: t[0], current_two), proposed.features, new_two,
                             None)
        return out[2], out[3]

    def forward_merge(_):
        return merge_proposal(z, current_two, new_two, None)[1], jnp.where(z == k2, k1, z)

    lq_fwd, alloc_fwd = jax.lax.cond(is_split, forward_split, forward_merge, None)
    counts_fwd = _eta_counts(alloc_fwd, proposed.features, data.mask, proposed.is_gated)
    return _log_ratio(current, proposed, emission, data, hyper, anchors, k1, k2, is_split, proposals, lq_fwd,
                      counts_fwd)


def _users(features, real):
    """m_k: the trajectories with steps (``real``) that have skill k, (K,)."""
    return jnp.sum(jnp.where(real[:, None], features, 0.0), axis=0)


def skill_counts(z, mask, K):
    """(K,) the number of real steps each skill labels in z (N, T)."""
    return jnp.sum(jax.nn.one_hot(z, K, dtype=jnp.float64) * mask[..., None], axis=(0, 1))


def _choose_anchors(key, z, mask, K):
    """Anchors by skill: with probability 1/2 a split (a used skill uniformly, two distinct
    steps of it uniformly), else a merge (an ordered pair of distinct used skills uniformly,
    one step of each uniformly). Small skills are anchored as often as large ones.

    Returns (anchors, possible, log-probability of the choice)."""
    N, T = mask.shape
    counts = skill_counts(z, mask, K)
    used = counts > 0
    n_used = jnp.sum(used)
    k_mode, k_first, k_second, k_a, k_b = jax.random.split(key, 5)
    split = jax.random.bernoulli(k_mode)
    first = jax.random.categorical(k_first, jnp.where(used, 0.0, -jnp.inf))
    other = jax.random.categorical(k_second, jnp.where(used & (jnp.arange(K) != first), 0.0, -jnp.inf))
    second = jnp.where(split, first, other)
    flat_z, flat_mask = z.ravel(), mask.ravel()
    a = jax.random.categorical(k_a, jnp.where(flat_mask & (flat_z == first), 0.0, -jnp.inf))
    b = jax.random.categorical(k_b, jnp.where(flat_mask & (flat_z == second) & (jnp.arange(N * T) != a), 0.0, -jnp.inf))
    possible = jnp.where(split, counts[first] >= 2, n_used >= 2)
    log_p = _choice_log_prob(split, counts, first, second)
    return (a // T, a % T, b // T, b % T), possible, log_p


def _choice_log_prob(split, counts, first, second):
    n_used = jnp.maximum(jnp.sum(counts > 0), 1.0)
    n1, n2 = jnp.maximum(counts[first], 1.0), jnp.maximum(counts[second], 1.0)
    return jnp.log(0.5) + jnp.where(split, -jnp.log(n_used) - jnp.log(n1) - jnp.log(jnp.maximum(n1 - 1.0, 1.0)),
                                    -jnp.log(n_used) - jnp.log(jnp.maximum(n_used - 1.0, 1.0)) - jnp.log(n1) - jnp.log(n2))


def split_merge(key, state: MoveState, emission, data, hyper, num_blocks: int = 2):
    """One split-merge trial: returns (state, :class:`SplitMergeInfo`).

    The anchors are chosen by skill (:func:`_choose_anchors`); the probability of choosing the
    same anchors for the reverse move in the proposed state enters the acceptance ratio."""
    K = state.features.shape[1]
    mask = data.mask
    z = state.z
    k_anchor, k_move, k_acc = jax.random.split(key, 3)
    anchors, can, log_p_fwd = _choose_anchors(k_anchor, z, mask, K)
    proposal = propose_split_merge(k_move, state, emission, data, hyper, anchors, num_blocks)
    is_split, z2 = proposal.is_split, proposal.state.z
    ia, ta, ib, tb = anchors
    k1 = z[ia, ta]
    k2 = jnp.where(is_split, z2[ib, tb], z[ib, tb])
    # the reverse: a merge of (k1, k2) after a split, a split of k1 after a merge, in z2
    log_p_rev = _choice_log_prob(~is_split, skill_counts(z2, mask, K), k1, jnp.where(is_split, k2, k1))
    log_ratio = proposal.log_ratio
    log_ratio = log_ratio + log_p_rev - log_p_fwd
    possible = proposal.possible & can
    accept, _ = metropolis_accept(k_acc, log_ratio, possible)
    info = SplitMergeInfo(is_split, possible, accept, jnp.where(possible, log_ratio, -jnp.inf), k1, k2)
    return select(accept, proposal.state, state), info


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
