"""Two versions of rvggt-jax side by side: whole forwards, alternating, in pairs.

    python benchmarks/bench_ab.py A B [--frames 64] [--presets dense regime] [--pairs 21]

A and B: source trees of rvggt-jax (a folder holding `rvggt_jax/` and `benchmarks/`), or
git revisions of this repository (checked out into temporary worktrees, removed after).
Each runs in a worker process of its own (`--worker`, started by this script), which
compiles the forward of every preset once on the benchmarks' speed layout with the
configurations `bench_peers.py` times (the camera and depth heads; the compressed presets
with duplicate_protected=True), on the same random weights and images, and then runs one
forward each time it is asked.

Why pairs: this host's speed moves by 5-40% in stretches of seconds to minutes, from
neighbours it cannot see (docs/benchmarks.md, "Noise this machine cannot see"). A change
worth 1-2% is lost between separate runs, and even between medians of one alternating
run. Each pair here is one forward of A and one of B, back to back (the order
alternating from pair to pair), so both sides of a pair almost always fall in the same
stretch: the median of the pairs' ratios B / A is what the comparison reads. It also
prints the ratio of the fastest forwards, the medians, the cores other processes held
during each pair (`host_load`: steady near 0 on a quiet host; it cannot see the
neighbours), and how far B's outputs are from A's (max |B - A| / max |A| per output).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks import host_load  # noqa: E402

OUTPUTS = ("depth", "depth_conf", "pose_enc")


def worker(tree: Path, frames: int, presets: list[str], out_dir: Path) -> None:
    """Compile every preset's forward from `tree`'s own rvggt_jax, save each one's outputs
    in out_dir, print "ready", then run the preset named on each line of stdin and print
    its wall seconds."""
    sys.path[:0] = [str(tree), str(tree / "benchmarks")]
    import jax
    import jax.numpy as jnp

    import rvggt_jax
    from bench_memory import random_params, small_layout

    if not Path(rvggt_jax.__file__).resolve().is_relative_to(tree.resolve()):
        raise SystemExit(f"the worker for {tree} imported rvggt_jax from {rvggt_jax.__file__}")
    rvggt_jax.prefer_threaded_convolutions()
    rvggt_jax.keep_freed_host_memory()
    base = dataclasses.replace(small_layout(), enable_point=False)
    params = random_params(base)
    images = jnp.asarray(np.random.default_rng(frames).random((1, frames, 3, 168, 224)), jnp.float32)
    programs = {}
    for preset in presets:
        cfg = base if preset == "dense" else base.with_compression(preset, duplicate_protected=True)
        programs[preset] = jax.jit(lambda p, x, c=cfg: rvggt_jax.rvggt_forward(p, x, c)).lower(params, images).compile()
        out = programs[preset](params, images)
        np.savez(out_dir / f"{preset}.npz", **{k: np.asarray(out[k]) for k in OUTPUTS})
    print("ready", flush=True)
    for line in sys.stdin:
        preset = line.strip()
        t0 = time.perf_counter()
        jax.block_until_ready(programs[preset](params, images))
        print(f"{time.perf_counter() - t0:.6f}", flush=True)


def _tree(spec: str, keep: list) -> Path:
    """A source tree for `spec`: the folder itself, or a temporary worktree of this
    repository at the git revision `spec` (appended to `keep` for removal)."""
    path = Path(spec)
    if (path / "rvggt_jax").is_dir():
        return path
    rev = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--verify", "--quiet", spec + "^{commit}"],
                         capture_output=True, text=True)
    if rev.returncode != 0:
        raise SystemExit(f"{spec!r} is neither a source tree (a folder with rvggt_jax/) nor a git revision of {REPO}")
    where = Path(tempfile.mkdtemp(prefix="rvggt-ab-")) / "tree"
    subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", "--quiet", str(where), rev.stdout.strip()],
                   check=True)
    keep.append(where)
    return where


def pair_summary(first: list[float], second: list[float]) -> dict:
    """Times of the pairs' two sides -> the median of the ratios second / first, their
    quartiles, the ratio of the minima and of the medians."""
    if len(first) != len(second) or not first:
        raise ValueError(f"need as many times on each side, at least one; got {len(first)} and {len(second)}")
    ratios = [b / a for a, b in zip(first, second)]
    q1, q3 = np.percentile(ratios, [25, 75])
    return dict(ratio=statistics.median(ratios), q1=float(q1), q3=float(q3),
                ratio_min=min(second) / min(first), ratio_median=statistics.median(second) / statistics.median(first))


def max_rel_diff(a: dict, b: dict) -> float:
    """The largest max |b - a| / max |a| over the outputs: `bench_peers.parity`, A as the
    reference (imported here: at the top it would load this repository's rvggt_jax into
    a worker before the worker's own tree)."""
    from benchmarks.bench_peers import parity

    return max(parity(b, a).values())


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("a", help="source tree or git revision: the reference")
    ap.add_argument("b", help="source tree or git revision: the one compared with it")
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--presets", nargs="+", default=["dense", "regime"])
    ap.add_argument("--pairs", type=int, default=21)
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        return worker(Path(args.worker), args.frames, args.presets, Path(args.out))
    if args.pairs < 1:
        raise SystemExit("--pairs must be at least 1")
    made: list[Path] = []
    outs: list[Path] = []
    procs = []
    try:
        trees = [_tree(args.a, made), _tree(args.b, made)]
        outs += [Path(tempfile.mkdtemp(prefix="rvggt-ab-out-")) for _ in trees]
        env = dict(os.environ)
        for tree, out in zip(trees, outs):
            procs.append(subprocess.Popen(
                [sys.executable, __file__, str(args.a), str(args.b), "--worker", str(tree), "--out", str(out),
                 "--frames", str(args.frames), "--presets", *args.presets],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env))
        for proc, tree in zip(procs, trees):
            line = proc.stdout.readline().strip()
            if line != "ready":
                raise SystemExit(f"the worker for {tree} did not start (said {line!r})")

        def run(i: int, preset: str) -> tuple[float, float | None]:
            before = host_load.snapshot(pids=(procs[i].pid,), own=False)
            procs[i].stdin.write(preset + "\n")
            procs[i].stdin.flush()
            dt = float(procs[i].stdout.readline())
            return dt, host_load.others(before, host_load.snapshot(pids=(procs[i].pid,), own=False))

        print(f"A = {trees[0]}\nB = {trees[1]}\n{args.frames} frames of 168 x 224, speed layout, {args.pairs} pairs")
        rows = []
        for preset in args.presets:
            times: tuple[list, list] = ([], [])
            load = []
            for k in range(args.pairs):
                for i in ((0, 1) if k % 2 == 0 else (1, 0)):
                    dt, others = run(i, preset)
                    times[i].append(dt)
                    if others is not None:
                        load.append(others)
            s = pair_summary(*times)
            diff = max_rel_diff(*(dict(np.load(o / f"{preset}.npz")) for o in outs))
            rows.append((preset, times, s, diff, max(load) if load else None))
        print("| preset | A median s | B median s | B / A, median of pairs (quartiles) | by minima | by medians "
              "| max rel diff of outputs | others' cores, max |")
        print("| --- | --- | --- | --- | --- | --- | --- | --- |")
        for preset, (ta, tb), s, diff, load in rows:
            print(f"| {preset} | {statistics.median(ta):.3f} | {statistics.median(tb):.3f} | **{s['ratio']:.3f}** "
                  f"({s['q1']:.3f}-{s['q3']:.3f}) | {s['ratio_min']:.3f} | {s['ratio_median']:.3f} | {diff:.1e} "
                  f"| {'-' if load is None else f'{load:.2f}'} |")
    finally:
        for proc in procs:
            if proc.stdin:
                proc.stdin.close()
            proc.wait()
        for where in made:
            subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(where)], check=False)
            shutil.rmtree(where.parent, ignore_errors=True)
        for out in outs:
            shutil.rmtree(out, ignore_errors=True)


if __name__ == "__main__":
    main()
