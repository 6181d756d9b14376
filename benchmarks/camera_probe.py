"""Does a trained model's camera head use the other frames? Three probes of rvggt-small (or
any checkpoint, or a `rvggt train-small` run's saved state) that separate "cameras not
learned yet" from "cameras cannot be learned by this run":

    python benchmarks/camera_probe.py [--weights rvggt-small | --state RUN_DIR [--step N]]

1. **LayerScale**: the mean |gamma| of each frame, global and camera-trunk block. Upstream
   starts them at 0.01 (`rvggt_jax.model.initializers.AGGREGATOR_LAYER_SCALE`); a block
   whose gamma stayed near it adds about 1% to the token stream.
2. **Cross-frame sensitivity**: the mean relative change of frames 1..3's pose encoding,
   depth and points when frame 0 is replaced by another scene's first frame
   (`make_scene` seeds 101 and 105, 4 frames). Near 0: the frames are treated one by one.
3. **Pairs**: two-frame `make_scene` pairs (held-out seeds 200-211) with arcs of 5 to 60
   degrees: the predicted relative rotation against the true one, their correlation,
   and the mean error against that of the best constant guess (the true mean).

Prints one table per probe. Held-out seeds only (`rvggt_jax.synthetic.HELD_OUT_SEEDS`).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _load(args):
    import jax

    import rvggt_jax

    if args.state is None:
        return rvggt_jax.load_pretrained(args.weights, skip_track=True)
    from rvggt_jax.config import VGGTConfig
    from rvggt_jax.train.step import TrainConfig, init_state, restore_state

    config = VGGTConfig.rvggt_small()
    like = jax.eval_shape(lambda: init_state(rvggt_jax.init_params(config, 0), TrainConfig()))
    params = restore_state(args.state, like, args.step).params
    params.pop("track_head", None)
    return params, dataclasses.replace(config, enable_track=False)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", default="rvggt-small")
    ap.add_argument("--state", default=None, help="a `rvggt train-small` output folder: probe its saved state")
    ap.add_argument("--step", type=int, default=None, help="the state's step (default: the newest)")
    args = ap.parse_args(argv)

    import jax
    import numpy as np

    from rvggt_jax.eval.camera import rotation_angle_deg
    from rvggt_jax.eval.heldout import images_of, predicted_cameras
    from rvggt_jax.model.forward import rvggt_forward
    from rvggt_jax.synthetic import HELD_OUT_SEEDS, make_scene

    params, config = _load(args)
    fn = jax.jit(lambda p, x: rvggt_forward(p, x, config))
    h, w = 84, 112

    print("| blocks | mean abs LayerScale gamma (ls1 / ls2), block by block |\n|---|---|")
    groups = {"frame": params["aggregator"]["frame_blocks"], "global": params["aggregator"]["global_blocks"],
              "camera trunk": params["camera_head"]["trunk"]}
    for name, blocks in groups.items():
        vals = [f"{float(np.abs(np.asarray(blocks[k]['ls1']['gamma'])).mean()):.4f} / "
                f"{float(np.abs(np.asarray(blocks[k]['ls2']['gamma'])).mean()):.4f}" for k in sorted(blocks, key=int)]
        print(f"| {name} | {', '.join(vals)} |")

    a_scene, b_scene = (make_scene(frames=4, height=h, width=w, seed=s) for s in (101, 105))
    x = images_of(a_scene)
    swapped = x.copy()
    swapped[0, 0] = images_of(b_scene)[0, 0]
    a, b = jax.device_get(fn(params, x)), jax.device_get(fn(params, swapped))
    print("\n| output | relative change of frames 1-3 when frame 0 is swapped |\n|---|---|")
    for k in ("pose_enc", "depth", "world_points"):
        change = np.abs(a[k][0, 1:] - b[k][0, 1:]).mean() / np.abs(a[k][0, 1:]).mean()
        print(f"| {k} | {change:.2e} |")

    pred, true = [], []
    for i, seed in enumerate(range(200, 212)):
        assert seed in HELD_OUT_SEEDS
        sc = make_scene(frames=2, height=h, width=w, seed=seed, arc_deg=5.0 + 55.0 * ((i * 5) % 12) / 11)
        ext, _ = predicted_cameras(jax.device_get(fn(params, images_of(sc))), (h, w))
        # the rotation between the pair's two cameras (world-to-camera [2, 3, 4])
        pred.append(float(rotation_angle_deg(ext[0, :3, :3], ext[1, :3, :3])))
        true.append(float(rotation_angle_deg(sc.extrinsics[0, :3, :3], sc.extrinsics[1, :3, :3])))
    pred, true = np.array(pred), np.array(true)
    print("\n| pairs (deg) | values |\n|---|---|")
    print(f"| true relative rotation | {', '.join(f'{v:.1f}' for v in true)} |")
    print(f"| predicted | {', '.join(f'{v:.1f}' for v in pred)} |")
    print(f"| correlation | {np.corrcoef(pred, true)[0, 1]:.3f} |")
    print(f"| mean abs error | {np.abs(pred - true).mean():.2f} (best constant guess: "
          f"{np.abs(true - true.mean()).mean():.2f}) |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
