"""Quickstart: load a checkpoint, run the jitted forward pass on a few images, print what
came out. Defaults to the bundled random-weight test checkpoint and demo images.

    python examples/quickstart.py [--weights DIR_OR_FILE] [--preset regime] [IMAGE ...]
"""

import argparse
import time
from pathlib import Path

import jax
import numpy as np

import rvggt_jax
import rvggt_jax.geometry

DATA = Path(rvggt_jax.__file__).parent / "examples_data"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("images", nargs="*", help="image files (default: the bundled demo images)")
    ap.add_argument("--weights", default=str(DATA / "tiny"), help="checkpoint folder or .safetensors")
    ap.add_argument("--preset", default="dense", help="compression preset (dense, regime, ...)")
    args = ap.parse_args()
    rvggt_jax.prefer_threaded_convolutions()  # CPU: multi-threaded convolutions (before anything starts JAX)

    paths = args.images or sorted(str(p) for p in (DATA / "images").iterdir())
    params, config = rvggt_jax.load_pretrained(args.weights)
    config = config.with_compression(args.preset)
    images = rvggt_jax.load_images(paths, mode="crop")
    h, w = images.shape[-2:]
    query_points = np.array([[w / 3, h / 3], [w / 2, h / 2], [2 * w / 3, 2 * h / 3]], np.float32)

    forward = jax.jit(rvggt_jax.rvggt_forward)
    t0 = time.perf_counter()
    out = jax.block_until_ready(forward(params, images, config, query_points))
    t1 = time.perf_counter()
    out = jax.block_until_ready(forward(params, images, config, query_points))
    t2 = time.perf_counter()

    print(f"{len(paths)} images -> {tuple(images.shape)}, preset {args.preset!r}")
    print(f"first call (compile + run) {t1 - t0:.1f} s, second call {t2 - t1:.2f} s")
    for key, value in out.items():
        if key == "pose_enc_list":
            print(f"  {key:18s} {len(value)} x {tuple(value[0].shape)}")
        else:
            v = np.asarray(value)
            print(f"  {key:18s} {str(tuple(v.shape)):24s} min {v.min():+.3g} max {v.max():+.3g}")
    extrinsic, intrinsic = rvggt_jax.geometry.pose_encoding_to_extri_intri(out["pose_enc"], (h, w))
    print("camera 0 extrinsic (world-to-camera):\n", np.round(np.asarray(extrinsic[0, 0]), 3))


if __name__ == "__main__":
    main()
