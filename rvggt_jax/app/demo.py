"""`rvggt demo`: the bundled trained model rvggt-small on the bundled held-out procedural
scene (`rvggt_jax/examples_data/scene`, rendered by `rvggt_jax.examples_data.generate`),
reconstructed as `rvggt reconstruct` does, and its cameras compared with the scene's true
ones."""

from __future__ import annotations

import json
from pathlib import Path

from rvggt_jax.app.commands import EXAMPLES_DIR, reconstruct_folder
from rvggt_jax.app.console import say
from rvggt_jax.app.messages import CLIError
from rvggt_jax.app.options import ReconstructOptions

__all__ = ["DEMO_MODEL", "DEMO_NOTICE", "DEMO_SCENE", "demo", "demo_camera_errors"]

DEMO_SCENE = EXAMPLES_DIR / "scene"  # the demo's held-out procedural scene: images/, cameras.json, depth/
DEMO_MODEL = "rvggt-small"  # the small VGGT trained here (rvggt_jax.weights.pretrained.BUNDLED)

DEMO_NOTICE = (
    "rvggt demo: rvggt-small, a 6M-parameter VGGT trained here from scratch on procedural scenes "
    "(model card: rvggt_jax/examples_data/rvggt_small/README.md), on 8 views of a held-out procedural room "
    "(rvggt_jax/examples_data/scene, 112x84). It knows only such rooms; for photos run "
    "`rvggt reconstruct IMAGES --weights facebook/VGGT-1B --out OUT`."
)


def demo(out_dir: str | Path = "rvggt_demo", options: ReconstructOptions = ReconstructOptions()) -> dict:
    """Run `reconstruct_folder` on the bundled held-out scene with the bundled trained
    model rvggt-small and compare its cameras with the scene's true ones (`options`: those
    of `rvggt demo`: --preset, --dtype, --ba, --overwrite and --quiet). The summary gains
    "ground_truth" (`demo_camera_errors`)."""
    say(options.quiet, DEMO_NOTICE)
    if not (DEMO_SCENE / "images").is_dir() or not (DEMO_SCENE / "cameras.json").is_file():
        raise CLIError(f"bundled demo scene missing under {DEMO_SCENE} (broken install?)")
    summary = reconstruct_folder(DEMO_SCENE / "images", DEMO_MODEL, out_dir, options)
    summary["ground_truth"] = demo_camera_errors(Path(out_dir) / "cameras.json", DEMO_SCENE / "cameras.json")
    g = summary["ground_truth"]
    say(options.quiet, f"against the scene's true cameras: relative rotation error median {g['rot_err_median']:.1f} "
                       f"deg (every camera predicted as the first: {g['rot_err_identity']:.1f} deg), AUC@30 "
                       f"{g['auc@30']:.3f}, RRA@15 {g['rra@15']:.2f}, RTA@15 {g['rta@15']:.2f}")
    if "ba" in summary:
        from rvggt_jax.ba.refine import CAMERAS_NAME

        b = summary["ground_truth_ba"] = demo_camera_errors(Path(out_dir) / CAMERAS_NAME, DEMO_SCENE / "cameras.json")
        say(options.quiet, f"after bundle adjustment: relative rotation error median {b['rot_err_median']:.1f} deg, "
                           f"AUC@30 {b['auc@30']:.3f}, RRA@15 {b['rra@15']:.2f}, RTA@15 {b['rta@15']:.2f}")
    say(options.quiet, f"demo outputs in {out_dir} (rvggt view {out_dir} to look at them)")
    return summary


def demo_camera_errors(predicted: Path, truth: Path) -> dict[str, float]:
    """Relative pose errors of the cameras.json a run wrote against a scene's true
    cameras.json (matched by image name): median rotation error (degrees), the same for
    identity rotations (every camera the first), AUC@30, RRA@15 and RTA@15."""
    import numpy as np

    from rvggt_jax.eval.heldout import camera_scores

    pred = {f["image"]: f["extrinsic"] for f in json.loads(predicted.read_text())["frames"]}
    gt = {Path(f["image"]).name: f["extrinsic"] for f in json.loads(truth.read_text())["frames"]}
    names = [n for n in sorted(gt) if n in pred]
    if len(names) < 2:
        raise CLIError(f"{predicted} and {truth} share fewer than 2 images")
    return camera_scores(np.array([pred[n] for n in names], np.float64), np.array([gt[n] for n in names], np.float64))
