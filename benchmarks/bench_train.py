"""One fine-tuning step (`rvggt_jax.train.make_train_step`: forward, VGGT loss, gradient,
clipping, AdamW) on this CPU, and the memory XLA plans for it.

1. `run`: the small benchmark layout of bench_memory.py (24 layers of width 64, DINO
   depth 1, small heads, no track head; upstream random init) at S = 8 frames of
   168 x 224, all parameters trained, with and without remat (`VGGTConfig.remat`): compile
   time, wall time of one step (median of the repeats after a warm-up) and XLA's memory
   analysis (arguments, outputs, temporaries):

       python benchmarks/bench_train.py run

2. `plan`: compile only (nothing allocated, nothing runs) of the VGGT-1B train step
   (no track head) at 24 frames of 518 x 518, bfloat16 aggregator compute, float32
   weights and AdamW moments, remat on (and `--no-remat` for the comparison):

       python benchmarks/bench_train.py plan
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import rvggt_jax  # noqa: E402
from benchmarks.bench_memory import small_layout  # noqa: E402
from rvggt_jax import train  # noqa: E402
from rvggt_jax.config import VGGTConfig  # noqa: E402
from rvggt_jax.planning.memory import abstract_params  # noqa: E402

GB = 1e9


def _mem(compiled) -> dict:
    m = compiled.memory_analysis()
    return {"arguments": m.argument_size_in_bytes, "outputs": m.output_size_in_bytes,
            "temporaries": m.temp_size_in_bytes, "aliased": m.alias_size_in_bytes,
            "total": m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes
            - m.alias_size_in_bytes}


def _abstract_batch(b: int, s: int, h: int, w: int) -> dict:
    f = jnp.float32
    return {"images": jax.ShapeDtypeStruct((b, s, 3, h, w), f), "extrinsics": jax.ShapeDtypeStruct((b, s, 3, 4), f),
            "intrinsics": jax.ShapeDtypeStruct((b, s, 3, 3), f), "depth": jax.ShapeDtypeStruct((b, s, h, w), f),
            "world_points": jax.ShapeDtypeStruct((b, s, h, w, 3), f),
            "point_mask": jax.ShapeDtypeStruct((b, s, h, w), jnp.bool_)}


def run(args) -> list[str]:
    config = small_layout()
    tc = train.TrainConfig(learning_rate=1e-4, warmup_steps=1, total_steps=100)
    params = rvggt_jax.init_params(config, 0)
    batch = jax.device_put(train.stack([train.synthetic_example(args.frames, (args.height, args.width), seed=0)]))
    rows = ["| layout | S | H x W | remat | compile s | step median s | step min s | arguments MB | "
            "temporaries MB | total MB |", "|---|---:|---|---|---:|---:|---:|---:|---:|---:|"]
    for remat in {"both": (False, True), "off": (False,), "on": (True,)}[args.remat]:
        cfg = config.with_remat(remat)
        # a copy: the step donates its state, the next configuration starts from params again
        state = train.init_state(jax.tree.map(jnp.copy, params), tc)
        step = train.make_train_step(cfg, tc, donate=True)
        t0 = time.perf_counter()
        compiled = step.lower(state, batch).compile()
        compile_s = time.perf_counter() - t0
        mem = _mem(compiled)
        state, m = compiled(state, batch)  # warm-up
        jax.block_until_ready(m)
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            state, m = compiled(state, batch)
            jax.block_until_ready((state, m))
            times.append(time.perf_counter() - t0)
        row = (f"| small (bench_memory) | {args.frames} | {args.height} x {args.width} | {'on' if remat else 'off'} | "
               f"{compile_s:.0f} | {statistics.median(times):.2f} | {min(times):.2f} | "
               f"{mem['arguments'] / 2**20:.0f} | {mem['temporaries'] / 2**20:.0f} | {mem['total'] / 2**20:.0f} |")
        print(row, flush=True)
        rows.append(row)
    return rows


def plan(args) -> list[str]:
    config = dataclasses.replace(VGGTConfig.vggt_1b(), enable_track=False).with_dtype("bfloat16")
    tc = train.TrainConfig()
    params = abstract_params(config)  # float32 master weights
    state = jax.eval_shape(lambda p: train.init_state(p, tc), params)
    batch = _abstract_batch(1, args.frames, args.size, args.size)
    rows = ["| model | S | H x W | compute | remat | compile s | arguments GB | temporaries GB | total GB |",
            "|---|---:|---|---|---|---:|---:|---:|---:|"]
    for remat in ([True, False] if args.no_remat else [True]):
        step = train.make_train_step(config.with_remat(remat), tc, donate=True)
        t0 = time.perf_counter()
        compiled = step.lower(state, batch).compile()
        mem = _mem(compiled)
        row = (f"| VGGT-1B (no track head) | {args.frames} | {args.size} x {args.size} | bfloat16 | "
               f"{'on' if remat else 'off'} | {time.perf_counter() - t0:.0f} | {mem['arguments'] / GB:.1f} | "
               f"{mem['temporaries'] / GB:.1f} | {mem['total'] / GB:.1f} |")
        print(row, flush=True)
        rows.append(row)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--frames", type=int, default=8)
    r.add_argument("--height", type=int, default=168)
    r.add_argument("--width", type=int, default=224)
    r.add_argument("--repeats", type=int, default=3)
    r.add_argument("--remat", choices=("both", "off", "on"), default="both")
    p = sub.add_parser("plan")
    p.add_argument("--frames", type=int, default=24)
    p.add_argument("--size", type=int, default=518)
    p.add_argument("--no-remat", action="store_true", help="also plan the step without remat")
    args = ap.parse_args()
    if args.cmd == "run":  # timed
        rvggt_jax.prefer_threaded_convolutions()  # before anything starts JAX: threaded CPU convs, as `rvggt` runs
    rows = run(args) if args.cmd == "run" else plan(args)
    print("\n".join(rows))


if __name__ == "__main__":
    main()
