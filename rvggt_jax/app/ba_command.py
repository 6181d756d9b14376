"""`rvggt reconstruct --ba`: the model side of bundle adjustment (the track head as the
tracker of `rvggt_jax.ba`) and what the command says about it. The refinement itself is
`rvggt_jax.ba.refine`."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from rvggt_jax.app.console import say, warn
from rvggt_jax.app.messages import CLIError

__all__ = ["check_ba_available", "run_bundle_adjustment", "split_track_head", "tell_bundle_adjustment", "track_head_fn"]


def check_ba_available() -> None:
    """`CLIError` naming the extra to install when pycolmap is missing (checked before
    anything slow runs)."""
    from rvggt_jax.ba import PycolmapMissing, require_pycolmap

    try:
        require_pycolmap()
    except PycolmapMissing as e:
        raise CLIError(str(e)) from None


def split_track_head(params, config, weights):
    """(params without the track head, for the reconstruction's forward pass, which was
    compiled without it; the track head's program params and config). `CLIError` when
    the checkpoint has no track head."""
    if not config.enable_track or "track_head" not in params:
        raise CLIError(f"--ba needs the track head, and checkpoint {weights} has none (a checkpoint converted "
                       f"with --no-track?)")
    forward = {k: v for k, v in params.items() if k != "track_head"}
    return forward, {k: params[k] for k in ("aggregator", "track_head")}


def track_head_fn(params, config):
    """The `rvggt_jax.ba.tracks.TrackFn` of the model: `(images [S, 3, H, W], queries [N, 2])
    -> (tracks [S, N, 2], vis [S, N], conf [S, N])`, queries in frame 0. The program runs
    the aggregator and the track head only (the camera and dense heads are switched off:
    their outputs are already known, and a smaller program compiles faster); it is
    compiled once, every query frame having as many queries."""
    import jax
    import jax.numpy as jnp

    from rvggt_jax.model.forward import rvggt_forward

    config = dataclasses.replace(config, enable_camera=False, enable_depth=False, enable_point=False)
    forward = jax.jit(rvggt_forward)

    def track(images: np.ndarray, queries: np.ndarray):
        out = forward(params, jnp.asarray(images, jnp.float32)[None], config,
                      jnp.asarray(queries, jnp.float32)[None])
        tracks, vis = np.asarray(out["track"])[0], np.asarray(out["vis"])[0]
        conf = np.ones_like(vis) if out.get("conf") is None else np.asarray(out["conf"])[0]
        return tracks, vis, conf

    return track


def run_bundle_adjustment(out_dir: Path, recon, params, config, options) -> dict:
    """Bundle-adjust `recon` with the model's track head (`params`, `config`: the track
    program's, `split_track_head`) as `options.ba` says, write its outputs in `out_dir`
    (`rvggt_jax.ba.refine.write_outputs`) and say the reprojection errors before and
    after; the cameras are those of the COLMAP export (--camera-type, --shared-camera).
    Returns the report. Too few frames or tracks: `CLIError` (the feed-forward
    outputs are already written, and the message says so)."""
    from rvggt_jax.app.model_runner import enable_compilation_cache
    from rvggt_jax.ba import BAError, PycolmapMissing
    from rvggt_jax.ba.refine import CAMERAS_NAME, POINTS_NAME, REPORT_NAME, SPARSE_DIR, refine, write_outputs

    enable_compilation_cache()
    ba = dataclasses.replace(options.ba, camera_model=options.camera_type, shared_camera=options.shared_camera)
    try:
        outcome = refine(recon, track_head_fn(params, config), ba)
    except (BAError, PycolmapMissing) as e:
        raise CLIError(f"bundle adjustment: {e} (the feed-forward outputs are in {out_dir})") from None
    report = write_outputs(out_dir, outcome, recon.names, recon.sizes, ba)
    report["files"] = [f"{SPARSE_DIR}/", CAMERAS_NAME, POINTS_NAME, REPORT_NAME]
    if not outcome.usable:
        warn(f"bundle adjustment: pycolmap reports an unusable solution ({outcome.summary})")
    if outcome.error_after > outcome.error_before:
        warn(f"bundle adjustment raised the mean reprojection error ({outcome.error_before:.3g} -> "
             f"{outcome.error_after:.3g} px): the tracks are poor (lower --ba-max-error, raise the thresholds)")
    return report


def tell_bundle_adjustment(report: dict, out_dir: Path, quiet: bool) -> None:
    """The line `rvggt reconstruct --ba` prints: points, observations and the reprojection
    errors before and after (also in ba_report.json)."""
    say(quiet, f"bundle adjustment: {report['points']} points, {report['observations']} observations "
               f"(from {report['query_points']} query points in {len(report['query_frames'])} frames); mean "
               f"reprojection error {report['mean_reprojection_error_before_px']:.4g} px -> "
               f"{report['mean_reprojection_error_after_px']:.4g} px (network-input pixels); wrote "
               f"{', '.join(str(Path(out_dir) / f) for f in report['files'])}")
