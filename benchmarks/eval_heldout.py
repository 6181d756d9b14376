"""A trained model (default: the shipped rvggt-small) on held-out procedural scenes against
the trivial baselines: the numbers of its model card.

    python benchmarks/eval_heldout.py --frames 4 8 --scenes 10 [--weights DIR] [--json out.json]

Scenes: `rvggt_jax.synthetic.make_scene(frames, H, W, seed)` at the model's training size
with seeds `--seed0` ... (held out: `HELD_OUT_SEEDS`). Metrics: `rvggt_jax.eval.heldout`
(medians over scenes): depth AbsRel (median-scaled) and that of the best constant depth
per image; the median relative rotation error between frames and that of identity
rotations (every camera predicted as the first); camera AUC@30, RRA@15, RTA@15; point
Chamfer (units of the scene size).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default="rvggt-small")
    ap.add_argument("--frames", type=int, nargs="+", default=[4, 8])
    ap.add_argument("--scenes", type=int, default=10)
    ap.add_argument("--seed0", type=int, default=100)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)

    import jax
    import numpy as np

    import rvggt_jax
    from rvggt_jax.eval.heldout import images_of, score_scene, summarize
    from rvggt_jax.model.forward import rvggt_forward
    from rvggt_jax.synthetic import HELD_OUT_SEEDS, make_scene
    from rvggt_jax.train.small import train_image_size
    from rvggt_jax.weights.pretrained import BUNDLED

    params, config = rvggt_jax.load_pretrained(args.weights, skip_track=True)
    h, w = train_image_size(BUNDLED.get(args.weights, Path(args.weights))) or (84, 112)
    seeds = list(range(args.seed0, args.seed0 + args.scenes))
    assert all(s in HELD_OUT_SEEDS for s in seeds)
    fn = jax.jit(lambda p, x: rvggt_forward(p, x, config))
    out = {}
    print("| frames | AbsRel | best constant | ratio | rot. err. median (deg) | identity | ratio | AUC@30 | RRA@15 | "
          "RTA@15 | Chamfer |")
    print("|" + "|".join(["---"] * 11) + "|")
    for frames in args.frames:
        rows = []
        for seed in seeds:
            sc = make_scene(frames=frames, height=h, width=w, seed=seed)
            rows.append(score_scene(jax.device_get(fn(params, images_of(sc))), sc))
        m = summarize(rows)
        out[frames] = dict(median=m, scenes=rows)
        print(f"| {frames} | {m['abs_rel']:.3f} | {m['abs_rel_constant']:.3f} | {m['abs_rel'] / m['abs_rel_constant']:.2f} "
              f"| {m['rot_err_median']:.2f} | {m['rot_err_identity']:.2f} | "
              f"{m['rot_err_median'] / m['rot_err_identity']:.2f} | {m['auc@30']:.3f} | {m['rra@15']:.3f} | "
              f"{m['rta@15']:.3f} | {m['chamfer']:.3f} |")
        ratio_d = np.array([r["abs_rel"] / r["abs_rel_constant"] for r in rows])
        ratio_r = np.array([r["rot_err_median"] / r["rot_err_identity"] for r in rows])
        print(f"  (per scene: AbsRel ratio <= 0.6 in {int((ratio_d <= 0.6).sum())}/{len(rows)}, rotation ratio <= 0.5 "
              f"in {int((ratio_r <= 0.5).sum())}/{len(rows)})", file=sys.stderr)
    if args.json:
        Path(args.json).write_text(json.dumps(dict(weights=args.weights, size=[h, w], seeds=seeds,
                                                   results={str(k): v for k, v in out.items()}), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
