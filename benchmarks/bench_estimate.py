"""The time estimate `rvggt reconstruct` prints before a long run, against measured forwards.

    python benchmarks/bench_estimate.py                    # every case below (~20 min on 2 cores)
    python benchmarks/bench_estimate.py --cases tiny:3:112:154 small:32:168:224
    python benchmarks/bench_estimate.py --json out.jsonl   # also the raw rows (the fit's input)

A case is NAME:FRAMES:HEIGHT:WIDTH[:PRESET]; NAME is one of
  tiny   the test fixture's config (tests/data/vggt_tiny: width 32, 24 layers, DINO depth 2)
  small  `VGGTConfig.rvggt_small()` (width 128, 6 layers, DINO depth 3, DPT 32)
  mid    width 384 (6 heads of 64), 24 layers, DINO depth 12, DPT 128 (64, 128, 256, 256)
  1b     the VGGT-1B layout (width 1024, 16 heads, DINO ViT-L, DPT 256): not a default case,
         it needs > 10 GB of free memory (4.8 GB of weights)
with random weights (the values do not change the time) and random images, no track head
(`rvggt reconstruct` runs without it). Per case, in this order: the estimate
(`planning.estimate.estimate_forward`, its probe measured afresh, as a new `rvggt`
process would), the compilation (`jit(...).lower(...).compile()`, no persistent cache),
then the forward run `--repeats` times (the median is "actual"; the first run after
the compilation is one of them). Prints estimate / actual for the forward and for the
compilation.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import rvggt_jax  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TINY_CONFIG = ROOT / "tests" / "data" / "vggt_tiny" / "config.json"

DEFAULT_CASES = (
    "tiny:3:112:154", "tiny:6:392:518", "small:8:168:224", "small:32:168:224", "small:128:168:224",
    "small:128:168:224:regime", "mid:8:168:224", "mid:24:168:224", "mid:24:168:224:regime",
    # not among the cases the constants were fitted on
    "small:48:252:336", "mid:4:392:518",
)


def config_of(name: str):
    from rvggt_jax.config import CameraHeadConfig, DinoConfig, DPTHeadConfig, VGGTConfig

    if name == "tiny":
        config = VGGTConfig.from_json(TINY_CONFIG)
    elif name == "small":
        config = VGGTConfig.rvggt_small()
    elif name == "1b":
        config = VGGTConfig.vggt_1b()
    elif name == "mid":
        config = VGGTConfig(embed_dim=384, depth=24, num_heads=6, dino=DinoConfig(depth=12, num_heads=6),
                            camera_head=CameraHeadConfig(num_heads=6),
                            dpt_head=DPTHeadConfig(features=128, out_channels=(64, 128, 256, 256)))
    else:
        raise SystemExit(f"unknown config {name!r}: tiny, small, mid or 1b")
    return dataclasses.replace(config, enable_track=False).validate()


def random_params(config, seed: int = 0):
    """Random float32 weights of the model's shapes (normal, std 0.02: finite activations;
    drawn by numpy, much faster than the upstream initialisers on a small CPU)."""
    import jax
    import numpy as np

    from rvggt_jax.model.modules import init_params

    shapes = jax.eval_shape(init_params, config, jax.random.PRNGKey(0))
    rng = np.random.default_rng(seed)
    return jax.tree.map(lambda s: jax.numpy.asarray(0.02 * rng.standard_normal(s.shape, dtype=np.float32)), shapes)


def measure(spec: str, repeats: int) -> dict:
    import jax
    import numpy as np

    from rvggt_jax.model.forward import rvggt_forward
    from rvggt_jax.planning import estimate

    name, frames, height, width, *rest = spec.split(":")
    frames, height, width = int(frames), int(height), int(width)
    config = config_of(name)
    preset = rest[0] if rest else "dense"
    if preset != "dense":
        config = config.with_compression(preset)
    params = random_params(config)
    images = jax.numpy.asarray(np.random.default_rng(1).random((1, frames, 3, height, width), dtype=np.float32))

    estimate._RATES.clear()  # a fresh probe, as a new `rvggt` process measures it
    t0 = time.perf_counter()
    est = estimate.estimate_forward(config, frames, height, width, alternative=None)
    est_s = time.perf_counter() - t0

    t0 = time.perf_counter()
    compiled = jax.jit(rvggt_forward).lower(params, images, config).compile()
    compile_s = time.perf_counter() - t0
    runs = []
    while len(runs) < repeats or (len(runs) < 3 and max(runs) < 5.0):  # short cases: the median of 3
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(params, images, config))
        runs.append(time.perf_counter() - t0)
    rate_after = estimate._probe()  # the fit reads the rate around the run (a shared machine's load moves)
    return dict(case=spec, rate_after=rate_after, config=name, frames=frames, height=height, width=width, preset=preset,
                rate=est.rate, estimate_call_s=est_s, est_forward_s=est.seconds, est_compile_s=est.compile_seconds,
                forward_s=statistics.median(runs), runs=runs, compile_s=compile_s, **est.flops)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="+", default=list(DEFAULT_CASES))
    ap.add_argument("--repeats", type=int, default=1, help="forward runs per case (median); cases under 5 s run 3x")
    ap.add_argument("--json", type=Path, help="append each case's raw row (FLOPs by part, times, probe rate) here")
    args = ap.parse_args(argv)
    rvggt_jax.prefer_threaded_convolutions()  # as `rvggt` runs: before anything starts JAX
    rvggt_jax.keep_freed_host_memory()

    print(f"{'case':28s} {'GFLOP':>7s} {'probe GF/s':>10s} {'est s':>7s} {'actual s':>8s} {'est/act':>7s} "
          f"{'est compile':>11s} {'compile s':>9s} {'est/act':>7s}", flush=True)
    for spec in args.cases:
        row = measure(spec, args.repeats)
        if args.json:
            with open(args.json, "a") as f:
                f.write(json.dumps(row) + "\n")
        print(f"{spec:28s} {row['total'] / 1e9:7.0f} {row['rate'] / 1e9:10.0f} {row['est_forward_s']:7.1f} "
              f"{row['forward_s']:8.1f} {row['est_forward_s'] / row['forward_s']:7.2f} {row['est_compile_s']:11.0f} "
              f"{row['compile_s']:9.0f} {row['est_compile_s'] / row['compile_s']:7.2f}", flush=True)


if __name__ == "__main__":
    main()
