"""The paper's sampled attention rank (appendix "Rank Spectrum of Global Attention").

For a global layer l and head h, m query rows are sampled out of the N = S * P tokens of
the sequence and their attention probabilities over all N keys form an [m, N] matrix.
Its singular values s_1 >= s_2 >= ... give

    r95 = min { r : sum_{i <= r} s_i^2 / sum_i s_i^2 >= 0.95 },

reported as the normalised rank r95 / m, averaged over heads (and scenes): the layer's
rank profile. The whole [N, N] matrix is never formed: only q of the m sampled rows and
k of the whole sequence ([B, N, H, D], what the block computes anyway), and one head's
[B, m, N] rows at a time.

    x, psi = layer_inputs(params, images, config, layers)   # global blocks' inputs
    prof = rank_profile(params, images, config, m=256)      # numpy, per layer and head
    diagnostics.r95(rows)                                    # one concrete [m, N] -> int
"""

from __future__ import annotations

import functools
import math
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

ENERGY = 0.95  # the paper's spectral-energy fraction


# ---------------------------------------------------------------------------------------
# rows, spectra, r95
# ---------------------------------------------------------------------------------------


def sample_queries(tokens: int, m: int, seed: int = 0) -> np.ndarray:
    """[min(m, tokens)] sorted query positions drawn without replacement from the N =
    `tokens` positions of the sequence (static: numpy, a fixed seed)."""
    if m < 1:
        raise ValueError(f"the number of sampled query rows m must be >= 1; got {m}")
    if tokens < 1:
        raise ValueError(f"a sequence of {tokens} tokens has no rows to sample")
    m = min(m, tokens)
    return np.sort(np.random.default_rng(seed).choice(tokens, m, replace=False)).astype(np.int32)


def attention_rows(q: jax.Array, k: jax.Array, query_idx, head: int | jax.Array | None = None) -> jax.Array:
    """Attention probabilities of the sampled queries over every key.

    q, k [B, N, H, D] (after qk-norm and RoPE, as the block attends), query_idx [m] ->
    [B, H, m, N] float32, softmax(q k^T / sqrt(D)) over the N keys; with `head`, that
    head's [B, m, N] alone. Jit-able; memory m * N per head, never N * N."""
    qs = jnp.take(q, jnp.asarray(query_idx), axis=1).astype(jnp.float32)  # [B, m, H, D]
    kf = k.astype(jnp.float32)
    if head is not None:
        qs, kf = qs[:, :, head], kf[:, :, head]
        logits = jnp.einsum("bmd,bnd->bmn", qs, kf)
    else:
        logits = jnp.einsum("bmhd,bnhd->bhmn", qs, kf)
    return jax.nn.softmax(logits / math.sqrt(q.shape[-1]), axis=-1)


def singular_values(rows: jax.Array) -> jax.Array:
    """rows [..., m, N] -> singular values [..., min(m, N)], descending (jit-able)."""
    return jnp.linalg.svd(rows.astype(jnp.float32), compute_uv=False)


def r95_of_spectrum(s: jax.Array, energy: float = ENERGY) -> jax.Array:
    """Singular values [..., m] (descending) -> int32 [...]: the smallest r whose leading
    r squared singular values hold `energy` of their sum (jit-able; 0 for an all-zero
    spectrum)."""
    e = jnp.square(s.astype(jnp.float32))
    total = jnp.sum(e, axis=-1, keepdims=True)
    frac = jnp.cumsum(e, axis=-1) / jnp.where(total > 0, total, 1.0)
    # the prefixes still short of the target, plus the one that reaches it; the relative
    # slack keeps an exact tie (e.g. 19 of 20 equal values) on the paper's side of >=
    short = jnp.sum(frac < energy * (1 - 1e-6), axis=-1)
    return jnp.where(total[..., 0] > 0, jnp.minimum(short + 1, s.shape[-1]), 0).astype(jnp.int32)


def r95(rows, energy: float = ENERGY) -> int:
    """The paper's r95 of one concrete [m, N] array of attention weights (the m sampled
    query rows over all N keys) -> a Python int. Computed in float64 (numpy)."""
    a = np.asarray(rows, dtype=np.float64)
    if a.ndim != 2:
        raise ValueError(f"r95 takes one [m, N] matrix of attention rows; got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError("r95: the attention rows hold NaN or infinite values")
    e = np.square(np.linalg.svd(a, compute_uv=False))
    total = e.sum()
    if total <= 0:
        return 0
    frac = np.cumsum(e) / total
    return int(min(np.sum(frac < energy * (1 - 1e-9)) + 1, e.size))


def head_ranks(q: jax.Array, k: jax.Array, query_idx, energy: float = ENERGY) -> tuple[jax.Array, jax.Array]:
    """Per head: (r95 int32 [B, H], singular values [B, H, m]) of the sampled attention
    rows of q, k [B, N, H, D]. One head's [B, m, N] rows live at a time (`lax.map` over
    heads). Jit-able."""
    heads = q.shape[2]

    def one(h):
        s = singular_values(attention_rows(q, k, query_idx, h))  # [B, m]
        return r95_of_spectrum(s, energy), s

    r, s = jax.lax.map(one, jnp.arange(heads))  # [H, B], [H, B, m]
    return r.T, jnp.swapaxes(s, 0, 1)


# ---------------------------------------------------------------------------------------
# the model's global layers
# ---------------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnames=("config", "layers", "with_output"))
def layer_inputs(params, images: jax.Array, config, layers: tuple[int, ...], with_output: bool = False):
    """The inputs of global blocks `layers` (the frame-block output of each layer, what
    the global block reads) and the saliency Psi.

    images [B, S, 3, H, W] in [0, 1] -> (x [K, B, S*P, C] float32 for the K layers, Psi
    [B, S, h*w]), and with `with_output` (the last layer among `layers`) also the
    aggregator's output [B, S, P, 2C] (what the heads read of the last layer: every
    global block then runs). Runs the aggregator under `config` (its compression
    included) through its kept-layer machinery: no hook in the hot path."""
    from rvggt_jax.model.aggregator import aggregator_forward

    if not layers:
        raise ValueError("layer_inputs needs at least one layer")
    if with_output and config.depth - 1 not in layers:
        raise ValueError(f"the aggregator's output is layer {config.depth - 1}'s: add it to `layers`")
    b, s = images.shape[:2]
    agg, _, saliency = aggregator_forward(params["aggregator"], images, config, layers)
    c = config.embed_dim
    x = jnp.stack([agg[i].array()[..., :c].reshape(b, -1, c) for i in layers])
    if with_output:
        return x, saliency, agg[config.depth - 1].array()
    return x, saliency


@functools.partial(jax.jit, static_argnames=("config", "image_hw", "query_idx", "energy"))
def layer_head_ranks(p_block, x: jax.Array, config, image_hw: tuple[int, int],
                     query_idx: tuple[int, ...], energy: float = ENERGY) -> tuple[jax.Array, jax.Array]:
    """A global block's (params `p_block`) dense attention on its input x
    [B, S*P, C]: (r95 int32 [B, H], singular values [B, H, m]) for the sampled queries
    `query_idx` (a static tuple of positions). q and k as the block computes them
    (norm1, projection, qk-norm, RoPE of the sequence), in token chunks."""
    from rvggt_jax import compression
    from rvggt_jax.model import layers as L
    from rvggt_jax.model.aggregator import rope_tables

    n = x.shape[1]
    per_frame = config.patch_start_idx + (image_hw[0] // config.patch_size) * (image_hw[1] // config.patch_size)
    frames = n // per_frame
    geom = compression.Geometry(frames, image_hw[0] // config.patch_size, image_hw[1] // config.patch_size,
                                config.patch_start_idx)
    _, tables = rope_tables(geom, config, frames)
    q, k = L.block_qkv(p_block, x, config.num_heads, tables, dtype=config.compute_dtype, parts="qk")
    return head_ranks(q, k, np.asarray(query_idx), energy)


def rank_profile(params, images, config, m: int = 256, seed: int = 0, layers: Sequence[int] | None = None,
                 energy: float = ENERGY) -> dict:
    """The rank profile of one scene: images [S, 3, H, W] or [B, S, 3, H, W].

    Attention is measured in the dense model (the paper's VGGT: `config` with the dense
    preset), `m` query rows sampled with `seed`. Returns numpy/Python values:
      r95 [K, H] int (batch element 0), normalised [K, H] = r95 / m, profile [K] (mean
      over heads), spectra [K, H, m], layers (K), m, tokens N, frames S."""
    images = jnp.asarray(images, jnp.float32)
    if images.ndim == 4:
        images = images[None]
    if images.ndim != 5:
        raise ValueError(f"images must be [S, 3, H, W] or [B, S, 3, H, W]; got shape {images.shape}")
    dense = config.with_compression("dense")
    layers = tuple(range(config.depth)) if layers is None else tuple(sorted(set(int(i) for i in layers)))
    bad = [i for i in layers if not 0 <= i < config.depth]
    if bad:
        raise ValueError(f"layers {bad} outside the model's {config.depth} global layers")
    x, _ = layer_inputs(params, images, dense, layers)
    hw = tuple(int(v) for v in images.shape[-2:])
    idx = tuple(int(i) for i in sample_queries(x.shape[2], m, seed))
    ranks, spectra = [], []
    for j, layer in enumerate(layers):
        # (one compiled program for every layer: same shapes, the block's params an argument)
        r, s = layer_head_ranks(params["aggregator"]["global_blocks"][str(layer)], x[j], dense, hw, idx, energy)
        ranks.append(np.asarray(r)[0])
        spectra.append(np.asarray(s)[0])
    ranks = np.stack(ranks)
    m_eff = len(idx)
    return dict(layers=list(layers), m=m_eff, tokens=int(x.shape[2]), frames=int(images.shape[1]),
                r95=ranks, normalised=ranks / m_eff, profile=(ranks / m_eff).mean(axis=1),
                spectra=np.stack(spectra), energy=energy)


def average_profiles(profiles: Sequence[Sequence[float]]) -> np.ndarray:
    """The mean rank profile over scenes: each [depth] r95/m -> [depth]."""
    arr = [np.asarray(p, np.float64) for p in profiles]
    if not arr:
        raise ValueError("no rank profiles to average")
    shapes = {a.shape for a in arr}
    if len(shapes) != 1 or arr[0].ndim != 1:
        raise ValueError(f"rank profiles must all be 1-D of one length (one value per layer); got {sorted(shapes)}")
    return np.mean(arr, axis=0)
