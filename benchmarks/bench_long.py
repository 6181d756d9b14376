"""Long sequences chunk by chunk: time per frame and peak host RSS against the sequence
length S, with a predictor that needs no weights (`--predictor oracle`:
`rvggt_jax.sequence.oracle.OraclePredictor` on `rvggt_jax.synthetic.loop_walkthrough`, a
walk around a closed corridor; one loop for every S, 5 cm a frame for the largest).

Each S runs in a fresh subprocess, so that its peak RSS (`ru_maxrss`, reported by the
child itself) is that run's alone. The child predicts the chunks (`plan_chunks(S, 60,
10)`) one at a time and writes each to a `ChunkStore` on disk; then `align_chunks` chains
the stored chunks without loop closure and with it (loops verified by the predictor).
Chunks are read back by `ChunkStore.load` (every read maps the file anew, so the frames
the alignment has read do not stay resident). Nothing of a chunk but its cameras and
descriptors is held after it is written.

`--predictor tiny` runs the whole `rvggt reconstruct --chunk-frames` path instead
(`rvggt_jax.app.long_sequence.ChunkedRun`, `align`, `long_export.export_chunked`: the
chunk cache, alignment, loop closure and every output file) with the bundled tiny
random-weight model on the walk's frames written as PNG files at --height x --width
(multiples of 14; the images are read at that size, not resized to 518 as the command
does, which would make 10,000 frames hours of tiny-model time). Its points are capped at
--max-points (the cap is a constant of the run, not of S).

Columns: chunks; loops accepted; milliseconds per frame to predict and store, to align
the open chain, to align with loop closure; RSS after the imports and the walk (before
any chunk) and at the peak; ATE after a Sim(3) fit of the camera centres, in % of the
extent (the diagonal of the true centres' bounding box), open chain and loop-closed.

    python benchmarks/bench_long.py                        # S = 500, 2000, 10000 (~2 min)
    python benchmarks/bench_long.py --loop-block 128       # loop candidates 128 rows at a time
    python benchmarks/bench_long.py --store mmap           # ChunkStore.load's memory maps
    python benchmarks/bench_long.py --quick                # S = 200, 400 (seconds)

The markdown table goes to stdout (`--json PATH`: the rows too); each child's row to stderr.

A predictor is a function (walk, args) -> (frames [F] -> ChunkPrediction), registered by
name in `PREDICTORS` (`--predictor NAME`); a model-backed one renders the walk's images
for the frames asked (`walk.render(frames).images` at `--height` x `--width`) and runs
the model on them.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rvggt_jax.sequence.align import AlignOptions, align_chunks  # noqa: E402
from rvggt_jax.sequence.chunking import plan_chunks  # noqa: E402
from rvggt_jax.sequence.loops import LoopOptions  # noqa: E402
from rvggt_jax.sequence.oracle import OraclePredictor  # noqa: E402
from rvggt_jax.sequence.prediction import ChunkPrediction  # noqa: E402
from rvggt_jax.sequence.sim3 import umeyama  # noqa: E402
from rvggt_jax.sequence.store import ChunkStore  # noqa: E402
from rvggt_jax.synthetic import LoopWalk, loop_walkthrough  # noqa: E402

Predictor = Callable[[list[int]], ChunkPrediction]


def oracle_predictor(walk: LoopWalk, args: argparse.Namespace) -> Predictor:
    # the cache holds one chunk: the next chunk's overlap frames are not rendered twice
    return OraclePredictor(walk, noise=args.noise, bias_deg=args.bias_deg, seed=args.seed, cache_frames=args.chunk)


PREDICTORS: dict[str, Callable[[LoopWalk, argparse.Namespace], Predictor]] = {"oracle": oracle_predictor,
                                                                             "tiny": None}  # run_tiny


def rss_mib() -> float:
    """This process' peak resident set so far, MiB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def ate_percent(traj_centres: np.ndarray, true_centres: np.ndarray) -> float:
    """RMS centre error [S, 3] vs [S, 3] after a Sim(3) fit, in % of the true extent."""
    fit = umeyama(traj_centres, true_centres)
    err = np.sqrt(np.mean(np.sum((fit.apply(traj_centres) - true_centres) ** 2, axis=1)))
    lo, hi = true_centres.min(axis=0), true_centres.max(axis=0)
    return float(100.0 * err / np.linalg.norm(hi - lo))


def run_tiny(frames: int, args: argparse.Namespace) -> dict[str, Any]:
    """The `rvggt reconstruct --chunk-frames` pipeline on the walk with the tiny model."""
    from PIL import Image

    from rvggt_jax.app.long_export import export_chunked
    from rvggt_jax.app.long_sequence import ChunkedRun, align
    from rvggt_jax.app.options import ReconstructOptions
    from rvggt_jax.app.outdir import Manifest
    from rvggt_jax.io.images import ImageInfo
    from rvggt_jax.weights.pretrained import load_pretrained

    class SmallImages(ChunkedRun):
        """The frames at their own size (the command resizes them to 518 wide)."""

        def _load(self, frames):
            images = np.stack([np.asarray(Image.open(self.paths[f]), np.float32).transpose(2, 0, 1) / np.float32(255)
                               for f in frames])
            h, w = images.shape[2:]
            infos = [ImageInfo(path=str(self.paths[f]), name=self.paths[f].name, width=w, height=h, sx=1.0, sy=1.0,
                               ox=0.0, oy=0.0, valid=(0, 0, w, h)) for f in frames]
            return images, infos

    walk = loop_walkthrough(frames, seed=args.seed, height=args.height, width=args.width, length=args.length)
    params, config = load_pretrained(Path(__file__).resolve().parents[1] / "rvggt_jax" / "examples_data" / "tiny")
    config = config.with_outputs(descriptors=True)
    options = ReconstructOptions(chunk_frames=args.chunk, overlap=args.overlap, loop_closure=True, quiet=True,
                                 max_points=args.max_points)
    with tempfile.TemporaryDirectory(prefix="bench-long-") as tmp:
        src, out = Path(tmp) / "frames", Path(tmp) / "out"
        src.mkdir()
        out.mkdir()
        for start in range(0, frames, 500):  # rendered in batches: the walk is never held whole
            block = list(range(start, min(start + 500, frames)))
            for f, im in zip(block, walk.render(block).images):
                Image.fromarray(im).save(src / f"frame_{f:06d}.png")
        rss_start = rss_mib()
        run = SmallImages(sorted(src.iterdir()), (args.height, args.width), params, config, options, args.chunk,
                          args.overlap)
        store = ChunkStore(out / "chunks")
        t0 = time.perf_counter()
        plan = run.run_chunks(store, Manifest(out), quiet=True)
        t1 = time.perf_counter()
        trajectory = align(run, store)
        t2 = time.perf_counter()
        summary = export_chunked(out, run, store, trajectory, src, "tiny")
        t3 = time.perf_counter()
    return dict(frames=frames, chunks=len(plan), loops=len(trajectory.loops), predict_ms=1e3 * (t1 - t0) / frames,
                open_ms=float("nan"), closed_ms=1e3 * (t2 - t1) / frames, export_ms=1e3 * (t3 - t2) / frames,
                points=summary["points"], rss_start_mib=rss_start, rss_peak_mib=rss_mib(),
                ate_open_pct=float("nan"), ate_closed_pct=ate_percent(trajectory.centers, walk.centers))


def run_one(frames: int, args: argparse.Namespace) -> dict[str, Any]:
    """One sequence of `frames` frames, in this process -> the row's numbers."""
    if args.predictor == "tiny":
        return run_tiny(frames, args)
    walk = loop_walkthrough(frames, seed=args.seed, height=args.height, width=args.width, length=args.length)
    predict = PREDICTORS[args.predictor](walk, args)
    plan = plan_chunks(frames, args.chunk, args.overlap)
    rss_start = rss_mib()
    with tempfile.TemporaryDirectory(prefix="bench-long-") as tmp:
        store = ChunkStore(tmp)
        t0 = time.perf_counter()
        for k, f in enumerate(plan):
            store.save(k, predict([int(i) for i in f]))
        t1 = time.perf_counter()
        chunks = [store.load(k) for k in range(len(plan))]
        options = AlignOptions(loops=LoopOptions(block=args.loop_block))
        open_chain = align_chunks(chunks, options=options)
        t2 = time.perf_counter()
        closed = align_chunks(chunks, loop_closure=True, verify=predict, options=options)
        t3 = time.perf_counter()
        truth = walk.centers
        row = dict(frames=frames, chunks=len(plan), loops=len(closed.loops),
                   predict_ms=1e3 * (t1 - t0) / frames, open_ms=1e3 * (t2 - t1) / frames,
                   closed_ms=1e3 * (t3 - t2) / frames, rss_start_mib=rss_start, rss_peak_mib=rss_mib(),
                   ate_open_pct=ate_percent(open_chain.centers, truth),
                   ate_closed_pct=ate_percent(closed.centers, truth))
    return row


def table(rows: list[dict[str, Any]], args: argparse.Namespace) -> str:
    head = ("| S | chunks | loops | predict+store ms/frame | align ms/frame | align+loops ms/frame "
            "| export ms/frame | RSS start MiB | RSS peak MiB | ATE open % | ATE closed % |")
    lines = [f"predictor {args.predictor}, chunks of {args.chunk} (overlap {args.overlap}), {args.height}x{args.width} "
             f"px, a {args.length:g} m loop, noise {args.noise}, bias {args.bias_deg} deg/chunk, loop block "
             f"{args.loop_block}{f', at most {args.max_points} points' if args.predictor == 'tiny' else ''}", "",
             head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        lines.append(f"| {r['frames']} | {r['chunks']} | {r['loops']} | {r['predict_ms']:.2f} | {r['open_ms']:.3f} "
                     f"| {r['closed_ms']:.3f} | {r.get('export_ms', float('nan')):.2f} | {r['rss_start_mib']:.0f} "
                     f"| {r['rss_peak_mib']:.0f} "
                     f"| {r['ate_open_pct']:.3f} | {r['ate_closed_pct']:.4f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--frames", type=int, nargs="+", default=[500, 2000, 10000], help="sequence lengths S")
    ap.add_argument("--quick", action="store_true", help="S = 200, 400: a check that the script runs")
    ap.add_argument("--predictor", choices=sorted(PREDICTORS), default="oracle")
    ap.add_argument("--chunk", type=int, default=60)
    ap.add_argument("--overlap", type=int, default=10)
    ap.add_argument("--length", type=float,
                    help="the loop's length, metres, the same for every S, so that what a frame sees (and costs to "
                         "render) does not change with S; default 5 cm a frame of the largest S (at least 40 m)")
    ap.add_argument("--height", type=int, default=24)
    ap.add_argument("--width", type=int, default=32)
    ap.add_argument("--noise", type=float, default=0.01, help="oracle: pixel noise, a fraction of the depth")
    ap.add_argument("--bias-deg", type=float, default=0.3, help="oracle: rotation bias per chunk, degrees")
    ap.add_argument("--loop-block", type=int, default=LoopOptions().block,
                    help="rows of the descriptor similarity matrix computed at a time (memory ~ rows x S)")
    ap.add_argument("--max-points", type=int, default=100_000, help="tiny: the point cloud's cap")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, help="also write the rows here")
    ap.add_argument("--child", type=int, help=argparse.SUPPRESS)  # one S, in this process: prints a JSON row
    args = ap.parse_args(argv)
    if args.child is not None:
        print(json.dumps(run_one(args.child, args)))
        return
    sizes = [200, 400] if args.quick else args.frames
    if args.length is None:
        args.length = max(40.0, 0.05 * max(sizes))
    passed = [a for a in (argv if argv is not None else sys.argv[1:]) if a != "--quick"] + ["--length", str(args.length)]
    rows = []
    for s in sizes:
        # a fresh interpreter per S: ru_maxrss is a process' peak, never lowered
        out = subprocess.run([sys.executable, __file__, *passed, "--child", str(s)], check=True,
                             capture_output=True, text=True).stdout
        rows.append(json.loads(out.strip().splitlines()[-1]))
        print(f"S = {s}: {rows[-1]}", file=sys.stderr)
    print(table(rows, args))
    if args.json:
        args.json.write_text(json.dumps(dict(args={k: str(v) for k, v in vars(args).items()}, rows=rows), indent=1))


if __name__ == "__main__":
    main()
