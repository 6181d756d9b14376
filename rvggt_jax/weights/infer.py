"""The VGGT layout of a checkpoint from its tensor shapes, for a `.safetensors` found
without its `config.json`.

Shapes fix every width and depth. Head counts do not (they only split widths), except
the aggregator's, read from its q-norm (one weight per head dimension); the others take
VGGT-1B's value when the widths are VGGT-1B's, else the aggregator's head count, and
`infer_config` says which values were assumed.
"""

from __future__ import annotations

import dataclasses
import re
from typing import Mapping

from rvggt_jax.config import CameraHeadConfig, DinoConfig, DPTHeadConfig, TrackHeadConfig, VGGTConfig

Shape = tuple[int, ...]


def _count(shapes: Mapping[str, Shape], pattern: str) -> int:
    rx = re.compile(pattern)
    return len({m.group(1) for k in shapes if (m := rx.match(k))})


def infer_config(shapes: Mapping[str, Shape]) -> tuple[VGGTConfig, list[str]]:
    """`(config, assumed)` for an upstream state dict given as {key: shape}; `assumed`
    names the fields not determined by the shapes (empty for the VGGT-1B layout, whose
    values are then exactly VGGT-1B's). Raises ValueError when the keys are not VGGT's."""
    try:
        e = shapes["aggregator.camera_token"][-1]
        n_pos = shapes["aggregator.patch_embed.pos_embed"][1] - 1
        patch = shapes["aggregator.patch_embed.patch_embed.proj.weight"][-1]
        regs = shapes["aggregator.register_token"][2]
    except (KeyError, IndexError):
        raise ValueError("not a VGGT checkpoint (no aggregator.camera_token / patch_embed tensors)") from None
    side = round(n_pos ** 0.5)
    depth = _count(shapes, r"aggregator\.frame_blocks\.(\d+)\.")
    qk = shapes.get("aggregator.frame_blocks.0.attn.q_norm.weight")
    heads = e // qk[0] if qk else None
    ref = VGGTConfig()
    one_b = e == ref.embed_dim
    assumed: list[str] = []

    def guess(name: str, value_1b: int) -> int:
        v = value_1b if one_b else (heads or value_1b)
        if not one_b:
            assumed.append(f"{name}={v}")
        return v

    if heads is None:
        heads = guess("num_heads", ref.num_heads)
    fc1 = shapes["aggregator.frame_blocks.0.mlp.fc1.weight"][0]
    dino_fc1 = shapes["aggregator.patch_embed.blocks.0.mlp.fc1.weight"][0]
    dino = DinoConfig(depth=_count(shapes, r"aggregator\.patch_embed\.blocks\.(\d+)\."),
                      num_heads=guess("dino.num_heads", ref.dino.num_heads), mlp_ratio=dino_fc1 / e)
    has = {h: any(k.startswith(h + ".") for k in shapes) for h in ("camera_head", "depth_head", "point_head",
                                                                      "track_head")}
    cam = ref.camera_head
    if has["camera_head"]:
        cam = CameraHeadConfig(num_heads=guess("camera_head.num_heads", ref.camera_head.num_heads),
                               trunk_depth=_count(shapes, r"camera_head\.trunk\.(\d+)\."),
                               mlp_ratio=shapes["camera_head.trunk.0.mlp.fc1.weight"][0] / (2 * e))
    dpt = ref.dpt_head
    head = "depth_head" if has["depth_head"] else "point_head" if has["point_head"] else None
    if head:
        layers = dpt.intermediate_layer_idx if depth == ref.depth else None
        if layers is None:  # which layers the heads read is not in the shapes
            layers = tuple(round(i * (depth - 1) / 23) for i in ref.dpt_head.intermediate_layer_idx)
            assumed.append(f"dpt_head.intermediate_layer_idx={layers}")
        dpt = DPTHeadConfig(features=shapes[f"{head}.scratch.layer1_rn.weight"][0],
                            out_channels=tuple(shapes[f"{head}.projects.{i}.weight"][0] for i in range(4)),
                            intermediate_layer_idx=layers)
    track = ref.track_head
    if has["track_head"]:
        corr_in = shapes["track_head.tracker.corr_mlp.fc1.weight"][1]
        for r in (ref.track_head.corr_radius, 3, 2, 1, 5, 6):  # levels * (2r+1)^2 inputs
            if corr_in % (2 * r + 1) ** 2 == 0:
                break
        fe = "track_head.feature_extractor"
        oc = tuple(shapes[f"{fe}.projects.{i}.weight"][0] for i in range(4))
        track = TrackHeadConfig(features=shapes[f"{fe}.scratch.layer1_rn.weight"][0],
                                hidden_size=shapes["track_head.tracker.updateformer.input_transform.weight"][0],
                                corr_levels=corr_in // (2 * r + 1) ** 2, corr_radius=r,
                                predict_conf="track_head.tracker.conf_predictor.0.weight" in shapes,
                                out_channels=None if oc == dpt.out_channels else oc)
    config = VGGTConfig(img_size=side * patch, patch_size=patch, embed_dim=e, depth=depth, num_heads=heads,
                        mlp_ratio=fc1 / e, num_register_tokens=regs, qk_norm=qk is not None, dino=dino,
                        camera_head=cam, dpt_head=dpt, track_head=track, enable_camera=has["camera_head"],
                        enable_depth=has["depth_head"], enable_point=has["point_head"],
                        enable_track=has["track_head"])
    if config == dataclasses.replace(ref, enable_track=config.enable_track):
        return config, []
    return config.validate(), assumed
