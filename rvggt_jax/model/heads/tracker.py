"""Point tracker of the VGGT track head (upstream `BaseTrackerPredictor`, CoTracker-style).

Parameters are the `track_head.tracker` subtree of the converted state dict
(docs/conventions.md): `fmap_norm`, `ffeat_norm` (GroupNorm(1, C) -> {scale, bias}),
`corr_mlp.{fc1,fc2}`, `query_ref_token [1, 2, D]`, `ffeat_updater.0`, `vis_predictor.0`,
`conf_predictor.0` (only with `predict_conf`) and `updateformer`: `input_norm`,
`input_transform`, `output_norm`, `flow_head`, `virual_tracks [1, V, 1, hidden]` (upstream
spelling kept), `time_blocks.{i}`, `space_virtual_blocks.{j}` (self-attention blocks:
`norm1`, `attn.{q,k,v,out_proj}`, `norm2`, `mlp`) and `space_point2virtual_blocks.{j}`,
`space_virtual2point_blocks.{j}` (cross-attention blocks: `norm1`, `norm_context`,
`cross_attn.{q,k,v,out_proj}`, `norm2`, `mlp`).

Coordinates are pixel (x, y). Feature maps are NHWC: [B, S, h, w, C].

Sampling follows upstream's `bilinear_sampler`, i.e. `grid_sample(align_corners=True)`
on coordinates normalised by 2 / (size - 1): a coordinate x addresses the centre of pixel x
(0 is the centre of the first pixel, size - 1 the centre of the last). The query features
and the positional embedding are sampled with border padding (coordinates clamped to
[0, size - 1]), the correlation windows with zero padding (taps outside the map read 0).
An axis of size 1 collapses every coordinate onto its single pixel, as in torch.

Numerics: the flow embedding uses frequencies up to ~1000 rad per feature pixel, so from the
third iteration on, float32 rounding differences in the coordinates are amplified ~10^3 per
iteration; upstream run twice with 1e-7 relative input noise differs by ~1e-3 (tracks) and
~1e-2 (vis) after 4 iterations. Parity is therefore tight only for the first two iterations
(see tests/model/test_track_head.py).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.model import layers
from rvggt_jax.ops.shards import frame_layout
from rvggt_jax.config import TrackHeadConfig
from rvggt_jax.model.params import Params


# ---------------------------------------------------------------------------------------
# Constants upstream hard-codes (BaseTrackerPredictor / EfficientUpdateFormer defaults that
# TrackHead never overrides). Depths, the MLP ratio and the number of virtual tracks are
# read from the parameter shapes instead.
# ---------------------------------------------------------------------------------------
UPDATE_FORMER_NUM_HEADS = 8  # heads of every attention in the update transformer
FLOW_MAX_SCALE = 518.0  # raw flows enter the transformer divided by this
SINCOS_GRID_TEMPERATURE = 10000.0  # base of the query-position sin/cos embedding
FLOW_EMBED_FREQ_SCALE = 1000.0  # flow embedding frequencies: arange(0, C, 2) * this / C


# ---------------------------------------------------------------------------------------
# Sin/cos embeddings
# ---------------------------------------------------------------------------------------


def flow_embedding(xy: jax.Array, dim: int) -> jax.Array:
    """Upstream `get_2d_embedding(xy, dim, cat_coords=False)`: xy [..., 2] -> [..., 2*dim].

    Per axis, channels alternate sin, cos of `coord * f_k`, f_k = 2k * 1000 / dim (linear in
    k, not geometric); the x block comes first, then the y block."""
    freqs = np.arange(0, dim, 2, dtype=np.float32) * np.float32(FLOW_EMBED_FREQ_SCALE / dim)
    freqs = jnp.asarray(freqs)

    def one_axis(c):  # c [..., 1] -> [..., dim]
        ang = c * freqs
        return jnp.stack([jnp.sin(ang), jnp.cos(ang)], axis=-1).reshape(c.shape[:-1] + (dim,))

    return jnp.concatenate([one_axis(xy[..., 0:1]), one_axis(xy[..., 1:2])], axis=-1)


def _sincos_table(dim: int, size: int) -> np.ndarray:
    """[size, dim] sin then cos of `i * T^(-k / (dim/2))` at integer positions i < size,
    formed in float64 and rounded to float32 like upstream's
    `get_1d_sincos_pos_embed_from_grid`."""
    omega = 1.0 / SINCOS_GRID_TEMPERATURE ** (np.arange(dim // 2, dtype=np.float64) / (dim / 2.0))
    ang = np.arange(size, dtype=np.float64)[:, None] * omega[None, :]
    return np.concatenate([np.sin(ang), np.cos(ang)], axis=1).astype(np.float32)


def _pixel_coord(c: jax.Array, size: int) -> jax.Array:
    """Continuous pixel index addressed by coordinate c under align_corners=True; an axis of
    size 1 maps everything to 0 (torch's unnormalisation multiplies by size - 1)."""
    return c if size > 1 else jnp.zeros_like(c)


def _border_taps(c: jax.Array, size: int) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Border-padded linear taps along one axis: (lower index, upper index, upper weight)."""
    c = jnp.clip(_pixel_coord(c, size), 0.0, size - 1)
    lo = jnp.floor(c)
    frac = c - lo
    lo = lo.astype(jnp.int32)
    return lo, jnp.minimum(lo + 1, size - 1), frac


def sample_grid_embed(dim: int, hw: tuple[int, int], xy: jax.Array) -> jax.Array:
    """Bilinear, border-padded sample of upstream's `get_2d_sincos_pos_embed(dim, hw)` map
    (channels [0, dim/2) embed the column x, [dim/2, dim) the row y) at xy [..., 2]
    (feature-map pixels) -> [..., dim]. The map is separable (x half depends on the column
    only, y half on the row only), so each half is a 1-D interpolation of a small table."""
    h, w = hw

    def interp(table, c, size):
        lo, hi, frac = _border_taps(c, size)
        t = jnp.asarray(table)
        return t[lo] * (1.0 - frac)[..., None] + t[hi] * frac[..., None]

    return jnp.concatenate([interp(_sincos_table(dim // 2, w), xy[..., 0], w),
                            interp(_sincos_table(dim // 2, h), xy[..., 1], h)], axis=-1)


# ---------------------------------------------------------------------------------------
# Bilinear sampling
# ---------------------------------------------------------------------------------------


def sample_features(fmap: jax.Array, xy: jax.Array) -> jax.Array:
    """Upstream `sample_features4d`: bilinear, border padding, align_corners.

    fmap [B, h, w, C]; xy [B, M, 2] pixel (x, y) -> [B, M, C]."""
    b, h, w, c = fmap.shape
    x0, x1, fx = _border_taps(xy[..., 0], w)
    y0, y1, fy = _border_taps(xy[..., 1], h)
    flat = fmap.reshape(b, h * w, c)

    def tap(yi, xi):
        return jnp.take_along_axis(flat, (yi * w + xi)[..., None], axis=1)

    fx, fy = fx[..., None], fy[..., None]
    return ((1.0 - fy) * ((1.0 - fx) * tap(y0, x0) + fx * tap(y0, x1))
            + fy * ((1.0 - fx) * tap(y1, x0) + fx * tap(y1, x1)))


# ---------------------------------------------------------------------------------------
# Correlation pyramid
# ---------------------------------------------------------------------------------------


def avg_pool2(x: jax.Array) -> jax.Array:
    """`F.avg_pool2d(kernel_size=2, stride=2)` on [..., h, w, C] (odd edges dropped)."""
    h, w = x.shape[-3] // 2, x.shape[-2] // 2
    x = x[..., : 2 * h, : 2 * w, :]
    x = x.reshape(x.shape[:-3] + (h, 2, w, 2, x.shape[-1]))
    return (x[..., 0, :, 0, :] + x[..., 0, :, 1, :] + x[..., 1, :, 0, :] + x[..., 1, :, 1, :]) / 4.0


def feature_pyramid(fmaps: jax.Array, levels: int) -> list[jax.Array]:
    """[B, S, h, w, C] -> `levels` maps, each half the previous resolution (floor)."""
    pyr = [fmaps]
    for _ in range(levels - 1):
        pyr.append(avg_pool2(pyr[-1]))
    return pyr


@functools.partial(jax.tree_util.register_dataclass, data_fields=["flat"], meta_fields=["shapes"])
@dataclasses.dataclass(frozen=True)
class CorrPyramid:
    """Every pyramid level packed into one buffer, so that one traced body (a scan over
    levels) serves all of them and only one level's window is alive at a time.

    flat [B, S, T, C]: the levels' pixels row-major one after the other, then one zero row
    (index T-1) that every zero-padding tap reads. shapes: static (h, w) per level (pytree
    metadata, so it stays static under jit)."""

    flat: jax.Array
    shapes: tuple[tuple[int, int], ...]


def build_corr_pyramid(fmaps: jax.Array, levels: int) -> CorrPyramid:
    """fmaps [B, S, h, w, C] (normalised) -> the packed `levels`-level pyramid."""
    b, s, h, w, c = fmaps.shape
    if min(h, w) >> (levels - 1) == 0:
        raise ValueError(f"a {h}x{w} feature map is too small for {levels} correlation levels "
                         f"(each halves it; upstream's avg_pool2d fails too)")
    pyr = feature_pyramid(fmaps, levels)
    flat = jnp.concatenate([f.reshape(b, s, -1, c) for f in pyr] + [jnp.zeros((b, s, 1, c), fmaps.dtype)], axis=2)
    return CorrPyramid(flat, tuple((f.shape[2], f.shape[3]) for f in pyr))


def _window_axis(c: jax.Array, size: jax.Array, radius: int) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Taps of the 2r+1 zero-padded samples at c - r, ..., c + r along one axis of `size`.

    The offsets are integers, so all samples share c's fractional part and read the 2r+2
    consecutive pixels from floor(c) - r on. Returns (indices [..., 2r+2] clipped into the
    axis, in-bounds mask [..., 2r+2], frac [...]). On a size-1 axis every sample reads
    pixel 0 with weight 1 (torch's align-corners unnormalisation multiplies by size - 1)."""
    wide = size > 1
    # Beyond r + 2 pixels outside the axis every tap is outside anyway; clamping there keeps
    # the integer indices far from overflow without changing any result.
    c = jnp.where(wide, jnp.clip(c, -radius - 2.0, (size + radius + 1).astype(c.dtype)), 0.0)
    lo = jnp.floor(c)
    offsets = jnp.where(wide, jnp.arange(-radius, radius + 2, dtype=jnp.int32), 0)
    idx = lo.astype(jnp.int32)[..., None] + offsets
    inside = (idx >= 0) & (idx < size)
    return jnp.clip(idx, 0, size - 1), inside, c - lo


def _correlation_window(flat: jax.Array, base: jax.Array, h: jax.Array, w: jax.Array, targets: jax.Array,
                        xy: jax.Array, radius: int) -> jax.Array:
    """One level of upstream's `CorrBlock.corr_sample`, without the full correlation volume.

    flat [B, S, T, C] holds the level's [h, w] pixels from row `base` on and a zero row at
    T-1; targets [B, S, N, C]; xy [B, S, N, 2] in this level's pixels. Upstream correlates
    each target with the whole map (dot / sqrt(C)) and samples that volume bilinearly (zero
    padding) on a (2r+1)^2 grid of integer offsets; as sampling is linear, the same numbers
    come from correlating with the (2r+2)^2 pixels under the window only. Returns
    [B, S, N, (2r+1)^2], ordered x-offset-major (upstream stacks its (dy, dx) meshgrid into
    the (x, y) slots of the sampling grid)."""
    b, s, n, c = targets.shape
    k = 2 * radius + 1
    xi, x_in, fx = _window_axis(xy[..., 0], w, radius)  # [B, S, N, k+1] x2, [B, S, N]
    yi, y_in, fy = _window_axis(xy[..., 1], h, radius)
    idx = base + yi[..., :, None] * w + xi[..., None, :]  # [B, S, N, k+1 (y), k+1 (x)]
    idx = jnp.where(y_in[..., :, None] & x_in[..., None, :], idx, flat.shape[2] - 1)
    win = jnp.take_along_axis(flat, idx.reshape(b, s, -1, 1), axis=2).reshape(b, s, n, k + 1, k + 1, c)
    corr = jnp.einsum("bsnc,bsnyxc->bsnyx", targets, win) / math.sqrt(c)
    fx, fy = fx[..., None, None], fy[..., None, None]
    # bilinear along x then y: [B, S, N, k (y), k (x)]
    cx = (1.0 - fx) * corr[..., :, :k] + fx * corr[..., :, 1:]
    out = (1.0 - fy) * cx[..., :k, :] + fy * cx[..., 1:, :]
    return jnp.swapaxes(out, -1, -2).reshape(b, s, n, k * k)


def correlation_level(fmap: jax.Array, targets: jax.Array, xy: jax.Array, radius: int) -> jax.Array:
    """A single map's correlation features: fmap [B, S, h, w, C], targets [B, S, N, C],
    xy [B, S, N, 2] in the map's pixels -> [B, S, N, (2r+1)^2] (see `_correlation_window`)."""
    b, s, h, w, c = fmap.shape
    flat = jnp.concatenate([fmap.reshape(b, s, h * w, c), jnp.zeros((b, s, 1, c), fmap.dtype)], axis=2)
    return _correlation_window(flat, jnp.int32(0), jnp.int32(h), jnp.int32(w), targets, xy, radius)


def correlation_features(pyramid: CorrPyramid, targets: jax.Array, coords: jax.Array, radius: int) -> jax.Array:
    """All levels of `CorrBlock.corr_sample`: targets [B, S, N, C], coords [B, S, N, 2] in
    level-0 pixels -> [B, S, N, levels * (2r+1)^2], level-major like upstream's concat.
    Level i samples at coords / 2^i."""
    hw = np.array(pyramid.shapes, np.int32)
    bases = np.concatenate([[0], np.cumsum(hw[:, 0] * hw[:, 1])[:-1]]).astype(np.int32)
    scales = (1.0 / 2.0 ** np.arange(len(hw))).astype(np.float32)  # exact powers of two

    def level(_, xs):
        base, h, w, scale = xs
        return None, _correlation_window(pyramid.flat, base, h, w, targets, coords * scale, radius)

    _, out = jax.lax.scan(level, None, (jnp.asarray(bases), jnp.asarray(hw[:, 0]), jnp.asarray(hw[:, 1]),
                                        jnp.asarray(scales)))
    b, s, n, _ = targets.shape
    return jnp.moveaxis(out, 0, 3).reshape(b, s, n, -1)


# ---------------------------------------------------------------------------------------
# Update transformer (EfficientUpdateFormer)
# ---------------------------------------------------------------------------------------


def multihead_attention(p: Params, x: jax.Array, context: jax.Array, num_heads: int) -> jax.Array:
    """nn.MultiheadAttention(x, context, context), batch-first, no mask.

    x [B, Nq, E], context [B, Nk, E] -> [B, Nq, E]."""
    bq, nq, e = x.shape
    nk = context.shape[1]
    d = e // num_heads
    q = layers.linear(p["q"], x).reshape(bq, nq, num_heads, d)
    k = layers.linear(p["k"], context).reshape(bq, nk, num_heads, d)
    v = layers.linear(p["v"], context).reshape(bq, nk, num_heads, d)
    return layers.linear(p["out_proj"], layers.attention(q, k, v).reshape(bq, nq, e))


def attn_block(p: Params, x: jax.Array, num_heads: int) -> jax.Array:
    """Upstream `AttnBlock`: the residual stream restarts from norm1(x). x [B, N, E]."""
    x = layers.layer_norm(p["norm1"], x)
    x = x + multihead_attention(p["attn"], x, x, num_heads)
    return x + layers.mlp(p["mlp"], layers.layer_norm(p["norm2"], x))


def cross_attn_block(p: Params, x: jax.Array, context: jax.Array, num_heads: int) -> jax.Array:
    """Upstream `CrossAttnBlock`: x [B, Nq, E] attends to context [B, Nk, E]; the residual
    stream restarts from norm1(x)."""
    x = layers.layer_norm(p["norm1"], x)
    context = layers.layer_norm(p["norm_context"], context)
    x = x + multihead_attention(p["cross_attn"], x, context, num_heads)
    return x + layers.mlp(p["mlp"], layers.layer_norm(p["norm2"], x))


def update_former(p: Params, x: jax.Array, num_heads: int = UPDATE_FORMER_NUM_HEADS) -> jax.Array:
    """Upstream `EfficientUpdateFormer`: x [B, N, T, D_in] (tracks, frames) -> [B, N, T, D_out].

    Each layer attends over time per track (virtual tracks included); every
    (time_depth // space_depth)-th layer, starting with the first, then mixes tracks through
    the V learnt virtual tracks: virtual <- points (cross), virtual self-attention,
    points <- virtual (cross). Depths come from the params (upstream: 6 and 6); the layers
    run as a scan over groups of time blocks, so one copy of the body is traced."""
    tokens = layers.linear(p["input_transform"], layers.layer_norm(p["input_norm"], x))
    init_tokens = tokens
    b, n, t, e = tokens.shape
    time_depth = len(p["time_blocks"])
    space_depth = len(p.get("space_virtual_blocks", {}))
    every = 1
    if space_depth:
        every = time_depth // space_depth
        # Upstream indexes space block i // every after time block i (i % every == 0): any
        # other layout runs out of space blocks there too.
        if every == 0 or time_depth != every * space_depth:
            raise ValueError(f"update former with {time_depth} time blocks and {space_depth} space blocks: "
                             "time_depth must be a multiple of space_depth")
        virtual = p["virual_tracks"]  # [1, V, 1, E]
        tokens = jnp.concatenate([tokens, jnp.broadcast_to(virtual, (b, virtual.shape[1], t, e))], axis=1)
    n_all = tokens.shape[1]

    def time_block(tok, bp):
        return attn_block(bp, tok.reshape(b * n_all, t, e), num_heads).reshape(b, n_all, t, e)

    def space_blocks(tok, v2p, virt_p, p2v):
        space = jnp.swapaxes(tok, 1, 2).reshape(b * t, n_all, e)
        points, virt = space[:, :n], space[:, n:]
        virt = cross_attn_block(v2p, virt, points, num_heads)
        virt = attn_block(virt_p, virt, num_heads)
        points = cross_attn_block(p2v, points, virt, num_heads)
        return jnp.swapaxes(jnp.concatenate([points, virt], axis=1).reshape(b, t, n_all, e), 1, 2)

    groups = space_depth or time_depth
    space_names = ("space_virtual2point_blocks", "space_virtual_blocks", "space_point2virtual_blocks")

    def group(tok, g):  # time blocks g * every ... (g + 1) * every - 1, space blocks g
        for k in range(every):
            tok = time_block(tok, layers.select_block(p["time_blocks"], range(time_depth), g * every + k))
            if k == 0 and space_depth:
                tok = space_blocks(tok, *(layers.select_block(p[name], range(space_depth), g) for name in space_names))
        return tok, None

    tokens, _ = jax.lax.scan(group, tokens, jnp.arange(groups))
    tokens = tokens[:, :n] + init_tokens
    return layers.linear(p["flow_head"], layers.layer_norm(p["output_norm"], tokens))


# ---------------------------------------------------------------------------------------
# Tracker
# ---------------------------------------------------------------------------------------


def track_predictor(p: Params, query_points: jax.Array, fmaps: jax.Array, config: TrackHeadConfig,
                    iters: int | None = None, down_ratio: int = 1) -> tuple[jax.Array, jax.Array, jax.Array | None]:
    """Upstream `BaseTrackerPredictor.forward` (inference; sigmoid applied).

    query_points [B, N, 2] pixel (x, y) in frame 0 of the images; fmaps [B, S, h, w, C]
    (h, w = image size / (stride * down_ratio)). Returns (coords [iters, B, S, N, 2] in
    image pixels, one entry per refinement iteration; vis [B, S, N]; conf [B, S, N] or
    None when `config.predict_conf` is off). Frame 0 always returns the query.

    With the frames split over devices (`ops.shards.frame_layout`): fmaps and the results
    hold this device's frames; the update transformer, which attends across frames, runs
    on every frame's [B, N, D] inputs on every device (gathered each iteration) and each
    keeps its frames."""
    if query_points.ndim != 3 or query_points.shape[-1] != 2:
        raise ValueError(f"query_points must be [B, N, 2], got shape {query_points.shape}")
    b, n, _ = query_points.shape
    fb, s, h, w, c = fmaps.shape
    layout = frame_layout(s)
    first = (layout.frame_ids() == 0)[None, :, None, None]  # [1, S, 1, 1]: global frame 0
    if fb != b:
        raise ValueError(f"query_points batch {b} != feature maps batch {fb}")
    iters = config.iters if iters is None else iters
    levels, radius = config.corr_levels, config.corr_radius
    scale = float(config.stride * down_ratio)

    fmaps = layers.layer_norm(p["fmap_norm"], fmaps)
    pyramid = build_corr_pyramid(fmaps, levels)

    query = query_points.astype(jnp.float32)
    if down_ratio > 1:
        query = query / float(down_ratio)
    query = query / float(config.stride)  # [B, N, 2] in feature pixels
    query_feat = layout.first(sample_features(fmaps[:, 0], query)[:, None], 1)  # [B, N, C], frame 0's

    d_model = p["query_ref_token"].shape[-1]  # 3C + 4
    pos = sample_grid_embed(d_model, (h, w), query)  # [B, N, D]
    ref = p["query_ref_token"][0]  # [2, D]: frame 0, frames >= 1
    ref = jnp.where(first[0, :, :, 0], ref[0], ref[1])  # [S, D]
    bias = pos[:, :, None, :] + ref  # [B, N, S, D] added to the transformer input

    coords0 = jnp.broadcast_to(query[:, None], (b, s, n, 2))
    feats0 = jnp.broadcast_to(query_feat[:, None], (b, s, n, c))

    def step(carry, _):
        coords, feats = carry  # [B, S, N, 2], [B, S, N, C]
        coords = jax.lax.stop_gradient(coords)  # upstream detaches the previous iteration's coordinates
        corr = layers.mlp(p["corr_mlp"], correlation_features(pyramid, feats, coords, radius))
        flows = coords - query[:, None]  # (frame 0's coords are the query)
        flows_emb = jnp.concatenate(
            [flow_embedding(flows, c // 2), flows / FLOW_MAX_SCALE, flows / FLOW_MAX_SCALE], axis=-1)
        x = jnp.concatenate([flows_emb, corr, feats], axis=-1)  # [B, S, N, D]
        x = layout.gather(jnp.swapaxes(x, 1, 2) + bias, 2)  # [B, N, S, D], every frame
        delta = jnp.swapaxes(layout.local_part(update_former(p["updateformer"], x), 2), 1, 2)  # [B, S, N, 2 + C]
        # ffeat_norm is GroupNorm(1, C) on [B*N*S, C] rows: a LayerNorm over C.
        feats = feats + layers.gelu(layers.linear(p["ffeat_updater"]["0"],
                                                  layers.layer_norm(p["ffeat_norm"], delta[..., 2:])))
        coords = coords + delta[..., :2]
        coords = jnp.where(first, coords0, coords)
        return (coords, feats), coords * scale

    (_, feats), coord_preds = jax.lax.scan(step, (coords0, feats0), None, length=iters)

    vis = jax.nn.sigmoid(layers.linear(p["vis_predictor"]["0"], feats)[..., 0])
    conf = None
    if config.predict_conf:
        conf = jax.nn.sigmoid(layers.linear(p["conf_predictor"]["0"], feats)[..., 0])
    return coord_preds, vis, conf
