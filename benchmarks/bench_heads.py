"""The depth and point DPT heads on this machine: each upsampling fused with the 3x3
convolution after it (what the model runs: `heads/resize.patchwise_conv3x3`, levels 0
and 1's transposed convs with layer1_rn / layer2_rn; `resized_conv3x3`, refinenet1's
resize with output_conv1 and the last one with output_conv2's first conv) against the
compositions they replace (upsample, then convolve at the higher resolution), timed
alternately in one run on random aggregator tokens.

    python benchmarks/bench_heads.py --layout small --frames 64 --height 168 --width 224
    python benchmarks/bench_heads.py --layout vggt1b --frames 8 --height 392 --width 518

Layouts: "small" (bench_memory.py's speed layout: features 16, the last conv 8 -> 32) and
"vggt1b" (VGGT-1B's heads: features 256, output_conv1 256 -> 128, then 128 -> 32; the
small layout's 16 -> 8 is fused, its 8 -> 32 stays as written, C < O). Prints the median wall
time of each variant, their ratio and the largest relative difference of the outputs.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import rvggt_jax  # noqa: E402
from benchmarks.bench_memory import small_layout  # noqa: E402
from rvggt_jax.model.heads import dpt, resize  # noqa: E402


def build(variant: str, config, grid):
    """A jitted dense_heads for `variant` ("fused" or "resize-then-conv"): the reference
    swaps dpt's `resized_conv3x3` and `patchwise_levels` while tracing, so each program has one form throughout."""
    def heads(p, agg):
        if variant == "fused":
            return dpt.dense_heads(p, agg, config.dpt_head, grid)
        saved = dpt.resized_conv3x3, dpt.patchwise_levels
        dpt.resized_conv3x3, dpt.patchwise_levels = resize.resize_then_conv3x3, lambda params, grid_hw: {}
        try:
            return dpt.dense_heads(p, agg, config.dpt_head, grid)
        finally:
            dpt.resized_conv3x3, dpt.patchwise_levels = saved
    return jax.jit(heads)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--layout", choices=("small", "vggt1b"), default="small")
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--height", type=int, default=168)
    ap.add_argument("--width", type=int, default=224)
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args(argv)
    rvggt_jax.prefer_threaded_convolutions()
    rvggt_jax.keep_freed_host_memory()  # each run reuses the host memory the last one freed, as `rvggt` runs
    config = small_layout() if args.layout == "small" else rvggt_jax.VGGTConfig(enable_track=False)
    params = rvggt_jax.init_params(config, 0)
    hp = {k: params[k] for k in ("depth_head", "point_head")}
    grid = config.token_grid((args.height, args.width))
    tokens = grid.patch_start_idx + grid.hw[0] * grid.hw[1]
    rng = np.random.default_rng(0)
    agg = {i: jnp.asarray(rng.standard_normal((1, args.frames, tokens, 2 * config.embed_dim)).astype(np.float32))
           for i in config.dpt_head.intermediate_layer_idx}
    fns = {v: build(v, config, grid) for v in ("fused", "resize-then-conv")}
    outs = {v: jax.block_until_ready(f(hp, agg)) for v, f in fns.items()}
    diff = max(float(jnp.max(jnp.abs(outs["fused"][k] - outs["resize-then-conv"][k]))
                     / jnp.max(jnp.abs(outs["resize-then-conv"][k]))) for k in outs["fused"])
    times = {v: [] for v in fns}
    for _ in range(args.repeats):
        for v, f in fns.items():
            t = time.perf_counter()
            jax.block_until_ready(f(hp, agg))
            times[v].append(time.perf_counter() - t)
    med = {v: statistics.median(t) for v, t in times.items()}
    print(f"jax {jax.__version__}, {jax.default_backend()}; {args.layout} heads (depth + point), "
          f"{args.frames} frames of {args.height} x {args.width}, median of {args.repeats} alternations")
    for v, t in times.items():
        print(f"  {v:17s} {med[v]:.3f} s   ({', '.join(f'{x:.3f}' for x in t)})")
    print(f"  resize-then-conv / fused: {med['resize-then-conv'] / med['fused']:.2f}x; "
          f"max rel difference of the outputs {diff:.1e}")


if __name__ == "__main__":
    main()
