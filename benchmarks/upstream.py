"""Build the upstream PyTorch VGGT for any `VGGTConfig` (benchmarks and parity checks only).

torch and the upstream `vggt` source are optional: pass the folder that holds the
upstream `vggt/` package (e.g. a checkout of facebookresearch/vggt). Upstream's `VGGT()`
only exposes the 1B widths, so the submodules are built here with the config's sizes.
Nothing in the package or its tests imports this file.
"""

from __future__ import annotations

import sys
from functools import partial
from pathlib import Path

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # annotations only: peer_worker.py imports this file without jax
    from rvggt_jax.config import VGGTConfig


def import_upstream(vggt_src: str | Path):
    src = Path(vggt_src).resolve()
    if not (src / "vggt" / "models" / "aggregator.py").exists():
        raise SystemExit(f"{src} does not hold the upstream vggt package (vggt/models/aggregator.py)")
    sys.path.insert(0, str(src))
    import torch  # noqa: F401  (optional benchmark dependency)
    import vggt  # noqa: F401

    return src


def build_upstream(config: VGGTConfig, vggt_src: str | Path, seed: int = 0, gamma: float = 0.5):
    """A randomly initialised upstream VGGT with `config`'s sizes (eval mode).

    Parameters are re-drawn like the test fixture's (LayerScale gammas near `gamma`, norm
    weights near 1, tokens with std 0.5) so that every path changes the output."""
    import_upstream(vggt_src)
    import torch
    from vggt.heads.camera_head import CameraHead
    from vggt.heads.dpt_head import DPTHead
    from vggt.heads.track_head import TrackHead
    from vggt.layers.attention import MemEffAttention
    from vggt.layers.block import Block
    from vggt.layers.vision_transformer import DinoVisionTransformer
    from vggt.models.aggregator import Aggregator
    from vggt.models.vggt import VGGT

    torch.manual_seed(seed)
    c = config
    model = VGGT.__new__(VGGT)
    torch.nn.Module.__init__(model)
    agg = Aggregator.__new__(Aggregator)
    torch.nn.Module.__init__(agg)
    # Build the aggregator without its hard-coded ViT-L patch embed, then attach ours.
    orig = Aggregator.__build_patch_embed__
    Aggregator.__build_patch_embed__ = lambda self, *a, **k: None  # not name-mangled: ends in __
    try:
        Aggregator.__init__(agg, img_size=c.img_size, patch_size=c.patch_size, embed_dim=c.embed_dim,
                            depth=c.depth, num_heads=c.num_heads, mlp_ratio=c.mlp_ratio,
                            num_register_tokens=c.num_register_tokens, rope_freq=c.rope_freq,
                            qk_norm=c.qk_norm)
    finally:
        Aggregator.__build_patch_embed__ = orig
    agg.patch_embed = DinoVisionTransformer(
        img_size=c.img_size, patch_size=c.patch_size, embed_dim=c.embed_dim, depth=c.dino.depth,
        num_heads=c.dino.num_heads, mlp_ratio=c.dino.mlp_ratio,
        block_fn=partial(Block, attn_class=MemEffAttention), num_register_tokens=c.num_register_tokens,
        interpolate_antialias=c.dino.interpolate_antialias, interpolate_offset=c.dino.interpolate_offset,
        block_chunks=0, init_values=1.0)
    model.aggregator = agg
    dim_in = 2 * c.embed_dim
    dpt = dict(features=c.dpt_head.features, out_channels=list(c.dpt_head.out_channels),
               intermediate_layer_idx=list(c.dpt_head.intermediate_layer_idx))
    ch = c.camera_head
    model.camera_head = CameraHead(dim_in=dim_in, trunk_depth=ch.trunk_depth, num_heads=ch.num_heads,
                                   mlp_ratio=int(ch.mlp_ratio)) if c.enable_camera else None
    model.point_head = DPTHead(dim_in=dim_in, output_dim=4, activation="inv_log", conf_activation="expp1",
                               **dpt) if c.enable_point else None
    model.depth_head = DPTHead(dim_in=dim_in, output_dim=2, activation="exp", conf_activation="expp1",
                               **dpt) if c.enable_depth else None
    if c.enable_track:
        th = c.track_head
        model.track_head = TrackHead(dim_in=dim_in, patch_size=c.patch_size, features=th.features,
                                     iters=th.iters, predict_conf=th.predict_conf, stride=th.stride,
                                     corr_levels=th.corr_levels, corr_radius=th.corr_radius,
                                     hidden_size=th.hidden_size)
        fe = model.track_head.feature_extractor
        # the feature extractor's projections follow the configured out_channels
        fe_new = DPTHead(dim_in=dim_in, patch_size=c.patch_size, features=th.features, feature_only=True,
                         down_ratio=2, pos_embed=False, out_channels=list(c.track_out_channels),
                         intermediate_layer_idx=list(c.track_layer_idx))
        model.track_head.feature_extractor = fe_new if fe is not None else fe
    else:
        model.track_head = None
    model.eval()
    randomize_(model, gamma)
    return model


def randomize_(model, gamma: float = 0.5) -> None:
    """Re-draw every parameter so no block is close to the identity."""
    import torch

    g = torch.Generator().manual_seed(1234)
    with torch.no_grad():
        for name, p in model.named_parameters():
            leaf = name.rsplit(".", 1)[-1]
            if leaf == "gamma":
                p.copy_(gamma + 0.1 * torch.randn(p.shape, generator=g))
            elif "norm" in name and leaf == "weight" and p.ndim == 1:
                p.copy_(1.0 + 0.1 * torch.randn(p.shape, generator=g))
            elif p.ndim <= 1:
                p.copy_(0.02 * torch.randn(p.shape, generator=g))
            elif "token" in leaf or leaf in ("pos_embed", "virual_tracks"):
                p.copy_(0.5 * torch.randn(p.shape, generator=g))
            else:
                fan_in = int(np.prod(p.shape[1:]))
                p.copy_(torch.randn(p.shape, generator=g) / np.sqrt(fan_in))


def save_checkpoint(model, config: VGGTConfig, folder: str | Path) -> Path:
    """model.safetensors + config.json, the layout `rvggt_jax.load_pretrained` reads."""
    from safetensors.torch import save_file

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    state = {k: v.contiguous() for k, v in model.state_dict().items()}
    save_file(state, str(folder / "model.safetensors"))
    config.to_json(folder / "config.json")
    return folder
