"""One command for a lent GPU: environment, parity, speed and memory of VGGT-1B (issue 24).

    python benchmarks/gpu_check.py                 # ~9 minutes on one H200 (--budget 540)
    python benchmarks/gpu_check.py --quick         # 100 frames only, one timed run
    python benchmarks/gpu_check.py --dense-1000    # also dense at 1000 frames (~1e17 FLOP)
    python benchmarks/gpu_check.py --smoke         # tiny layout, any machine (CPU: a few minutes)
    python benchmarks/gpu_check.py --only regime@1000 --parity-variants float32

Parts, each caught and reported (a failing part never stops the next):
1. env: jax, jaxlib, CUDA plugin, CUDA/cuDNN versions, the device and its memory. The
   package is installed (`pip install -e .`) if it does not import.
2. parity: the tiny upstream fixture (tests/data/vggt_tiny) through `load_pretrained`:
   float32 at rel_err = max|ours - ref| / max|ref| <= 1e-4 (the config's own precision,
   "highest" for float32), float32 at the platform's default precision (TF32 on a GPU,
   reported against 1e-2), bfloat16 within twice upstream's own bf16 deviation; the
   ring's share kernel (cuDNN with its log-sum-exp) against the blocked one, values and
   gradients.
3. speed: `regime` and dense at 100 frames, `regime` at 1000, both at 300 when the budget
   leaves time (most wanted first; `--only` picks) (VGGT-1B, no track head,
   bf16 compute and aggregator weights, random weights, 392 x 518): trace + compile time,
   the median of timed runs after one warm-up, the device's peak bytes, XLA's plan of the
   same compiled program, and whether it calls cuDNN's flash attention (`__cudnn$fmha`).
   Each program runs in a fresh process (JAX cannot reset a device's peak) with a timeout.
   On a GPU compiling allocates on the device (38-40 GB of peak on an H200 whatever the
   program; most likely XLA's autotuner), so each program is compiled into JAX's persistent cache
   by one process and loaded and run by the next, whose peak is the run's alone (the
   peak before the runs is reported too; --one-process does both in one).
4. plan: the same programs compiled deviceless for the H200 (`rvggt_jax.planning.targets`'
   "h200": XLA's h200.txtpb, shipped in rvggt_jax/planning/gpu_specs/; JAX_PLATFORMS=cpu,
   XLA's CUDA compiler on the host), in the background while 2-3 run.

The report goes to stdout and to --out (default $OUT, else ./gpu_check_out) as
gpu_check.json and gpu_check.md; the last line is a one-line summary.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# The parent process never imports jax: a CUDA client would preallocate most of the GPU
# and starve the workers. Workers import it (after sys.path gets the repository).
REPO = Path(__file__).resolve().parents[1]
TARGET = "h200"  # the deviceless plan's target (rvggt_jax.planning.targets)
TINY = REPO / "tests" / "data" / "vggt_tiny"
RESULT = "GPU_CHECK_RESULT "  # prefix of each result line a worker prints
FMHA = "__cudnn$fmha"
GB = 1e9

# Tolerances copied from the tests (a benchmark does not import tests/): float32 from
# tests/model/test_forward.py, the tracker's last iteration from tests/helpers/tolerances.py,
# upstream's own bf16 deviation from tests/model/test_bf16.py (bf16 passes within 2x).
F32_TOL = 1e-4
# float32 at the platform's default precision (TF32 on an NVIDIA GPU: a 10-bit mantissa):
# what a user who asks for speed over exactness gets, reported against a TF32-sized bound
TF32_TOL = 1e-2
TRACK_TOL = {"track": 6e-3, "vis": 9e-2, "conf": 2e-2}
UPSTREAM_BF16 = {"aggregated": 1.1e-2, "pose_enc": 1.6e-2, "depth": 7.0e-3, "depth_conf": 7.9e-3,
                 "world_points": 1.9e-2, "world_points_conf": 5.9e-3}
LAYERS = (0, 4, 11, 17, 23)
HEADS = ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf")


# ---------------------------------------------------------------------------------------
# Workers: each runs in a fresh process and prints RESULT lines (JSON) as it goes, so a
# worker that times out still reports what it finished.
# ---------------------------------------------------------------------------------------

def emit(**fields) -> None:
    print(RESULT + json.dumps(fields), flush=True)


def make_config(spec: dict):
    """VGGT-1B ("1b") or a small layout ("small", for --smoke), no track head, with the
    spec's preset and compute dtype."""
    from rvggt_jax.config import CameraHeadConfig, DinoConfig, DPTHeadConfig, VGGTConfig

    if spec["layout"] == "1b":
        cfg = dataclasses.replace(VGGTConfig(), enable_track=False)
    else:  # benchmarks/bench_memory.py's small layout: 24 layers of width 64
        cfg = VGGTConfig(embed_dim=64, num_heads=1, dino=DinoConfig(depth=1, num_heads=1),
                         camera_head=CameraHeadConfig(num_heads=1, trunk_depth=1),
                         dpt_head=DPTHeadConfig(features=16, out_channels=(8, 16, 32, 32)), enable_track=False)
    return cfg.with_compression(spec["preset"]).with_dtype(spec["dtype"])


def worker_env(spec: dict) -> None:
    """Versions, devices and whether the package imports."""
    import importlib.metadata as md

    import jax
    import jaxlib

    packages = {d.metadata["Name"]: d.version for d in md.distributions()
                if any(k in (d.metadata["Name"] or "").lower() for k in ("jax", "cudnn", "cublas", "cuda-runtime"))}
    cuda = {}
    for name in ("cuda_runtime_get_version", "cuda_driver_get_version", "cudnn_get_version", "cublas_get_version",
                 "cuda_compute_capability"):
        try:
            from jax._src.lib import cuda_versions  # private, None without the CUDA plugin: may move

            fn = getattr(cuda_versions, name)
            cuda[name.replace("_get_version", "")] = fn(0) if "capability" in name else fn()
        except Exception as e:  # noqa: BLE001 - one missing library or a moved module: report, go on
            cuda[name.replace("_get_version", "")] = f"n/a ({type(e).__name__})"
    dev = jax.devices()[0]
    stats = dev.memory_stats() or {}
    kernels = {}
    try:
        import rvggt_jax.model.forward  # noqa: F401 - the whole forward's imports
        import rvggt_jax
        package = rvggt_jax.__file__
        # what "auto" can pick here: both rest on JAX-private functions that may move
        from rvggt_jax.ops.attention import compilable_platforms, kernel_for
        from rvggt_jax.ops.kernels.fused import cudnn_lse_available

        kernels = {"compilable_platforms": list(compilable_platforms()), "cudnn_lse": cudnn_lse_available(),
                   "auto_bf16_d64": kernel_for("cuda", "bfloat16", 64)}
    except Exception as e:  # noqa: BLE001
        package = f"IMPORT FAILED: {e!r}"
    emit(python=sys.version.split()[0], jax=jax.__version__, jaxlib=jaxlib.__version__, packages=packages,
         cuda=cuda, backend=jax.default_backend(), platform=dev.platform, device_kind=dev.device_kind,
         device_count=jax.device_count(), bytes_limit=stats.get("bytes_limit"), package=package, kernels=kernels,
         environment_info=jax.print_environment_info(return_string=True))


def rel_err(ours, ref) -> float:
    """max|ours - ref| / max|ref| in float64 (tests/helpers/metrics.py's metric)."""
    import numpy as np

    ours, ref = np.asarray(ours, np.float64), np.asarray(ref, np.float64)
    return float(np.abs(ours - ref).max() / np.abs(ref).max())


def worker_parity(spec: dict) -> None:
    """The tiny fixture's forward against upstream's golden outputs, one RESULT per variant
    (spec "variants": which; default all): float32 at the config's precision ("highest"),
    float32 at the platform's default ("float32 TF32": TF32 on a GPU does not reach 1e-4),
    bfloat16 (aggregator weights in bf16, heads float32), then "ring": the ring's kernel."""
    import jax
    from safetensors.numpy import load_file

    import rvggt_jax

    golden = load_file(TINY / "io.safetensors")
    wanted = spec.get("variants")
    for variant, dtype, precision in (("float32", "float32", None), ("float32 TF32", "float32", "default"),
                                      ("bfloat16", "bfloat16", None)):
        if wanted and variant not in wanted:
            continue
        try:
            params, config = rvggt_jax.load_pretrained(TINY, param_dtype=dtype)
            # "float32": the config's own precision ("highest" for float32 configs);
            # "float32 TF32": the platform's default precision, which may be TF32 on a GPU
            cfg = config.with_dtype(dtype).with_precision(precision).with_outputs(layers=LAYERS)
            queries = golden["query_points"] if dtype == "float32" else None
            out = jax.device_get(jax.jit(rvggt_jax.rvggt_forward, static_argnums=2)(params, golden["images"], cfg,
                                                                                     queries))
            rows = []
            for key in [f"aggregated_{i:02d}" for i in LAYERS] + list(HEADS) + list(TRACK_TOL) * (queries is not None):
                tol = (2 * UPSTREAM_BF16[key if key in HEADS else "aggregated"] if dtype == "bfloat16"
                       else TRACK_TOL.get(key, F32_TOL) if precision is None
                       else max(TRACK_TOL.get(key, F32_TOL), TF32_TOL))
                err = rel_err(out[key], golden[key])
                rows.append({"output": key, "rel_err": err, "tol": tol, "pass": bool(err <= tol)})
            emit(variant=variant, device=str(jax.devices()[0].device_kind), rows=rows)
        except Exception as e:  # noqa: BLE001 - one variant failing: report, go on
            emit(variant=variant, error=repr(e)[:2000])
    if wanted and "ring" not in wanted:
        return
    try:
        emit(variant="ring kernel vs blocked", device=str(jax.devices()[0].device_kind), rows=ring_kernel_rows())
    except Exception as e:  # noqa: BLE001
        emit(variant="ring kernel vs blocked", error=repr(e)[:2000])


def random_params(abstract: dict, seed: int = 0) -> dict:
    """Random weights for an abstract tree (`ShapeDtypeStruct` leaves), on the default
    device: each leaf cut from one pool of 2^22 N(0, 0.02^2) draws from a random offset,
    repeated cyclically as needed. Timing and memory do not depend on the values, and this avoids
    compiling an initializer of 1800 leaves (minutes on XLA)."""
    import jax
    import numpy as np

    rng = np.random.default_rng(seed)
    pool = rng.standard_normal(2**22, dtype=np.float32) * 0.02

    def leaf(s):
        start = int(rng.integers(pool.size // 2))  # at least 2^21 distinct values per leaf
        return jax.device_put(np.resize(pool[start:], s.shape).astype(s.dtype))

    return jax.tree.map(leaf, abstract)


def kernel_of(hlo_text: str) -> dict:
    """Which attention the optimized HLO calls: cuDNN's flash kernel (call sites) or none."""
    n = hlo_text.count(FMHA)
    return {"fmha_calls": n, "kernel": f"cuDNN flash ({FMHA} x{n})" if n else "XLA (no cuDNN fmha)"}


def plan_bytes(compiled) -> int | None:
    """XLA's peak for a compiled program: arguments + outputs + temporaries - aliased."""
    m = compiled.memory_analysis()
    if m is None:
        return None
    return int(m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes - m.alias_size_in_bytes)


def worker_run(spec: dict) -> None:
    """Compile and time one forward [1, S, 3, H, W] on the default device; RESULT lines
    after compiling and after the timed runs (peak bytes: the whole process' peak)."""
    import jax
    import numpy as np

    import rvggt_jax
    from rvggt_jax.planning.memory import abstract_params

    cfg = make_config(spec)
    s, h, w = spec["frames"], spec["height"], spec["width"]
    params = random_params(abstract_params(cfg, param_dtype=spec["dtype"]))
    images = jax.device_put(np.random.default_rng(s).random((1, s, 3, h, w), dtype=np.float32))
    if spec.get("cache_dir"):  # JAX's persistent cache, every program in it (not --one-process)
        jax.config.update("jax_compilation_cache_dir", spec["cache_dir"])
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    t0 = time.perf_counter()
    compiled = jax.jit(rvggt_jax.rvggt_forward).lower(params, images, cfg).compile()
    dev = jax.devices()[0]
    # the device's peak so far: parameters, images and whatever compiling allocated
    # (on a GPU most likely XLA's autotuner, which runs candidate kernels there)
    emit(stage="compiled", compile_s=time.perf_counter() - t0, plan_bytes=plan_bytes(compiled),
         platform=dev.platform, peak_after_compile=(dev.memory_stats() or {}).get("peak_bytes_in_use"),
         **kernel_of(compiled.as_text()))
    if spec.get("compile_only"):
        return
    t0 = time.perf_counter()
    jax.block_until_ready(compiled(params, images, cfg))
    warmup = time.perf_counter() - t0
    times = []
    # a few runs, fewer when each is long: stop once the timed runs reach run_seconds
    while warmup < spec["run_seconds"] and len(times) < spec["repeats"] and sum(times) < spec["run_seconds"]:
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(params, images, cfg))
        times.append(time.perf_counter() - t0)
    stats = dev.memory_stats() or {}
    emit(stage="ran", warmup_s=warmup, times=times, run_s=statistics.median(times) if times else warmup,
         runs=len(times) or "warm-up only", peak_bytes=stats.get("peak_bytes_in_use"))


def worker_plan(spec: dict) -> None:
    """The spec's programs compiled deviceless for the target (JAX_PLATFORMS=cpu): XLA's
    plan and attention kernel of each, one RESULT line per program."""
    import jax
    import jax.numpy as jnp

    from rvggt_jax.model.forward import rvggt_forward
    from rvggt_jax.planning.memory import abstract_params
    from rvggt_jax.planning.targets import target_device

    # (the attention kernel follows the target, not this host's CPU backend: "auto" in
    # rvggt_jax.ops.attention picks cuDNN for bf16 in a program compiled for a GPU)
    dev = target_device(TARGET)
    where = jax.sharding.SingleDeviceSharding(dev)
    for prog in spec["programs"]:
        try:
            cfg = make_config(prog)
            params = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=where),
                                  abstract_params(cfg, param_dtype=prog["dtype"]))
            images = jax.ShapeDtypeStruct((1, prog["frames"], 3, prog["height"], prog["width"]), jnp.float32,
                                          sharding=where)
            t0 = time.perf_counter()
            compiled = jax.jit(rvggt_forward).lower(params, images, cfg).compile()
            emit(key=prog["key"], target=dev.device_kind, compile_s=time.perf_counter() - t0,
                 plan_bytes=plan_bytes(compiled), **kernel_of(compiled.as_text()))
        except Exception as e:  # noqa: BLE001 - one program failing: report, go on
            emit(key=prog["key"], error=repr(e)[:2000])


WORKERS = {"env": worker_env, "parity": worker_parity, "run": worker_run, "plan": worker_plan}


# ---------------------------------------------------------------------------------------
# The parent: starts workers with timeouts, collects, reports.
# ---------------------------------------------------------------------------------------

def ring_kernel_rows() -> list[dict]:
    """The ring's share kernel (`attention_with_lse`, cuDNN's with its statistics on a GPU,
    bfloat16) against the blocked kernel on the same device: output, log-sum-exp and the
    gradients of a loss on both (the lse cotangent enters cuDNN's backward through a spare
    v column: docs/accelerators.md), within bf16's 2e-2."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from rvggt_jax.ops import attention as attn

    rng = np.random.default_rng(0)
    q, k, v = (jnp.asarray(rng.standard_normal((1, n, 4, 64)), jnp.bfloat16) for n in (777, 1001, 1001))
    sizes = np.floor(1 + 6 * rng.random((1, 1001)))
    bias = attn.log_sizes(jnp.asarray(sizes), jnp.asarray(rng.random((1, 1001)) > 0.2))
    wl = jnp.asarray(rng.standard_normal((1, 777, 4)), jnp.float32)

    def run(kernel):
        def loss(q, k, v, b):
            out, lse = attn.attention_with_lse(q, k, v, b, 0.125, out_dtype=jnp.float32, implementation=kernel)
            return jnp.sum(out * out) + jnp.sum(jnp.sin(lse) * wl), (out, lse)
        (_, (out, lse)), grads = jax.jit(jax.value_and_grad(loss, (0, 1, 2, 3), has_aux=True))(q, k, v, bias)
        return {"out": out, "lse": lse, **{f"grad_{n}": g for n, g in zip("qkvb", grads)}}

    ours, ref = run("auto"), run("blocked")
    return [{"output": f"ring share {n}", "rel_err": (e := rel_err(ours[n], ref[n])), "tol": 2e-2,
             "pass": bool(e <= 2e-2)} for n in ours]


def worker_cmd(kind: str, spec: dict) -> list[str]:
    return [sys.executable, str(Path(__file__).resolve()), "--worker", kind, "--spec", json.dumps(spec)]


def worker_env_vars(cpu: bool) -> dict:
    env = dict(os.environ, TPU_WORKER_HOSTNAMES="localhost")  # quiets libtpu where installed
    if cpu:
        env["JAX_PLATFORMS"] = "cpu"
    return env


def parse(stdout: str | bytes | None) -> list[dict]:
    if isinstance(stdout, bytes):
        stdout = stdout.decode(errors="replace")
    return [json.loads(line[len(RESULT):]) for line in (stdout or "").splitlines() if line.startswith(RESULT)]


def call(kind: str, spec: dict, timeout: float, cpu: bool = False) -> tuple[list[dict], str | None]:
    """Run a worker: (its results, None) or (what it finished, the error)."""
    try:
        p = subprocess.run(worker_cmd(kind, spec), cwd=REPO, env=worker_env_vars(cpu), capture_output=True,
                           text=True, timeout=max(timeout, 1))
    except subprocess.TimeoutExpired as e:  # its partial stdout is bytes whatever text= says
        return parse(e.stdout), f"timed out after {timeout:.0f} s"
    results = parse(p.stdout)
    if p.returncode:
        return results, f"exit {p.returncode}: " + " | ".join(p.stderr.strip().splitlines()[-3:])[-600:]
    return results, None


def ensure_package(log: list[str]) -> tuple[dict, str | None]:
    """The env worker's result; when the package does not import, `pip install -e .`
    (offline-safe: no retries) and ask again."""
    results, err = call("env", {}, 180)
    if results and not results[0]["package"].startswith("IMPORT FAILED"):
        return results[0], err
    log.append(f"rvggt_jax does not import ({(results[0]['package'] if results else err)}); pip install -e .")
    pip = subprocess.run([sys.executable, "-m", "pip", "install", "--retries", "0", "--timeout", "10", "-e", "."],
                         cwd=REPO, capture_output=True, text=True, timeout=300)
    log.append(f"pip exit {pip.returncode}: " + " | ".join(pip.stdout.strip().splitlines()[-2:]))
    results, err = call("env", {}, 180)
    return (results[0] if results else {}), err


def programs(args) -> list[dict]:
    """The speed part's forwards, most wanted first (a budget cut drops the last)."""
    if args.smoke:
        base = dict(layout="small", dtype="bfloat16", height=56, width=70)
        sizes = [("regime", 3), ("dense", 3)]
    else:
        base = dict(layout="1b", dtype="bfloat16", height=392, width=518)
        # 1000 frames before 300: the first run (2026-12-04) spent its budget before it
        sizes = ([("regime", 100), ("dense", 100)] if args.quick else
                 [("regime", 100), ("dense", 100), ("regime", 1000), ("regime", 300), ("dense", 300)])
        if args.dense_1000:
            sizes.append(("dense", 1000))
    progs = [dict(base, preset=p, frames=s, key=f"{p}@{s}") for p, s in sizes]
    if args.only:
        progs = [dict(base, preset=key.split("@")[0], frames=int(key.split("@")[1]), key=key) for key in args.only]
    return progs


def part_speed(args, progs: list[dict], gpu: bool, deadline: float) -> list[dict]:
    """Each program in a fresh process, within its limit and what is left of the budget."""
    rows = []
    for prog in progs:
        row = {"key": prog["key"], "preset": prog["preset"], "frames": prog["frames"]}
        left = deadline - time.monotonic()
        if not (gpu or args.smoke):
            row["error"] = "skipped: no GPU (--smoke runs a small layout here)"
        elif left < 20:
            row["error"] = "skipped: time budget"
        else:
            spec = dict(prog, repeats=1 if args.quick else args.repeats, run_seconds=args.run_seconds)
            if args.runtime_peak:  # compile into the cache in one process, load and run in the next
                # outside --out: the device tool brings back what is there
                spec["cache_dir"] = args.cache_dir or str(Path(tempfile.gettempdir()) / "rvggt_gpu_check_cache")
                first, err = call("run", dict(spec, compile_only=True), min(args.program_limit, left))
                for r in first:
                    row.update(compile_s=r.get("compile_s"), peak_with_compile=r.get("peak_after_compile"))
                left = deadline - time.monotonic()
                if not err:
                    results, err = call("run", spec, min(args.program_limit, left))
                    for r in results:
                        row.update({("cache_load_s" if k == "compile_s" else k): v for k, v in r.items()})
            else:
                results, err = call("run", spec, min(args.program_limit, left))
                for r in results:
                    row.update(r)
            if err:
                row["error"] = err
            if row.get("platform") not in (None, "gpu", "cuda"):
                row["kernel"] = "skipped: no GPU"
        print(f"  {row['key']}: compile {fmt_s(row.get('compile_s'))} s, run {fmt_s(row.get('run_s'))} s, peak "
              f"{fmt_gb(row.get('peak_bytes'))} (after compiling or loading: {fmt_gb(row.get('peak_after_compile'))}"
              + (f"; with compiling: {fmt_gb(row['peak_with_compile'])}" if "peak_with_compile" in row else "")
              + ")" + (f" ({row['error']})" if "error" in row else ""), flush=True)
        rows.append(row)
    return rows


def fmt_gb(b) -> str:
    """Bytes in GB; small programs (--smoke) in MB."""
    return "n/a" if b is None else f"{b / GB:.1f} GB" if b >= 0.1 * GB else f"{b / 1e6:.1f} MB"


def fmt_s(x) -> str:
    return "n/a" if x is None else f"{x:.1f}" if x >= 1 else f"{x:.3f}"


def markdown(rep: dict) -> str:
    """The report as markdown: environment, parity, speed and memory, notes, summary."""
    env = rep.get("env", {})
    cuda = env.get("cuda", {})
    lines = ["# GPU check", "",
             f"{rep['date']}, {env.get('device_kind', '?')} x{env.get('device_count', '?')} "
             f"({env.get('platform', '?')}, memory limit {fmt_gb(env.get('bytes_limit'))}); python "
             f"{env.get('python', '?')}, jax {env.get('jax', '?')}, jaxlib {env.get('jaxlib', '?')}; "
             + ", ".join(f"{k} {v}" for k, v in sorted(env.get("packages", {}).items()) if k not in ("jax", "jaxlib")),
             "", "CUDA: " + (", ".join(f"{k} {v}" for k, v in cuda.items()) or "n/a"),
             "", "Attention kernels: " + (", ".join(f"{k} {v}" for k, v in env.get("kernels", {}).items()) or "n/a"),
             "", "## Parity (tests/data/vggt_tiny; rel_err = max|ours - ref| / max|ref|)", "",
             "| variant | output | rel err | tol | result |", "|---|---|---:|---:|---|"]
    for v in rep.get("parity", []):
        if "error" in v:
            lines.append(f"| {v['variant']} | (all) | | | ERROR: {v['error'][:300]} |")
        for r in v.get("rows", []):
            lines.append(f"| {v['variant']} | {r['output']} | {r['rel_err']:.2e} | {r['tol']:.0e} | "
                         f"{'PASS' if r['pass'] else 'FAIL'} |")
    lines += ["", f"## Speed and memory ({rep['layout']}, bf16, {rep['size']}, no track head, random weights)", "",
              "| preset | S | compile s | run s (median) | runs | peak (measured) | peak before the runs | "
              "XLA plan (this device) | deviceless plan (H200) | attention (this device) | "
              "attention (deviceless) | note |",
              "|---|---:|---:|---:|---|---:|---:|---:|---:|---|---|---|"]
    plans = {p["key"]: p for p in rep.get("plan", [])}
    for r in rep.get("speed", []):
        p = plans.get(r["key"], {})
        note = "; ".join(x for x in (r.get("error"), p.get("error") and "plan: " + p["error"][:200]) if x)
        lines.append(f"| {r['preset']} | {r['frames']} | {fmt_s(r.get('compile_s'))} | {fmt_s(r.get('run_s'))} | "
                     f"{r.get('runs', '')} | {fmt_gb(r.get('peak_bytes'))} | {fmt_gb(r.get('peak_after_compile'))}"
                     + (f" (loaded; compiling: {fmt_gb(r['peak_with_compile'])})" if "peak_with_compile" in r else "")
                     + f" | {fmt_gb(r.get('plan_bytes'))} | "
                     f"{fmt_gb(p.get('plan_bytes'))} | {r.get('kernel', '')} | {p.get('kernel', '')} | {note} |")
    lines += ["", "Peak: `memory_stats()['peak_bytes_in_use']`, each program in a fresh process; before the runs: "
              "after loading from the persistent cache (after compiling with --one-process). XLA plan: "
              "arguments + outputs + temporaries - aliased of the compiled program. Attention: call sites of "
              f"`{FMHA}` in the optimized HLO.", ""]
    lines += [f"- {n}" for n in rep.get("notes", [])]
    if env.get("environment_info"):
        lines += ["", "`jax.print_environment_info()`:", "", "```", env["environment_info"].strip(), "```"]
    return "\n".join(lines + ["", rep["summary"], ""])


def summary(rep: dict) -> str:
    """One line: what passed, ran and was planned, out of how many."""
    par, speed = rep.get("parity", []), rep.get("speed", [])
    rows = [r for v in par for r in v.get("rows", [])]
    bad = [f"{v['variant']}:{r['output']}" for v in par for r in v.get("rows", []) if not r["pass"]]
    bad += [f"{v['variant']}:error" for v in par if "error" in v]
    ran = sum("run_s" in r for r in speed)
    planned = f"{sum('plan_bytes' in p for p in rep['plan'])}/{len(speed)}" if "plan" in rep else "skipped"
    return (f"SUMMARY: env {'ok' if rep.get('env') else 'FAILED'}; parity {sum(r['pass'] for r in rows)}/{len(rows)} "
            f"PASS in {sum('rows' in v for v in par)}/{max(len(par), 4)} variants" + (f" (FAIL {', '.join(bad[:6])})" if bad else "")
            + f"; speed {ran}/{len(speed)} ran; deviceless plan {planned}; {rep['seconds']:.0f} s"
            + (f"; {len(rep['notes'])} note(s)" if rep["notes"] else ""))


class _Skipped(Exception):
    """A part the command line leaves out."""


def run_parts(args, rep: dict, deadline: float) -> None:
    """env, then the deviceless plan in the background (CPU), parity, speed; each caught."""
    try:
        rep["env"], err = ensure_package(rep["notes"])
        if err:
            rep["notes"].append(f"env: {err}")
        print(f"env: {rep['env'].get('device_kind')} ({rep['env'].get('platform')}), jax {rep['env'].get('jax')}, "
              f"rvggt_jax {rep['env'].get('package')}", flush=True)
    except Exception as e:  # noqa: BLE001
        rep["notes"].append(f"env: {e!r}")
    gpu = rep.get("env", {}).get("platform") in ("gpu", "cuda")
    progs = programs(args)
    plan_proc = plan_out = None
    if not args.no_plan:
        try:  # stdout to a file: a pipe nobody reads until the end could fill and block it
            plan_out = open(Path(args.out) / "plan_worker.log", "w+")
            plan_proc = subprocess.Popen(worker_cmd("plan", {"programs": progs}), cwd=REPO, stdout=plan_out,
                                         stderr=subprocess.STDOUT, env=worker_env_vars(cpu=True))
        except Exception as e:  # noqa: BLE001
            rep["notes"].append(f"plan: {e!r}")
    try:
        if args.parity_variants == []:
            raise _Skipped
        results, err = call("parity", {"variants": args.parity_variants},
                            min(args.parity_limit, deadline - time.monotonic()))
        rep["parity"] = results
        if err:
            rep["notes"].append(f"parity: {err}")
        print(f"parity: {sum(len(v.get('rows', [])) for v in results)} outputs checked", flush=True)
    except _Skipped:
        rep["notes"].append("parity: skipped (--parity-variants with none)")
    except Exception as e:  # noqa: BLE001
        rep["notes"].append(f"parity: {e!r}")
    try:
        rep["speed"] = part_speed(args, progs, gpu, deadline)
    except Exception as e:  # noqa: BLE001
        rep["notes"].append(f"speed: {e!r}")
    if plan_proc is not None:
        try:
            plan_proc.wait(timeout=max(deadline - time.monotonic(), 5))
        except subprocess.TimeoutExpired:
            plan_proc.kill()  # our own child, by its handle
            plan_proc.wait()
            rep["notes"].append("plan: timed out (time budget); the programs it finished are reported")
        plan_out.seek(0)
        text = plan_out.read()
        rep["plan"] = parse(text)
        if plan_proc.returncode and not rep["plan"]:
            rep["notes"].append("plan: " + " | ".join(text.strip().splitlines()[-3:])[-600:])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=os.environ.get("OUT") or "gpu_check_out", help="folder for the report")
    ap.add_argument("--smoke", action="store_true", help="a small layout on 56 x 70 images: runs on a CPU")
    ap.add_argument("--quick", action="store_true", help="100 frames only, one timed run")
    ap.add_argument("--dense-1000", action="store_true", help="also dense at 1000 frames (~1e17 FLOP)")
    ap.add_argument("--no-plan", action="store_true", help="skip the deviceless plan")
    ap.add_argument("--only", nargs="+", metavar="PRESET@FRAMES", help="these programs only, e.g. regime@1000")
    ap.add_argument("--one-process", dest="runtime_peak", action="store_false",
                    help="compile and run each program in one process (its peak then holds what compiling "
                         "allocated: 38-40 GB on an H200, most likely XLA:GPU's autotuning); by default each "
                         "program is compiled into JAX's persistent cache by one process and loaded and run by "
                         "the next")
    ap.add_argument("--cache-dir", help="the persistent cache the programs pass through (default: in the temp folder)")
    ap.add_argument("--parity-variants", nargs="*", metavar="VARIANT",
                    help="parity variants to run ('float32', 'float32 TF32', 'bfloat16', 'ring'; default all; "
                         "none: skip)")
    ap.add_argument("--budget", type=float, default=540,
                    help="seconds for the whole check (fits one 10-minute device call)")
    ap.add_argument("--program-limit", type=float, default=240, help="seconds for one speed program")
    ap.add_argument("--parity-limit", type=float, default=150, help="seconds for the parity part")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs after the warm-up, at most")
    ap.add_argument("--run-seconds", type=float, default=20, help="stop timing a program past this")
    ap.add_argument("--worker", choices=sorted(WORKERS), help=argparse.SUPPRESS)
    ap.add_argument("--spec", default="{}", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        sys.path.insert(0, str(REPO))  # the repository's package, installed or not
        WORKERS[args.worker](json.loads(args.spec))
        return
    t0 = time.monotonic()
    Path(args.out).mkdir(parents=True, exist_ok=True)
    rep = {"date": time.strftime("%Y-%m-%d %H:%M"), "notes": [], "layout": "small layout (--smoke)" if args.smoke
           else "VGGT-1B", "size": "56 x 70" if args.smoke else "392 x 518"}
    run_parts(args, rep, t0 + args.budget)
    rep["seconds"] = time.monotonic() - t0
    rep["summary"] = summary(rep)
    text = markdown(rep)
    (Path(args.out) / "gpu_check.json").write_text(json.dumps(rep, indent=1, default=str))
    (Path(args.out) / "gpu_check.md").write_text(text)
    print(text.replace(rep["summary"], "").rstrip() + f"\n\n(written to {Path(args.out).resolve()})")
    print(rep["summary"], flush=True)


if __name__ == "__main__":
    main()
