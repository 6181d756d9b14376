"""The parameter layout of the model: what a `VGGTConfig` implies, key by key.

The model is pure functions over an explicit parameter pytree (`Params`) that mirrors
upstream VGGT's PyTorch state dict: each upstream key maps to one or more leaves of the
tree by a rule of `param_rules.py` (a Linear's weight becomes `kernel` [in, out], the
fused qkv three Linears, ...). This module states the upstream keys and shapes of a
config (`upstream_state_dict_shapes`: for `VGGTConfig()` the published VGGT-1B state
dict, 1797 tensors) and, through the rules, every path and shape of the converted tree
(`expected_param_paths`). The converter (`rvggt_jax.weights`) and the model's input
checks (`model.inputs.check_params`) and initialisation (`model.initializers`) build on
it; the model never imports the converter.

A few sizes are constants upstream (not constructor arguments of `VGGT`), so they are
not in `VGGTConfig`; they are named below.
"""

from __future__ import annotations

from typing import Any, Mapping

from rvggt_jax.config import VGGTConfig
from rvggt_jax.model.param_rules import Path as TreePath
from rvggt_jax.model.param_rules import converted_shapes, find_rule

__all__ = ["Params", "Shape", "expected_param_paths", "flatten_params", "upstream_state_dict_shapes"]

# A parameter pytree: nested {name: sub-tree or array} in the converter's layout. Defined
# once here; every module imports this one.
Params = Mapping[str, Any]

Shape = tuple[int, ...]

# ---- upstream constants that fix shapes but are not config fields ----------------------
# DPTHead: channels of the hidden conv in `scratch.output_conv2` (head_features_2).
DPT_HEAD_FEATURES_2 = 32
# DPTHead output channels: depth (value + confidence), points (xyz + confidence).
DEPTH_OUTPUT_DIM = 2
POINT_OUTPUT_DIM = 4
# CameraHead: absT_quaR_FoV pose encoding (3 translation + 4 quaternion + 2 FoV).
POSE_ENCODING_DIM = 9
# BaseTrackerPredictor(depth=6, use_spaceatt=True) -> EfficientUpdateFormer with
# space_depth = time_depth = 6, num_heads=8, mlp_ratio=4.0, num_virtual_tracks=64.
TRACKER_TIME_DEPTH = 6
TRACKER_SPACE_DEPTH = 6
TRACKER_NUM_HEADS = 8
TRACKER_MLP_RATIO = 4.0
TRACKER_NUM_VIRTUAL_TRACKS = 64


def _linear(out: dict, prefix: str, d_in: int, d_out: int, bias: bool = True) -> None:
    out[f"{prefix}.weight"] = (d_out, d_in)
    if bias:
        out[f"{prefix}.bias"] = (d_out,)


def _norm(out: dict, prefix: str, dim: int) -> None:
    out[f"{prefix}.weight"] = (dim,)
    out[f"{prefix}.bias"] = (dim,)


def _conv(out: dict, prefix: str, c_in: int, c_out: int, k: int, bias: bool = True) -> None:
    out[f"{prefix}.weight"] = (c_out, c_in, k, k)
    if bias:
        out[f"{prefix}.bias"] = (c_out,)


def _conv_transpose(out: dict, prefix: str, c_in: int, c_out: int, k: int) -> None:
    out[f"{prefix}.weight"] = (c_in, c_out, k, k)
    out[f"{prefix}.bias"] = (c_out,)


def _vit_block(out: dict, prefix: str, dim: int, mlp_ratio: float, qk_norm_dim: int | None) -> None:
    """`vggt.layers.block.Block` with LayerScale (init_values set) and biases everywhere."""
    _norm(out, f"{prefix}.norm1", dim)
    _linear(out, f"{prefix}.attn.qkv", dim, 3 * dim)
    if qk_norm_dim is not None:
        _norm(out, f"{prefix}.attn.q_norm", qk_norm_dim)
        _norm(out, f"{prefix}.attn.k_norm", qk_norm_dim)
    _linear(out, f"{prefix}.attn.proj", dim, dim)
    out[f"{prefix}.ls1.gamma"] = (dim,)
    _norm(out, f"{prefix}.norm2", dim)
    hidden = int(dim * mlp_ratio)
    _linear(out, f"{prefix}.mlp.fc1", dim, hidden)
    _linear(out, f"{prefix}.mlp.fc2", hidden, dim)
    out[f"{prefix}.ls2.gamma"] = (dim,)


def _aggregator(out: dict, c: VGGTConfig) -> None:
    e = c.embed_dim
    p = "aggregator.patch_embed"  # DINOv2 ViT with registers, width embed_dim
    num_patches = (c.img_size // c.patch_size) ** 2
    out[f"{p}.cls_token"] = (1, 1, e)
    out[f"{p}.pos_embed"] = (1, 1 + num_patches, e)
    if c.num_register_tokens:
        out[f"{p}.register_tokens"] = (1, c.num_register_tokens, e)
    out[f"{p}.mask_token"] = (1, e)
    _conv(out, f"{p}.patch_embed.proj", 3, e, c.patch_size)
    for i in range(c.dino.depth):
        _vit_block(out, f"{p}.blocks.{i}", e, c.dino.mlp_ratio, None)
    _norm(out, f"{p}.norm", e)

    qk = c.head_dim if c.qk_norm else None
    for kind in ("frame_blocks", "global_blocks"):
        for i in range(c.depth):
            _vit_block(out, f"aggregator.{kind}.{i}", e, c.mlp_ratio, qk)
    out["aggregator.camera_token"] = (1, 2, 1, e)
    out["aggregator.register_token"] = (1, 2, c.num_register_tokens, e)


def _camera_head(out: dict, c: VGGTConfig) -> None:
    d = 2 * c.embed_dim
    p = "camera_head"
    for i in range(c.camera_head.trunk_depth):
        _vit_block(out, f"{p}.trunk.{i}", d, c.camera_head.mlp_ratio, None)
    _norm(out, f"{p}.token_norm", d)
    _norm(out, f"{p}.trunk_norm", d)
    out[f"{p}.empty_pose_tokens"] = (1, 1, POSE_ENCODING_DIM)
    _linear(out, f"{p}.embed_pose", POSE_ENCODING_DIM, d)
    _linear(out, f"{p}.poseLN_modulation.1", d, 3 * d)  # index 0 is the SiLU
    _linear(out, f"{p}.pose_branch.fc1", d, d // 2)
    _linear(out, f"{p}.pose_branch.fc2", d // 2, POSE_ENCODING_DIM)


def _dpt(out: dict, p: str, dim_in: int, features: int, oc: tuple[int, ...], output_dim: int | None) -> None:
    """`DPTHead`; `output_dim=None` is the feature-only variant (no output_conv2)."""
    _norm(out, f"{p}.norm", dim_in)
    for i, ch in enumerate(oc):
        _conv(out, f"{p}.projects.{i}", dim_in, ch, 1)
    _conv_transpose(out, f"{p}.resize_layers.0", oc[0], oc[0], 4)
    _conv_transpose(out, f"{p}.resize_layers.1", oc[1], oc[1], 2)
    # resize_layers.2 is an Identity (no parameters)
    _conv(out, f"{p}.resize_layers.3", oc[3], oc[3], 3)
    for i, ch in enumerate(oc):
        _conv(out, f"{p}.scratch.layer{i + 1}_rn", ch, features, 3, bias=False)
    for i in (1, 2, 3, 4):
        r = f"{p}.scratch.refinenet{i}"
        _conv(out, f"{r}.out_conv", features, features, 1)
        units = (2,) if i == 4 else (1, 2)  # refinenet4 has no residual input
        for u in units:
            _conv(out, f"{r}.resConfUnit{u}.conv1", features, features, 3)
            _conv(out, f"{r}.resConfUnit{u}.conv2", features, features, 3)
    if output_dim is None:
        _conv(out, f"{p}.scratch.output_conv1", features, features, 3)
    else:
        _conv(out, f"{p}.scratch.output_conv1", features, features // 2, 3)
        # output_conv2 = Sequential(Conv2d, ReLU, Conv2d): indices 0 and 2
        _conv(out, f"{p}.scratch.output_conv2.0", features // 2, DPT_HEAD_FEATURES_2, 3)
        _conv(out, f"{p}.scratch.output_conv2.2", DPT_HEAD_FEATURES_2, output_dim, 1)


def _mha_block(out: dict, p: str, h: int, cross: bool) -> None:
    """track_modules AttnBlock (self) / CrossAttnBlock over nn.MultiheadAttention."""
    _norm(out, f"{p}.norm1", h)
    if cross:
        _norm(out, f"{p}.norm_context", h)
    _norm(out, f"{p}.norm2", h)
    a = f"{p}.cross_attn" if cross else f"{p}.attn"
    out[f"{a}.in_proj_weight"] = (3 * h, h)
    out[f"{a}.in_proj_bias"] = (3 * h,)
    _linear(out, f"{a}.out_proj", h, h)
    hidden = int(h * TRACKER_MLP_RATIO)
    _linear(out, f"{p}.mlp.fc1", h, hidden)
    _linear(out, f"{p}.mlp.fc2", hidden, h)


def _track_head(out: dict, c: VGGTConfig) -> None:
    t = c.track_head
    _dpt(out, "track_head.feature_extractor", 2 * c.embed_dim, t.features, c.track_out_channels, None)

    p = "track_head.tracker"
    latent, hidden = t.features, t.hidden_size
    transformer_dim = 3 * latent + 4
    _linear(out, f"{p}.corr_mlp.fc1", t.corr_levels * (2 * t.corr_radius + 1) ** 2, hidden)
    _linear(out, f"{p}.corr_mlp.fc2", hidden, latent)
    out[f"{p}.query_ref_token"] = (1, 2, transformer_dim)
    u = f"{p}.updateformer"
    _norm(out, f"{u}.input_norm", transformer_dim)
    _linear(out, f"{u}.input_transform", transformer_dim, hidden)
    _norm(out, f"{u}.output_norm", hidden)
    _linear(out, f"{u}.flow_head", hidden, latent + 2)
    out[f"{u}.virual_tracks"] = (1, TRACKER_NUM_VIRTUAL_TRACKS, 1, hidden)  # sic
    for i in range(TRACKER_TIME_DEPTH):
        _mha_block(out, f"{u}.time_blocks.{i}", hidden, cross=False)
    for i in range(TRACKER_SPACE_DEPTH):
        _mha_block(out, f"{u}.space_virtual_blocks.{i}", hidden, cross=False)
        _mha_block(out, f"{u}.space_point2virtual_blocks.{i}", hidden, cross=True)
        _mha_block(out, f"{u}.space_virtual2point_blocks.{i}", hidden, cross=True)
    _norm(out, f"{p}.fmap_norm", latent)  # LayerNorm
    _norm(out, f"{p}.ffeat_norm", latent)  # GroupNorm(1, latent)
    _linear(out, f"{p}.ffeat_updater.0", latent, latent)
    _linear(out, f"{p}.vis_predictor.0", latent, 1)
    if t.predict_conf:
        _linear(out, f"{p}.conf_predictor.0", latent, 1)


def upstream_state_dict_shapes(config: VGGTConfig, *, skip_track: bool = False) -> dict[str, Shape]:
    """Every upstream state-dict key -> its shape (a tuple of ints) for `config`.

    Heads follow the `enable_*` flags; `skip_track=True` also leaves out the track head."""
    out: dict[str, Shape] = {}
    _aggregator(out, config)
    d = 2 * config.embed_dim
    if config.enable_camera:
        _camera_head(out, config)
    if config.enable_depth:
        h = config.dpt_head
        _dpt(out, "depth_head", d, h.features, h.out_channels, DEPTH_OUTPUT_DIM)
    if config.enable_point:
        h = config.dpt_head
        _dpt(out, "point_head", d, h.features, h.out_channels, POINT_OUTPUT_DIM)
    if config.enable_track and not skip_track:
        _track_head(out, config)
    return out


def flatten_params(params: Mapping[str, Any], prefix: TreePath = ()) -> dict[TreePath, Any]:
    """Nested dicts -> {path tuple: leaf}."""
    flat: dict[TreePath, Any] = {}
    for k, v in params.items():
        if isinstance(v, Mapping):
            flat.update(flatten_params(v, prefix + (k,)))
        else:
            flat[prefix + (k,)] = v
    return flat


def expected_param_paths(config: VGGTConfig, *, skip_track: bool = False) -> dict[TreePath, tuple[int, ...]]:
    """{our path tuple: converted shape} for `config`, derived through the rule table."""
    flat: dict[TreePath, tuple[int, ...]] = {}
    for key, shape in upstream_state_dict_shapes(config, skip_track=skip_track).items():
        rule = find_rule(key)
        if rule is None:
            raise ValueError(f"no conversion rule for upstream key {key}")
        for path, s in converted_shapes(rule.kind, key, shape):
            if path in flat:
                raise ValueError(f"conversion rules write {'.'.join(path)} twice")
            flat[path] = s
    return flat
