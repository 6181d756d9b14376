"""A micro VGGT layout for training tests: every module of the real architecture at the
smallest widths and depths (4 aggregator layers, 1 DINO block), so that a gradient step
compiles in seconds on a CPU."""

from rvggt_jax.config import CameraHeadConfig, DinoConfig, DPTHeadConfig, TrackHeadConfig, VGGTConfig


def micro_config(**overrides) -> VGGTConfig:
    """4 layers of width 32 (2 heads), DPT heads reading layers 0-3, image size 56."""
    base = dict(img_size=56, embed_dim=32, depth=4, num_heads=2,
                dino=DinoConfig(depth=1, num_heads=2),
                camera_head=CameraHeadConfig(num_heads=2, trunk_depth=1, iters=2),
                dpt_head=DPTHeadConfig(features=8, out_channels=(4, 8, 16, 16), intermediate_layer_idx=(0, 1, 2, 3)),
                track_head=TrackHeadConfig(features=8, hidden_size=16, corr_levels=2, corr_radius=1, iters=2))
    base.update(overrides)
    return VGGTConfig(**base).validate()


def train_config(layers: int = 2) -> VGGTConfig:
    """The smallest layouts with a camera loss and a masked depth loss, for train steps:
    `layers` aggregator layers of `micro_config` (2: `plan_config`'s) with the camera head
    (one trunk block, one iteration) and the depth head (DPT, reading layers 0, 1 and the
    last)."""
    return micro_config(depth=layers, enable_point=False, enable_track=False,
                        camera_head=CameraHeadConfig(num_heads=2, trunk_depth=1, iters=1),
                        dpt_head=DPTHeadConfig(features=8, out_channels=(4, 8, 16, 16),
                                               intermediate_layer_idx=(0, 1, layers - 1, layers - 1)))


def plan_config(head: str = "camera") -> VGGTConfig:
    """The smallest forward the memory plans compile (deviceless, for each target, in a
    few seconds): 2 layers of `micro_config`, one head, "camera" (one trunk block, one
    iteration) or "depth" (the DPT head: its small float32 gemms are what XLA's GPU compiler
    cannot tile for Ampere without `NO_TRITON_GEMM`)."""
    if head not in ("camera", "depth"):
        raise ValueError(f"head must be 'camera' or 'depth'; got {head!r}")
    return micro_config(depth=2, enable_camera=head == "camera", enable_depth=head == "depth", enable_point=False,
                        enable_track=False, camera_head=CameraHeadConfig(num_heads=2, trunk_depth=1, iters=1),
                        dpt_head=DPTHeadConfig(features=8, out_channels=(4, 8, 16, 16),
                                               intermediate_layer_idx=(0, 1, 1, 1)))
