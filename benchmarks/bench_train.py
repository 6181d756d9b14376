"""One fine-tuning step (`rvggt_jax.train.make_train_step`: forward, VGGT loss, gradient,
clipping, AdamW) on this CPU, and the memory XLA plans for it.

1. `run`: the small benchmark layout of bench_memory.py (24 layers of width 64, DINO
   depth 1, small heads, no track head; upstream random init) at S = 8 frames of
   168 x 224, all parameters trained, with and without remat (`VGGTConfig.remat`, True:
   "full"): compile
   time, wall time of one step (median of the repeats after a warm-up) and XLA's memory
   analysis (arguments, outputs, temporaries):

       python benchmarks/bench_train.py run

2. `plan`: compile only (nothing allocated, nothing runs) of the VGGT-1B train step
   (no track head) at 518 x 518, bfloat16 aggregator compute, float32 master weights and
   AdamW moments, remat "full", for issue 25's rows: (a) everything trained, 24 frames;
   (b) `train="heads"`, 48 frames. XLA's memory analysis (arguments, outputs,
   temporaries; total = their sum less the aliased bytes, the donated state) and the
   compile time, for this host's CPU (default) or, compiled here without the device, for
   accelerators of `rvggt_jax.planning.targets` (XLA:GPU, XLA:TPU: the `[plan]` extra);
   each row names the compiler that planned it:

       python benchmarks/bench_train.py plan --target h200 cpu
       python benchmarks/bench_train.py plan --target h200 --rows all:24 --remat layers full dots
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
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


# the rows of issue 25's "Done when": (what is trained, frames)
PLAN_ROWS = (("all", 24), ("heads", 48))


def _placed(tree, device):
    """Abstract leaves of `tree` placed on `device` (a target's abstract device)."""
    where = jax.sharding.SingleDeviceSharding(device)
    return jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=where), tree)


def plan_step(target: str, train_what: str, frames: int, size: int, remat, compiler_options=None) -> dict:
    """XLA's plan of one VGGT-1B train step (no track head; bfloat16 aggregator compute,
    float32 master weights and AdamW moments) for `target` (a name of
    `rvggt_jax.planning.targets`; "cpu": this host), compiled here without the device
    (nothing runs). Returns the memory analysis (bytes), compile seconds, the compiler,
    the attention kernel, or `needed` when XLA:TPU refused the program."""
    from rvggt_jax.planning.memory import attention_kernel
    from rvggt_jax.planning.targets import exhausted_hbm, get_target, target_device

    tgt = get_target(target)
    dev = target_device(tgt)
    config = dataclasses.replace(VGGTConfig.vggt_1b(), enable_track=False).with_dtype("bfloat16").with_remat(remat)
    tc = train.TrainConfig(train=train_what)
    params = abstract_params(config)  # float32 master weights
    state = _placed(jax.eval_shape(lambda p: train.init_state(p, tc), params), dev)
    batch = _placed(_abstract_batch(1, frames, size, size), dev)
    step = train.make_train_step(config, tc, donate=True)
    options = {**tgt.options(), **(compiler_options or {})}
    t0 = time.perf_counter()
    lowered = step.lower(state, batch)
    out = dict(target=tgt.name, compiler=f"XLA:{'GPU' if tgt.platform == 'cuda' else tgt.platform.upper()} "
                                         f"({dev.device_kind}; {tgt.described_by})",
               attention=attention_kernel(lowered.as_text()), options=options, remat=config.remat,
               train=train_what, frames=frames, size=size, memory=tgt.memory()[0])
    try:
        compiled = lowered.compile(compiler_options=options or None)
    except Exception as e:  # noqa: BLE001 - XLA's error types move between versions
        exhausted = exhausted_hbm(str(e))
        if exhausted is None:
            raise
        return dict(out, needed=exhausted[0], seconds=time.perf_counter() - t0)
    return dict(out, **_mem(compiled), seconds=time.perf_counter() - t0, compiled=compiled)


def plan(args) -> list[str]:
    gib = 2 ** 30

    def cell(d, key):
        return f"{d[key] / gib:.2f}" if key in d else "n/a"

    rows = ["| target | compiler | trained | S | H x W | remat | arguments GiB | outputs GiB | temporaries GiB | "
            "total GiB | attention | compile s |", "|---|---|---|---:|---|---|---:|---:|---:|---:|---|---:|"]
    extra = dict(kv.split("=", 1) for kv in args.xla_option)
    extra = {k: {"true": True, "false": False}.get(v.lower(), v) for k, v in extra.items()}
    for target in args.target:
        for row in args.rows:
            what, frames = row.split(":")
            for remat in args.remat:
                d = plan_step(target, what, int(frames), args.size, remat, extra)
                total = cell(d, "total") if "needed" not in d else f"{d['needed'] / gib:.2f} (refused)"
                options = "".join(f", {k}={v}" for k, v in d["options"].items())
                line = (f"| {d['target']} | {d['compiler']}{options} | {what} | {frames} | {args.size} x {args.size} | "
                        f"{d['remat']} | {cell(d, 'arguments')} | {cell(d, 'outputs')} | {cell(d, 'temporaries')} | "
                        f"{total} | {d['attention']} | {d['seconds']:.0f} |")
                print(line, flush=True)
                rows.append(line)
                del d
                gc.collect()
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
    p.add_argument("--target", nargs="+", default=["cpu"], metavar="T",
                   help="compile for these (names of rvggt_jax.planning.targets: h200, h100, tpu-v6e, ...), here "
                        "without the device; default: this host's CPU")
    p.add_argument("--rows", nargs="+", default=[f"{w}:{s}" for w, s in PLAN_ROWS], metavar="TRAIN:FRAMES",
                   help="what is trained (all, heads) and the frames of each plan (default: %(default)s)")
    p.add_argument("--size", type=int, default=518)
    p.add_argument("--remat", nargs="+", default=["full"],
                   help="VGGTConfig.remat of each plan: none, layers, full, dots (default %(default)s)")
    p.add_argument("--xla-option", nargs="*", default=[], metavar="NAME=VALUE",
                   help="extra XLA compiler options (e.g. xla_gpu_enable_triton_gemm=false)")
    args = ap.parse_args()
    if args.cmd == "run":  # timed
        rvggt_jax.prefer_threaded_convolutions()  # before anything starts JAX: threaded CPU convs, as `rvggt` runs
        rvggt_jax.keep_freed_host_memory()  # each run reuses the host memory the last one freed, as `rvggt` runs
    else:  # deviceless: no device client (as `rvggt plan`)
        from rvggt_jax.app.plan_command import use_host_compilers

        use_host_compilers()
        args.remat = [{"true": True, "false": False}.get(r.lower(), r) for r in args.remat]
    rows = run(args) if args.cmd == "run" else plan(args)
    print("\n".join(rows))


if __name__ == "__main__":
    main()
