"""The long sequence whose memory the tests plan (nothing runs): 200 frames of 168 x 224
(39,400 tokens) through a 24-layer width-256 model (tests/planning/test_memory.py), and
the same plan split over 4 devices (tests/helpers/sharded_worker.py)."""

from rvggt_jax.config import CameraHeadConfig, DinoConfig, DPTHeadConfig, VGGTConfig

# The DPT levels' widths are VGGT-1B's fractions of the layer (2C = 512 here): 1/8, 1/4,
# 1/2, 1/2, so the depth and point heads' projections of layers 4 and 11 are narrower than
# the layers and kept in their place, and layers 17 and 23 are kept whole, as in VGGT-1B.
BASE = VGGTConfig(embed_dim=256, num_heads=4, dino=DinoConfig(depth=1, num_heads=4),
                  camera_head=CameraHeadConfig(num_heads=4, trunk_depth=1),
                  dpt_head=DPTHeadConfig(features=16, out_channels=(64, 128, 256, 256)), enable_track=False)
S, H, W = 200, 168, 224
