"""Model configuration: frozen, hashable dataclasses used as static `jax.jit` arguments.

`VGGTConfig` is registered as a static pytree node, so `jax.jit(rvggt_forward)(params,
images, config)` treats it as part of the compiled function's identity (one compilation
per (input shape, config)) without `static_argnames`.

The JSON form is the extended VGGT `config.json` of the test fixtures: every key that is
absent takes the VGGT-1B value.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Mapping, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.compression.config import CompressionConfig, make_compression
from rvggt_jax.ops.kernels.names import HALF_ONLY, KERNELS

# Compute dtypes of the aggregator.
DTYPES = ("float32", "bfloat16")
# Rematerialisation policies of a training step (`VGGTConfig.remat`, `rvggt_jax.model.remat`);
# True and False name the default policy and none
REMAT_POLICIES = ("none", "layers", "full", "dots")
REMAT_OF_BOOL = {False: "none", True: "full"}
# Precisions of float32 matmuls and convolutions (`VGGTConfig.matmul_precision`), as
# `jax.default_matmul_precision` names them: "default" is the platform's fast one (TF32 on
# an NVIDIA GPU, one bf16 pass on a TPU), "highest" full float32 everywhere
MATMUL_PRECISIONS = ("default", "high", "highest")


class TokenGrid(NamedTuple):
    """How the aggregator's tokens of a frame sit on its image: what a head needs besides
    its own sub-config (`VGGTConfig.token_grid`). Every head is called as
    `head(params, aggregated, head_config, grid, ...)` (the camera head, which reads the
    camera token alone, without the grid)."""

    image_hw: tuple[int, int]  # (H, W) of the network input
    patch_size: int
    patch_start_idx: int  # camera + register tokens before the patches

    @property
    def hw(self) -> tuple[int, int]:
        """(h, w) of the patch grid."""
        return self.image_hw[0] // self.patch_size, self.image_hw[1] // self.patch_size


@dataclass(frozen=True)
class DinoConfig:
    """DINOv2 ViT/14 with registers used as the patch embed (its width is `embed_dim`)."""

    depth: int = 24
    num_heads: int = 16
    mlp_ratio: float = 4.0
    interpolate_antialias: bool = True
    interpolate_offset: float = 0.0
    layer_norm_eps: float = 1e-6


@dataclass(frozen=True)
class CameraHeadConfig:
    num_heads: int = 16
    trunk_depth: int = 4
    iters: int = 4
    mlp_ratio: float = 4.0
    trans_act: str = "linear"
    quat_act: str = "linear"
    fl_act: str = "relu"


@dataclass(frozen=True)
class DPTHeadConfig:
    features: int = 256
    out_channels: tuple[int, ...] = (256, 512, 1024, 1024)
    intermediate_layer_idx: tuple[int, ...] = (4, 11, 17, 23)
    pos_embed: bool = True


@dataclass(frozen=True)
class TrackHeadConfig:
    """Track head sizes. `out_channels`/`intermediate_layer_idx` of its DPT feature
    extractor default (None) to the DPT head's."""

    features: int = 128
    hidden_size: int = 384
    corr_levels: int = 7
    corr_radius: int = 4
    stride: int = 2
    iters: int = 4
    predict_conf: bool = True
    out_channels: tuple[int, ...] | None = None
    intermediate_layer_idx: tuple[int, ...] | None = None


@dataclass(frozen=True)
class VGGTConfig:
    """Everything that fixes the model's shapes and the forward computation."""

    img_size: int = 518
    patch_size: int = 14
    embed_dim: int = 1024
    depth: int = 24
    num_heads: int = 16
    mlp_ratio: float = 4.0
    num_register_tokens: int = 4
    rope_freq: float = 100.0
    qk_norm: bool = True
    dino: DinoConfig = field(default_factory=DinoConfig)
    camera_head: CameraHeadConfig = field(default_factory=CameraHeadConfig)
    dpt_head: DPTHeadConfig = field(default_factory=DPTHeadConfig)
    track_head: TrackHeadConfig = field(default_factory=TrackHeadConfig)
    enable_camera: bool = True
    enable_depth: bool = True
    enable_point: bool = True
    enable_track: bool = True
    compression: CompressionConfig = field(default_factory=CompressionConfig)
    # Output requests (static, so they live here): extra entries of rvggt_forward's dict.
    return_saliency: bool = False  # "saliency" [B,S,h*w] (Psi) and "patch_tokens" [B*S,h*w,C]
    return_layers: tuple[int, ...] = ()  # "aggregated_XX" [B,S,P,2C] for these layers
    # "descriptors" [B,S,C]: each frame's place descriptor for loop detection in long
    # sequences (rvggt_jax.sequence): its DINOv2 patch tokens, mean-pooled, unit length
    return_descriptors: bool = False
    # "images" [B,S,3,H,W]: a copy of the input, which upstream always returns; on request
    # here (2.3 GiB of float32 at 1000 frames of 392 x 518, for what the caller has already)
    return_images: bool = False
    # Compute dtype of the aggregator (patch embed, frame and global blocks), as upstream's
    # torch.autocast: "float32" (exact, the default) or "bfloat16". The heads always run
    # in float32. See docs/method.md ("Mixed precision").
    dtype: str = "float32"
    # Rematerialisation for training (`rvggt_jax.model.remat`, docs/training.md "Memory"):
    # "none"; "layers" (each aggregator layer and DINO block a `jax.checkpoint`); "full"
    # (also the DINOv2 patch embed as a whole and each frame group of the DPT heads: a step
    # keeps the images, each layer's input and the kept layers the heads read); "dots"
    # ("full", the matmul outputs saved in each checkpoint: less recomputation, more
    # memory). True is "full", False "none". Values are unchanged; a forward alone is
    # unaffected.
    remat: str = "none"
    # The attention kernel (`rvggt_jax.ops.attention`; names in ops/kernels/names.py):
    # "auto" takes the kernel of the platform the program is compiled for (cuDNN for
    # bfloat16 on an NVIDIA GPU, Pallas flash on a TPU, the blocked kernel on a CPU and for
    # float32 on a GPU). A 16-bit-only kernel ("cudnn") needs dtype "bfloat16" and runs
    # the aggregator's attention; the float32 heads then take "auto".
    attention: str = "auto"
    # Precision of the float32 matmuls and convolutions (one of MATMUL_PRECISIONS; the
    # aggregator's bf16 ones are bf16 whatever this says). None follows `dtype`: "highest"
    # for float32, so that float32 is float32 on every platform (a GPU's default TF32 moved
    # the tiny fixture's outputs by 1.5e-3 on an H200, against 2e-6 at "highest",
    # docs/benchmarks.md "GPU check"; a CPU computes float32 either way), and JAX's own
    # setting for bfloat16, whose float32 heads then take the platform's fast matmuls
    # (TF32 on a GPU) unless `jax_default_matmul_precision` says otherwise.
    matmul_precision: str | None = None
    # Low-memory inference (`with_low_memory`; `rvggt plan --low-memory`): the dense outputs
    # in 16 bits (depth and points float16, confidences bfloat16: a confidence 1 + exp(x)
    # overflows float16 past x = 11), the camera head's weights stored like the
    # aggregator's (`half_weight_heads`), and the layers the DPT heads read at their coarse levels (2 and 3)
    # kept as those heads' reassembled maps instead of tokens (VGGT-1B: layer 23 as 2 x 256
    # channels at a quarter of the positions, not 2048 channels of float32 stream and
    # bf16 slot). docs/memory_layout.md ("Low-memory mode") has what each saves. An
    # inference mode: a training step (remat) refuses it.
    low_memory: bool = False

    def __post_init__(self):
        # remat=True / False (the flag it was before the policies) names a policy
        if isinstance(self.remat, (bool, np.bool_)):
            object.__setattr__(self, "remat", REMAT_OF_BOOL[bool(self.remat)])

    # ---- derived sizes -------------------------------------------------------------
    @property
    def half_weight_heads(self) -> tuple[str, ...]:
        """The heads whose weights are stored in the aggregator's 16-bit dtype (they still
        compute in float32): the camera head in the low-memory mode (0.8 of VGGT-1B's
        1.0 GiB of float32 head weights). The DPT heads' stay float32: in bfloat16 they
        moved the tiny fixture's depth confidence past twice upstream's own bf16
        deviation (1.7e-2 against 1.6e-2)."""
        return ("camera_head",) if self.low_memory else ()

    @property
    def head_dim(self) -> int:
        return self.embed_dim // self.num_heads

    @property
    def compute_dtype(self) -> Any:
        """The aggregator's compute dtype as a jnp dtype."""
        return jnp.dtype(self.dtype)

    @property
    def dot_precision(self) -> str | None:
        """The precision of float32 matmuls (`matmul_precision`, else by `dtype`) that
        `rvggt_forward` runs under (`ops.precision.precision_scope`; its gradients too); None
        leaves JAX's own default (`jax_default_matmul_precision`, the platform's when unset)."""
        if self.matmul_precision is not None:
            return self.matmul_precision
        return "highest" if self.dtype == "float32" else None

    @property
    def patch_start_idx(self) -> int:
        """Camera token + register tokens precede the patches in every frame."""
        return 1 + self.num_register_tokens

    @property
    def track_out_channels(self) -> tuple[int, ...]:
        return self.track_head.out_channels or self.dpt_head.out_channels

    @property
    def track_layer_idx(self) -> tuple[int, ...]:
        return self.track_head.intermediate_layer_idx or self.dpt_head.intermediate_layer_idx

    def token_grid(self, image_hw: tuple[int, int]) -> TokenGrid:
        """The heads' view of images of `image_hw` = (H, W)."""
        return TokenGrid((int(image_hw[0]), int(image_hw[1])), self.patch_size, self.patch_start_idx)

    @property
    def track_head_config(self) -> TrackHeadConfig:
        """`track_head` with its DPT extractor's defaults (None: the DPT head's) filled in:
        the sub-config `heads.track.track_head` takes."""
        return replace(self.track_head, out_channels=self.track_out_channels,
                       intermediate_layer_idx=self.track_layer_idx)

    def needed_layers(self, with_track: bool) -> tuple[int, ...]:
        """Aggregator layers some head reads; only these outputs are kept alive."""
        need: set[int] = set()
        if self.enable_camera:
            need.add(self.depth - 1)
        if self.enable_depth or self.enable_point:
            need.update(self.dpt_head.intermediate_layer_idx)
        if with_track and self.enable_track:
            need.update(self.track_layer_idx)
        return tuple(sorted(need))

    # ---- presets and variants ------------------------------------------------------
    @classmethod
    def vggt_1b(cls) -> "VGGTConfig":
        """The published facebook/VGGT-1B layout."""
        return cls()

    @classmethod
    def rvggt_small(cls) -> "VGGTConfig":
        """The small VGGT trained here from scratch on procedural scenes and shipped as
        "rvggt-small" (`rvggt_jax.train.small`): the same architecture at width 128 (4
        heads), 6 frame/global block pairs, a 3-block DINO patch embed, a 1-block camera
        trunk, DPT heads of 32 features, a track head of 64 hidden units over 3
        correlation levels. Trained at 84 x 112 images."""
        return cls(img_size=112, embed_dim=128, depth=6, num_heads=4,
                   dino=DinoConfig(depth=3, num_heads=4),
                   camera_head=CameraHeadConfig(num_heads=8, trunk_depth=1, iters=4),
                   dpt_head=DPTHeadConfig(features=32, out_channels=(16, 32, 64, 64), intermediate_layer_idx=(1, 3, 4, 5)),
                   track_head=TrackHeadConfig(features=32, hidden_size=64, corr_levels=3, corr_radius=2, stride=2,
                                              iters=4)).validate()

    def with_outputs(self, saliency: bool = False, layers: tuple[int, ...] = (), images: bool = False,
                     descriptors: bool = False) -> "VGGTConfig":
        """A copy that also returns the saliency / these aggregator layers / the input
        images / the frames' place descriptors."""
        return replace(self, return_saliency=saliency, return_layers=tuple(layers), return_images=bool(images),
                       return_descriptors=bool(descriptors))

    def with_dtype(self, dtype: Any) -> "VGGTConfig":
        """A copy computing the aggregator in `dtype` ("float32" or "bfloat16")."""
        try:
            name = jnp.dtype(dtype).name
        except TypeError:
            raise ValueError(f"dtype must be one of {DTYPES}; got {dtype!r}") from None
        return replace(self, dtype=name).validate()

    def with_attention(self, kernel: str) -> "VGGTConfig":
        """A copy whose attention runs on `kernel` (one of `KERNELS`)."""
        return replace(self, attention=kernel).validate()

    def with_precision(self, precision: str | None) -> "VGGTConfig":
        """A copy whose float32 matmuls run at `precision` (one of MATMUL_PRECISIONS; None
        follows the dtype: "highest" for float32, JAX's own setting for bfloat16)."""
        return replace(self, matmul_precision=precision).validate()

    def with_remat(self, remat: bool | str = True) -> "VGGTConfig":
        """A copy with the rematerialisation policy `remat` (one of `REMAT_POLICIES`;
        True: "full", False: "none")."""
        return replace(self, remat=remat).validate()

    def with_low_memory(self, on: bool = True) -> "VGGTConfig":
        """A copy in (or out of) the low-memory inference mode (see the `low_memory` field)."""
        return replace(self, low_memory=bool(on)).validate()

    def with_compression(self, name: str, **overrides: Any) -> "VGGTConfig":
        """A copy of this config with the named compression preset (see
        `rvggt_jax.compression.config.PRESETS`), fields overridden by name."""
        return replace(self, compression=make_compression(name, self.depth, **overrides))

    def validate(self) -> "VGGTConfig":
        if self.dtype not in DTYPES:
            raise ValueError(f"dtype must be one of {DTYPES}; got {self.dtype!r}")
        if self.remat not in REMAT_POLICIES:
            raise ValueError(f"remat must be one of {REMAT_POLICIES} (or True / False); got {self.remat!r}")
        if self.matmul_precision is not None and self.matmul_precision not in MATMUL_PRECISIONS:
            raise ValueError(f"matmul_precision must be None or one of {MATMUL_PRECISIONS}; got "
                             f"{self.matmul_precision!r}")
        if self.attention not in KERNELS:
            raise ValueError(f"attention must be one of {KERNELS}; got {self.attention!r}")
        if self.attention in HALF_ONLY and self.dtype == "float32":
            raise ValueError(f"the {self.attention!r} attention kernel takes bfloat16 only: use dtype 'bfloat16', or "
                             f"attention 'auto' or 'blocked' for float32 (choices: {KERNELS})")
        if self.low_memory and self.remat != "none":
            raise ValueError(f"low_memory is an inference mode; a training step's remat ({self.remat!r}) keeps the "
                             f"layers as tokens: use remat 'none' or low_memory False")
        if self.embed_dim % self.num_heads:
            raise ValueError(f"embed_dim {self.embed_dim} is not divisible by num_heads {self.num_heads}")
        if self.head_dim % 4:
            raise ValueError(f"2D RoPE needs a head dimension divisible by 4, got {self.head_dim}")
        if self.embed_dim % self.dino.num_heads:
            raise ValueError(f"embed_dim {self.embed_dim} is not divisible by dino.num_heads {self.dino.num_heads}")
        for i in self.dpt_head.intermediate_layer_idx + self.track_layer_idx:
            if not 0 <= i < self.depth:
                raise ValueError(f"intermediate layer {i} outside the aggregator's {self.depth} layers")
        if len(self.dpt_head.out_channels) != 4 or len(self.dpt_head.intermediate_layer_idx) != 4:
            raise ValueError("the DPT head reads exactly 4 layers and needs 4 out_channels")
        return self

    # ---- JSON ----------------------------------------------------------------------
    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "VGGTConfig":
        """Build from the extended VGGT `config.json`; unknown keys are an error, except
        `fixture` (test metadata), `train_image_size` (the [H, W] a model was trained
        at) and the hub mixin's bookkeeping keys."""
        ignored = {"fixture", "_name_or_path", "architectures", "model_type", "train_image_size"}
        return _build(cls, {k: v for k, v in d.items() if k not in ignored}).validate()

    @classmethod
    def from_json(cls, path: str | Path) -> "VGGTConfig":
        with open(path) as f:
            return cls.from_dict(json.load(f))

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def to_json(self, path: str | Path) -> None:
        with open(path, "w") as f:
            json.dump(self.to_dict(), f, indent=1)


def _build(cls, d: Mapping[str, Any]):
    known = {f.name: f for f in fields(cls)}
    unknown = sorted(set(d) - set(known))
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown config keys {unknown}")
    kwargs = {}
    for name, value in d.items():
        default = getattr(cls(), name) if name != "compression" else None
        if name == "compression":
            kwargs[name] = CompressionConfig.from_dict(value)
        elif dataclasses.is_dataclass(default):
            kwargs[name] = _build(type(default), value)
        elif isinstance(value, list):
            kwargs[name] = tuple(value)
        else:
            kwargs[name] = value
    return cls(**kwargs)


jax.tree_util.register_static(VGGTConfig)
