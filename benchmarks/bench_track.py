"""Track head cost against the aggregator, for a growing number of query points.

Random weights (no checkpoint needed, no torch): every parameter of the converted tree
for the chosen config is drawn from its shape (kernels N(0, 1/fan_in), norm scales 1,
biases 0, LayerScale 0.1, tokens N(0, 0.02)). The aggregator runs once per input; the track
head then runs on its kept layers for each N.

Default config (CPU-sized; pass --vggt-1b-track for the published track-head widths):
  aggregator: depth 24, embed_dim 256, 4 heads, DINO patch embed depth 2;
  track head: DPT features 64, out_channels (32, 64, 128, 128), tracker hidden 192,
  corr_levels 7, corr_radius 4, stride 2, 4 iterations (upstream's levels/radius/iters);
  input: 1 x 8 frames of 168 x 224.

    python benchmarks/bench_track.py [--frames 8] [--num-queries 64 256 1024]

Time: median wall time of `--repeats` jitted runs after a warm-up (compile excluded).
Memory: XLA's buffer assignment of each compiled executable (arguments + outputs + temp),
i.e. the peak device memory that call needs; RSS growth is not meaningful across calls.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rvggt_jax.model.aggregator import aggregator_forward  # noqa: E402
import rvggt_jax  # noqa: E402
from rvggt_jax.config import DinoConfig, DPTHeadConfig, TrackHeadConfig, VGGTConfig  # noqa: E402
from rvggt_jax.model.heads.track import track_head  # noqa: E402


def bench_config(args) -> VGGTConfig:
    if args.vggt_1b_track:
        track = TrackHeadConfig()  # features 128, hidden 384, levels 7, radius 4
        dpt = DPTHeadConfig(features=256, out_channels=(256, 512, 1024, 1024))
    else:
        f = args.features
        track = TrackHeadConfig(features=f, hidden_size=args.hidden)
        dpt = DPTHeadConfig(features=f, out_channels=(f // 2, f, 2 * f, 2 * f))
    return VGGTConfig(embed_dim=args.embed_dim, num_heads=args.heads, depth=24,
                      dino=DinoConfig(depth=args.dino_depth, num_heads=args.heads),
                      dpt_head=dpt, track_head=track).validate()


def random_params(config: VGGTConfig, seed: int = 0) -> dict:
    """A random tree for `config` with upstream's initialisation (`rvggt_jax.init_params`)."""
    return rvggt_jax.init_params(config, seed)


def memory_mb(compiled) -> float:
    m = compiled.memory_analysis()
    if m is None:
        return float("nan")
    total = m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes - m.alias_size_in_bytes
    return total / 2 ** 20


def timed(fn, args, repeats: int) -> float:
    jax.block_until_ready(fn(*args))  # warm-up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--height", type=int, default=168)
    ap.add_argument("--width", type=int, default=224)
    ap.add_argument("--num-queries", type=int, nargs="+", default=[64, 256, 1024])
    ap.add_argument("--embed-dim", type=int, default=256)
    ap.add_argument("--heads", type=int, default=4)
    ap.add_argument("--dino-depth", type=int, default=2)
    ap.add_argument("--features", type=int, default=64, help="track/DPT feature width")
    ap.add_argument("--hidden", type=int, default=192, help="tracker transformer width")
    ap.add_argument("--vggt-1b-track", action="store_true", help="VGGT-1B track head and DPT widths")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    rvggt_jax.prefer_threaded_convolutions()  # before anything starts JAX: threaded CPU convs, as `rvggt` runs
    rvggt_jax.keep_freed_host_memory()  # each run reuses the host memory the last one freed, as `rvggt` runs

    config = bench_config(args)
    t = config.track_head
    params = random_params(config)
    rng = np.random.default_rng(0)
    images = jnp.asarray(rng.random((1, args.frames, 3, args.height, args.width), dtype=np.float32))
    keep = tuple(config.track_layer_idx)

    agg_fn = jax.jit(lambda p, im: aggregator_forward(p, im, config, keep)[0])
    agg_c = agg_fn.lower(params["aggregator"], images).compile()
    agg_time = timed(agg_c, (params["aggregator"], images), args.repeats)
    agg_mem = memory_mb(agg_c)
    aggregated = agg_c(params["aggregator"], images)

    print(f"jax {jax.__version__} on {jax.devices()[0].platform} ({os.cpu_count()} cpus)")
    print(f"aggregator: depth {config.depth}, embed_dim {config.embed_dim}, {config.num_heads} heads, "
          f"DINO depth {config.dino.depth}; input 1 x {args.frames} x {args.height} x {args.width}")
    print(f"track head: features {t.features}, DPT out_channels {config.track_out_channels}, hidden {t.hidden_size}, "
          f"corr_levels {t.corr_levels}, corr_radius {t.corr_radius}, stride {t.stride}, iters {t.iters}")
    print()
    print("|    N | aggregator ms | track ms | track/agg | agg MiB | track MiB | track compile s |")
    print("|-----:|--------------:|---------:|----------:|--------:|----------:|----------------:|")
    hh, ww = args.height, args.width
    for n in args.num_queries:
        q = jnp.asarray(rng.uniform([0, 0], [ww - 1, hh - 1], size=(1, n, 2)).astype(np.float32))
        grid = config.token_grid(images.shape[-2:])
        fn = jax.jit(lambda p, a, im, qq: track_head(p, a, config.track_head_config, grid, qq))
        t0 = time.perf_counter()
        comp = fn.lower(params["track_head"], aggregated, images, q).compile()
        compile_s = time.perf_counter() - t0
        tr_time = timed(comp, (params["track_head"], aggregated, images, q), args.repeats)
        print(f"| {n:4d} | {agg_time * 1e3:13.1f} | {tr_time * 1e3:8.1f} | {tr_time / agg_time:9.2f} | "
              f"{agg_mem:7.1f} | {memory_mb(comp):9.1f} | {compile_s:15.1f} |", flush=True)


if __name__ == "__main__":
    main()
