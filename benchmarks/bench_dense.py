"""Dense forward: jitted rvggt-jax against the upstream PyTorch VGGT, interleaved in one run.

Both load the same random-weight checkpoint (written by the upstream model, read by
`rvggt_jax.load_pretrained`) and run the same images. torch and the upstream source are
benchmark-only dependencies:

    pip install torch==2.13.0 huggingface_hub einops
    python benchmarks/bench_dense.py --vggt-src /path/to/vggt-checkout

Prints per-run times, the medians, the speed ratio and the parity of the outputs.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import rvggt_jax  # noqa: E402
from benchmarks.upstream import build_upstream, save_checkpoint  # noqa: E402
from rvggt_jax.config import CameraHeadConfig, DinoConfig, DPTHeadConfig, VGGTConfig  # noqa: E402


def bench_config(embed_dim: int, heads: int, dino_depth: int, features: int) -> VGGTConfig:
    return VGGTConfig(
        embed_dim=embed_dim, num_heads=heads, depth=24,
        dino=DinoConfig(depth=dino_depth, num_heads=heads),
        camera_head=CameraHeadConfig(num_heads=heads),
        dpt_head=DPTHeadConfig(features=features,
                               out_channels=(features // 2, features, 2 * features, 2 * features)),
        enable_track=False,
    ).validate()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--vggt-src", required=True, help="folder holding the upstream vggt/ package")
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--height", type=int, default=168)
    ap.add_argument("--width", type=int, default=224)
    ap.add_argument("--embed-dim", type=int, default=256)
    ap.add_argument("--heads", type=int, default=4, help="head dimension = embed-dim / heads (64)")
    ap.add_argument("--dino-depth", type=int, default=12)
    ap.add_argument("--features", type=int, default=64, help="DPT feature width")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op threads (the machine's cores)")
    ap.add_argument("--layout", choices=("small", "1b"), default="small",
                    help="small: the widths above; 1b: the full VGGT-1B layout (embed 1024, 16 heads, "
                         "DINO ViT-L, DPT 256), random weights, ~5 GB")
    args = ap.parse_args(argv)
    rvggt_jax.prefer_threaded_convolutions()  # before anything starts JAX: threaded CPU convs, as `rvggt` runs
    rvggt_jax.keep_freed_host_memory()  # each run reuses the host memory the last one freed, as `rvggt` runs

    import torch

    torch.set_num_threads(args.threads)
    if args.layout == "1b":
        config = dataclasses.replace(VGGTConfig.vggt_1b(), enable_track=False).validate()
    else:
        config = bench_config(args.embed_dim, args.heads, args.dino_depth, args.features)
    model = build_upstream(config, args.vggt_src)
    with tempfile.TemporaryDirectory() as tmp:
        save_checkpoint(model, config, tmp)
        params, config = rvggt_jax.load_pretrained(tmp)

    rng = np.random.default_rng(0)
    images = rng.random((1, args.frames, 3, args.height, args.width), dtype=np.float32)
    fwd = jax.jit(rvggt_jax.rvggt_forward)
    images_j = jax.device_put(images)

    def run_jax():
        return jax.block_until_ready(fwd(params, images_j, config))

    def run_torch():
        with torch.inference_mode():
            return model(torch.from_numpy(images))

    t0 = time.perf_counter()
    out_j = run_jax()
    compile_s = time.perf_counter() - t0
    out_t = run_torch()
    errs = {k: float(np.abs(np.asarray(out_j[k]) - out_t[k].numpy()).max() / np.abs(out_t[k].numpy()).max())
            for k in ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf")}

    times = {"jax": [], "torch": []}
    for _ in range(args.repeats):  # interleaved, so machine noise hits both alike
        for name, fn in (("torch", run_torch), ("jax", run_jax)):
            t = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t)

    med = {k: statistics.median(v) for k, v in times.items()}
    shape = dataclasses.asdict(config)
    print(f"config: depth {shape['depth']}, embed_dim {config.embed_dim}, heads {config.num_heads} "
          f"(head dim {config.head_dim}), dino depth {config.dino.depth}, DPT features {config.dpt_head.features}")
    print(f"input: {args.frames} frames of {args.height}x{args.width}, float32, torch threads {args.threads}, "
          f"jax {jax.__version__} on {jax.devices()[0].platform}, torch {torch.__version__}")
    print(f"jax compile + first run: {compile_s:.1f} s")
    for k in ("torch", "jax"):
        print(f"{k:6s} runs: " + ", ".join(f"{t:.2f}" for t in times[k]) + f"  median {med[k]:.3f} s")
    print(f"speed-up jax over torch (median): {med['torch'] / med['jax']:.2f}x")
    print("parity (max rel err): " + ", ".join(f"{k} {v:.1e}" for k, v in errs.items()))


if __name__ == "__main__":
    main()
