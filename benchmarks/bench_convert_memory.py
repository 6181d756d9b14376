"""Peak memory of the checkpoint converter vs the size of the checkpoint file.

Writes a random upstream checkpoint of the real VGGT-1B layout (every key and shape of
tests/data/vggt_1b_manifest.json, ~5 GB float32) to a temporary folder, converts it in a
fresh subprocess and reports that process's peak RSS (kernel high-water mark,
`ru_maxrss`) against the file size; the file is deleted afterwards. Target: < 1.3x
(for `--scale small/tiny` counted above the ~190 MB the imports take, which would
dominate there).

    python benchmarks/bench_convert_memory.py                 # full VGGT-1B layout (~5 GB)
    python benchmarks/bench_convert_memory.py --scale small   # ~0.3 GB, a quick run
    python benchmarks/bench_convert_memory.py --what cli      # convert + Orbax save only

Measured, each in a fresh process (`--what`, default all): `convert` =
`convert.load_safetensors` (upstream file -> numpy params, the target above); `cli` =
`rvggt convert SRC DST` (conversion + writing the Orbax checkpoint); `restore` =
`load_pretrained` of that Orbax folder; `load_st` = `load_pretrained` of the upstream
file (conversion with each leaf put on the default device).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import shutil
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

MANIFEST = ROOT / "tests" / "data" / "vggt_1b_manifest.json"
TINY_CONFIG = ROOT / "tests" / "data" / "vggt_tiny" / "config.json"
TARGET_RATIO = 1.3
# convert: convert.load_safetensors (numpy leaves); cli: `rvggt convert` (conversion +
# Orbax save); restore: load_pretrained(the CLI's Orbax folder); load_st:
# load_pretrained(the upstream file) with device_put.
WHATS = ("convert", "cli", "restore", "load_st")


# ---- the random checkpoint --------------------------------------------------------------------


def _layout(scale: str):
    """(config, {key: shape}) for the chosen scale."""
    from rvggt_jax.model.params import upstream_state_dict_shapes
    from rvggt_jax.config import VGGTConfig

    if scale == "1b":
        with open(MANIFEST) as f:
            shapes = {k: tuple(v[0]) for k, v in json.load(f).items()}
        config = VGGTConfig()
        assert upstream_state_dict_shapes(config) == shapes, "manifest and shape table disagree"
        return config, shapes
    if scale == "tiny":
        config = VGGTConfig.from_json(TINY_CONFIG)
    else:  # small: a quarter-width VGGT (~0.2 GB)
        base = VGGTConfig()
        config = dataclasses.replace(
            base,
            embed_dim=256,
            num_heads=4,
            dino=dataclasses.replace(base.dino, num_heads=4),
            camera_head=dataclasses.replace(base.camera_head, num_heads=4),
            dpt_head=dataclasses.replace(base.dpt_head, features=64, out_channels=(64, 128, 256, 256)),
            track_head=dataclasses.replace(base.track_head, features=32, hidden_size=96),
        )
    return config, upstream_state_dict_shapes(config)


def write_random_safetensors(path: Path, shapes: dict[str, tuple[int, ...]], seed: int = 0) -> int:
    """Stream a float32 safetensors file tensor by tensor (never all in memory); returns
    its size in bytes."""
    rng = np.random.default_rng(seed)
    header, offset = {}, 0
    for k in sorted(shapes):
        n = int(np.prod(shapes[k], dtype=np.int64)) * 4
        header[k] = {"dtype": "F32", "shape": list(shapes[k]), "data_offsets": [offset, offset + n]}
        offset += n
    raw = json.dumps(header, separators=(",", ":")).encode()
    raw += b" " * (-len(raw) % 8)  # the data section starts 8-byte aligned
    with open(path, "wb") as f:
        f.write(struct.pack("<Q", len(raw)))
        f.write(raw)
        for k in sorted(shapes):
            x = rng.standard_normal(shapes[k], dtype=np.float32)
            x *= 0.02
            f.write(x.tobytes())
            del x
    return path.stat().st_size


# ---- the measured child process ----------------------------------------------------------------


def _status_kb(field: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    return 0


class _Sampler(threading.Thread):
    """Peak RssAnon / RssFile (the kernel's ru_maxrss only has their sum)."""

    def __init__(self, period: float = 0.02):
        super().__init__(daemon=True)
        self.period, self.stop, self.anon, self.file = period, threading.Event(), 0, 0

    def run(self) -> None:
        while not self.stop.is_set():
            self.anon = max(self.anon, _status_kb("RssAnon"))
            self.file = max(self.file, _status_kb("RssFile"))
            time.sleep(self.period)


def _child(args) -> None:
    from rvggt_jax.weights.converter import load_safetensors
    from rvggt_jax.config import VGGTConfig

    import jax  # imported up front: its own footprint is the baseline
    import orbax.checkpoint  # noqa: F401

    jax.devices()

    config = VGGTConfig.from_json(args.config)
    baseline_kb = _status_kb("VmRSS")
    sampler = _Sampler()
    sampler.start()
    t0 = time.perf_counter()
    params, t1 = None, None
    if args.what == "cli":  # exactly what `rvggt convert SRC DST` does
        from rvggt_jax.app.convert_command import main as cli_main

        timings = {}
        assert cli_main([str(args.src), str(args.dst), "--config", str(args.config), "--quiet"], timings=timings) == 0
        t1 = t0 + timings["convert_s"]
    elif args.what == "convert":
        params = load_safetensors(args.src, config)
    elif args.what == "load_st":  # load_pretrained(upstream file): convert + device_put leaf by leaf
        from rvggt_jax.weights.pretrained import load_pretrained

        params, _ = load_pretrained(args.src)
    else:  # restore: load_pretrained(Orbax folder written by the CLI)
        from rvggt_jax.weights.pretrained import load_pretrained

        params, _ = load_pretrained(args.dst)
    jax.block_until_ready(params)
    t2 = time.perf_counter()
    t1 = t2 if t1 is None else t1
    sampler.stop.set()
    sampler.join()
    nbytes = sum(int(x.nbytes) for x in jax.tree.leaves(params)) if params is not None else None
    print(json.dumps({
        "baseline_kb": baseline_kb,
        "peak_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
        "peak_anon_kb": sampler.anon,
        "peak_file_kb": sampler.file,
        "params_bytes": nbytes,
        "seconds": t2 - t0,
        "convert_s": t1 - t0,
        "save_s": t2 - t1,
    }))


# ---- driver ------------------------------------------------------------------------------------


def _run_child(what: str, src: Path, cfg: Path, dst: Path) -> dict:
    cmd = [sys.executable, __file__, "--child", what, "--src", str(src), "--config", str(cfg), "--dst", str(dst)]
    out = subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=ROOT)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scale", choices=("1b", "small", "tiny"), default="1b",
                    help="1b: the real layout (~5 GB); small: quarter width (~0.3 GB); tiny: the test fixture's config")
    ap.add_argument("--what", choices=WHATS + ("all",), default="all")
    ap.add_argument("--tmp", type=Path, default=Path(tempfile.gettempdir()), help="where the temporary files go")
    ap.add_argument("--keep", action="store_true", help="keep the temporary folder")
    ap.add_argument("--child", choices=WHATS, help=argparse.SUPPRESS)
    ap.add_argument("--src", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--config", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--dst", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        args.what = args.child
        _child(args)
        return 0

    config, shapes = _layout(args.scale)
    need = sum(int(np.prod(s, dtype=np.int64)) * 4 for s in shapes.values())
    free = shutil.disk_usage(args.tmp).free
    factor = 2 if args.what in ("convert", "load_st") else 3  # the file + one Orbax copy, with margin
    if free < factor * need:
        print(f"not enough space in {args.tmp}: {free / 2**30:.1f} GiB free, need ~{factor * need / 2**30:.1f} GiB")
        return 2
    work = Path(tempfile.mkdtemp(prefix="rvggt_bench_convert_", dir=args.tmp))
    results = {}
    try:
        src, cfg = work / "model.safetensors", work / "config.json"
        config.to_json(cfg)
        t = time.perf_counter()
        size = write_random_safetensors(src, shapes)
        print(f"wrote {src} ({size / 2**30:.2f} GiB, {len(shapes)} tensors) in {time.perf_counter() - t:.0f}s")
        whats = WHATS if args.what == "all" else ("cli", "restore") if args.what == "restore" else (args.what,)
        for what in whats:
            r = _run_child(what, src, cfg, work / "orbax")  # restore reads what cli wrote
            peak, base = r["peak_kb"] * 1024, r["baseline_kb"] * 1024
            r.update(file_bytes=size, ratio=peak / size, ratio_above_baseline=(peak - base) / size)
            judged = r["ratio"] if args.scale == "1b" else r["ratio_above_baseline"]
            r["ok"] = judged < TARGET_RATIO or args.scale == "tiny"  # tiny: a smoke run, not judged
            results[what] = r
            print(
                f"[{what}] peak RSS {peak / 2**30:.2f} GiB = {r['ratio']:.3f}x the file "
                f"({(peak - base) / 2**30:.2f} GiB above the {base / 2**20:.0f} MiB after imports = "
                f"{r['ratio_above_baseline']:.3f}x); peak anon {r['peak_anon_kb'] / 2**20:.2f} GiB, "
                f"file-backed {r['peak_file_kb'] / 2**20:.2f} GiB; {r['seconds']:.1f}s"
                + (f" (convert {r['convert_s']:.1f}s, Orbax save {r['save_s']:.1f}s)" if what == "cli" else "")
                + (f"  [{'ok' if r['ok'] else 'OVER'} vs target {TARGET_RATIO}x]" if what == "convert" else "")
            )
    finally:
        if args.keep:
            print(f"kept {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)
    print(json.dumps({"scale": args.scale, **results}, indent=1))
    return 0 if "convert" not in results or results["convert"]["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
