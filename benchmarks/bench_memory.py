"""Memory of long sequences, and the CPU speed of RegimeVGGT against dense.

1. XLA's plan (`rvggt_jax.memory_report`: compile only, nothing runs) of the VGGT-1B
   forward, without the track head, on images of 392 x 518, for S frames, presets and
   compute dtypes (the aggregator's weights in the compute dtype, as
   `load_pretrained(..., param_dtype=...)` loads them):

       python benchmarks/bench_memory.py plan --frames 100 300 1000

   `--param-dtype float32` plans the compute dtype with float32 weights instead (what
   upstream's autocast runs: the weights stay float32, only the matmuls run in bf16):

       python benchmarks/bench_memory.py plan --frames 1000 --dtypes bfloat16 --param-dtype float32

   `--target` compiles for accelerators that need not be here (XLA's GPU and TPU
   compilers on this host, the `[plan]` extra; names in `rvggt_jax.planning.targets`) and
   holds each plan against the target's memory, in GiB:

       python benchmarks/bench_memory.py plan --frames 1000 --target h200 tpu-v6e --presets dense regime

2. A real run on this CPU of a small layout (24 layers of width 64, one head of 64, DINO
   depth 1, small heads; random weights) on 168 x 224 images: wall time (median of the
   repeats, the presets interleaved) of the whole forward and of the aggregator alone (the
   part the cost model prices: `cost_report`'s predicted trunk speedup sits next to it),
   the process' peak RSS growth and XLA's plan:

       python benchmarks/bench_memory.py run --frames 64 128 256

The tables go to stdout (and, with --out, are appended to a markdown file).
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import resource
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import rvggt_jax  # noqa: E402
from rvggt_jax.model.aggregator import aggregator_forward  # noqa: E402
from rvggt_jax.config import CameraHeadConfig, DinoConfig, DPTHeadConfig, VGGTConfig  # noqa: E402


def small_layout() -> VGGTConfig:
    """24 aggregator layers of width 64 with one head of 64, DINO depth 1, small heads."""
    return VGGTConfig(embed_dim=64, num_heads=1, dino=DinoConfig(depth=1, num_heads=1),
                      camera_head=CameraHeadConfig(num_heads=1, trunk_depth=1),
                      dpt_head=DPTHeadConfig(features=16, out_channels=(8, 16, 32, 32)), enable_track=False)


def random_params(config: VGGTConfig, seed: int = 0) -> dict:
    """A random tree for `config` with upstream's initialisation (`rvggt_jax.init_params`)."""
    return rvggt_jax.init_params(config, seed)


def plan(args) -> list[str]:
    if args.target:
        return plan_targets(args)
    rows = ["| S | preset | dtype | weights | total GB | arguments GB | outputs GB | temporaries GB | vs dense |",
            "|---:|---|---|---|---:|---:|---:|---:|---:|"]
    dense_total = None
    for s, dtype, preset, rep in _reports(args):
        if preset == args.presets[0]:
            dense_total = None  # a new (frames, dtype) group
        if preset == "dense":
            dense_total = rep.total_bytes
        ratio = f"{rep.total_bytes / dense_total:.2f}x" if dense_total else ""
        rows.append(_print(f"| {s} | {preset} | {dtype} | {rep.param_dtype} | {rep.total_bytes / 1e9:.1f} | "
                           f"{rep.argument_bytes / 1e9:.1f} | {rep.output_bytes / 1e9:.1f} | "
                           f"{rep.temp_bytes / 1e9:.1f} | {ratio} |"))
    return rows


def _reports(args, **target):
    """(frames, dtype, preset, `memory_report`) of VGGT-1B (no track head) for every
    frames x dtype x preset of the arguments, in that order."""
    cfg = dataclasses.replace(VGGTConfig.vggt_1b(), enable_track=False)
    for s in args.frames:
        for dtype in args.dtypes:
            param_dtype = dtype if args.param_dtype == "compute" else args.param_dtype
            for preset in args.presets:
                yield s, dtype, preset, rvggt_jax.memory_report(cfg.with_compression(preset), s, args.height,
                                                                args.width, dtype=dtype, param_dtype=param_dtype,
                                                                image_dtype=args.images, **target)
                gc.collect()


def warm_up(target: str) -> float:
    """Compile one small attention program for `target` first and return its seconds: the
    compiler's one-time start-up in this process (XLA:GPU's LLVM, ptxas and cuDNN, libtpu)
    then lands in no preset's compile time, so the presets' times compare whichever
    compiles first."""
    from rvggt_jax.ops.attention import attention
    from rvggt_jax.planning.targets import get_target, target_device

    x = jax.ShapeDtypeStruct((1, 256, 2, 64), jnp.bfloat16,
                             sharding=jax.sharding.SingleDeviceSharding(target_device(target)))
    t0 = time.perf_counter()
    try:
        jax.jit(lambda q: attention(q, q, q)).lower(x).compile(
            compiler_options=get_target(target).options())
    except Exception as e:  # noqa: BLE001 - a failed warm-up only leaves the start-up in the first row
        print(f"{target}: warm-up failed ({type(e).__name__}: {str(e)[:200]})", flush=True)
    return time.perf_counter() - t0


def _print(row: str) -> str:
    print(row, flush=True)
    return row


def plan_targets(args) -> list[str]:
    """The plan of every target x frames x dtype x preset, held against the target's memory."""
    gib = 2 ** 30

    def cell(b):
        return "n/a" if b is None else f"{b / gib:.2f}"

    rows = ["| target | S | preset | dtype | weights | arguments GiB | outputs GiB | temporaries GiB | total GiB | "
            "memory GiB | fits | attention | compile s |",
            "|---|---:|---|---|---|---:|---:|---:|---:|---:|---|---|---:|"]
    for target in args.target:
        print(f"{target}: warm-up compile {warm_up(target):.1f} s (not in any row)", flush=True)
        for s, dtype, preset, rep in _reports(args, target=target, devices=args.devices):
            fits = {True: "yes (XLA:TPU compiled it for the chip)" if rep.compiler_checked else "yes",
                    False: "no (XLA:TPU refused it)" if rep.exhausted else "no", None: "?"}[rep.fits]
            rows.append(_print(
                f"| {rep.target}{f' x{rep.devices}' if rep.devices > 1 else ''} | {s} | {preset} | {dtype} | "
                f"{rep.param_dtype} | {cell(rep.argument_bytes)} | {cell(rep.output_bytes)} | "
                f"{cell(rep.temp_bytes)} | {cell(rep.total_bytes)} | {cell(rep.memory_bytes)} | {fits} | "
                f"{rep.attention or 'n/a'} | {rep.compile_seconds:.0f} |"))
    return rows


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def run(args) -> list[str]:
    base = small_layout()
    params = random_params(base)
    rows = ["| S | preset | wall median s | wall min s | speedup (wall) | aggregator s | aggregator speedup | "
            "predicted (aggregator) | measured/predicted (aggregator) | peak RSS growth MiB | XLA total MiB |",
            "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for s in args.frames:
        images = jnp.asarray(np.random.default_rng(s).random((1, s, 3, args.height, args.width)), jnp.float32)
        fns, times, rss, plans = {}, {p: [] for p in args.presets}, {}, {}
        agg_times = {p: [] for p in args.presets}
        for preset in args.presets:
            cfg = base.with_compression(preset).with_dtype(args.dtype)
            before = peak_rss_mb()
            fn = jax.jit(rvggt_jax.rvggt_forward)
            plans[preset] = fn.lower(params, images, cfg).compile().memory_analysis()
            jax.block_until_ready(fn(params, images, cfg)["depth"])  # compile + first run
            rss[preset] = peak_rss_mb() - before
            agg = jax.jit(lambda p, x, cfg=cfg: {i: t.array() for i, t in aggregator_forward(
                p["aggregator"], x, cfg, cfg.needed_layers(False))[0].items()})
            jax.block_until_ready(agg(params, images))
            fns[preset] = (fn, cfg, agg)
        for r in range(args.repeats):
            order = args.presets[r % len(args.presets):] + args.presets[:r % len(args.presets)]
            for preset in order:
                fn, cfg, agg = fns[preset]
                t0 = time.perf_counter()
                jax.block_until_ready(fn(params, images, cfg)["depth"])
                times[preset].append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                jax.block_until_ready(agg(params, images))
                agg_times[preset].append(time.perf_counter() - t0)
        dense = statistics.median(times["dense"]) if "dense" in times else None
        dense_agg = statistics.median(agg_times["dense"]) if "dense" in agg_times else None
        for preset in args.presets:
            med, agg_med = statistics.median(times[preset]), statistics.median(agg_times[preset])
            pred = rvggt_jax.cost_report(base.with_compression(preset), s, args.height, args.width)["predicted_speedup"]
            speed = dense / med if dense else float("nan")
            agg_speed = dense_agg / agg_med if dense_agg else float("nan")
            m = plans[preset]
            total = (m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes
                     - m.alias_size_in_bytes) / 2**20
            row = (f"| {s} | {preset} | {med:.2f} | {min(times[preset]):.2f} | {speed:.2f}x | {agg_med:.2f} | "
                   f"{agg_speed:.2f}x | {pred:.2f}x | {agg_speed / pred:.2f} | {rss[preset]:.0f} | {total:.0f} |")
            print(row, flush=True)
            rows.append(row)
        del fns
        gc.collect()
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="mode", required=True)
    p = sub.add_parser("plan", help="XLA's memory plan of VGGT-1B (compile only)")
    p.add_argument("--frames", type=int, nargs="+", default=[100, 300, 1000])
    p.add_argument("--presets", nargs="+", default=["dense", "regime", "fastvggt", "avggt"])
    p.add_argument("--dtypes", nargs="+", default=["float32", "bfloat16"])
    p.add_argument("--height", type=int, default=392)
    p.add_argument("--width", type=int, default=518)
    p.add_argument("--param-dtype", default="compute", choices=["compute", "float32", "bfloat16"],
                   help="the aggregator's weight dtype: the compute dtype (as `load_pretrained(..., "
                        "param_dtype=...)` and the CLI load them; default) or a fixed one")
    p.add_argument("--images", default="uint8", choices=["uint8", "float32"],
                   help="the images' dtype in the program: uint8 as `rvggt reconstruct` passes them (default)")
    p.add_argument("--target", nargs="+", default=None, metavar="T",
                   help="compile for these accelerators without them (h200, tpu-v6e, ...; "
                        "rvggt_jax.planning.targets) and hold each plan against its memory")
    p.add_argument("--devices", type=int, default=1, help="with --target: frames split over N of its devices")
    r = sub.add_parser("run", help="a real CPU run of the small layout")
    r.add_argument("--frames", type=int, nargs="+", default=[64, 128, 256])
    r.add_argument("--presets", nargs="+", default=["dense", "regime"])
    r.add_argument("--dtype", default="float32")
    r.add_argument("--height", type=int, default=168)
    r.add_argument("--width", type=int, default=224)
    r.add_argument("--repeats", type=int, default=3)
    for q in (p, r):
        q.add_argument("--out", default=None, help="append the markdown table to this file")
    args = ap.parse_args(argv)
    if args.mode == "run":  # timed
        rvggt_jax.prefer_threaded_convolutions()  # before anything starts JAX: threaded CPU convs, as `rvggt` runs
        rvggt_jax.keep_freed_host_memory()  # each run reuses the host memory the last one freed, as `rvggt` runs
    if args.mode == "plan" and args.target:  # deviceless: no device client (as `rvggt plan`)
        from rvggt_jax.app.plan_command import use_host_compilers

        use_host_compilers()
    print(f"jax {jax.__version__}, {jax.devices()[0].device_kind}, {jax.device_count()} device(s)", flush=True)
    rows = plan(args) if args.mode == "plan" else run(args)
    if args.out:
        with open(args.out, "a") as f:
            f.write(f"\n`python benchmarks/bench_memory.py {' '.join(sys.argv[1:] if argv is None else argv)}`\n\n")
            f.write("\n".join(rows) + "\n")


if __name__ == "__main__":
    main()
