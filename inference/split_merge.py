"""Split-merge moves of the BP-HMM sampler by sequential allocation (after Hughes, Fox and
Sudderth 2012, "Effective split-merge Monte Carlo methods for nonparametric models of
sequential data"), for emissions whose parameters have no conjugate update.

The move acts on (features F, skill sequences z, emission parameters) with the transition
weights eta and the popularities omega integrated out (the target ``log_target``); the sweep
redraws eta | z, F and omega | F right after it, so the composition leaves the full
posterior invariant (DESIGN.md, "Sampler notes").

Two anchor steps are drawn uniformly from all real steps. If their skills are equal (k1) the
move proposes a *split* of k1 into k1 and a free slot k2 (drawn uniformly among the slots no
trajectory uses); otherwise a *merge* of the anchors' skills k1 and k2 into k1.

Split, in the merged state M (F^M, z^M, params^M):

1. Two intermediate point fits (``emission.fit_point``) start from the run of k1-steps around
   each anchor.
2. The trajectories with f_ik1 = 1 are visited in blocks (the anchors' trajectories first,
   then a random order, an auxiliary choice independent of the state). In each trajectory that
   uses k1, its k1-steps are reallocated between k1 and k2 by forward filtering, backward
   sampling under a sticky proposal chain (transition weights gamma + kappa [j == k], the prior
   mean of eta), the other steps and the anchors held fixed. Its features (f_ik1, f_ik2) are
   drawn uniformly among the pairs that cover the skills it uses (not both 0). After each
   block the two point fits are refitted to the allocation so far, warm-started.
3. The two skills' parameters are drawn from the emission's data-driven proposal fitted to
   their final allocations (started at the point fits).

Merge, in the split state S: z^M relabels k2 as k1, f^M_k1 = f_k1 | f_k2, f^M_k2 = 0;
params^M_k1 is drawn from the data-driven proposal fitted to the union of the two skills'
steps (started at the step-weighted mean of the two final point fits, which the reverse split
reproduces), params^M_k2 from the prior (an unused slot's parameters follow the prior).

With q(S | M) the probability of the whole split (1 / #free slots, every FFBS path, every
feature pair, both parameter densities) and q(M | S) that of the merge (the union proposal's
density and the prior density of the freed slot), the split's log acceptance ratio is

    log pi(S) - log pi(M) + log q(M | S) - log q(S | M)

and the merge's is its negative. The merge evaluates q(S | M) honestly by running the same
allocation with every choice forced to the current state's (a state that no split could
produce is never merged).
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp

from npbrs.models.bphmm import collapsed_feature_log_prob, collapsed_sequence_log_prob
from npbrs.models.hmm import NEG_LOG, backward_sample, forward_filter, path_log_prob

__all__ = ["SplitMergeInfo", "log_target", "split_merge", "split_merge_at"]


class SplitMergeInfo(NamedTuple):
    """Diagnostics of one split-merge trial."""

    is_split: jax.Array
    possible: jax.Array
    accepted: jax.Array
    log_ratio: jax.Array


def _real_log_lik(log_lik, z, mask):
    K = log_lik.shape[-1]
    picked = jnp.take_along_axis(log_lik, jnp.clip(z, 0, K - 1)[..., None], axis=-1)[..., 0]
    return jnp.sum(jnp.where(mask, picked, 0.0))


def log_target(emission, data, hyper, features, z, params, log_lik):
    """log p(x, z, F, params) with eta and omega integrated out (up to a constant)."""
    return (collapsed_feature_log_prob(features, hyper.alpha)
            + jnp.sum(collapsed_sequence_log_prob(z, data.mask, features, hyper.kappa, hyper.gamma))
            + _real_log_lik(log_lik, z, data.mask) + jnp.sum(emission.log_prior(params)))


def _two_slots(params, k1, k2):
    return jax.tree.map(lambda p: jnp.stack([p[k1], p[k2]]), params)


def _set_two(params, k1, k2, two):
    return jax.tree.map(lambda p, t: p.at[k1].set(t[0]).at[k2].set(t[1]), params, two)


def _run_around(z_row, mask_row, t):
    """(T,) bool: the run of equal labels of ``z_row`` that contains step t."""
    change = jnp.concatenate([jnp.zeros(1, bool), z_row[1:] != z_row[:-1]])
    run = jnp.cumsum(change)
    return (run == run[t]) & mask_row


def _allocate(key, emission, data, hyper, z_m, f_m, k1, k2, anchors, order, forced, z_s, f_s, num_blocks):
    """The split's sequential allocation from the merged state (z_m, f_m).

    Sampled when ``forced`` is False; otherwise every choice is the split state's (z_s, f_s)
    and only its probability is computed. Returns (z, features, log q, feasible, point fits
    (2, ...) of the final allocation)."""
    N, T = data.mask.shape
    K = f_m.shape[1]
    mask = data.mask
    ia, ta, ib, tb = anchors
    per_block = -(-N // num_blocks)
    padded = jnp.concatenate([order, jnp.full(per_block * num_blocks - N, -1, order.dtype)])
    blocks = padded.reshape(num_blocks, per_block)
    t_idx = jnp.arange(T)
    log_trans = jnp.log(hyper.gamma + hyper.kappa * jnp.eye(K))

    def weights_of(z, done):
        w = jnp.stack([(z == k1), (z == k2)], -1) & (mask & done[:, None])[..., None]
        return w.astype(jnp.float64)  # (N, T, 2)

    seg = jnp.zeros((N, T, 2)).at[ia, :, 0].set(_run_around(z_m[ia], mask[ia], ta).astype(jnp.float64))
    seg = seg.at[ib, :, 1].set(_run_around(z_m[ib], mask[ib], tb).astype(jnp.float64))
    fits0 = emission.fit_point(data, seg)

    def one_trajectory(key, i, valid, lik_ab):
        """Allocation of trajectory i: (z_i, f_ik1, f_ik2, log q, feasible)."""
        i = jnp.maximum(i, 0)
        zi, mi = z_m[i], mask[i]
        involved = valid & (f_m[i, k1] > 0)
        is_k = (zi == k1) & mi
        uses_k = jnp.any(is_k)
        cols = jnp.arange(K)
        allow_a = is_k & ~((i == ib) & (t_idx == tb))
        allow_b = is_k & ~((i == ia) & (t_idx == ta))
        fixed = (cols[None, :] == zi[:, None]) & ~is_k[:, None]
        allowed = fixed | ((cols == k1)[None, :] & allow_a[:, None]) | ((cols == k2)[None, :] & allow_b[:, None])
        emit = jnp.where(cols[None, :] == k1, lik_ab[i, :, 0:1], jnp.where(cols[None, :] == k2, lik_ab[i, :, 1:2], 0.0))
        ll = jnp.where(allowed, emit, NEG_LOG)
        active = (f_m[i] > 0) | (cols == k2)
        log_init = jnp.zeros(K)
        log_marg, log_alpha = forward_filter(log_init, log_trans, ll, mi, active)
        k_path, k_feat = jax.random.split(key)
        sampled = backward_sample(k_path, log_trans, log_alpha, mi, active)
        z_new = jnp.where(forced, z_s[i], sampled)
        z_new = jnp.where(involved & uses_k, z_new, jnp.where(forced, z_s[i], zi))
        lp = path_log_prob(log_init, log_trans, ll, z_new, mi, active) - log_marg
        ok_path = lp > 0.5 * NEG_LOG
        lq_path = jnp.where(involved & uses_k, lp, 0.0)
        used_a = jnp.any((z_new == k1) & mi)
        used_b = jnp.any((z_new == k2) & mi)
        # feature pairs covering (used_a, used_b), not both 0: 1, 2 or 3 options
        n_opts = jnp.where(used_a & used_b, 1, jnp.where(used_a | used_b, 2, 3))
        u = jax.random.randint(k_feat, (), 0, n_opts)
        fa_s = jnp.where(used_a, 1.0, jnp.where(used_b, (u == 1) * 1.0, (u != 1) * 1.0))
        fb_s = jnp.where(used_b, 1.0, jnp.where(used_a, (u == 1) * 1.0, (u != 0) * 1.0))
        fa = jnp.where(forced, f_s[i, k1], fa_s)
        fb = jnp.where(forced, f_s[i, k2], fb_s)
        ok_feat = (fa >= used_a) & (fb >= used_b) & ((fa + fb) > 0)
        lq_feat = -jnp.log(n_opts.astype(jnp.float64))
        # a trajectory that does not have k1 keeps both off (and must, when forced)
        ok_out = (z_s[i] != k2).all() & (f_s[i, k2] == 0) & (f_s[i, k1] == 0)
        feasible = jnp.where(involved, jnp.where(uses_k, ok_path, True) & ok_feat, jnp.where(forced, ok_out, True))
        fa = jnp.where(involved, fa, f_m[i, k1])
        fb = jnp.where(involved, fb, 0.0)
        lq = jnp.where(involved, lq_path + lq_feat, 0.0)
        z_out = jnp.where(involved, z_new, zi)
        return z_out, fa, fb, lq, feasible

    def block(carry, inputs):
        z, f, done, fits, lq, feasible = carry
        key, rows = inputs
        lik_ab, _ = emission.log_likelihoods(fits, data, emission.init_cache(2))  # (N, T, 2)
        valid = rows >= 0
        keys = jax.random.split(key, rows.shape[0])
        zs, fas, fbs, lqs, oks = jax.vmap(lambda k, i, v: one_trajectory(k, i, v, lik_ab))(keys, rows, valid)
        safe = jnp.where(valid, rows, N)  # out of range: dropped by the scatter
        z = z.at[safe].set(zs, mode="drop")
        f = f.at[safe, k1].set(fas, mode="drop").at[safe, k2].set(fbs, mode="drop")
        done = done.at[safe].set(True, mode="drop")
        fits = emission.fit_point(data, weights_of(z, done), fits)
        return (z, f, done, fits, lq + jnp.sum(jnp.where(valid, lqs, 0.0)), feasible & jnp.all(oks | ~valid)), None

    init = (z_m, f_m.at[:, k2].set(0.0), jnp.zeros(N, bool), fits0, jnp.zeros(()), jnp.array(True))
    (z, f, _, fits, lq, feasible), _ = jax.lax.scan(block, init, (jax.random.split(key, num_blocks), blocks))
    return z, f, lq, feasible, fits


def split_merge_at(key, emission, data, hyper, features, z, params, log_lik, anchors, num_blocks: int = 4,
                   forced_params=None):
    """One split-merge proposal with given anchors ((i_a, t_a, i_b, t_b)): returns
    (log acceptance ratio, possible, is_split, features', z', params', log_lik').

    ``forced_params`` (optional, two skills' parameters stacked): use these instead of the
    proposal's draws for the two slots of the proposed state (k1 and k2 after a split; k1 and
    the freed k2 after a merge): a test hook that evaluates the ratio of a given reverse move.
    """
    N, T = data.mask.shape
    K = features.shape[1]
    mask = data.mask
    ia, ta, ib, tb = anchors
    k_slot, k_order, k_alloc, k_prop, k_prior = jax.random.split(key, 5)
    k1 = z[ia, ta]
    l2 = z[ib, tb]
    same_step = (ia == ib) & (ta == tb)
    is_split = k1 == l2
    m = features.sum(0)
    free = m == 0
    k2_free = jax.random.categorical(k_slot, jnp.where(free, 0.0, -jnp.inf))
    k2 = jnp.where(is_split, jnp.where(jnp.any(free), k2_free, (k1 + 1) % K), l2)
    # the merged state M (the current one for a split)
    z_merged = jnp.where(z == k2, k1, z)
    f_merged = features.at[:, k1].set(jnp.maximum(features[:, k1], features[:, k2])).at[:, k2].set(0.0)
    z_m = jnp.where(is_split, z, z_merged)
    f_m = jnp.where(is_split, features, f_merged)
    n_free_m = jnp.sum(f_m.sum(0) == 0)
    # auxiliary visiting order: the anchors' trajectories first, then at random
    priority = jax.random.uniform(k_order, (N,)).at[ib].set(-1.0).at[ia].set(-2.0)
    order = jnp.argsort(priority).astype(jnp.int32)
    z_s, f_s, lq_alloc, feasible, fits = _allocate(k_alloc, emission, data, hyper, z_m, f_m, k1, k2,
                                                   (ia, ta, ib, tb), order, ~is_split, z, features, num_blocks)
    # data-driven proposals: the union (merge) and the two halves (split)
    w_union = ((z_m == k1) & mask).astype(jnp.float64)
    w_a = ((z_s == k1) & mask).astype(jnp.float64)
    w_b = ((z_s == k2) & mask).astype(jnp.float64)
    n_a, n_b = jnp.sum(w_a), jnp.sum(w_b)
    mean_fit = jax.tree.map(lambda f: (n_a * f[0] + n_b * f[1]) / jnp.maximum(n_a + n_b, 1.0), fits)
    inits = jax.tree.map(lambda u, f: jnp.stack([u, f[0], f[1]]), mean_fit, fits)
    current_two = _two_slots(params, k1, k2)
    others = jax.tree.map(lambda c: jnp.stack([c[0], c[0], c[1]]), current_two)
    weights3 = jnp.stack([w_union, w_a, w_b])
    new3, lq_new3, lq_other3 = jax.vmap(lambda k, w, o, i: emission.propose_and_score(k, data, w, o, i))(
        jax.random.split(k_prop, 3), weights3, others, inits)
    prior_draw = emission.sample_prior_one(k_prior)
    if forced_params is not None:
        new3 = jax.tree.map(lambda n, fp: jnp.where(is_split, jnp.stack([n[0], fp[0], fp[1]]),
                                                    jnp.stack([fp[0], n[1], n[2]])), new3, forced_params)
        prior_draw = jax.tree.map(lambda p, fp: jnp.where(is_split, p, fp[1]), prior_draw, forced_params)
        lq_new3 = jax.vmap(lambda w, o, i: emission.propose_and_score(k_prop, data, w, o, i)[2])(
            weights3, new3, inits)
    # the proposed state's two slots
    split_two = jax.tree.map(lambda n: jnp.stack([n[1], n[2]]), new3)
    merge_two = jax.tree.map(lambda n, p: jnp.stack([n[0], p]), new3, prior_draw)
    new_two = jax.tree.map(lambda s, mm: jnp.where(is_split, s, mm), split_two, merge_two)
    new_params = _set_two(params, k1, k2, new_two)
    new_cols, _ = emission.log_likelihoods(new_two, data, emission.init_cache(2))  # (N, T, 2)
    new_log_lik = log_lik.at[:, :, k1].set(new_cols[..., 0]).at[:, :, k2].set(new_cols[..., 1])
    new_z = jnp.where(is_split, z_s, z_m)
    new_f = jnp.where(is_split, f_s, f_m)
    lp_new = log_target(emission, data, hyper, new_f, new_z, new_params, new_log_lik)
    lp_old = log_target(emission, data, hyper, features, z, params, log_lik)
    log_p0 = lambda one: emission.log_prior(jax.tree.map(lambda x: x[None], one))[0]  # noqa: E731
    # q(S | M): slot choice, allocation, the halves' densities; q(M | S): union density, prior of the freed slot
    lq_halves = jnp.where(is_split, lq_new3[1] + lq_new3[2], lq_other3[1] + lq_other3[2])
    lq_s_given_m = -jnp.log(jnp.maximum(n_free_m, 1).astype(jnp.float64)) + lq_alloc + lq_halves
    slot_k2 = jax.tree.map(lambda p: p[k2], params)
    lq_m_given_s = jnp.where(is_split, lq_other3[0] + log_p0(slot_k2), lq_new3[0] + log_p0(prior_draw))
    sign = jnp.where(is_split, 1.0, -1.0)
    log_ratio = (lp_new - lp_old) + sign * (lq_m_given_s - lq_s_given_m)
    possible = ~same_step & jnp.where(is_split, jnp.any(free), feasible) & jnp.isfinite(log_ratio)
    return log_ratio, possible, is_split, new_f, new_z, new_params, new_log_lik


def _anchors(key, mask):
    N, T = mask.shape
    k1, k2 = jax.random.split(key)
    logits = jnp.where(mask.ravel(), 0.0, -jnp.inf)
    a = jax.random.categorical(k1, logits)
    b = jax.random.categorical(k2, logits)
    return (a // T, a % T, b // T, b % T)


def split_merge(key, emission, data, hyper, features, z, params, log_lik, num_blocks: int = 4,
                forced_params: Optional[dict] = None):
    """One split-merge trial: returns (features, z, params, log_lik, info)."""
    k_anchor, k_move, k_acc = jax.random.split(key, 3)
    anchors = _anchors(k_anchor, data.mask)
    log_ratio, possible, is_split, f2, z2, p2, ll2 = split_merge_at(
        k_move, emission, data, hyper, features, z, params, log_lik, anchors, num_blocks, forced_params)
    accept = possible & (jnp.log(jax.random.uniform(k_acc)) < log_ratio)
    pick = lambda a, b: jax.tree.map(lambda x, y: jnp.where(accept, x, y), a, b)  # noqa: E731
    info = SplitMergeInfo(is_split, possible, accept, jnp.where(possible, log_ratio, -jnp.inf))
    return pick(f2, features), pick(z2, z), pick(p2, params), pick(ll2, log_lik), info
