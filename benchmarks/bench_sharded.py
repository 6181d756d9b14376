"""Frame-sharded forward: per-device memory from XLA's plan, bytes exchanged per layer, and
a CPU wall-time run on host devices.

1. XLA's plan (compile only) of `sharded_forward` for VGGT-1B without the track head on
   images of 392 x 518, S frames over D devices, next to the single-device program's,
   presets and compute dtypes (aggregator weights in the compute dtype):

       python benchmarks/bench_sharded.py plan --frames 1000 --devices 8

2. Bytes each device receives per global layer (from the layers' static plans; no
   compile):

       python benchmarks/bench_sharded.py exchange --frames 1000 --devices 8

3. Wall time on this CPU of the small layout of bench_memory.py (random weights, 168 x
   224) on 2 host devices against one, side by side (on a 2-core machine the split
   cannot be faster: both "devices" share the same cores):

       python benchmarks/bench_sharded.py run --frames 32 --devices 2

Host devices are made with XLA_FLAGS=--xla_force_host_platform_device_count (set here
before JAX starts).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


def _devices_from_argv() -> int:
    for i, a in enumerate(sys.argv):
        if a == "--devices" and i + 1 < len(sys.argv):
            return int(sys.argv[i + 1])
    return 8


if "jax" not in sys.modules:
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                               + f" --xla_force_host_platform_device_count={_devices_from_argv()}")

import time  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rvggt_jax import VGGTConfig  # noqa: E402
from rvggt_jax.compression import Geometry, layer_plan  # noqa: E402
from rvggt_jax.planning.memory import memory_report  # noqa: E402
from rvggt_jax.parallel.sharded import frames_mesh  # noqa: E402

GB = 1e9


def _config(preset: str) -> VGGTConfig:
    cfg = VGGTConfig.vggt_1b()
    return cfg if preset == "dense" else cfg.with_compression(preset)


def plan(frames: list[int], devices: int, presets: list[str], dtypes: list[str], out: str | None) -> None:
    mesh = frames_mesh(devices)
    lines = [f"| S | preset | dtype | one device (GB) | per device of {devices} (GB) | ratio | args / temps (GB) |",
             "|---|---|---|---|---|---|---|"]
    print(lines[0], lines[1], sep="\n", flush=True)
    for s in frames:
        for preset in presets:
            for dtype in dtypes:
                cfg = _config(preset)
                one = memory_report(cfg, s, 392, 518, dtype=dtype)
                many = memory_report(cfg, s, 392, 518, dtype=dtype, mesh=mesh)
                line = (f"| {s} | {preset} | {dtype} | {one.total_bytes / GB:.1f} | {many.total_bytes / GB:.1f} | "
                        f"{many.total_bytes / one.total_bytes:.2f} | {many.argument_bytes / GB:.1f} / "
                        f"{many.temp_bytes / GB:.1f} |")
                lines.append(line)
                print(line, flush=True)
    _append(out, f"### Sharded plan, {devices} devices\n\n`python benchmarks/bench_sharded.py plan --frames "
                 f"{' '.join(map(str, frames))} --devices {devices}`\n\n" + "\n".join(lines))


def layer_exchange(cfg: VGGTConfig, layer: int, frames: int, h: int, w: int, devices: int, itemsize: int) -> dict:
    """Bytes one device receives in global layer `layer` (batch 1): what
    the global blocks exchange (`compression/`), from the layer's static plan. A ring step receives
    one device's share; an all-reduce (psum) of X bytes receives 2 (D - 1) / D X."""
    c, n = cfg.embed_dim, devices
    per_frame = cfg.patch_start_idx + h * w
    tokens = frames * per_frame
    allreduce = 2 * (n - 1) / n
    if cfg.compression.is_dense:
        return {"kind": "dense", "K/V ring": 2 * (n - 1) * (-(-tokens // n)) * c * itemsize}
    p = layer_plan(cfg.compression, layer, Geometry(frames, h, w, cfg.patch_start_idx))
    if p.kind == "dense":
        return {"kind": "dense", "K/V ring": 2 * (n - 1) * (-(-tokens // n)) * c * itemsize}
    if p.kind == "frame":
        return {"kind": "frame"}
    if p.kind == "kv":
        return {"kind": "kv", "kept rows (psum)": allreduce * p.n_kv * c * 4}
    rows = -(-(p.n_query + 1) // n)
    out = {"kind": f"merge/{p.kv_mode}"}
    if p.match == "compute":
        out["dst blocks (ring)"] = (n - 1) * (-(-p.n_dst // n)) * c * itemsize
        out["src scores (all-gather)"] = (n - 1) / n * p.n_src * 8
    out["Q/K/V sums (ring reduce-scatter)"] = 3 * (n - 1) * rows * c * 4
    # every merged row travels (with its float32 size bias); rows a layer does not keep are masked
    out["K/V ring"] = (n - 1) * rows * (2 * c * itemsize + 4)
    out["output rows (ring)"] = (n - 1) * rows * c * itemsize
    return out


def exchange(frames: int, devices: int, presets: list[str], dtypes: list[str], out: str | None) -> None:
    h, w = 392 // 14, 518 // 14
    lines = [f"| preset | dtype | layer kind | layers | received per layer, per device (MB) |", "|---|---|---|---|---|"]
    for preset in presets:
        cfg = _config(preset)
        for dtype in dtypes:
            itemsize = jnp.dtype(dtype).itemsize
            rows: dict[str, list] = {}
            for layer in range(cfg.depth):
                ex = layer_exchange(cfg, layer, frames, h, w, devices, itemsize)
                kind = ex.pop("kind") + (" (match)" if "dst blocks (ring)" in ex else "")
                key = (kind, tuple(sorted((k, round(v)) for k, v in ex.items())))
                rows.setdefault(key, []).append(layer)
            for (kind, parts), layers in rows.items():
                detail = ", ".join(f"{k} {v / 1e6:.0f}" for k, v in parts) or "nothing"
                total = sum(v for _, v in parts) / 1e6
                lines.append(f"| {preset} | {dtype} | {kind} | {len(layers)} | {total:.0f}: {detail} |")
    print("\n".join(lines))
    _append(out, f"### Exchanged per global layer, {frames} frames of 392 x 518 over {devices} devices\n\n"
                 f"`python benchmarks/bench_sharded.py exchange --frames {frames} --devices {devices}`\n\n"
                 + "\n".join(lines))


def run(frames: int, devices: int, repeats: int, out: str | None) -> None:
    from benchmarks.bench_memory import random_params, small_layout

    import rvggt_jax
    from rvggt_jax.parallel.sharded import sharded_forward

    cfg = small_layout()
    params = random_params(cfg)
    images = jax.random.uniform(jax.random.PRNGKey(0), (1, frames, 3, 168, 224))
    mesh = frames_mesh(devices)
    lines = [f"| preset | one device (s) | {devices} host devices (s) | ratio |", "|---|---|---|---|"]
    for preset in ("dense", "regime"):
        c = cfg if preset == "dense" else cfg.with_compression(preset)
        one = jax.jit(rvggt_jax.rvggt_forward)
        many = jax.jit(lambda p, x, c=c: sharded_forward(p, x, c, mesh))
        times = {"one": [], "many": []}
        jax.block_until_ready(one(params, images, c))
        jax.block_until_ready(many(params, images))
        for _ in range(repeats):  # interleaved: the machine is shared and noisy
            for name, fn, args in (("one", one, (params, images, c)), ("many", many, (params, images))):
                t = time.perf_counter()
                jax.block_until_ready(fn(*args))
                times[name].append(time.perf_counter() - t)
        a, b = float(np.median(times["one"])), float(np.median(times["many"]))
        lines.append(f"| {preset} | {a:.2f} | {b:.2f} | {b / a:.2f} |")
        print(lines[-1], flush=True)
    _append(out, f"### CPU wall time, {frames} frames of 168 x 224, small layout\n\n"
                 f"`python benchmarks/bench_sharded.py run --frames {frames} --devices {devices}`\n\n"
                 + "\n".join(lines))


def _append(path: str | None, text: str) -> None:
    if path:
        with open(path, "a") as f:
            f.write(text + "\n\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=("plan", "exchange", "run"))
    ap.add_argument("--frames", type=int, nargs="+", default=[1000])
    ap.add_argument("--devices", type=int, default=8)
    ap.add_argument("--presets", nargs="+", default=["dense", "regime"])
    ap.add_argument("--dtypes", nargs="+", default=["float32", "bfloat16"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=None, help="append the table to this markdown file")
    args = ap.parse_args()
    if args.what == "run":  # timed
        import rvggt_jax

        rvggt_jax.prefer_threaded_convolutions()  # before anything starts JAX: threaded CPU convs, as `rvggt` runs
        rvggt_jax.keep_freed_host_memory()  # each run reuses the host memory the last one freed, as `rvggt` runs
    if args.what == "plan":
        plan(args.frames, args.devices, args.presets, args.dtypes, args.out)
    elif args.what == "exchange":
        exchange(args.frames[0], args.devices, args.presets, args.dtypes, args.out)
    else:
        run(args.frames[0], args.devices, args.repeats, args.out)


if __name__ == "__main__":
    main()
