"""Bipartite token merging with static shapes: matching, group ids, sizes, merge, unmerge.

A *match* (what the band cache stores) is
  group   [B, N] int32  index of every token's group in the query layout
                        [dst (N_dst) ; unmerged src (U)]; a merged src points at its dst.
  sizes   [B, N_m] f32  g = 1 + number of src merged into a dst, 1 otherwise.
  unm_pos [B, U] int32  sequence positions of the unmerged src, in query-layout order.

Merging averages q, k, v (after qk-norm and RoPE) over each group; unmerging gives
every token its group's row.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.compression.partition import Partition
from rvggt_jax.compression.plan import LayerPlan

# Score of protected src: below every cosine similarity, so never among the top r.
PROTECTED_SCORE = -4.0


def normalize(x: jax.Array, eps: float = 1e-6) -> jax.Array:
    """Rows scaled to unit L2 norm (zero rows stay zero)."""
    return x * jax.lax.rsqrt(jnp.maximum(jnp.sum(x * x, axis=-1, keepdims=True), eps * eps))


def best_match(a: jax.Array, b: jax.Array, chunk: int) -> tuple[jax.Array, jax.Array]:
    """For unit rows a [..., Na, C] and b [..., Nb, C]: (max_j a.b_j, argmax_j) over b,
    each [..., Na]; evaluated in chunks of `chunk` rows of a (0: one chunk)."""
    def one(a_c):
        sims = jnp.einsum("...ic,...jc->...ij", a_c, b)
        return jnp.max(sims, axis=-1), jnp.argmax(sims, axis=-1).astype(jnp.int32)

    na = a.shape[-2]
    if chunk <= 0 or na <= chunk:
        return one(a)
    n_chunks = -(-na // chunk)
    pad = n_chunks * chunk - na
    a_p = jnp.pad(a, [(0, 0)] * (a.ndim - 2) + [(0, pad), (0, 0)])
    a_p = a_p.reshape(a.shape[:-2] + (n_chunks, chunk, a.shape[-1]))
    a_p = jnp.moveaxis(a_p, -3, 0)
    best, arg = jax.lax.map(one, a_p)  # [n_chunks, ..., chunk]
    best = jnp.moveaxis(best, 0, -2).reshape(a.shape[:-2] + (n_chunks * chunk,))[..., :na]
    arg = jnp.moveaxis(arg, 0, -2).reshape(a.shape[:-2] + (n_chunks * chunk,))[..., :na]
    return best, arg


def _inverse_permutation(order: jax.Array) -> jax.Array:
    """order [..., n] (a permutation along the last axis) -> its inverse."""
    n = order.shape[-1]
    ranks = jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32), order.shape)
    return jnp.put_along_axis(jnp.zeros_like(ranks), order, ranks, axis=-1, inplace=False)


def compute_match(metric: jax.Array, protected_src: jax.Array | None, part: Partition, plan: LayerPlan,
                  chunk: int) -> dict[str, jax.Array]:
    """metric [B, N, C] (similarity features), protected_src [B, N_src] bool or None ->
    the match of this layer's plan (see the module docstring)."""
    b = metric.shape[0]
    m = normalize(metric)
    n_dst, n_src, r, U = plan.n_dst, plan.n_src, plan.r, plan.n_unm

    if plan.scope == "sequence":
        src = jnp.take(m, part.src_pos, axis=1, mode="clip")
        dst = jnp.take(m, part.dst_pos, axis=1, mode="clip")
        score, arg = best_match(src, dst, chunk)  # [B, N_src], arg indexes dst_pos
        if protected_src is not None:
            score = jnp.where(protected_src, PROTECTED_SCORE, score)
        order = jnp.argsort(-score, axis=-1, stable=True)  # best first
        rank = _inverse_permutation(order)  # position of each src in `order`
        merged = rank < r
        group_src = jnp.where(merged, arg, n_dst + rank - r)
        unm_pos = jnp.take(jnp.asarray(part.src_pos, jnp.int32), order[:, r:], mode="clip")
    else:
        s1, n_src_f = part.src_pos_f.shape
        r_f = plan.r_frame
        u_f = n_src_f - r_f
        src = jnp.take(m, part.src_pos_f, axis=1, mode="clip")  # [B, S-1, n_src_f, C]
        dst = jnp.take(m, jnp.asarray(part.dst_pos[part.dst_rank_f]), axis=1, mode="clip")  # [B, S-1, n_dst_f, C]
        score, arg = best_match(src, dst, chunk)  # [B, S-1, n_src_f], arg local to the frame
        arg = jnp.take(jnp.asarray(part.dst_rank_f, jnp.int32), arg + jnp.arange(s1, dtype=jnp.int32)[:, None]
                       * part.dst_rank_f.shape[1], mode="clip")
        if protected_src is not None:
            score = jnp.where(protected_src.reshape(b, s1, n_src_f), PROTECTED_SCORE, score)
        order = jnp.argsort(-score, axis=-1, stable=True)
        rank = _inverse_permutation(order)
        merged = rank < r_f
        frame_base = n_dst + jnp.arange(s1, dtype=jnp.int32)[:, None] * u_f
        group_src = jnp.where(merged, arg, frame_base + rank - r_f).reshape(b, n_src)
        merged = merged.reshape(b, n_src)
        unm_pos = jnp.take_along_axis(jnp.broadcast_to(jnp.asarray(part.src_pos_f, jnp.int32), order.shape),
                                      order[..., r_f:], axis=-1, mode="promise_in_bounds").reshape(b, U)

    group_src = group_src.astype(jnp.int32)
    dst_ranks = jnp.broadcast_to(jnp.arange(n_dst, dtype=jnp.int32), (b, n_dst))
    group = jnp.take(jnp.concatenate([dst_ranks, group_src], axis=1), part.perm_to_pos, axis=1, mode="clip")
    counts = jax.vmap(lambda g, w: jax.ops.segment_sum(w, g, num_segments=n_dst + 1))(
        jnp.where(merged, group_src, n_dst), merged.astype(jnp.float32))[:, :n_dst]
    sizes = jnp.concatenate([1.0 + counts, jnp.ones((b, U), jnp.float32)], axis=1)
    return {"group": group, "sizes": sizes, "unm_pos": unm_pos.astype(jnp.int32)}


def merge(x: jax.Array, match: dict[str, jax.Array], n_query: int) -> jax.Array:
    """x [B, N, F] -> group means [B, N_m, F]."""
    b, n, f = x.shape
    ids = (match["group"] + (jnp.arange(b, dtype=jnp.int32) * n_query)[:, None]).reshape(-1)
    sums = jax.ops.segment_sum(x.reshape(b * n, f), ids, num_segments=b * n_query)
    return sums.reshape(b, n_query, f) / match["sizes"][..., None]


def unmerge(y: jax.Array, match: dict[str, jax.Array]) -> jax.Array:
    """y [B, N_m, F] -> [B, N, F]: every token takes its group's row."""
    return jnp.take_along_axis(y, match["group"][..., None], axis=1, mode="promise_in_bounds")


def identity_match(n: int, batch: int) -> dict[str, jax.Array]:
    """The match of r = 0 (every token its own group), for tests."""
    return {"group": jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32), (batch, n)),
            "sizes": jnp.ones((batch, n), jnp.float32),
            "unm_pos": jnp.zeros((batch, 0), jnp.int32)}


def static_protected_flags(positions: np.ndarray, n: int) -> np.ndarray:
    flags = np.zeros(n, bool)
    flags[positions] = True
    return flags
