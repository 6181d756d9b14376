"""DPT dense-prediction head (depth, world points) and its feature-only variant (track head).

Parameters are the `depth_head` / `point_head` / `track_head.feature_extractor` subtree
of the converted state dict (docs/conventions.md): `norm`, `projects.{0..3}`,
`resize_layers.{0,1,3}` (0, 1 transposed convs; 2 is an identity and has none),
`scratch.layer{1..4}_rn`, `scratch.refinenet{1..4}`, `scratch.output_conv1` and, unless
feature-only, `scratch.output_conv2.{0,2}`. All feature maps are NHWC.

Upstream runs the head over chunks of frames; every op here is per frame, so running
all frames at once gives the same numbers.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping, Sequence

import chex
import jax
import jax.numpy as jnp

from rvggt_jax.model import layers
from rvggt_jax.ops.ordering import zeros_after
from rvggt_jax.config import DPTHeadConfig, TokenGrid
from rvggt_jax.model.heads.camera import inverse_log_transform
from rvggt_jax.model.heads.conv import conv2d, conv_transpose_patchwise, relu_pointwise
from rvggt_jax.model.heads.pos_embed import add_pos_embed, pos_embed_map
from rvggt_jax.model.heads.resize import patchwise_conv3x3, resize_bilinear_align_corners, resized_conv3x3
from rvggt_jax.model.kept import KeptLayer, Part, ProjectedLayer
from rvggt_jax.model.params import Params

# A list of every aggregator layer's tokens, or a dict {layer index: tokens} holding at
# least the layers the head reads; each entry is a `KeptLayer` [B, S, P, 2E], which the
# head slices per group of frames (a plain array is taken as `KeptLayer.of(array)`), or
# a `ProjectedLayer` holding the head's first step on it (`projections.head_projections`).
Aggregated = Sequence[KeptLayer | ProjectedLayer | jax.Array] | Mapping[int, KeptLayer | ProjectedLayer | jax.Array]

# ---------------------------------------------------------------------------------------
# Fusion (RefineNet-style) blocks
# ---------------------------------------------------------------------------------------


def residual_conv_unit(p: Params, x: jax.Array) -> jax.Array:
    """conv2(relu(conv1(relu(x)))) + relu(x).

    The skip adds relu(x), not x: upstream's in-place ReLU overwrites its input before
    the skip connection reads it."""
    x = jax.nn.relu(x)
    return conv2d(p["conv2"], jax.nn.relu(conv2d(p["conv1"], x))) + x


def fusion_block(p: Params, x: jax.Array, skip: jax.Array | None, size: tuple[int, int] | None,
                 then: Params | None = None) -> jax.Array:
    """x (+ residual unit of `skip`), residual unit, align-corners upsampling to `size`
    (default: twice the input), 1x1 out_conv. NHWC. `then`: a 3x3 conv that follows
    (the head's output_conv1), run with the upsampling (`resize.resized_conv3x3`)."""
    if skip is not None:
        x = x + residual_conv_unit(p["resConfUnit1"], skip)
    x = residual_conv_unit(p["resConfUnit2"], x)
    if size is None:
        size = (2 * x.shape[1], 2 * x.shape[2])
    # Upstream resizes, then applies the 1x1 out_conv. Both are linear and the resize
    # weights of every output pixel sum to 1, so the conv commutes with the resize
    # (equal up to float rounding): run it on the input, up to 4x fewer pixels.
    x = conv2d(p["out_conv"], x)
    return resize_bilinear_align_corners(x, size) if then is None else resized_conv3x3(then, size)(x)


def _scratch_fuse(p: Params, rn: list[jax.Array], exact_order: bool = False) -> jax.Array:
    """Four multi-scale maps after their `layer{i}_rn` convs (finest first) -> fused map at
    twice the finest resolution. exact_order: output_conv1 after the upsampling, in
    upstream's float32 order (for the track head, whose tracker amplifies rounding:
    tests/helpers/tolerances.py)."""
    out = fusion_block(p["refinenet4"], rn[3], None, rn[2].shape[1:3])
    out = fusion_block(p["refinenet3"], out, rn[2], rn[1].shape[1:3])
    out = fusion_block(p["refinenet2"], out, rn[1], rn[0].shape[1:3])
    if exact_order:
        return conv2d(p["output_conv1"], fusion_block(p["refinenet1"], out, rn[0], None))
    return fusion_block(p["refinenet1"], out, rn[0], None, then=p["output_conv1"])


# ---------------------------------------------------------------------------------------
# Token maps -> fused features
# ---------------------------------------------------------------------------------------


def _resize_layer(params: Params, i: int, x: jax.Array) -> jax.Array:
    """Level i to its DPT scale: x4 and x2 (patchwise transposed convs), x1, x0.5 (3x3/2)."""
    if i in (0, 1):
        return conv_transpose_patchwise(params["resize_layers"][str(i)], x)
    if i == 2:
        return x
    return conv2d(params["resize_layers"]["3"], x, stride=2, padding=1)


def _token_map(params: Params, tokens: jax.Array, patch_start_idx: int, grid_hw: tuple[int, int]) -> jax.Array:
    """Patch tokens [N, P, C] -> normalised map [N, h, w, C]."""
    n, _, c = tokens.shape
    x = tokens[:, patch_start_idx:].reshape(n, grid_hw[0], grid_hw[1], c)
    return layers.layer_norm(params["norm"], x)


def level_map(params: Params, level: int, tokens: jax.Array, patch_start_idx: int, grid_hw: tuple[int, int]
              ) -> jax.Array:
    """The head's first step on one of its 4 layers: tokens [N, P, C] -> the normalised
    patch tokens projected to level `level`'s width, [N, h, w, out_channels[level]]."""
    return conv2d(params["projects"][str(level)], _token_map(params, tokens, patch_start_idx, grid_hw))


def reassemble(params: Params, level: int, x: jax.Array, image_hw: tuple[int, int], pos_embed: bool) -> jax.Array:
    """A level map [N, h, w, out_channels[level]] (`level_map`) -> the level's input to
    the fusion blocks [N, h', w', F]: the positional map when `pos_embed`, the resize to
    the level's scale, then its layer_rn 3x3 conv."""
    if pos_embed:
        x = add_pos_embed(x, image_hw)
    return conv2d(params["scratch"][f"layer{level + 1}_rn"], _resize_layer(params, level, x))


def _fused_map(params: Params, tokens: Sequence[jax.Array], image_hw: tuple[int, int], patch_start_idx: int,
               patch_size: int, pos_embed: bool, columns: Sequence[Part | None] = (None,) * 4,
               upsampled: Mapping[int, Callable] | None = None) -> jax.Array:
    """Shared trunk of both modes on frames: 4 token sets [N, P, C] -> the fused map
    [N, 8h, 8w, F/2] (output_conv1's, before the final upsampling; (h, w) the token grid).
    A layer with `columns` (a `kept.Part`) holds this head's first steps already
    (`ProjectedLayer` frames [N, Q, F']): its level map, or with `Part.hw` the whole
    reassembled level. `upsampled`: {0: f, 1: f}, levels 0 and 1's transposed convs and
    their layer_rn convs as one map (`patchwise_levels`, made outside the frame loop);
    None: every op in upstream's float32 order (`_scratch_fuse`'s exact_order, the track
    head)."""
    grid_hw = (image_hw[0] // patch_size, image_hw[1] // patch_size)
    rn = []
    for i, (t, col) in enumerate(zip(tokens, columns)):
        if col is not None and col.hw is not None:
            rn.append(t[..., col.first:col.first + col.width].reshape(t.shape[0], *col.hw, col.width))
            continue
        if col is None:
            x = level_map(params, i, t, patch_start_idx, grid_hw)
        else:
            x = t[..., col.first:col.first + col.width].reshape(t.shape[0], *grid_hw, col.width)
        if upsampled is not None and i in upsampled:
            rn.append(upsampled[i](add_pos_embed(x, image_hw) if pos_embed else x))
        else:
            rn.append(reassemble(params, i, x, image_hw, pos_embed))
    return _scratch_fuse(params["scratch"], rn, exact_order=upsampled is None)


def patchwise_levels(params: Params, grid_hw: tuple[int, int]) -> dict[int, Callable]:
    """Levels 0 and 1 (x4 and x2 transposed convs) with their 3x3 layer_rn convs, each as
    one map x [N, h, w, C_i] -> [N, k h, k w, F], (h, w) = grid_hw (`resize.patchwise_conv3x3`: VGGT-1B's
    level 0 does 36 [256, 256] products per token instead of 160)."""
    return {i: patchwise_conv3x3(params["resize_layers"][str(i)], params["scratch"][f"layer{i + 1}_rn"], grid_hw)
            for i in (0, 1)}


def _output_hw(image_hw: tuple[int, int], patch_size: int, down_ratio: int) -> tuple[int, int]:
    return tuple(d // patch_size * patch_size // down_ratio for d in image_hw)


def _fused_features(params: Params, tokens: Sequence[jax.Array], image_hw: tuple[int, int], patch_start_idx: int,
                    patch_size: int, pos_embed: bool, down_ratio: int,
                    columns: Sequence[Part | None] = (None,) * 4) -> jax.Array:
    """The feature-only trunk: `_fused_map` upsampled to
    [N, h*p/down, w*p/down, F] (plus the positional embedding when `pos_embed`)."""
    out = _fused_map(params, tokens, image_hw, patch_start_idx, patch_size, pos_embed, columns)
    out = resize_bilinear_align_corners(out, _output_hw(image_hw, patch_size, down_ratio))
    return add_pos_embed(out, image_hw) if pos_embed else out


# Output pixels per group of frames the head processes at once. Every op of the head is
# per frame; groups this small keep the conv activations in cache: 16 frames of 168x224
# run ~35% faster in groups of 2 than all at once on a 2-core CPU (upstream's torch head
# chunks frames for the same reason).
GROUP_PIXELS = 2 * 168 * 224


def frames_per_group(num_frames: int, image_hw: tuple[int, int], group_pixels: int | None = None) -> int:
    """How many frames `map_frame_groups` takes at once (at least 1, at most all);
    `group_pixels` defaults to GROUP_PIXELS."""
    group_pixels = GROUP_PIXELS if group_pixels is None else group_pixels
    return int(min(num_frames, max(1, group_pixels // (image_hw[0] * image_hw[1]))))


def map_frame_groups(fn, tokens: Sequence[Any], image_hw: tuple[int, int], remat: Callable | None = None):
    """Run a per-frame `fn(tokens [G, P, C] x 4) -> pytree of [G, ...]` over groups of G
    frames (a `fori_loop` writing each group's result in place). `remat`: how a group
    runs in a training step (a `jax.checkpoint`: its backward pass keeps where the group
    starts, re-reads its tokens and recomputes its feature maps; `model.remat.checkpoint`),
    or None.

    tokens: `KeptLayer`s [B, S, P, C]; returns the pytree
    with leaves [B, S, ...]. Nothing is padded or copied: when G does not divide B*S, the
    last group starts G frames before the end and recomputes a few frames (every op is
    per frame, so they get the same values)."""
    b, s = tokens[0].shape[:2]
    chex.assert_equal(len({t.ndim for t in tokens}), 1)
    n = b * s
    g = frames_per_group(n, image_hw)
    groups = -(-n // g)

    def group(start):  # (the frames are read inside: a checkpoint keeps `start` and the buffers, no copy)
        return fn([t.frames(start, g) for t in tokens])

    if remat is not None:
        group = remat(group)

    def run(i):
        start = jnp.minimum(i * g, n - g)
        return start, group(start)

    if groups == 1:
        out = run(0)[1]
    else:
        shapes = jax.eval_shape(lambda: run(0)[1])
        dep = tokens[0].frames(0, 1)  # made when the tokens are, not at the program start
        init = jax.tree.map(lambda o: zeros_after((n,) + o.shape[1:], o.dtype, dep), shapes)

        def body(i, acc):
            start, res = run(i)
            return jax.tree.map(lambda a, r: jax.lax.dynamic_update_slice_in_dim(a, r, start, 0), acc, res)

        out = jax.lax.fori_loop(0, groups, body, init)
    return jax.tree.map(lambda o: o.reshape((b, s) + o.shape[1:]), out)


def _layers_read(aggregated: Aggregated, layer_idx: Sequence[int]) -> list[KeptLayer | ProjectedLayer]:
    if len(layer_idx) != 4:
        raise ValueError(f"the DPT head reads exactly 4 layers, got {layer_idx}")
    return [t if isinstance(t, (KeptLayer, ProjectedLayer)) else KeptLayer.of(t)
            for t in (aggregated[i] for i in layer_idx)]


def _columns(read: Sequence[KeptLayer | ProjectedLayer], reader: str | None) -> tuple[Part | None, ...]:
    """`reader`'s columns of each projected layer it reads (None: a layer of tokens)."""
    if reader is None and any(isinstance(t, ProjectedLayer) for t in read):
        raise ValueError(f"these layers hold DPT heads' projections: say which head this is (reader=, one of {READERS})")
    return tuple(t.part(reader) if isinstance(t, ProjectedLayer) else None for t in read)


# A DPT head's name for its columns of a `ProjectedLayer`: its parameter subtree's.
READERS = ("depth_head", "point_head", "track_head")


def dpt_features(params: Params, aggregated: Aggregated, grid: TokenGrid, *,
                 layer_idx: Sequence[int] = (4, 11, 17, 23), down_ratio: int = 2, pos_embed: bool = False,
                 remat: Callable | None = None, reader: str | None = None) -> jax.Array:
    """Feature-only DPT (upstream `DPTHead(feature_only=True)`, the track head's extractor).

    aggregated: aggregator tokens, each [B, S, P, 2E]; grid: the images' `TokenGrid`.
    Returns [B, S, h*p/down_ratio, w*p/down_ratio, F] with (h, w) = `grid.hw`, p the patch
    size and F the width of `scratch.output_conv1`. The defaults are the track head's
    (down_ratio 2, no positional embedding). `remat`: see `map_frame_groups`. `reader`:
    whose columns of a `ProjectedLayer` are this head's (`head_projections`)."""
    image_hw, patch_start_idx, patch_size = grid.image_hw, grid.patch_start_idx, grid.patch_size
    read = _layers_read(aggregated, layer_idx)
    columns = _columns(read, reader)

    def per_frames(tokens):
        return _fused_features(params, tokens, image_hw, patch_start_idx, patch_size, pos_embed, down_ratio, columns)

    return map_frame_groups(per_frames, read, image_hw, remat)


# ---------------------------------------------------------------------------------------
# Output activations
# ---------------------------------------------------------------------------------------


def activate_head(out: jax.Array, activation: str = "norm_exp",
                  conf_activation: str = "expp1") -> tuple[jax.Array, jax.Array]:
    """Split the raw head output [..., C] into activated values [..., C-1] and a
    confidence [...] (last channel)."""
    xyz, conf = out[..., :-1], out[..., -1]
    if activation == "norm_exp":
        d = jnp.maximum(jnp.linalg.norm(xyz, axis=-1, keepdims=True), 1e-8)
        pts = xyz / d * jnp.expm1(d)
    elif activation == "norm":
        pts = xyz / jnp.linalg.norm(xyz, axis=-1, keepdims=True)
    elif activation == "exp":
        pts = jnp.exp(xyz)
    elif activation == "relu":
        pts = jax.nn.relu(xyz)
    elif activation == "inv_log":
        pts = inverse_log_transform(xyz)
    elif activation == "xy_inv_log":
        z = inverse_log_transform(xyz[..., 2:3])
        pts = jnp.concatenate([xyz[..., :2] * z, z], axis=-1)
    elif activation == "sigmoid":
        pts = jax.nn.sigmoid(xyz)
    elif activation == "linear":
        pts = xyz
    else:
        raise ValueError(f"unknown activation {activation!r}")

    if conf_activation == "expp1":
        conf = 1 + jnp.exp(conf)
    elif conf_activation == "expp0":
        conf = jnp.exp(conf)
    elif conf_activation == "sigmoid":
        conf = jax.nn.sigmoid(conf)
    else:
        raise ValueError(f"unknown conf_activation {conf_activation!r}")
    return pts, conf


# ---------------------------------------------------------------------------------------
# Dense prediction heads
# ---------------------------------------------------------------------------------------


def _dpt_per_frames(params: Params, config: DPTHeadConfig, image_hw, patch_start_idx: int, patch_size: int,
                    activation: str, conf_activation: str, columns=(None,) * 4):
    """The dense DPT head on one group of frames: tokens [G, P, 2E] x 4 -> (pred, conf)
    (`columns`: see `_fused_map`)."""
    conv2 = params["scratch"]["output_conv2"]
    out_hw = _output_hw(image_hw, patch_size, 1)
    width = params["scratch"]["output_conv1"]["kernel"].shape[-1]
    # The upsampling, the positional map and output_conv2's 3x3 conv are one linear map;
    # made here, once, its input-free part is not recomputed per group of frames
    upsample_conv = resized_conv3x3(conv2["0"], out_hw, pos_embed_map(*out_hw, width, image_hw[1] / image_hw[0])
                                    if config.pos_embed else None)
    upsampled = patchwise_levels(params, (image_hw[0] // patch_size, image_hw[1] // patch_size))

    def per_frames(tokens):
        x = _fused_map(params, tokens, image_hw, patch_start_idx, patch_size, config.pos_embed, columns, upsampled)
        x = relu_pointwise(conv2["2"], upsample_conv(x))
        return activate_head(x, activation, conf_activation)

    return per_frames


def dpt_head(params: Params, aggregated: Aggregated, config: DPTHeadConfig, grid: TokenGrid, *,
             activation: str = "inv_log", conf_activation: str = "expp1", remat: Callable | None = None,
             reader: str | None = None) -> tuple[jax.Array, jax.Array]:
    """Dense DPT prediction (upstream `DPTHead`, not feature-only).

    aggregated: aggregator tokens, each [B, S, P, 2E] (list of all layers or dict by layer
    index); grid: the images' `TokenGrid` ((H, W), patch size). Returns (pred [B, S, H', W', C-1],
    conf [B, S, H', W']) with C the output_conv2 width and H' = H // patch_size * patch_size
    (= H for the usual multiples of the patch size), W' likewise. `remat`: see
    `map_frame_groups`. `reader`: whose columns of a `ProjectedLayer` are this head's."""
    read = _layers_read(aggregated, config.intermediate_layer_idx)
    per_frames = _dpt_per_frames(params, config, grid.image_hw, grid.patch_start_idx, grid.patch_size, activation,
                                 conf_activation, _columns(read, reader))
    pred, conf = map_frame_groups(per_frames, read, grid.image_hw, remat)
    chex.assert_equal_shape_prefix([pred, conf], 4)
    return pred, conf


# (activation, conf_activation) of VGGT's two dense heads
DEPTH_ACTIVATIONS = ("exp", "expp1")
POINT_ACTIVATIONS = ("inv_log", "expp1")


def depth_head(params: Params, aggregated: Aggregated, config: DPTHeadConfig, grid: TokenGrid
               ) -> tuple[jax.Array, jax.Array]:
    """VGGT's depth head: (depth [B, S, H, W, 1] = exp, depth_conf [B, S, H, W] = 1 + exp)."""
    return dpt_head(params, aggregated, config, grid, activation=DEPTH_ACTIVATIONS[0],
                    conf_activation=DEPTH_ACTIVATIONS[1], reader="depth_head")


def point_head(params: Params, aggregated: Aggregated, config: DPTHeadConfig, grid: TokenGrid
               ) -> tuple[jax.Array, jax.Array]:
    """VGGT's point head: (world_points [B, S, H, W, 3] = inv_log, world_points_conf
    [B, S, H, W] = 1 + exp)."""
    return dpt_head(params, aggregated, config, grid, activation=POINT_ACTIVATIONS[0],
                    conf_activation=POINT_ACTIVATIONS[1], reader="point_head")


# The low-memory mode's 16-bit outputs (value, confidence): geometry in float16 (an 11-bit
# mantissa; a normalised scene's depths and points are far inside its range), a
# confidence 1 + exp(x) in bfloat16 (float16 overflows past x = 11)
HALF_OUTPUTS = (jnp.float16, jnp.bfloat16)


def dense_heads(params: Mapping[str, Params], aggregated: Aggregated, config: DPTHeadConfig, grid: TokenGrid,
                remat: Callable | None = None, half_outputs: bool = False) -> dict[str, jax.Array]:
    """The depth and point heads whose params are given ({"depth_head": ...,
    "point_head": ...}, either or both) in one loop over groups of frames: {"depth",
    "depth_conf", "world_points", "world_points_conf"} as `depth_head` / `point_head`
    return them. One loop reads the kept aggregator layers once (two loops would each
    need their own copy of them). `remat`: see `map_frame_groups`. `half_outputs`: each
    group's values and confidences stored in `HALF_OUTPUTS` (float32 otherwise)."""
    if not ({"depth_head", "point_head"} & set(params)):
        return {}
    heads = {}
    args = (config, grid.image_hw, grid.patch_start_idx, grid.patch_size)
    read = _layers_read(aggregated, config.intermediate_layer_idx)
    if "depth_head" in params:
        heads[("depth", "depth_conf")] = _dpt_per_frames(params["depth_head"], *args, *DEPTH_ACTIVATIONS,
                                                         _columns(read, "depth_head"))
    if "point_head" in params:
        heads[("world_points", "world_points_conf")] = _dpt_per_frames(params["point_head"], *args,
                                                                       *POINT_ACTIVATIONS, _columns(read, "point_head"))

    def per_frames(tokens):
        res = {names: fn(tokens) for names, fn in heads.items()}
        if half_outputs:
            res = {names: tuple(x.astype(dt) for x, dt in zip(pair, HALF_OUTPUTS)) for names, pair in res.items()}
        return res

    res = map_frame_groups(per_frames, read, grid.image_hw, remat)
    return {name: value for names, pair in res.items() for name, value in zip(names, pair)}
