"""Test helpers: random block params and an independent float64 numpy reference of the
compressed global block (variable-size sets, explicit additive log-size bias, no static
padding, no caching), written from the method's definition rather than from the
static-shape code it checks. Only tests use them, so they live under tests/helpers/."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.model import layers
from rvggt_jax.compression.merge import Match


def random_block_params(key, c: int = 32, heads: int = 2, mlp_ratio: float = 4.0) -> dict:
    """Params of one transformer block in our layout (random, non-trivial norms)."""
    hidden = int(c * mlp_ratio)
    d = c // heads
    ks = iter(jax.random.split(key, 32))

    def lin(i, o):
        return {"kernel": jax.random.normal(next(ks), (i, o), jnp.float32) / np.sqrt(i),
                "bias": 0.05 * jax.random.normal(next(ks), (o,), jnp.float32)}

    def ln(n):
        return {"scale": 1.0 + 0.1 * jax.random.normal(next(ks), (n,), jnp.float32),
                "bias": 0.1 * jax.random.normal(next(ks), (n,), jnp.float32)}

    return {"norm1": ln(c), "attn": {"q": lin(c, c), "k": lin(c, c), "v": lin(c, c), "q_norm": ln(d),
                                     "k_norm": ln(d), "proj": lin(c, c)},
            "ls1": {"gamma": 0.5 + 0.1 * jax.random.normal(next(ks), (c,), jnp.float32)}, "norm2": ln(c),
            "mlp": {"fc1": lin(c, hidden), "fc2": lin(hidden, c)},
            "ls2": {"gamma": 0.5 + 0.1 * jax.random.normal(next(ks), (c,), jnp.float32)}}


def identity_match(n: int, batch: int) -> Match:
    """The match of r = 0 (every token its own group)."""
    return Match(jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32), (batch, n)), jnp.ones((batch, n), jnp.float32),
                 jnp.zeros((batch, 0), jnp.int32))


def global_positions(frames: int, h: int, w: int, ns: int = 5) -> jax.Array:
    return jnp.tile(jnp.asarray(layers.patch_positions(h, w, ns))[None], (1, frames, 1))


def kept_by_rule(f: int, i: int, j: int, h: int, w: int, tile, phase: bool) -> bool:
    """The phase-shifted sub-grid rule for one patch, written out."""
    t, k = tile
    if t == 1:
        return True
    if i >= (h // t) * t or j >= (w // t) * t:
        return False
    rf, cf = ((f // t) % t, f % t) if phase else (0, 0)
    return ((i - rf) % t) < k and ((j - cf) % t) < k


def reference_match(metric: np.ndarray, is_dst: np.ndarray, protected: np.ndarray, r: int,
                    frame_of: np.ndarray | None = None):
    """One batch element. metric [N, C]; is_dst / protected [N] bool; r merges at most
    (the authors' count: min(r, unprotected src), the best-scoring unprotected src).
    Returns (parent [N]: the dst position each token is grouped with (itself if not
    merged), margins (top-r score gap, min best-vs-second gap of merged src)).
    frame_of: per-position frame, restricting matches to the same frame (frame scope),
    then r is per frame."""
    m = metric / np.maximum(np.linalg.norm(metric, axis=-1, keepdims=True), 1e-6)
    n = m.shape[0]
    parent = np.arange(n)
    groups = [np.arange(n)] if frame_of is None else [np.flatnonzero(frame_of == f) for f in np.unique(frame_of)]
    gaps, second = [], []
    for pos in groups:
        src = pos[~is_dst[pos]]
        dst = pos[is_dst[pos]]
        if src.size == 0 or r == 0:
            continue
        sims = m[src] @ m[dst].T
        best = sims.argmax(1)
        score = sims.max(1)
        srt = np.sort(sims, axis=1)
        score = np.where(protected[src], -np.inf, score)
        order = np.argsort(-score, kind="stable")
        chosen = order[:min(r, int((~protected[src]).sum()))]
        parent[src[chosen]] = dst[best[chosen]]
        if r < src.size:
            gaps.append(score[order[r - 1]] - score[order[r]])
        if srt.shape[1] > 1:
            second.append(np.min(srt[chosen, -1] - srt[chosen, -2]))
    return parent, (min(gaps) if gaps else np.inf, min(second) if second else np.inf)


def reference_block(p, x: np.ndarray, pos, heads: int, rope_freq: float, parent: np.ndarray,
                    kv_keep_pos: np.ndarray | None, size_bias: bool = True,
                    extra_pos: np.ndarray | None = None) -> np.ndarray:
    """Compressed block for one batch element in float64 from explicit sets.

    x [N, C]; parent [N]: group representative (dst position) of every token;
    kv_keep_pos [N] bool: the K/V rule evaluated at each *parent* position (None: all).
    Groups are the tokens sharing a parent; queries and keys are group means of q, k, v;
    a group is a key when its parent is kept; logits get + log(group size).
    extra_pos: positions whose own (un-merged) k, v are appended once more as size-1 keys
    when kept by the rule at their position, and whose own q attends as a query of its
    own, its output that token's (the authors' duplicated protected dst tokens)."""
    xj = jnp.asarray(x[None], jnp.float32)
    xn = layers.layer_norm(p["norm1"], xj)
    q, k, v = (np.asarray(t[0], np.float64) for t in layers.attention_qkv(p["attn"], xn, heads, pos, rope_freq))
    n, h, d = q.shape
    reps = np.unique(parent)
    idx = {int(rp): i for i, rp in enumerate(reps)}
    gid = np.array([idx[int(a)] for a in parent])
    size = np.bincount(gid, minlength=reps.size).astype(np.float64)
    qm = np.stack([q[gid == g].mean(0) for g in range(reps.size)])
    km = np.stack([k[gid == g].mean(0) for g in range(reps.size)])
    vm = np.stack([v[gid == g].mean(0) for g in range(reps.size)])
    keys = np.arange(reps.size) if kv_keep_pos is None else np.flatnonzero(kv_keep_pos[reps])
    kk, vv, lg = km[keys], vm[keys], np.log(size[keys])
    if extra_pos is not None:
        ex = extra_pos if kv_keep_pos is None else extra_pos[kv_keep_pos[extra_pos]]
        kk, vv, lg = np.concatenate([kk, k[ex]]), np.concatenate([vv, v[ex]]), np.concatenate([lg, np.zeros(ex.size)])
    queries = qm if extra_pos is None else np.concatenate([qm, q[extra_pos]])
    out = np.zeros_like(queries)
    for hh in range(h):
        logits = queries[:, hh] @ kk[:, hh].T / math.sqrt(d)
        if size_bias:
            logits = logits + lg[None]
        logits -= logits.max(1, keepdims=True)
        wgt = np.exp(logits)
        wgt /= wgt.sum(1, keepdims=True)
        out[:, hh] = wgt @ vv[:, hh]
    out = out.reshape(len(queries), h * d)
    proj = out @ np.asarray(p["attn"]["proj"]["kernel"], np.float64) + np.asarray(p["attn"]["proj"]["bias"])
    attn_tok = proj[gid]
    if extra_pos is not None:  # each duplicated token takes its own query's row
        attn_tok[extra_pos] = proj[reps.size:]
    y = x.astype(np.float64) + np.asarray(p["ls1"]["gamma"], np.float64) * attn_tok
    yj = jnp.asarray(y[None], jnp.float32)
    mlp = np.asarray(layers.mlp(p["mlp"], layers.layer_norm(p["norm2"], yj))[0], np.float64)
    return y + np.asarray(p["ls2"]["gamma"], np.float64) * mlp
