"""Which bundle-adjustment defaults (`BAOptions.query_frames`, `query_points`) give the
best cameras for their time: a grid of both on held-out procedural scenes with the
shipped trained model rvggt-small (docs/ba.md has the table and the choice).

    python benchmarks/bench_ba_defaults.py --seeds 7 11 13 --out docs/ba_defaults.json

For each scene (`rvggt_jax.synthetic.make_scene(frames, 84, 112, seed)`, seeds in
`HELD_OUT_SEEDS`; seed 7 is `rvggt demo`'s scene) the model runs once
(`rvggt_jax.app.pipeline.reconstruct`, as `rvggt reconstruct` does), then
`rvggt_jax.ba.refine.refine` (what `--ba` runs: query points, the track head, filters,
triangulation, pycolmap's BA) for every (query_frames, query_points) of the grid, the
other options at their defaults. Per run:

- seconds: wall-clock time of `refine` (tracking + adjustment, not the model's forward).
  The track head's program is compiled once per query count per frame before anything
  is timed (`warm_up`: those compile times are reported apart, in "compile_s"), so no
  setting pays a compilation the others do not; SIFT and pycolmap compile nothing.
  "cpu_seconds" is the process CPU time of the same call (all threads), less
  sensitive to other jobs on a shared machine;
- reprojection error (network-input pixels, mean over the kept observations) before and
  after BA (not comparable across settings: each keeps its own points);
- against the scene's true cameras (`rvggt_jax.eval.heldout.camera_scores`): median
  relative rotation error (degrees) and AUC@30, before BA (the model's cameras: the
  baseline, the same for every setting) and after;
- usable: `refine` returned (no `BAError`) and pycolmap called the solution usable.

Each row aggregates the scenes: means of the errors and AUCs, the median of the
seconds; usable only if usable on every scene.

The choice (`choose`): among the rows usable on every scene whose median BA seconds are
within `--budget-s` (the time a default may cost: an 8-frame BA on this 2-core CPU in a
few seconds, as the demo runs it), the best camera AUC@30 after BA (mean over scenes) is
found; every row within `--auc-tolerance` of it (default 0: the most accurate row within
the budget) counts as equally good, and of those the one with the lowest median seconds
is chosen (ties: fewer query frames, then fewer points). Without a budget the best AUC
costs 5x the seconds for 0.04 more AUC (docs/ba.md). The rows and the criterion go to --out (JSON) and a markdown table to stdout.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

FRAMES_GRID = (1, 2, 4, 8)
POINTS_GRID = (256, 512, 1024, 2048, 4096)
AUC_TOLERANCE = 0.0
BUDGET_S = 5.0


def choose(rows: list[dict], auc_tolerance: float = AUC_TOLERANCE, budget_s: float = BUDGET_S) -> dict | None:
    """The chosen row (the module docstring's criterion), None when no row is usable
    within the budget."""
    usable = [r for r in rows if r["usable"] and r["seconds"] <= budget_s]
    if not usable:
        return None
    best = max(r["auc30_after"] for r in usable)
    near = [r for r in usable if r["auc30_after"] >= best - auc_tolerance]
    return min(near, key=lambda r: (r["seconds"], r["query_frames"], r["query_points"]))


def warm_up(track_fn, images: np.ndarray, counts) -> dict[int, float]:
    """Compile (and run once) the track program for every query count per frame in
    `counts`; returns the seconds of each first call (compile + one forward)."""
    h, w = images.shape[2:]
    out = {}
    for n in sorted(set(counts)):
        q = np.stack([np.linspace(8, w - 8, n), np.full(n, h / 2)], axis=1)
        t0 = time.perf_counter()
        track_fn(images, q)
        out[n] = time.perf_counter() - t0
    return out


def run_one(recon, track_fn, truth: np.ndarray, options) -> dict:
    """One BA of `recon` with `options`: seconds, errors, camera scores (see the module
    docstring)."""
    from rvggt_jax.ba import BAError
    from rvggt_jax.ba.refine import refine
    from rvggt_jax.eval.heldout import camera_scores

    t0, c0 = time.perf_counter(), time.process_time()
    try:
        o = refine(recon, track_fn, options)
    except BAError as e:
        return dict(seconds=time.perf_counter() - t0, cpu_seconds=time.process_time() - c0, usable=False,
                    error=str(e))
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    cams = camera_scores(o.extrinsic, truth)
    return dict(seconds=seconds, cpu_seconds=cpu, usable=bool(o.usable), reproj_before=float(o.error_before),
                reproj_after=float(o.error_after), rot_err_after=cams["rot_err_median"],
                auc30_after=cams["auc@30"], points=int(o.counts["points"]),
                observations=int(o.counts["observations"]), query_frames_used=len(o.query_frames))


def aggregate(per_scene: list[dict], before: list[dict]) -> dict:
    """A grid row from its runs on every scene (`before`: the model's camera scores)."""
    ok = all(r["usable"] for r in per_scene)

    def mean(key):
        vals = [r[key] for r in per_scene if key in r]
        return float(np.mean(vals)) if vals and ok else None

    return dict(usable=ok, seconds=float(np.median([r["seconds"] for r in per_scene])),
                cpu_seconds=float(np.median([r["cpu_seconds"] for r in per_scene])),
                reproj_before=mean("reproj_before"), reproj_after=mean("reproj_after"),
                rot_err_before=float(np.mean([b["rot_err_median"] for b in before])),
                rot_err_after=mean("rot_err_after"),
                auc30_before=float(np.mean([b["auc@30"] for b in before])), auc30_after=mean("auc30_after"),
                points=mean("points"), per_scene=per_scene)


def _f(v, fmt):
    return "-" if v is None else format(v, fmt)


def table(rows: list[dict], chosen: dict | None, current: tuple[int, int]) -> str:
    lines = ["| query frames | query points | BA seconds (median) | CPU seconds | reproj. px before -> after | "
             "points | rot. err. deg before -> after | AUC@30 before -> after | usable |",
             "|---:|---:|---:|---:|---|---:|---|---|---|"]
    for r in rows:
        mark = []
        if r is chosen:
            mark.append("**chosen**")
        if (r["query_frames"], r["query_points"]) == current:
            mark.append("(old default)")
        lines.append(
            f"| {r['query_frames']} | {r['query_points']} | {r['seconds']:.2f} | {r['cpu_seconds']:.2f} | "
            f"{_f(r['reproj_before'], '.3f')} -> {_f(r['reproj_after'], '.3f')} | {_f(r['points'], '.0f')} | "
            f"{r['rot_err_before']:.2f} -> {_f(r['rot_err_after'], '.2f')} | "
            f"{r['auc30_before']:.3f} -> {_f(r['auc30_after'], '.3f')} | "
            f"{'yes' if r['usable'] else 'no'} {' '.join(mark)} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default="rvggt-small")
    ap.add_argument("--seeds", type=int, nargs="+", default=[7, 11, 13], help="held-out scene seeds (< 100000)")
    ap.add_argument("--frames", type=int, default=8, help="frames per scene")
    ap.add_argument("--query-frames", type=int, nargs="+", default=list(FRAMES_GRID))
    ap.add_argument("--query-points", type=int, nargs="+", default=list(POINTS_GRID))
    ap.add_argument("--auc-tolerance", type=float, default=AUC_TOLERANCE)
    ap.add_argument("--budget-s", type=float, default=BUDGET_S,
                    help="the most median BA seconds a default may cost (default %(default)s)")
    ap.add_argument("--out", default="docs/ba_defaults.json", help="JSON of every number")
    args = ap.parse_args(argv)

    import jax

    import rvggt_jax
    from rvggt_jax.app.ba_command import split_track_head, track_head_fn
    from rvggt_jax.app.pipeline import reconstruct
    from rvggt_jax.ba.refine import BAOptions
    from rvggt_jax.ba.tracks import choose_query_frames
    from rvggt_jax.eval.heldout import camera_scores, images_of
    from rvggt_jax.synthetic import HELD_OUT_SEEDS, make_scene
    from rvggt_jax.weights.pretrained import BUNDLED, train_image_size

    if not all(s in HELD_OUT_SEEDS for s in args.seeds):
        raise SystemExit(f"seeds must be held-out (< 100000): {args.seeds}")
    t_start = time.perf_counter()
    params, config = rvggt_jax.load_pretrained(args.weights)
    fparams, tparams = split_track_head(params, config, args.weights)
    h, w = train_image_size(BUNDLED.get(args.weights, Path(args.weights))) or (84, 112)
    track_fn = track_head_fn(tparams, config)
    default = BAOptions()
    current = (default.query_frames, default.query_points)

    # the grid, frames capped at the scene's frame count (duplicates dropped)
    grid = sorted({(min(f, args.frames), p) for f in args.query_frames for p in args.query_points})

    scenes, recons, before, forward_s = [], [], [], []
    for seed in args.seeds:
        sc = make_scene(frames=args.frames, height=h, width=w, seed=seed)
        t0 = time.perf_counter()
        recon = reconstruct(images_of(sc)[0], fparams, config)
        forward_s.append(time.perf_counter() - t0)
        scenes.append(sc)
        recons.append(recon)
        before.append(camera_scores(recon.extrinsic, sc.extrinsics))
        print(f"seed {seed}: model cameras rot. err. {before[-1]['rot_err_median']:.2f} deg, "
              f"AUC@30 {before[-1]['auc@30']:.3f} ({forward_s[-1]:.1f} s forward)", flush=True)
    # query counts per frame: refine splits the points as ceil(points / frames actually chosen)
    per_frame = [-(-p // len(choose_query_frames(args.frames, f))) for f, p in grid]
    compile_s = warm_up(track_fn, recons[0].images, per_frame)
    print(f"track program compiled for {len(compile_s)} query counts in {sum(compile_s.values()):.0f} s", flush=True)

    runs = {key: [] for key in grid}
    for i, (sc, recon) in enumerate(zip(scenes, recons)):
        for f, p in grid:
            r = run_one(recon, track_fn, sc.extrinsics, BAOptions(query_frames=f, query_points=p))
            r["seed"] = args.seeds[i]
            runs[(f, p)].append(r)
            print(f"seed {args.seeds[i]} frames {f} points {p}: {r['seconds']:.2f} s, usable {r['usable']}, "
                  f"AUC@30 {_f(r.get('auc30_after'), '.3f')}, rot {_f(r.get('rot_err_after'), '.2f')}", flush=True)

    rows = [dict(query_frames=f, query_points=p, **aggregate(runs[(f, p)], before)) for f, p in grid]
    chosen = choose(rows, args.auc_tolerance, args.budget_s)
    for r in rows:
        r["chosen"] = r is chosen
    total = time.perf_counter() - t_start
    print(table(rows, chosen, current))
    print(f"chosen: {None if chosen is None else (chosen['query_frames'], chosen['query_points'])}; "
          f"total {total:.0f} s")
    doc = dict(
        command="python benchmarks/bench_ba_defaults.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        weights=args.weights, size=[h, w], frames=args.frames, seeds=args.seeds,
        criterion=dict(
            text="among rows usable on every scene within budget_s median BA seconds: the best mean AUC@30 after "
                 "BA; rows within auc_tolerance of it "
                 "are equally good; of those the lowest median BA seconds (ties: fewer query frames, then fewer "
                 "points)",
            metric="auc30_after", auc_tolerance=args.auc_tolerance, budget_s=args.budget_s, cost="seconds"),
        timing="wall-clock seconds of rvggt_jax.ba.refine.refine per scene (median over scenes), the track program "
               "compiled beforehand for every query count (compile_s, not counted)",
        chosen=None if chosen is None else dict(query_frames=chosen["query_frames"],
                                                 query_points=chosen["query_points"]),
        previous_default=dict(query_frames=current[0], query_points=current[1]),
        model_before=before, forward_s=forward_s, compile_s={str(k): v for k, v in compile_s.items()},
        total_s=total, rows=rows,
        machine=dict(cpus=os.cpu_count(), platform=platform.platform(), jax=jax.__version__))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(doc, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
