"""Parity of rvggt-jax against the upstream PyTorch VGGT on freshly drawn random weights,
for layouts the committed fixture does not cover (other widths, head counts, batch 2,
other frame counts and image sizes, the full VGGT-1B layout). Needs torch and the
upstream source (development tool, not a dependency):

    python tools/check_parity.py --vggt-src /path/to/vggt [--layout 1b] [--batch 2 --frames 3]

Prints max |ours - ref| / max |ref| for every output.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import rvggt_jax  # noqa: E402
from benchmarks.upstream import build_upstream, save_checkpoint  # noqa: E402
from rvggt_jax.config import (CameraHeadConfig, DinoConfig, DPTHeadConfig, TrackHeadConfig,  # noqa: E402
                              VGGTConfig)

LAYOUTS = {
    "1b": VGGTConfig(),
    "wide": VGGTConfig(embed_dim=96, num_heads=3, dino=DinoConfig(depth=3, num_heads=4),
                       camera_head=CameraHeadConfig(num_heads=6, trunk_depth=2),
                       dpt_head=DPTHeadConfig(features=24, out_channels=(12, 24, 48, 48)),
                       track_head=TrackHeadConfig(features=24, hidden_size=48, corr_levels=3, corr_radius=3,
                                                  iters=3)),
    "narrow": VGGTConfig(embed_dim=64, num_heads=4, depth=24, dino=DinoConfig(depth=2, num_heads=2),
                         camera_head=CameraHeadConfig(num_heads=2, trunk_depth=1),
                         dpt_head=DPTHeadConfig(features=8, out_channels=(8, 8, 16, 16),
                                                intermediate_layer_idx=(2, 9, 15, 23)),
                         track_head=TrackHeadConfig(features=8, hidden_size=16, corr_levels=2, corr_radius=1,
                                                    iters=2)),
}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--vggt-src", required=True)
    ap.add_argument("--layout", choices=sorted(LAYOUTS), default="wide")
    ap.add_argument("--batch", type=int, default=2)
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--height", type=int, default=126)
    ap.add_argument("--width", type=int, default=98)
    ap.add_argument("--points", type=int, default=0, help="query points (0: no track head)")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)

    import torch

    torch.set_num_threads(args.threads)
    config = LAYOUTS[args.layout]
    model = build_upstream(config, args.vggt_src)
    with tempfile.TemporaryDirectory() as tmp:
        save_checkpoint(model, config, tmp)
        params, config = rvggt_jax.load_pretrained(tmp)

    rng = np.random.default_rng(1)
    images = rng.random((args.batch, args.frames, 3, args.height, args.width), dtype=np.float32)
    query = None
    if args.points:
        query = (rng.random((args.batch, args.points, 2)) * [args.width, args.height]).astype(np.float32)
    ours = jax.jit(rvggt_jax.rvggt_forward)(params, images, config, query)
    with torch.inference_mode():
        ref = model(torch.from_numpy(images), None if query is None else torch.from_numpy(query))
    print(f"layout {args.layout}: embed {config.embed_dim}, heads {config.num_heads}, "
          f"input {images.shape}, points {args.points}")
    for key in ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf", "track", "vis", "conf"):
        if key not in ref or ref[key] is None:
            continue
        r = ref[key].numpy()
        o = np.asarray(ours[key])
        err = float(np.abs(o - r).max() / np.abs(r).max())
        print(f"  {key:18s} {str(o.shape):22s} rel err {err:.2e}")
    pl = np.stack([np.asarray(p) for p in ours["pose_enc_list"]])
    rl = np.stack([p.numpy() for p in ref["pose_enc_list"]])
    print(f"  {'pose_enc_list':18s} {str(pl.shape):22s} rel err {np.abs(pl - rl).max() / np.abs(rl).max():.2e}")


if __name__ == "__main__":
    main()
