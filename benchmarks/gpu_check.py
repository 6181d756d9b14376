"""One command for a lent GPU: environment, parity, speed and memory of VGGT-1B (issues 24, 54).

    python benchmarks/gpu_check.py --out DIR             # under 8 minutes on one H100 (--budget 480)
    python benchmarks/gpu_check.py --quick               # 100 frames only, one timed run
    python benchmarks/gpu_check.py --dense-1000          # also dense at 1000 frames (~1e17 FLOP)
    python benchmarks/gpu_check.py --only regime@1000    # the biggest program alone
    python benchmarks/gpu_check.py --dry-run --out DIR   # every step on this CPU at tiny shapes (minutes)
    python benchmarks/gpu_check.py --only regime@1000 --parity-variants float32

It runs from the source tree (each worker puts this repository first on sys.path; PYTHONPATH=.
works too) on the packages the GPU machine has: jax, flax, optax, orbax-checkpoint, chex,
numpy, safetensors, pillow, tqdm, huggingface_hub (.ci/gpu-machine-requirements.txt; no av,
trimesh or viser, which rvggt_jax imports only where it uses them). It installs nothing: no
registry is reachable there.

Steps, each guarded: a failing step is recorded with its traceback (the report's
"Failures") and the next one runs. The report is written after every step, so a run that
is cut off still leaves what it finished:
1. env: jax, jaxlib, CUDA plugin, CUDA/cuDNN versions, the device and its memory, whether
   rvggt_jax imports and whether the JAX-private functions its kernels call are there.
2. parity: the tiny upstream fixture (tests/data/vggt_tiny) through `load_pretrained`:
   float32 at rel_err = max|ours - ref| / max|ref| <= 1e-4 (the config's own precision,
   "highest" for float32), float32 at the platform's default precision (TF32 on a GPU,
   reported against 1e-2), bfloat16 within twice upstream's own bf16 deviation; the
   ring's share kernel (cuDNN with its log-sum-exp) against the blocked one, values and
   gradients.
3. speed, at growing sizes: `regime` and dense at 100 frames, at 300, then `regime` at 1000
   (`--only` picks) (VGGT-1B, no track head, bf16 compute and aggregator weights, random
   weights, 392 x 518): trace + compile time, the median of timed runs after one warm-up,
   the device's peak bytes, XLA's plan of the same compiled program, and whether it calls
   cuDNN's flash attention (`__cudnn$fmha`). A program is started only when what is left of
   the budget covers its expected time (`expected_seconds`); else it is skipped, and the
   report says so. Each program runs in a fresh process (JAX cannot reset a device's peak)
   with a timeout. On a GPU compiling allocates on the device (38-40 GB of peak on an H200
   whatever the program; most likely XLA's autotuner), so each program is compiled into JAX's
   persistent cache by one process and loaded and run by the next, whose peak is the run's
   alone (the peak before the runs is reported too; --one-process does both in one).
4. plan: the same programs compiled deviceless (JAX_PLATFORMS=cpu) for `--plan-target`,
   by default the H200 (`rvggt_jax.planning.targets`' "h200": XLA's h200.txtpb, shipped in
   rvggt_jax/planning/gpu_specs/; XLA's CUDA compiler on the host, which the GPU machine's
   CUDA plugin carries), in the background while 2-3 run. The dry run plans for "cpu", the
   one target whose compiler every install has.

--dry-run runs all four on the CPU (JAX_PLATFORMS=cpu in every worker) with a small layout
of 24 layers on 56 x 70 images at 2 and 3 frames: what CI checks in an environment of
the GPU machine's packages alone (.ci/run), so that the real run works the first time.

The report goes to stdout and to --out (default $OUT, else ./gpu_check_out) as
gpu_check.json and gpu_check.md; the last line is a one-line summary. Exit status 0 when
every step that ran worked, 1 when any failed (skipped programs are no failure), 2 for a
bad command line.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

# The parent process never imports jax: a CUDA client would preallocate most of the GPU
# and starve the workers. Workers import it (after sys.path gets the repository).
REPO = Path(__file__).resolve().parents[1]
TARGET = "h200"  # the deviceless plan's target (rvggt_jax.planning.targets)
DRY_RUN_TARGET = "cpu"  # the dry run's: its compiler is in every install
TINY = REPO / "tests" / "data" / "vggt_tiny"
RESULT = "GPU_CHECK_RESULT "  # prefix of each result line a worker prints
FMHA = "__cudnn$fmha"
GB = 1e9
TRACEBACK_CHARS = 6000  # the tail of a traceback kept in the report
# Seconds. On the GPU: within 8 minutes on one H100 (env and parity took ~80 s on the H200).
# The dry run on a shared 2-core CPU (load 7): parity alone took 134-167 s (the plan
# compiling beside it), the whole run 240-300 s; the dry run's limits leave room for more.
BUDGET, PARITY_LIMIT = 480.0, 150.0
DRY_RUN_BUDGET, DRY_RUN_PARITY_LIMIT = 900.0, 450.0

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
    print(RESULT + json.dumps(fields, default=str), flush=True)


def caught(e: BaseException) -> dict:
    """The fields of a failure caught in a worker: the error and its traceback's tail."""
    return {"error": repr(e)[:2000], "traceback": traceback.format_exc()[-TRACEBACK_CHARS:]}


def make_config(spec: dict):
    """VGGT-1B ("1b") or a small layout ("small", for --dry-run), no track head, with the
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
    """Versions, devices, whether the package imports (with the traceback when not) and
    whether the JAX-private functions its kernels call are there. Each piece is caught on
    its own: one RESULT line with what could be found."""
    import importlib.metadata as md
    import warnings

    import jax
    import jaxlib

    info = {"python": sys.version.split()[0], "jax": jax.__version__, "jaxlib": jaxlib.__version__, "errors": {}}
    info["packages"] = {d.metadata["Name"]: d.version for d in md.distributions()
                        if any(k in (d.metadata["Name"] or "").lower()
                               for k in ("jax", "cudnn", "cublas", "cuda-runtime", "flax"))}
    cuda = {}
    for name in ("cuda_runtime_get_version", "cuda_driver_get_version", "cudnn_get_version", "cublas_get_version",
                 "cuda_compute_capability"):
        try:
            from jax._src.lib import cuda_versions  # private, None without the CUDA plugin: may move

            fn = getattr(cuda_versions, name)
            cuda[name.replace("_get_version", "")] = fn(0) if "capability" in name else fn()
        except Exception as e:  # noqa: BLE001 - one missing library or a moved module: report, go on
            cuda[name.replace("_get_version", "")] = f"n/a ({type(e).__name__})"
    info["cuda"] = cuda
    try:
        dev = jax.devices()[0]
        info.update(backend=jax.default_backend(), platform=dev.platform, device_kind=dev.device_kind,
                    device_count=jax.device_count())
        info["bytes_limit"] = (dev.memory_stats() or {}).get("bytes_limit")
    except Exception as e:  # noqa: BLE001 - memory_stats is not on every platform
        info["errors"]["devices"] = caught(e)
    try:
        import rvggt_jax
        import rvggt_jax.model.forward  # noqa: F401 - the whole forward's imports

        info["package"] = rvggt_jax.__file__
    except Exception as e:  # noqa: BLE001
        info["package"] = f"IMPORT FAILED: {e!r}"
        info["errors"]["package"] = caught(e)
    try:
        # what "auto" can pick here and what the kernels find of JAX's private API (each
        # falls back to the blocked kernel with a warning where it is missing)
        from rvggt_jax.ops.attention import compilable_platforms, kernel_for
        from rvggt_jax.ops.kernels import fused, tpu_flash

        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            info["kernels"] = {"compilable_platforms": list(compilable_platforms()),
                               "auto_bf16_d64": kernel_for("cuda", "bfloat16", 64),
                               "cudnn_lse": fused.cudnn_lse_missing() or "ok",
                               "tpu_flash": tpu_flash.flash_missing() or "ok",
                               "tpu_flash_lse": tpu_flash.lse_missing() or "ok"}
        info["kernels"]["warnings"] = [str(w.message) for w in seen]
    except Exception as e:  # noqa: BLE001
        info["errors"]["kernels"] = caught(e)
    try:
        info["environment_info"] = jax.print_environment_info(return_string=True)
    except Exception as e:  # noqa: BLE001
        info["errors"]["environment_info"] = caught(e)
    emit(**info)


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
            emit(variant=variant, **caught(e))
    if wanted and "ring" not in wanted:
        return
    try:
        emit(variant="ring kernel vs blocked", device=str(jax.devices()[0].device_kind), rows=ring_kernel_rows())
    except Exception as e:  # noqa: BLE001
        emit(variant="ring kernel vs blocked", **caught(e))


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
    """The spec's programs compiled deviceless for its target (JAX_PLATFORMS=cpu): XLA's
    plan and attention kernel of each, one RESULT line per program."""
    import jax
    import jax.numpy as jnp

    from rvggt_jax.model.forward import rvggt_forward
    from rvggt_jax.planning.memory import abstract_params
    from rvggt_jax.planning.targets import target_device

    # (the attention kernel follows the target, not this host's CPU backend: "auto" in
    # rvggt_jax.ops.attention picks cuDNN for bf16 in a program compiled for a GPU)
    dev = target_device(spec["target"])
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
            emit(key=prog["key"], **caught(e))


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
    """The RESULT lines of a worker's output (a line cut off by a kill is left out)."""
    if isinstance(stdout, bytes):
        stdout = stdout.decode(errors="replace")
    results = []
    for line in (stdout or "").splitlines():
        if line.startswith(RESULT):
            try:
                results.append(json.loads(line[len(RESULT):]))
            except json.JSONDecodeError:
                pass
    return results


def traceback_of(text: str | bytes | None) -> str:
    """A worker's traceback from its stderr: from the last "Traceback" on (JAX's own
    logging fills the lines before it), else the tail."""
    if isinstance(text, bytes):
        text = text.decode(errors="replace")
    text = (text or "").rstrip()
    at = text.rfind("Traceback (most recent call last)")
    return (text[at:] if at >= 0 else text)[-TRACEBACK_CHARS:]


def call(kind: str, spec: dict, timeout: float, cpu: bool = False) -> tuple[list[dict], dict | None]:
    """Run a worker: (its results, None), or (what it finished, {"error", "traceback"})."""
    try:
        p = subprocess.run(worker_cmd(kind, spec), cwd=REPO, env=worker_env_vars(cpu), capture_output=True,
                           text=True, timeout=max(timeout, 1))
    except subprocess.TimeoutExpired as e:  # its partial output is bytes whatever text= says
        return parse(e.stdout), {"error": f"timed out after {timeout:.0f} s", "traceback": traceback_of(e.stderr)}
    results = parse(p.stdout)
    if p.returncode:
        return results, {"error": f"the {kind} worker exited with {p.returncode}",
                         "traceback": traceback_of(p.stderr)}
    return results, None


def fail(rep: dict, step: str, error: str, tb: str | None = None) -> None:
    """Record a failed step (the exit status becomes 1)."""
    rep["failures"].append({"step": step, "error": str(error)[:2000], **({"traceback": tb} if tb else {})})
    print(f"FAILED {step}: {str(error)[:300]}", flush=True)


def part_env(args, rep: dict) -> None:
    """The env worker's result. Nothing is installed: when rvggt_jax does not import from
    this repository, the error is recorded with what to do."""
    results, err = call("env", {}, 180, cpu=args.dry_run)
    rep["env"] = results[0] if results else {}
    if err:
        fail(rep, "env", err["error"], err["traceback"])
    for piece, e in rep["env"].pop("errors", {}).items():
        if piece == "package":
            fail(rep, "env: rvggt_jax import",
                 f"rvggt_jax does not import from {REPO}: {e['error']}. This check installs nothing: run it from "
                 f"the repository (PYTHONPATH={REPO}), on the packages of .ci/gpu-machine-requirements.txt; a "
                 "missing one must be carried as a wheel", e["traceback"])
        else:
            rep["notes"].append(f"env: {piece}: {e['error']}")
    env = rep["env"]
    kernels = env.get("kernels", {})
    missing = {k: v for k, v in kernels.items() if k in ("cudnn_lse", "tpu_flash", "tpu_flash_lse") and v != "ok"}
    if missing:  # no failure: the kernels fall back (ops/attention.py), but the timings are the blocked kernel's
        rep["notes"].append("env: this JAX lacks private API the accelerator kernels call, so the blocked kernel "
                            "runs instead: " + "; ".join(f"{k}: {v}" for k, v in missing.items()))
    print(f"env: {env.get('device_kind')} ({env.get('platform')}), jax {env.get('jax')}, rvggt_jax "
          f"{env.get('package')}", flush=True)


def part_parity(args, rep: dict, deadline: float) -> None:
    """The parity worker's variants; an error or a result over its tolerance is a failure."""
    if args.parity_variants == []:
        rep["notes"].append("parity: skipped (--parity-variants with none)")
        return
    results, err = call("parity", {"variants": args.parity_variants},
                        min(args.parity_limit, deadline - time.monotonic()), cpu=args.dry_run)
    rep["parity"] = results
    if err:
        fail(rep, "parity", err["error"], err["traceback"])
    for v in results:
        if "error" in v:
            fail(rep, f"parity: {v['variant']}", v["error"], v.get("traceback"))
        over = [r["output"] for r in v.get("rows", []) if not r["pass"]]
        if over:
            fail(rep, f"parity: {v['variant']}", f"over tolerance: {', '.join(over)}")
    print(f"parity: {sum(len(v.get('rows', [])) for v in results)} outputs checked", flush=True)


def programs(args) -> list[dict]:
    """The speed step's forwards at growing sizes, `regime` before dense at each (the
    biggest last: a budget cut skips it, `part_speed`); `--only`: those, in its order."""
    if args.dry_run:
        base = dict(layout="small", dtype="bfloat16", height=56, width=70)
        sizes = list(DRY_RUN_PROGRAMS[:2] if args.quick else DRY_RUN_PROGRAMS)
    else:
        base = dict(layout="1b", dtype="bfloat16", height=392, width=518)
        sizes = [("regime", 100), ("dense", 100)]
        if not args.quick:
            sizes += [("regime", 300), ("dense", 300), ("regime", 1000)] + [("dense", 1000)] * args.dense_1000
    keys = args.only or [f"{p}@{s}" for p, s in sizes]
    return [dict(base, preset=key.split("@")[0], frames=int(key.split("@")[1]), key=key) for key in keys]


# the dry run's programs (frames of 56 x 70): both presets, then a bigger one. Each
# compiles in 15-50 s on 2 busy cores, twice (the cache's two processes) and once more in
# the plan: three keep the dry run within a few minutes
DRY_RUN_PROGRAMS = (("regime", 2), ("dense", 2), ("regime", 3))


def program_key(text: str) -> str:
    """A --only entry, PRESET@FRAMES (argparse's type: a malformed one is a command-line
    error; the parent imports nothing of the package, so an unknown preset is the
    program's failure)."""
    preset, _, frames = text.partition("@")
    if not preset or not frames.isdigit() or int(frames) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: want PRESET@FRAMES, e.g. regime@1000")
    return text


def expected_seconds(prog: dict, args) -> float:
    """About how long a program takes on one H100, to decide whether to start it: two
    process starts, compiling, the warm-up run and one timed run (none when the warm-up
    alone takes --run-seconds). From the H200 runs of 2026-12-04 (docs/history/gpu_check.md:
    compiling 34-96 s; runs 2.6 / 10.9 / 77 s for `regime` at 100 / 300 / 1000 frames, 4.4 /
    28.8 s for dense at 100 / 300, fitted as a S^2 + b S), runs x1.4 for an H100's slower
    memory. The dry run's small layout: 30 s."""
    if prog["layout"] != "1b":
        return 30.0
    s = prog["frames"]
    run = 1.4 * (5.3e-5 * s * s + 0.021 * s if prog["preset"] != "dense" else 2.6e-4 * s * s + 0.018 * s)
    runs = run if run >= args.run_seconds else 2 * run  # the warm-up, and a timed run if there is time
    return 20 + (60 + 0.04 * s) + runs


def part_speed(args, rep: dict, progs: list[dict], gpu: bool, deadline: float) -> None:
    """Each program in a fresh process, within its limit and what is left of the budget;
    one not started for want of time is skipped with the reason. The report is written
    after each."""
    rows = rep.setdefault("speed", [])
    for prog in progs:
        row = {"key": prog["key"], "preset": prog["preset"], "frames": prog["frames"]}
        rows.append(row)
        left, need = deadline - time.monotonic(), expected_seconds(prog, args)
        if not (gpu or args.dry_run):
            row["skipped"] = "no GPU (--dry-run runs a small layout on the CPU)"
        elif left < need:
            row["skipped"] = f"time budget: {max(left, 0):.0f} s left, it takes about {need:.0f} s"
        else:
            try:
                run_program(args, rep, prog, row, deadline)
            except Exception as e:  # noqa: BLE001 - this program's bookkeeping: report, go on
                row["error"] = repr(e)
                fail(rep, f"speed: {prog['key']}", repr(e), traceback.format_exc()[-TRACEBACK_CHARS:])
            if row.get("platform") not in (None, "gpu", "cuda"):
                row["kernel"] = "skipped: no GPU"
        print(f"  {row['key']}: compile {fmt_s(row.get('compile_s'))} s, run {fmt_s(row.get('run_s'))} s, peak "
              f"{fmt_gb(row.get('peak_bytes'))} (after compiling or loading: {fmt_gb(row.get('peak_after_compile'))}"
              + (f"; with compiling: {fmt_gb(row['peak_with_compile'])}" if "peak_with_compile" in row else "")
              + ")" + (f" (skipped: {row['skipped']})" if "skipped" in row else ""), flush=True)
        write_report(args, rep)


def run_program(args, rep: dict, prog: dict, row: dict, deadline: float) -> None:
    """One program: compiled into the persistent cache by one process, loaded and run by
    the next (or both in one with --one-process); a worker's failure is the step's."""
    spec = dict(prog, repeats=1 if args.quick else args.repeats, run_seconds=args.run_seconds)
    left = deadline - time.monotonic()
    if args.runtime_peak:  # compile into the cache in one process, load and run in the next
        # outside --out: the device tool brings back what is there
        spec["cache_dir"] = args.cache_dir or str(Path(tempfile.gettempdir()) / "rvggt_gpu_check_cache")
        first, err = call("run", dict(spec, compile_only=True), min(args.program_limit, left), cpu=args.dry_run)
        for r in first:
            row.update(compile_s=r.get("compile_s"), peak_with_compile=r.get("peak_after_compile"))
        left = deadline - time.monotonic()
        if not err:
            results, err = call("run", spec, min(args.program_limit, left), cpu=args.dry_run)
            for r in results:
                row.update({("cache_load_s" if k == "compile_s" else k): v for k, v in r.items()})
    else:
        results, err = call("run", spec, min(args.program_limit, left), cpu=args.dry_run)
        for r in results:
            row.update(r)
    if err:
        row["error"] = err["error"]
        fail(rep, f"speed: {prog['key']}", err["error"], err["traceback"])


def part_plan_start(args, rep: dict, progs: list[dict]):
    """The deviceless plan's worker, started in the background (CPU): (process, log file)."""
    # stdout to a file: a pipe nobody reads until the end could fill and block it
    log = open(Path(args.out) / "plan_worker.log", "w+")
    proc = subprocess.Popen(worker_cmd("plan", {"programs": progs, "target": rep["plan_target"]}), cwd=REPO,
                            stdout=log, stderr=subprocess.STDOUT, env=worker_env_vars(cpu=True))
    return proc, log


def part_plan_finish(rep: dict, proc, log, deadline: float) -> None:
    """Wait for the plan's worker within the budget; collect its programs. A program it
    reports an error for, or a worker that fails with none done, is a failure; one it did
    not reach in the budget is a note."""
    try:
        proc.wait(timeout=max(deadline - time.monotonic(), 5))
    except subprocess.TimeoutExpired:
        proc.kill()  # our own child, by its handle
        proc.wait()
        rep["notes"].append("plan: stopped at the end of the time budget; the programs it finished are reported")
    log.seek(0)
    text = log.read()
    rep["plan"] = parse(text)
    for p in rep["plan"]:
        if "error" in p:
            fail(rep, f"plan: {p['key']}", p["error"], p.get("traceback"))
    if proc.returncode and proc.returncode > 0:
        fail(rep, "plan", f"the plan worker exited with {proc.returncode}", traceback_of(text))


def fmt_gb(b) -> str:
    """Bytes in GB; small programs (--dry-run) in MB."""
    return "n/a" if b is None else f"{b / GB:.1f} GB" if b >= 0.1 * GB else f"{b / 1e6:.1f} MB"


def fmt_s(x) -> str:
    return "n/a" if x is None else f"{x:.1f}" if x >= 1 else f"{x:.3f}"


def markdown(rep: dict) -> str:
    """The report as markdown: environment, parity, speed and memory, failures (with their
    tracebacks), notes, summary."""
    env = rep.get("env", {})
    cuda = env.get("cuda", {})
    lines = ["# GPU check" + (" (dry run)" if rep.get("dry_run") else ""), "",
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
    target = rep.get("plan_target", TARGET)
    lines += ["", f"## Speed and memory ({rep['layout']}, bf16, {rep['size']}, no track head, random weights)", "",
              "| preset | S | compile s | run s (median) | runs | peak (measured) | peak before the runs | "
              f"XLA plan (this device) | deviceless plan ({target}) | attention (this device) | "
              "attention (deviceless) | note |",
              "|---|---:|---:|---:|---|---:|---:|---:|---:|---|---|---|"]
    plans = {p["key"]: p for p in rep.get("plan", [])}
    for r in rep.get("speed", []):
        p = plans.get(r["key"], {})
        note = "; ".join(x for x in (r.get("error"), r.get("skipped") and "skipped: " + r["skipped"],
                                     p.get("error") and "plan: " + p["error"][:200]) if x)
        lines.append(f"| {r['preset']} | {r['frames']} | {fmt_s(r.get('compile_s'))} | {fmt_s(r.get('run_s'))} | "
                     f"{r.get('runs', '')} | {fmt_gb(r.get('peak_bytes'))} | {fmt_gb(r.get('peak_after_compile'))}"
                     + (f" (loaded; compiling: {fmt_gb(r['peak_with_compile'])})" if "peak_with_compile" in r else "")
                     + f" | {fmt_gb(r.get('plan_bytes'))} | "
                     f"{fmt_gb(p.get('plan_bytes'))} | {r.get('kernel', '')} | {p.get('kernel', '')} | {note} |")
    lines += ["", "Peak: `memory_stats()['peak_bytes_in_use']`, each program in a fresh process; before the runs: "
              "after loading from the persistent cache (after compiling with --one-process). XLA plan: "
              "arguments + outputs + temporaries - aliased of the compiled program. Attention: call sites of "
              f"`{FMHA}` in the optimized HLO.", ""]
    if rep.get("failures"):
        lines += ["## Failures", ""]
        for f in rep["failures"]:
            lines += [f"- **{f['step']}**: {f['error']}"]
            if f.get("traceback"):
                lines += ["", "  ```", *("  " + t for t in f["traceback"].strip().splitlines()), "  ```", ""]
        lines.append("")
    lines += [f"- {n}" for n in rep.get("notes", [])]
    if env.get("environment_info"):
        lines += ["", "`jax.print_environment_info()`:", "", "```", env["environment_info"].strip(), "```"]
    return "\n".join(lines + ["", rep["summary"], ""])


def summary(rep: dict) -> str:
    """One line: OK or the failed steps, then what passed, ran and was planned."""
    par, speed = rep.get("parity", []), rep.get("speed", [])
    rows = [r for v in par for r in v.get("rows", [])]
    failed = list(dict.fromkeys(f["step"] for f in rep["failures"]))
    ran, skipped = sum("run_s" in r for r in speed), sum("skipped" in r for r in speed)
    planned = f"{sum('plan_bytes' in p for p in rep['plan'])}/{len(speed)}" if "plan" in rep else "not done"
    return (("SUMMARY: OK" if not failed else f"SUMMARY: FAILED {len(failed)} step(s) ({', '.join(failed[:6])})")
            + f"; env {'ok' if rep.get('env') else 'FAILED'}; parity {sum(r['pass'] for r in rows)}/{len(rows)} "
            f"PASS in {sum('rows' in v for v in par)}/{max(len(par), 4)} variants"
            + f"; speed {ran}/{len(speed)} ran" + (f" ({skipped} skipped)" if skipped else "")
            + f"; deviceless plan ({rep.get('plan_target')}) {planned}; {rep['seconds']:.0f} s"
            + (f"; {len(rep['notes'])} note(s)" if rep["notes"] else ""))


def write_report(args, rep: dict) -> str:
    """gpu_check.json and gpu_check.md in --out as things stand (after every step: a run
    cut off keeps what it finished); returns the markdown."""
    rep["seconds"] = time.monotonic() - rep["_t0"]
    rep["summary"] = summary(rep)
    text = markdown(rep)
    out = {k: v for k, v in rep.items() if not k.startswith("_")}
    (Path(args.out) / "gpu_check.json").write_text(json.dumps(out, indent=1, default=str))
    (Path(args.out) / "gpu_check.md").write_text(text)
    return text


def guarded(rep: dict, step: str, fn, *a) -> None:
    """fn(*a); an exception of the parent's own is the step's failure, with its traceback.
    The step's seconds go to the report's "step_seconds"."""
    t0 = time.monotonic()
    try:
        fn(*a)
    except Exception as e:  # noqa: BLE001 - one step failing never stops the next
        fail(rep, step, repr(e), traceback.format_exc()[-TRACEBACK_CHARS:])
    times = rep.setdefault("step_seconds", {})
    times[step] = round(times.get(step, 0) + time.monotonic() - t0, 1)


def run_parts(args, rep: dict, deadline: float) -> None:
    """env, then the deviceless plan in the background (CPU), parity, speed at growing
    sizes, the plan's results; each guarded, the report written after each."""
    guarded(rep, "env", part_env, args, rep)
    write_report(args, rep)
    platform = rep.get("env", {}).get("platform")
    gpu = platform in ("gpu", "cuda") or platform is None  # unknown (env failed): try the programs
    progs = programs(args)
    plan = []
    if args.no_plan:
        rep["notes"].append("plan: skipped (--no-plan)")
    else:
        guarded(rep, "plan", lambda: plan.extend(part_plan_start(args, rep, progs)))
    guarded(rep, "parity", part_parity, args, rep, deadline)
    write_report(args, rep)
    guarded(rep, "speed", part_speed, args, rep, progs, gpu, deadline)
    if plan:
        guarded(rep, "plan", part_plan_finish, rep, *plan, deadline)
        plan[1].close()


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=os.environ.get("OUT") or "gpu_check_out", help="folder for the report")
    ap.add_argument("--dry-run", action="store_true",
                    help="every step on this CPU at tiny shapes (a small layout on 56 x 70 images at 2 and 3 "
                         "frames; the plan for the 'cpu' target): checks that the real run works")
    ap.add_argument("--quick", action="store_true", help="100 frames only, one timed run")
    ap.add_argument("--dense-1000", action="store_true", help="also dense at 1000 frames (~1e17 FLOP)")
    ap.add_argument("--no-plan", action="store_true", help="skip the deviceless plan")
    ap.add_argument("--plan-target", help=f"the deviceless plan's target (rvggt_jax.planning.targets; default "
                                          f"{TARGET!r}, with --dry-run {DRY_RUN_TARGET!r})")
    ap.add_argument("--only", nargs="+", metavar="PRESET@FRAMES", type=program_key,
                    help="these programs only, in this order, e.g. regime@1000")
    ap.add_argument("--one-process", dest="runtime_peak", action="store_false",
                    help="compile and run each program in one process (its peak then holds what compiling "
                         "allocated: 38-40 GB on an H200, most likely XLA:GPU's autotuning); by default each "
                         "program is compiled into JAX's persistent cache by one process and loaded and run by "
                         "the next")
    ap.add_argument("--cache-dir", help="the persistent cache the programs pass through (default: in the temp folder; "
                                        "with --dry-run a fresh one, removed at the end)")
    ap.add_argument("--parity-variants", nargs="*", metavar="VARIANT",
                    help="parity variants to run ('float32', 'float32 TF32', 'bfloat16', 'ring'; default all; "
                         "none: skip)")
    ap.add_argument("--budget", type=float,
                    help=f"seconds for the whole check (default {BUDGET:.0f}: within 8 minutes, one 10-minute device "
                         f"call; with --dry-run {DRY_RUN_BUDGET:.0f}: a busy 2-core CPU)")
    ap.add_argument("--program-limit", type=float, default=240, help="seconds for one speed program")
    ap.add_argument("--parity-limit", type=float,
                    help=f"seconds for the parity part (default {PARITY_LIMIT:.0f}, with --dry-run "
                         f"{DRY_RUN_PARITY_LIMIT:.0f})")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs after the warm-up, at most")
    ap.add_argument("--run-seconds", type=float, default=20, help="stop timing a program past this")
    ap.add_argument("--worker", choices=sorted(WORKERS), help=argparse.SUPPRESS)
    ap.add_argument("--spec", default="{}", help=argparse.SUPPRESS)
    return ap


def parse_args(argv=None) -> argparse.Namespace:
    """The command line, with the defaults that depend on --dry-run filled in."""
    args = parser().parse_args(argv)
    if args.budget is None:
        args.budget = DRY_RUN_BUDGET if args.dry_run else BUDGET
    if args.parity_limit is None:
        args.parity_limit = DRY_RUN_PARITY_LIMIT if args.dry_run else PARITY_LIMIT
    return args


def main(argv=None) -> int:
    """The check (or, with --worker, one worker); returns the exit status."""
    args = parse_args(argv)
    if args.worker:
        sys.path.insert(0, str(REPO))  # the repository's package, installed or not
        WORKERS[args.worker](json.loads(args.spec))
        return 0
    t0 = time.monotonic()
    Path(args.out).mkdir(parents=True, exist_ok=True)
    own_cache = None
    if args.dry_run and args.runtime_peak and not args.cache_dir:
        # a cache of its own, removed at the end: every dry run compiles (on a GPU the cache
        # outlives the run, so that a second call on the same machine loads its programs)
        args.cache_dir = own_cache = tempfile.mkdtemp(prefix="rvggt_gpu_check_dry_run_")
    rep = {"date": time.strftime("%Y-%m-%d %H:%M"), "dry_run": args.dry_run, "notes": [], "failures": [],
           "layout": "small layout (--dry-run)" if args.dry_run else "VGGT-1B",
           "size": "56 x 70" if args.dry_run else "392 x 518",
           "plan_target": args.plan_target or (DRY_RUN_TARGET if args.dry_run else TARGET),
           "budget_s": args.budget, "_t0": t0}
    try:
        run_parts(args, rep, t0 + args.budget)
    finally:
        if own_cache:
            shutil.rmtree(own_cache, ignore_errors=True)
    text = write_report(args, rep)
    print(text.replace(rep["summary"], "").rstrip() + f"\n\n(written to {Path(args.out).resolve()})")
    print(rep["summary"], flush=True)
    return 1 if rep["failures"] else 0


if __name__ == "__main__":
    sys.exit(main())
