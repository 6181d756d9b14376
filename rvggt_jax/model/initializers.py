"""Upstream VGGT's random initialisation, leaf by leaf, for the converted parameter tree.

`param_specs(config)` lists every leaf of the converter's tree (the same paths and
shapes as `rvggt_jax.weights.converter.expected_param_paths`, derived from the same upstream
state-dict table `rvggt_jax/model/params.py` and rule table `rvggt_jax/model/param_rules.py`) with the
initialiser upstream's PyTorch modules give the tensor it comes from. The Flax modules of
`rvggt_jax.model.modules` register each leaf with `self.param(name, spec.initializer(), shape)`;
`rvggt_jax.init_params(config, key)` is `VGGT(config).init(...)` of those registrations.

Where the initialisers come from (upstream facebookresearch/vggt):

| upstream tensor | init |
| --- | --- |
| DINOv2 `patch_embed.blocks.*` Linear (qkv, proj, fc1, fc2) | trunc_normal std 0.02, bias 0 (`init_weights_vit_timm`) |
| DINOv2 `pos_embed` | trunc_normal std 0.02 |
| DINOv2 `cls_token`, `register_tokens` | normal std 1e-6 |
| DINOv2 `mask_token` | 0 |
| DINOv2 LayerScale `ls1/ls2.gamma` | 1.0 (the aggregator builds DINO with `init_values=1.0`) |
| aggregator `camera_token`, `register_token` | normal std 1e-6 |
| frame / global / camera-trunk LayerScale | 0.01 (`init_values=0.01`) |
| tracker `updateformer` Linears, MHA `in_proj` | xavier_uniform, bias 0 (`initialize_weights`; MHA's own reset) |
| tracker `flow_head.weight` | trunc_normal std 0.001 |
| tracker `query_ref_token`, `virual_tracks` | normal std 1 (`torch.randn`, never re-initialised) |
| camera head `empty_pose_tokens` | 0 |
| every LayerNorm / GroupNorm | scale 1, bias 0 |
| everything else: frame/global/camera-trunk Linears, camera-head Linears, every DPT conv and transposed conv, patchify conv, tracker `corr_mlp` / predictors | torch's default: weight and bias U(-1/sqrt(fan_in), 1/sqrt(fan_in)) (`kaiming_uniform_(a=sqrt(5))`) |

torch's `trunc_normal_(std=s)` cuts at the absolute values -2 and 2, not at 2 s: with
s = 0.02 that is a plain normal, and so is ours (we cut where torch does). Fused upstream
tensors split by the converter (`qkv` -> q, k, v; MHA `in_proj` -> q, k, v) use the fans
of the fused tensor, so each part has the distribution of its rows upstream.
`fan_in` of a transposed convolution is torch's: weight [I, O, k, k] -> O k k.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import re
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.config import VGGTConfig

Path = tuple[str, ...]

# LayerScale init values upstream passes to its blocks
DINO_LAYER_SCALE = 1.0
AGGREGATOR_LAYER_SCALE = 0.01


@dataclasses.dataclass(frozen=True)
class InitSpec:
    """How one leaf is drawn: `kind` in {"zeros", "ones", "constant", "normal",
    "trunc_normal", "uniform"}; `value` is the constant, the std or the uniform bound;
    `cut` the absolute truncation of "trunc_normal" (torch's default +-2)."""

    kind: str
    value: float = 0.0
    cut: float = 2.0

    def initializer(self) -> Callable[[jax.Array, tuple[int, ...], Any], jax.Array]:
        """A Flax-style initializer `(key, shape, dtype) -> array`."""
        spec = self

        def init(key: jax.Array, shape: tuple[int, ...], dtype: Any = jnp.float32) -> jax.Array:
            return draw(spec, key, tuple(shape), dtype)

        return init


# Random leaves are drawn in blocks of this many values, one compiled program per
# distribution for every leaf shape: drawing each shape directly compiles one program per
# (distribution, shape), ~40 s on a CPU for the ~1800 leaves of a VGGT tree, and one jit
# over the whole tree takes minutes to compile. Block i of a leaf uses fold_in(key, i).
BLOCK = 1 << 16


@functools.partial(jax.jit, static_argnames="kind")
def _block(key: jax.Array, kind: str, value: jax.Array, cut: jax.Array) -> jax.Array:
    """[BLOCK] float32 values of one distribution (value: std or bound)."""
    if kind == "normal":
        return value * jax.random.normal(key, (BLOCK,), jnp.float32)
    if kind == "trunc_normal":
        # torch cuts at absolute values (+-cut), i.e. at +-cut/std standard deviations
        return value * jax.random.truncated_normal(key, -cut / value, cut / value, (BLOCK,), jnp.float32)
    return jax.random.uniform(key, (BLOCK,), jnp.float32, -value, value)


def draw(spec: InitSpec, key: jax.Array, shape: tuple[int, ...], dtype: Any = jnp.float32) -> jax.Array:
    """One leaf of `shape` drawn per `spec` from `key`. Eagerly and under `jax.jit` the
    draws are the same up to float rounding (the compiled scaling fuses differently)."""
    if spec.kind in ("zeros", "ones", "constant"):
        v = {"zeros": 0.0, "ones": 1.0}.get(spec.kind, spec.value)
        return jnp.asarray(np.full(shape, v, np.float32)).astype(dtype)  # no per-shape program
    if spec.kind not in ("normal", "trunc_normal", "uniform"):
        raise ValueError(f"unknown init kind {spec.kind!r}")
    n = math.prod(shape)
    value, cut = np.float32(spec.value), np.float32(spec.cut)
    count = -(-n // BLOCK)
    if isinstance(key, jax.core.Tracer):
        # traced (jit, eval_shape): all blocks at once, one op instead of `count`
        blocks = jax.vmap(lambda i: _block(jax.random.fold_in(key, i), spec.kind, value, cut))(jnp.arange(count))
        return blocks.reshape(-1)[:n].reshape(shape).astype(dtype)
    blocks = [_block(jax.random.fold_in(key, i), spec.kind, value, cut) for i in range(count)]
    # eagerly: stitch on the host (a device concatenate would compile per shape too)
    flat = np.concatenate([np.asarray(b) for b in blocks])[:n] if blocks else np.zeros((0,), np.float32)
    return jnp.asarray(flat.reshape(shape)).astype(dtype)


ZEROS, ONES = InitSpec("zeros"), InitSpec("ones")

_DINO_BLOCK = re.compile(r"aggregator\.patch_embed\.blocks\.\d+\.")
_UPDATEFORMER = re.compile(r"track_head\.tracker\.updateformer\.")


def _torch_default(shape: tuple[int, ...]) -> InitSpec:
    """nn.Linear / nn.Conv2d / nn.ConvTranspose2d default: U(+-1/sqrt(fan_in)) for weight
    and bias alike (fan_in of the weight; torch takes dim 1 x receptive field, which for a
    transposed conv [I, O, k, k] is O k k)."""
    receptive = math.prod(shape[2:]) if len(shape) > 2 else 1
    return InitSpec("uniform", 1.0 / math.sqrt(shape[1] * receptive))


def upstream_init(key: str, shape: tuple[int, ...], weight_shape: tuple[int, ...] | None, kind: str) -> InitSpec:
    """The init of upstream tensor `key` (shape `shape`); `weight_shape` is the shape of
    its module's weight (for a bias's fan_in), `kind` the conversion rule's kind."""
    leaf = key.rsplit(".", 1)[-1]
    if kind == "norm":
        return ONES if leaf == "weight" else ZEROS
    if leaf == "gamma":
        return InitSpec("constant", DINO_LAYER_SCALE if _DINO_BLOCK.match(key) else AGGREGATOR_LAYER_SCALE)
    if kind == "raw":
        if key.endswith(("camera_token", "register_token", "cls_token", "register_tokens")):
            return InitSpec("normal", 1e-6)
        if key.endswith("pos_embed"):
            return InitSpec("trunc_normal", 0.02)
        if key.endswith(("mask_token", "empty_pose_tokens")):
            return ZEROS
        if key.endswith(("query_ref_token", "virual_tracks")):
            return InitSpec("normal", 1.0)
        raise ValueError(f"no initialisation rule for {key}")
    if _DINO_BLOCK.match(key):  # DINOv2's init_weights_vit_timm: every Linear
        return InitSpec("trunc_normal", 0.02) if leaf == "weight" else ZEROS
    if _UPDATEFORMER.match(key) and kind in ("linear", "mha_in_proj"):
        if leaf in ("bias", "in_proj_bias"):
            return ZEROS
        if key.endswith("flow_head.weight"):
            return InitSpec("trunc_normal", 0.001)
        fan_out, fan_in = shape  # xavier_uniform on the (fused) [out, in] weight
        return InitSpec("uniform", math.sqrt(6.0 / (fan_in + fan_out)))
    ws = weight_shape if weight_shape is not None else shape
    return _torch_default(ws)


def param_specs(config: VGGTConfig, *, skip_track: bool = False) -> dict[Path, tuple[tuple[int, ...], InitSpec]]:
    """{our path: (converted shape, InitSpec)} for every leaf of the converted tree of
    `config` (in the order of upstream's state dict). The paths and shapes are the
    layout's (`model.param_rules.converted_shapes` over `model.params.upstream_state_dict_shapes`)."""
    from rvggt_jax.model.param_rules import converted_shapes, find_rule
    from rvggt_jax.model.params import upstream_state_dict_shapes

    upstream = upstream_state_dict_shapes(config, skip_track=skip_track)
    out: dict[Path, tuple[tuple[int, ...], InitSpec]] = {}
    for key, shape in upstream.items():
        rule = find_rule(key)
        if rule is None:
            raise ValueError(f"no conversion rule for upstream key {key}")
        module, leaf = key.rsplit(".", 1)
        weight_shape = None
        if leaf == "bias":
            weight_shape = upstream.get(module + ".weight")
        elif leaf == "in_proj_bias":
            weight_shape = upstream.get(module + ".in_proj_weight")
        spec = upstream_init(key, shape, weight_shape, rule.kind)
        for path, s in converted_shapes(rule.kind, key, shape):
            if path in out:
                raise ValueError(f"conversion rules write {'.'.join(path)} twice")
            out[path] = (s, spec)
    return out
