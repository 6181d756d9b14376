"""The conversion rules: upstream state-dict key -> our pytree path(s) and array layout.

Each `Rule` names a regex that must match the *whole* upstream key and a `kind` saying
which PyTorch module the parameter belongs to. The kind alone fixes the renaming and the
re-layout (see docs/conventions.md); nothing is ever guessed from an array's rank.

Kinds (`P` = the module's key prefix, i.e. the key without its last component):

| kind             | upstream leaf                      | ours                                         |
| ---------------- | ---------------------------------- | -------------------------------------------- |
| `linear`         | `P.weight [out,in]`, `P.bias`      | `P.kernel [in,out]` (transposed), `P.bias`   |
| `qkv`            | `P.weight [3C,C]`, `P.bias [3C]`   | parent of P: `q`,`k`,`v` Linears (rows 0:C, C:2C, 2C:3C) |
| `mha_in_proj`    | `P.in_proj_weight [3E,E]`, `P.in_proj_bias` | `P.q`, `P.k`, `P.v` Linears          |
| `norm`           | `P.weight`, `P.bias`               | `P.scale`, `P.bias`                          |
| `conv`           | `P.weight [O,I,kh,kw]`, `P.bias`   | `P.kernel [kh,kw,I,O]` (HWIO), `P.bias`      |
| `conv_transpose` | `P.weight [I,O,kh,kw]`, `P.bias`   | `P.kernel [kh,kw,I,O]`, `P.bias`             |
| `raw`            | any (tokens, pos_embed, LayerScale gamma) | same name and shape                   |

Our path is the upstream key split on '.', numbered children kept as string keys, with
the last component renamed as above. An upstream key matching no rule is *unexpected*.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Iterator

import numpy as np

LINEAR = "linear"
QKV = "qkv"
MHA_IN_PROJ = "mha_in_proj"
NORM = "norm"
CONV = "conv"
CONV_TRANSPOSE = "conv_transpose"
RAW = "raw"
KINDS = (LINEAR, QKV, MHA_IN_PROJ, NORM, CONV, CONV_TRANSPOSE, RAW)

Path = tuple[str, ...]


@dataclass(frozen=True)
class Rule:
    pattern: str  # regex, matched against the whole upstream key
    kind: str
    note: str = ""

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown rule kind {self.kind!r}")

    def matches(self, key: str) -> bool:
        return _compiled(self.pattern).fullmatch(key) is not None


_RE_CACHE: dict[str, re.Pattern] = {}


def _compiled(pattern: str) -> re.Pattern:
    if pattern not in _RE_CACHE:
        _RE_CACHE[pattern] = re.compile(pattern)
    return _RE_CACHE[pattern]


# ---- regex fragments ---------------------------------------------------------------------
_WB = r"(?:weight|bias)"
# Every `vggt.layers.block.Block`: aggregator frame/global blocks, DINOv2 blocks, camera trunk.
_VIT_BLOCK = r"(?:aggregator\.(?:frame_blocks|global_blocks|patch_embed\.blocks)|camera_head\.trunk)\.\d+"
# The three DPT heads (the track head's feature extractor is a feature-only DPT).
_DPT = r"(?:depth_head|point_head|track_head\.feature_extractor)"
_TRK = r"track_head\.tracker"
_UPF = r"track_head\.tracker\.updateformer"
_UPF_BLOCK = _UPF + r"\.(?:time_blocks|space_virtual_blocks|space_point2virtual_blocks|space_virtual2point_blocks)\.\d+"

RULES: tuple[Rule, ...] = (
    # ---- aggregator: special tokens and the DINOv2 patch embed ---------------------------
    Rule(r"aggregator\.(?:camera_token|register_token)", RAW, "[1, 2, n, C] frame-0 / other-frames tokens"),
    Rule(r"aggregator\.patch_embed\.(?:cls_token|register_tokens|mask_token|pos_embed)", RAW),
    Rule(r"aggregator\.patch_embed\.patch_embed\.proj\." + _WB, CONV, "14x14 stride-14 patchify"),
    Rule(r"aggregator\.patch_embed\.norm\." + _WB, NORM),
    # ---- ViT blocks ------------------------------------------------------------------------
    Rule(_VIT_BLOCK + r"\.norm[12]\." + _WB, NORM),
    Rule(_VIT_BLOCK + r"\.attn\.qkv\." + _WB, QKV, "fused qkv -> attn.q / attn.k / attn.v"),
    Rule(_VIT_BLOCK + r"\.attn\.[qk]_norm\." + _WB, NORM, "per-head LayerNorm (aggregator only)"),
    Rule(_VIT_BLOCK + r"\.attn\.proj\." + _WB, LINEAR),
    Rule(_VIT_BLOCK + r"\.mlp\.fc[12]\." + _WB, LINEAR),
    Rule(_VIT_BLOCK + r"\.ls[12]\.gamma", RAW, "LayerScale"),
    # ---- camera head -----------------------------------------------------------------------
    Rule(r"camera_head\.(?:token_norm|trunk_norm)\." + _WB, NORM),
    Rule(r"camera_head\.empty_pose_tokens", RAW),
    Rule(r"camera_head\.embed_pose\." + _WB, LINEAR),
    Rule(r"camera_head\.poseLN_modulation\.1\." + _WB, LINEAR, "Sequential(SiLU, Linear)"),
    Rule(r"camera_head\.pose_branch\.fc[12]\." + _WB, LINEAR),
    # ---- DPT heads (depth, point, track feature extractor) ----------------------------------
    Rule(_DPT + r"\.norm\." + _WB, NORM),
    Rule(_DPT + r"\.projects\.[0-3]\." + _WB, CONV, "1x1 token -> channel projections"),
    Rule(_DPT + r"\.resize_layers\.[01]\." + _WB, CONV_TRANSPOSE, "4x / 2x upsampling"),
    Rule(_DPT + r"\.resize_layers\.3\." + _WB, CONV, "stride-2 downsampling (index 2 is Identity)"),
    Rule(_DPT + r"\.scratch\.layer[1-4]_rn\.weight", CONV, "no bias"),
    Rule(_DPT + r"\.scratch\.refinenet[1-4]\.out_conv\." + _WB, CONV),
    Rule(_DPT + r"\.scratch\.refinenet[1-4]\.resConfUnit[12]\.conv[12]\." + _WB, CONV),
    Rule(_DPT + r"\.scratch\.output_conv1\." + _WB, CONV),
    Rule(r"(?:depth_head|point_head)\.scratch\.output_conv2\.[02]\." + _WB, CONV, "Sequential(Conv, ReLU, Conv)"),
    # ---- track head: tracker (BaseTrackerPredictor) -----------------------------------------
    Rule(_TRK + r"\.query_ref_token", RAW),
    Rule(_TRK + r"\.corr_mlp\.fc[12]\." + _WB, LINEAR),
    Rule(_TRK + r"\.(?:fmap_norm|ffeat_norm)\." + _WB, NORM, "LayerNorm / GroupNorm(1, C)"),
    Rule(_TRK + r"\.(?:ffeat_updater|vis_predictor|conf_predictor)\.0\." + _WB, LINEAR, "Sequential(Linear, ...)"),
    Rule(_UPF + r"\.virual_tracks", RAW, "sic: upstream's spelling"),
    Rule(_UPF + r"\.(?:input_norm|output_norm)\." + _WB, NORM),
    Rule(_UPF + r"\.(?:input_transform|flow_head)\." + _WB, LINEAR),
    Rule(_UPF_BLOCK + r"\.(?:norm1|norm2|norm_context)\." + _WB, NORM),
    Rule(_UPF_BLOCK + r"\.(?:attn|cross_attn)\.in_proj_(?:weight|bias)", MHA_IN_PROJ, "-> .q / .k / .v"),
    Rule(_UPF_BLOCK + r"\.(?:attn|cross_attn)\.out_proj\." + _WB, LINEAR),
    Rule(_UPF_BLOCK + r"\.mlp\.fc[12]\." + _WB, LINEAR),
)


def find_rule(key: str) -> Rule | None:
    """The first rule whose pattern matches the whole key, or None (an unexpected key)."""
    for rule in RULES:
        if rule.matches(key):
            return rule
    return None


def matching_rules(key: str) -> list[Rule]:
    """All rules matching `key` (the table is meant to have at most one per key)."""
    return [r for r in RULES if r.matches(key)]


# ---- transforms ------------------------------------------------------------------------------


def _split3(x: np.ndarray, key: str) -> list[np.ndarray]:
    n = x.shape[0]
    if n % 3:
        raise ValueError(f"{key}: leading dim {n} is not divisible by 3")
    c = n // 3
    return [x[0:c], x[c : 2 * c], x[2 * c : 3 * c]]


def _rank(x: np.ndarray, rank: int, key: str, kind: str) -> None:
    if x.ndim != rank:
        raise ValueError(f"{key}: a {kind} parameter of rank {rank} was expected, got shape {tuple(x.shape)}")


def apply_rule(kind: str, key: str, x: np.ndarray) -> Iterator[tuple[Path, np.ndarray]]:
    """Convert one upstream tensor `x` (stored under `key`) to our `(path, array)` leaves.

    Returned arrays may be (strided) views of `x`; callers needing memory of their own
    copy them. Works on zero-stride placeholders too, which is how converted shapes are
    derived (`model.params.expected_param_paths`) by the very same code."""
    parts = key.split(".")
    module, leaf = tuple(parts[:-1]), parts[-1]
    if kind == RAW:
        yield tuple(parts), x
    elif kind == LINEAR:
        if leaf == "weight":
            _rank(x, 2, key, kind)
            yield module + ("kernel",), x.T
        elif leaf == "bias":
            _rank(x, 1, key, kind)
            yield module + ("bias",), x
        else:
            raise ValueError(f"{key}: a {kind} rule needs a .weight or .bias leaf")
    elif kind in (QKV, MHA_IN_PROJ):
        # fused q/k/v projections: rows 0:C, C:2C, 2C:3C become three Linears
        if kind == QKV:
            parent, w_leaf, b_leaf = module[:-1], "weight", "bias"  # '...attn.qkv' -> '...attn'
        else:
            parent, w_leaf, b_leaf = module, "in_proj_weight", "in_proj_bias"
        if leaf not in (w_leaf, b_leaf):
            raise ValueError(f"{key}: a {kind} rule needs a .{w_leaf} or .{b_leaf} leaf")
        _rank(x, 2 if leaf == w_leaf else 1, key, kind)
        for name, part in zip("qkv", _split3(x, key)):
            yield (parent + (name, "kernel"), part.T) if leaf == w_leaf else (parent + (name, "bias"), part)
    elif kind == NORM:
        _rank(x, 1, key, kind)
        if leaf == "weight":
            yield module + ("scale",), x
        elif leaf == "bias":
            yield module + ("bias",), x
        else:
            raise ValueError(f"{key}: a {kind} rule needs a .weight or .bias leaf")
    elif kind in (CONV, CONV_TRANSPOSE):
        if leaf == "weight":
            _rank(x, 4, key, kind)
            # Conv2d [O, I, kh, kw] -> [kh, kw, I, O]; ConvTranspose2d [I, O, kh, kw] -> [kh, kw, I, O]
            yield module + ("kernel",), x.transpose((2, 3, 1, 0) if kind == CONV else (2, 3, 0, 1))
        elif leaf == "bias":
            _rank(x, 1, key, kind)
            yield module + ("bias",), x
        else:
            raise ValueError(f"{key}: a {kind} rule needs a .weight or .bias leaf")
    else:  # pragma: no cover - Rule validates kinds
        raise ValueError(f"unknown rule kind {kind!r}")


def converted_shapes(kind: str, key: str, shape: tuple[int, ...]) -> list[tuple[Path, tuple[int, ...]]]:
    """`apply_rule` on shapes only (runs the same transforms on a zero-stride placeholder)."""
    placeholder = np.broadcast_to(np.zeros((), np.float32), tuple(shape))
    return [(path, tuple(a.shape)) for path, a in apply_rule(kind, key, placeholder)]
