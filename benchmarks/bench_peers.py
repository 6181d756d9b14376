"""Our presets against the PyTorch peers, on the same checkpoint and images, alternating.

    python benchmarks/bench_peers.py --torch-python /tmp/torchvenv/bin/python \\
        --upstream-src /tmp/peers/vggt --fastvggt-src /tmp/peers/fastvggt \\
        --regime-src /tmp/peers/regimevggt --frames 16 64

Pairs (ours vs peer; a pair runs when its peer's source folder is given):

  dense     vs upstream VGGT           (--upstream-src: the folder holding vggt/)
  fastvggt  vs FastVGGT's own code     (--fastvggt-src: the folder holding merging/ and vggt/)
  regime    vs the RegimeVGGT authors' code (--regime-src: upstream VGGT with the authors'
            methods/, eval/ and vggt/ files written over it; see docs/history/peers.md,
            "Against the PyTorch peers", for how the folder is assembled)

Layout: the benchmarks' speed layout (`bench_memory.small_layout`: 24 layers of width 64,
one head of 64, DINO depth 1, DPT 16 -> 8/16/32/32), random weights drawn by upstream's
modules (`upstream.build_upstream`), float32, frames of 168 x 224. The checkpoint is
written by the upstream worker and read by `rvggt_jax.load_pretrained`.

Each peer runs in its own subprocess (`peer_worker.py`) under `--torch-python` (a Python
with torch; torch is never a dependency of rvggt-jax) with torch.set_num_threads(2); ours
runs here, jitted, on XLA:CPU with its default threads (the 2 cores of this machine, as
bench_dense.py / bench_regime.py run it). Both sides run with glibc's malloc keeping freed
memory for the next run (`rvggt_jax.keep_freed_host_memory`, as `rvggt` runs; the peers
get it through the environment, `peer_environment`). Each peer runs as written except for the
changes it needs to run on CPU in float32: `peer_worker.CPU_CHANGES` (printed).

FastVGGT's configuration on our side: the `fastvggt` preset with duplicate_protected=True
(FastVGGT's protected dst tokens appear twice among the keys/values, as its code does) and
the point head off (FastVGGT's VGGT() default). Its dst draw is ours (dst_cells, seed 33)
so that both pick the same dst patches.

The authors' configuration on our side: the `regime` preset (their HYBRID_CONFIG as their
code runs it, docs/method.md) with duplicate_protected=True (their protected dst tokens
appear twice among the keys/values) and the point head off (their eval scripts run the
camera and depth heads only); the dst draw is shared as for FastVGGT. The two agree to
float32 rounding (docs/benchmarks.md, "Against the PyTorch peers").

Per frame count: one warm-up run of each side (ours: compile + run; outputs compared),
then `--repeats` rounds; in each round every pair runs peer and ours back to back, the
order alternating between rounds. Reported: median times, peer / ours, parity (max |diff|
/ max |peer| per output; dense must be within --tol), the ratio of the fastest rounds
(the least disturbed on this shared host), and how many cores other processes held while
each call ran (`host_load`; the largest over a row's calls in its table's last column): a
call that ran beside other work measured the host, not the code. Slow-downs from outside
this virtual machine do not show there (docs/benchmarks.md, "Noise this machine cannot
see").

Our dense runs with upstream's heads (camera, depth, point), our compressed presets with
the peers' (camera, depth). So that their speed-up over dense compares the same heads,
each round also times our dense forward with the point head off, and the run ends with
each compressed preset's dense / ours (issue 26's "regime over dense").
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

import jax
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import rvggt_jax  # noqa: E402
from benchmarks import host_load  # noqa: E402
from benchmarks.bench_memory import small_layout  # noqa: E402
from rvggt_jax.compression.partition import dst_cells  # noqa: E402
from rvggt_jax.app import host_heap  # noqa: E402

KEYS = ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf")
WORKER = ROOT / "benchmarks" / "peer_worker.py"
# our dense forward with the compressed presets' heads (camera and depth)
SAME_HEADS = "dense, camera + depth heads"


class Peer:
    """A peer_worker.py subprocess."""

    def __init__(self, torch_python: str, kind: str, src: str, ckpt: Path, images: Path, threads: int,
                 dst_draw: Path | None = None, trace_layer: int = -1):
        cmd = [torch_python, str(WORKER), "--kind", kind, "--src", src, "--ckpt", str(ckpt), "--images", str(images),
               "--threads", str(threads), "--trace-layer", str(trace_layer)]
        if dst_draw is not None:
            cmd += ["--dst-draw", str(dst_draw)]
        self.kind = kind
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=ROOT,
                                     env=peer_environment())
        self.info = self._read()

    def _read(self) -> dict:
        line = self.proc.stdout.readline()
        if not line:
            raise SystemExit(f"peer {self.kind} exited (code {self.proc.wait()})")
        return json.loads(line)

    def run(self, save: Path | None = None) -> float:
        self.proc.stdin.write(json.dumps({"cmd": "run", "save": str(save) if save else None}) + "\n")
        self.proc.stdin.flush()
        return self._read()["seconds"]

    def close(self):
        self.proc.stdin.write(json.dumps({"cmd": "quit"}) + "\n")
        self.proc.stdin.flush()
        self.proc.wait()


def peer_environment() -> dict[str, str]:
    """A peer's environment: ours, with glibc's malloc keeping freed memory as ours does
    (`rvggt_jax.keep_freed_host_memory`; glibc reads it from the environment at start)."""
    env = dict(os.environ)
    if host_heap.applied():
        env.update(host_heap.glibc_environment())
    return env


def dst_draw(frames: int, h: int, w: int, seed: int = 33) -> np.ndarray:
    """Our per-cell dst choice as FastVGGT's randint draw [S-1, h/2, w/2]: k = dy*2 + dx."""
    out = []
    for f in range(1, frames):
        p = dst_cells(h, w, f, seed)
        out.append((((p // w) % 2) * 2 + (p % w) % 2).reshape(h // 2, w // 2))
    return np.stack(out).astype(np.int64)


def parity(ours: dict, peer: dict) -> dict:
    return {k: float(np.abs(np.asarray(ours[k]) - peer[k]).max() / np.abs(peer[k]).max())
            for k in KEYS if k in peer and k in ours}


def _load(cores: float | None) -> str:
    return "n/a" if cores is None else f"{cores:.2f}"


def _max_load(values: list) -> float | None:
    known = [v for v in values if v is not None]
    return max(known) if known else None


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--torch-python", required=True, help="a Python with torch, numpy, safetensors, einops")
    ap.add_argument("--upstream-src", help="folder holding the upstream vggt/ package (also writes the checkpoint)")
    ap.add_argument("--fastvggt-src", help="folder holding FastVGGT's merging/ and vggt/")
    ap.add_argument("--regime-src", help="folder holding the RegimeVGGT authors' methods/ over upstream's vggt/")
    ap.add_argument("--peers", nargs="+", default=["upstream", "fastvggt", "regime"],
                    choices=("upstream", "fastvggt", "regime"))
    ap.add_argument("--frames", type=int, nargs="+", default=[16])
    ap.add_argument("--height", type=int, default=168)
    ap.add_argument("--width", type=int, default=224)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op threads")
    ap.add_argument("--tol", type=float, default=1e-4, help="dense parity bound (max rel err)")
    ap.add_argument("--keep", help="folder to keep the checkpoint, images and outputs in")
    args = ap.parse_args(argv)
    if not args.upstream_src:
        raise SystemExit("--upstream-src is needed (it writes the checkpoint every side loads)")
    rvggt_jax.prefer_threaded_convolutions()
    rvggt_jax.keep_freed_host_memory()  # each run reuses the host memory the last one freed, as `rvggt` runs
    print(f"freed host memory kept for reuse, both sides: {host_heap.applied()}", flush=True)

    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench-peers-"))
    work.mkdir(parents=True, exist_ok=True)
    config = small_layout().validate()
    config.to_json(work / "config.json")
    subprocess.run([args.torch_python, str(WORKER), "--kind", "upstream", "--src", args.upstream_src,
                    "--ckpt", str(work), "--build", "--threads", str(args.threads)], check=True, cwd=ROOT)
    params, config = rvggt_jax.load_pretrained(work)
    h, w = args.height // config.patch_size, args.width // config.patch_size

    ours_cfg = {"dense": config}
    ours_params = {"dense": params}
    fast = dataclasses.replace(config, enable_point=False).with_compression("fastvggt", duplicate_protected=True)
    ours_cfg["fastvggt"] = fast
    ours_params["fastvggt"] = {k: v for k, v in params.items() if k != "point_head"}
    regime = dataclasses.replace(config, enable_point=False).with_compression("regime", duplicate_protected=True)
    ours_cfg["regime"] = regime
    ours_params["regime"] = ours_params["fastvggt"]
    srcs = {"upstream": args.upstream_src, "fastvggt": args.fastvggt_src, "regime": args.regime_src}
    pairs = [(o, p) for o, p in (("dense", "upstream"), ("fastvggt", "fastvggt"), ("regime", "regime"))
             if p in args.peers and srcs[p]]
    # Our compressed presets run with the peers' heads (camera and depth), our dense with
    # upstream's (the point head too): the compressed presets' speed-up over dense is
    # measured against a dense forward with their heads, timed in every round
    compressed = [o for o, _ in pairs if o != "dense"]
    if compressed:
        ours_cfg[SAME_HEADS] = dataclasses.replace(config, enable_point=False)
        ours_params[SAME_HEADS] = ours_params["regime"]

    print(f"layout: depth {config.depth}, width {config.embed_dim}, head dim {config.head_dim}, "
          f"DINO depth {config.dino.depth}, DPT {config.dpt_head.features}; float32; jax {jax.__version__} "
          f"({jax.devices()[0].platform}), torch threads {args.threads}", flush=True)
    rows, speedups = [], []
    for S in args.frames:
        rng = np.random.default_rng(0)
        images = rng.random((1, S, 3, args.height, args.width), dtype=np.float32)
        np.save(work / f"images_{S}.npy", images)
        np.save(work / f"dst_{S}.npy", dst_draw(S, h, w))
        images_j = jax.device_put(images)
        peers, fns = {}, {}
        for ours, peer in pairs:
            peers[peer] = Peer(args.torch_python, peer, srcs[peer], work, work / f"images_{S}.npy", args.threads,
                               work / f"dst_{S}.npy" if peer in ("fastvggt", "regime") else None)
            if S == args.frames[0]:
                cfg_from = peers[peer].info.get("config_from")
                print(f"{peer}: torch {peers[peer].info['torch']}, {peers[peer].info['threads']} threads; "
                      + (f"configuration from {cfg_from}; " if cfg_from else "")
                      + "CPU changes: " + " | ".join(peers[peer].info["cpu_changes"]), flush=True)
        for ours in [o for o, _ in pairs] + ([SAME_HEADS] if compressed else []):
            fn = jax.jit(rvggt_jax.rvggt_forward)
            fns[ours] = (lambda f=fn, p=ours_params[ours], c=ours_cfg[ours]: jax.block_until_ready(f(p, images_j, c)))
        times = {(o, p): {"ours": [], "peer": []} for o, p in pairs}
        loads = {(o, p): {"ours": [], "peer": []} for o, p in pairs}  # others' cores during each call
        same_heads, same_loads = [], []

        def timed(peer, call):
            """(seconds, others' cores) of one call: ours (peer None) timed here around the
            call, a peer's as its worker measured it (without the pipe's round trip). Only
            the process running the call is measured: the other side is others' load."""
            who = dict(own=True) if peer is None else dict(pids=(peers[peer].proc.pid,), own=False)
            before = host_load.snapshot(**who)
            t = time.perf_counter()
            out = call()
            dt = time.perf_counter() - t if peer is None else out
            return dt, host_load.others(before, host_load.snapshot(**who))

        errs = {}
        if compressed:
            fns[SAME_HEADS]()  # compile
        for ours, peer in pairs:  # warm-up: compile, outputs compared
            t = time.perf_counter()
            out = fns[ours]()
            compile_s = time.perf_counter() - t
            peers[peer].run(work / f"{peer}_{S}.npz")
            ref = dict(np.load(work / f"{peer}_{S}.npz"))
            errs[(ours, peer)] = parity(out, ref)
            print(f"S={S} {ours} compile + run {compile_s:.1f} s; vs {peer}: "
                  + ", ".join(f"{k} {v:.1e}" for k, v in errs[(ours, peer)].items()), flush=True)
        for r in range(args.repeats):
            for ours, peer in pairs:
                order = ("peer", "ours") if r % 2 == 0 else ("ours", "peer")
                for side in order:
                    dt, load = timed(None, fns[ours]) if side == "ours" else timed(peer, peers[peer].run)
                    times[(ours, peer)][side].append(dt)
                    loads[(ours, peer)][side].append(load)
                tt, tl = times[(ours, peer)], loads[(ours, peer)]
                print(f"S={S} round {r}: {peer} {tt['peer'][-1]:.2f} s, ours {ours} {tt['ours'][-1]:.2f} s; "
                      f"others' cores {_load(tl['peer'][-1])} / {_load(tl['ours'][-1])}", flush=True)
            if compressed:
                dt, load = timed(None, fns[SAME_HEADS])
                same_heads.append(dt)
                same_loads.append(load)
                print(f"S={S} round {r}: ours {SAME_HEADS} {same_heads[-1]:.2f} s; others' cores {_load(load)}",
                      flush=True)
        for p in peers.values():
            p.close()
        for (ours, peer), tt in times.items():
            mo, mp = statistics.median(tt["ours"]), statistics.median(tt["peer"])
            e = errs[(ours, peer)]
            ok = "" if ours != "dense" else (" (within tol)" if max(e.values()) <= args.tol else " (OVER TOL)")
            rows.append(dict(S=S, ours=ours, peer=peer, t_ours=mo, t_peer=mp, ratio=mp / mo,
                             ratio_min=min(tt["peer"]) / min(tt["ours"]),
                             pairs=[p / o for p, o in zip(tt["peer"], tt["ours"])], err=max(e.values()), ok=ok,
                             errs=e, others=loads[(ours, peer)],
                             others_max=_max_load(loads[(ours, peer)]["peer"] + loads[(ours, peer)]["ours"])))
        for ours in compressed:
            tt = times[(ours, dict(pairs)[ours])]["ours"]
            speedups.append(dict(S=S, ours=ours, dense=statistics.median(same_heads), t_ours=statistics.median(tt),
                                 ratio_min=min(same_heads) / min(tt),
                                 pairs=[d / o for d, o in zip(same_heads, tt)], others_dense=same_loads,
                                 others_max=_max_load(same_loads + loads[(ours, dict(pairs)[ours])]["ours"])))
    print("\n| frames | ours | peer | peer median s | ours median s | peer / ours (median) | by minima | per round | "
          "max rel diff of outputs | others' cores, max |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['S']} | `{r['ours']}` | {r['peer']} | {r['t_peer']:.2f} | {r['t_ours']:.2f} | "
              f"**{r['ratio']:.2f}** | {r['ratio_min']:.2f} | {', '.join(f'{x:.2f}' for x in r['pairs'])} | "
              f"{r['err']:.1e}{r['ok']} | "
              f"{_load(r['others_max'])} |")
    if speedups:
        print(f"\nOurs over our dense with the same heads (`{SAME_HEADS}`, timed in every round after the pairs):\n")
        print("| frames | ours | dense median s | ours median s | dense / ours (medians) | by minima | per round | "
              "others' cores, max |")
        print("| --- | --- | --- | --- | --- | --- | --- | --- |")
        for r in speedups:
            print(f"| {r['S']} | `{r['ours']}` | {r['dense']:.2f} | {r['t_ours']:.2f} | **{r['dense'] / r['t_ours']:.2f}** | "
                  f"{r['ratio_min']:.2f} | {', '.join(f'{x:.2f}' for x in r['pairs'])} | {_load(r['others_max'])} |")
    (work / "rows.json").write_text(json.dumps({"pairs": rows, "over_dense": speedups}, indent=1))


if __name__ == "__main__":
    main()
