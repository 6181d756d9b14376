"""The paper's Table 1 in miniature: what each compression preset costs the shipped
trained model (rvggt-small) in accuracy, and what it saves, on held-out procedural scenes.

    python benchmarks/bench_trade.py --frames 8 64 --scenes 4 --out docs/eval_trade.json \
        --plot docs/images/eval_trade.png

For each sequence length S and preset (dense, regime, fastvggt, avggt, and "calibrated":
`rvggt_jax.diagnostics.propose` on this model's rank profile over `--calibrate-scenes`
other held-out scenes, as `rvggt calibrate` fits it), on `--scenes` held-out scenes
(`rvggt_jax.synthetic.make_scene(frames=S, height, width, seed)` with seeds from
`--seed0`, all in `HELD_OUT_SEEDS`):

- accuracy (`rvggt_jax.eval.heldout.score_scene`, medians over scenes): camera AUC@30,
  RRA@15, RTA@15, depth AbsRel (median-scaled), point Chamfer (units of the scene size);
- cost: the cost model's aggregator FLOPs (`rvggt_jax.planning.cost.cost_report`) and its
  predicted speedup, and the measured CPU time of the jitted forward (median over the
  scenes, compiled first; every preset of a length is timed in the same process, one
  after another per scene, so the ratios are side by side).
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

import jax  # noqa: E402
import numpy as np  # noqa: E402

PRESETS = ("dense", "regime", "fastvggt", "avggt", "calibrated")
METRICS = ("auc@30", "rra@15", "rta@15", "abs_rel", "chamfer")


def calibrated_preset(params, config, size, seeds, frames):
    """`propose` on the mean rank profile of the dense model over held-out scenes."""
    from rvggt_jax import diagnostics as D
    from rvggt_jax.eval.heldout import images_of
    from rvggt_jax.synthetic import make_scene

    profiles = []
    for seed in seeds:
        sc = make_scene(frames=frames, height=size[0], width=size[1], seed=seed)
        profiles.append(D.rank_profile(params, images_of(sc), config.with_compression("dense"), m=128)["profile"])
    comp, info = D.propose(D.average_profiles(profiles), name="calibrated")
    return comp, info, [float(v) for v in D.average_profiles(profiles)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default="rvggt-small")
    ap.add_argument("--frames", type=int, nargs="+", default=[8, 64])
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--seed0", type=int, default=1000, help="first held-out evaluation seed")
    ap.add_argument("--calibrate-scenes", type=int, default=2)
    ap.add_argument("--calibrate-frames", type=int, default=16)
    ap.add_argument("--presets", default=",".join(PRESETS))
    ap.add_argument("--out", default=None, help="JSON of every number")
    ap.add_argument("--plot", default=None, help="PNG: accuracy against measured time per preset")
    args = ap.parse_args(argv)

    import dataclasses

    import rvggt_jax
    from rvggt_jax.eval.heldout import images_of, score_scene, summarize
    from rvggt_jax.model.forward import rvggt_forward
    from rvggt_jax.planning.cost import cost_report
    from rvggt_jax.synthetic import HELD_OUT_SEEDS, make_scene
    from rvggt_jax.train.small import train_image_size
    from rvggt_jax.weights.pretrained import BUNDLED

    params, config = rvggt_jax.load_pretrained(args.weights, skip_track=True)
    folder = BUNDLED.get(args.weights, Path(args.weights))
    size = train_image_size(folder) or (84, 112)
    h, w = size
    seeds = list(range(args.seed0, args.seed0 + args.scenes))
    cal_seeds = list(range(args.seed0 + 500, args.seed0 + 500 + args.calibrate_scenes))
    assert all(s in HELD_OUT_SEEDS for s in seeds + cal_seeds)
    names = [p for p in args.presets.split(",") if p]

    configs = {}
    cal_info = None
    for name in names:
        if name == "calibrated":
            comp, cal_info, profile = calibrated_preset(params, config, size, cal_seeds, args.calibrate_frames)
            cal_info = dict(cal_info, profile=profile)
            configs[name] = dataclasses.replace(config, compression=comp)
        else:
            configs[name] = config.with_compression(name)

    rows = []
    for frames in args.frames:
        scenes = [make_scene(frames=frames, height=h, width=w, seed=s) for s in seeds]
        fns = {n: jax.jit(lambda p, x, c=c: rvggt_forward(p, x, c)) for n, c in configs.items()}
        compile_s = {}
        for n, fn in fns.items():  # compile (and warm) every preset first
            t0 = time.perf_counter()
            jax.block_until_ready(fn(params, images_of(scenes[0])))
            compile_s[n] = time.perf_counter() - t0
        times = {n: [] for n in fns}
        scores = {n: [] for n in fns}
        for sc in scenes:
            x = jax.device_put(images_of(sc))
            for n, fn in fns.items():
                t0 = time.perf_counter()
                out = jax.block_until_ready(fn(params, x))
                times[n].append(time.perf_counter() - t0)
                scores[n].append(score_scene(jax.device_get(out), sc))
        for n in fns:
            cost = cost_report(configs[n], frames, h, w)
            summ = summarize(scores[n])
            rows.append(dict(preset=n, frames=frames, **{k: summ[k] for k in METRICS},
                             rot_err_median=summ["rot_err_median"], rot_err_identity=summ["rot_err_identity"],
                             abs_rel_constant=summ["abs_rel_constant"],
                             aggregator_gflops=cost["aggregator_flops"] / 1e9,
                             predicted_speedup=cost["predicted_speedup"],
                             time_s=float(np.median(times[n])), compile_s=compile_s[n]))
        dense_t = next(r["time_s"] for r in rows if r["frames"] == frames and r["preset"] == "dense") \
            if "dense" in fns else None
        for r in rows:
            if r["frames"] == frames and dense_t:
                r["measured_speedup"] = dense_t / r["time_s"]
        print(f"--- {frames} frames, {len(scenes)} scenes, {h}x{w}")
        print(table([r for r in rows if r["frames"] == frames]))

    doc = dict(weights=args.weights, size=[h, w], seeds=seeds, calibration_seeds=cal_seeds, calibrated=cal_info,
               rows=rows, machine=dict(cpus=os.cpu_count(), platform=platform.platform(), jax=jax.__version__))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(doc, indent=1))
    if args.plot:
        plot(rows, args.plot)
    return 0


def table(rows) -> str:
    head = ("| frames | preset | AUC@30 | RRA@15 | RTA@15 | AbsRel | Chamfer | GFLOPs (model) | predicted x | "
            "CPU time (s) | measured x |")
    lines = [head, "|" + "|".join(["---"] * 11) + "|"]
    for r in rows:
        lines.append(f"| {r['frames']} | {r['preset']} | {r['auc@30']:.3f} | {r['rra@15']:.3f} | {r['rta@15']:.3f} | "
                     f"{r['abs_rel']:.3f} | {r['chamfer']:.3f} | {r['aggregator_gflops']:.2f} | "
                     f"{r['predicted_speedup']:.2f} | {r['time_s']:.3f} | {r.get('measured_speedup', float('nan')):.2f} |")
    return "\n".join(lines)


def plot(rows, path) -> None:
    """AUC@30 and AbsRel against measured CPU time, one marker per preset, one panel per
    metric, lengths as separate series."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, metric, label in ((axes[0], "auc@30", "camera AUC@30 (higher is better)"),
                              (axes[1], "abs_rel", "depth AbsRel (lower is better)")):
        for frames in sorted({r["frames"] for r in rows}):
            sub = [r for r in rows if r["frames"] == frames]
            ax.plot([r["time_s"] for r in sub], [r[metric] for r in sub], "o", label=f"{frames} frames")
            for r in sub:
                ax.annotate(r["preset"], (r["time_s"], r[metric]), fontsize=7, xytext=(3, 3),
                            textcoords="offset points")
        ax.set_xscale("log")
        ax.set_xlabel("forward time on CPU (s, log)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("rvggt-small on held-out procedural scenes: presets' accuracy against time")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    raise SystemExit(main())
