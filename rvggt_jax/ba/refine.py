"""Bundle adjustment of a `rvggt_jax.app.pipeline.Reconstruction` (`refine`) and its
outputs (`write_outputs`): what `rvggt reconstruct --ba` runs after the forward pass.

Everything is computed in network-input pixels (where the tracker, the depth
confidences and `network_intrinsic` live) and converted to the original images' pixels
only when written: the map from one to the other is affine per frame
(A = intrinsic @ network_intrinsic^-1: a scale and an offset), so cameras and 2-D
observations convert exactly and the 3-D points are unchanged.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from rvggt_jax.ba import BAError
from rvggt_jax.ba.tracks import (KEYPOINT_METHODS, TrackFn, choose_query_frames, filter_tracks, query_points,
                                 track_from_query_frames)
from rvggt_jax.ba.triangulate import Triangulated, mean_reprojection_error, reprojection_errors, triangulate_tracks

__all__ = ["BAOptions", "BAOutcome", "CAMERAS_NAME", "POINTS_NAME", "REPORT_NAME", "SPARSE_DIR", "refine", "write_outputs"]

REPORT_NAME = "ba_report.json"
SPARSE_DIR = "sparse_ba"  # COLMAP text model with tracks; the binary one in sparse_ba/bin
CAMERAS_NAME = "cameras_ba.json"
POINTS_NAME = "points_ba.ply"


@dataclass(frozen=True, kw_only=True)
class BAOptions:
    """How `--ba` runs (the `--ba-*` options of `rvggt reconstruct`).

    query_frames: frames the query points are taken in (evenly spaced, frame 0 first);
      each costs one forward pass with the track head.
    query_points: query points in all, split evenly over the query frames.
      Their defaults (2 frames, 512 points) were chosen by measurement: the best camera
      AUC@30 against the truth after BA on held-out scenes within a budget of 5 s per
      8-frame BA on a 2-core CPU, the fastest of the near-ties
      (docs/ba.md, benchmarks/bench_ba_defaults.py; tests/ba/test_ba_defaults.py keeps
      them equal to docs/ba_defaults.json's choice).
    keypoints: "sift" (SIFT keypoints ranked by depth confidence, topped up with grid
      points) or "grid" (the most confident pixel of each grid cell); see
      `rvggt_jax.ba.tracks`.
    vis_threshold / conf_threshold: keep a track's observation in a frame when the
      tracker's visibility / confidence there is at least this (both in [0, 1]).
    max_error: observations reprojecting farther than this many (network-input) pixels
      from the point triangulated with the predicted cameras are dropped; after BA,
      points with an observation this far (or behind a camera) are dropped.
    min_angle: points whose viewing rays meet at less than this many degrees are dropped
      before BA (their depth is barely constrained; BA would send them far away).
    min_points: fewer surviving points than this is an error (`BAError`), not a BA.
    refine_focal: also refine each frame's focal lengths (default: poses and points).
    loss: robust loss of the residuals (`rvggt_jax.ba.adjust.LOSSES`).
    max_iterations: the solver's iteration cap.
    camera_model / shared_camera: the COLMAP cameras adjusted and written (`rvggt
      reconstruct`'s --camera-type / --shared-camera, `rvggt_jax.io.colmap.colmap_cameras`):
      PINHOLE (fx, fy), SIMPLE_PINHOLE or SIMPLE_RADIAL (one f); one camera per frame or
      one for all.
    """

    query_frames: int = 2
    query_points: int = 512
    keypoints: str = "sift"
    vis_threshold: float = 0.2
    conf_threshold: float = 0.2
    max_error: float = 8.0
    min_angle: float = 1.0
    min_points: int = 16
    refine_focal: bool = False
    loss: str = "cauchy"
    max_iterations: int = 100
    camera_model: str = "PINHOLE"
    shared_camera: bool = False

    def check(self) -> None:
        """ValueError naming the command-line option of a value out of range."""
        from rvggt_jax.ba.adjust import LOSSES

        if self.query_frames < 1:
            raise ValueError(f"--ba-query-frames must be at least 1; got {self.query_frames}")
        if self.query_points < 1:
            raise ValueError(f"--ba-query-points must be at least 1; got {self.query_points}")
        if self.keypoints not in KEYPOINT_METHODS:
            raise ValueError(f"--ba-keypoints must be one of {', '.join(KEYPOINT_METHODS)}; got {self.keypoints!r}")
        for name, v in (("--ba-vis-threshold", self.vis_threshold), ("--ba-conf-threshold", self.conf_threshold)):
            if not (math.isfinite(v) and 0.0 <= v <= 1.0):
                raise ValueError(f"{name} must be in [0, 1]; got {v}")
        if not (math.isfinite(self.max_error) and self.max_error > 0):
            raise ValueError(f"--ba-max-error must be a positive number of pixels; got {self.max_error}")
        if not (math.isfinite(self.min_angle) and 0.0 <= self.min_angle < 90.0):
            raise ValueError(f"min_angle must be in [0, 90) degrees; got {self.min_angle}")
        if self.min_points < 1:
            raise ValueError(f"min_points must be at least 1; got {self.min_points}")
        if self.loss not in LOSSES:
            raise ValueError(f"loss must be one of {', '.join(LOSSES)}; got {self.loss!r}")
        if self.max_iterations < 1:
            raise ValueError(f"max_iterations must be at least 1; got {self.max_iterations}")
        from rvggt_jax.io.colmap import CAMERA_MODELS

        if self.camera_model not in CAMERA_MODELS:
            raise ValueError(f"--camera-type must be one of {', '.join(CAMERA_MODELS)}; got {self.camera_model!r}")


@dataclass(frozen=True, eq=False)
class BAOutcome:
    """A bundle-adjusted reconstruction: S frames, M points.

    extrinsic [S, 3, 4] world-to-camera (refined), intrinsic [S, 3, 3] in original-image
    pixels, network_intrinsic [S, 3, 3] in network-input pixels; points [M, 3] (refined),
    colors [M, 3] uint8; tracks [S, M, 2] in original pixels and network_tracks in
    network pixels, mask [S, M] the observations used; errors_before / errors_after [M]
    mean reprojection error of each point (network pixels); error_before / error_after:
    the mean over all observations (network pixels); counts: how many query points,
    observations kept by the filters, points triangulated, observations used;
    query_frames; summary: pycolmap's report; usable: pycolmap's verdict.
    """

    extrinsic: np.ndarray
    intrinsic: np.ndarray
    network_intrinsic: np.ndarray
    points: np.ndarray
    colors: np.ndarray
    tracks: np.ndarray
    network_tracks: np.ndarray
    mask: np.ndarray
    errors_before: np.ndarray
    errors_after: np.ndarray
    error_before: float
    error_after: float
    counts: dict
    query_frames: tuple[int, ...]
    summary: str
    usable: bool


def _point_errors(extrinsic, intrinsic, points, tracks, mask) -> np.ndarray:
    """Each point's mean reprojection error [M] over its observations."""
    err = np.where(mask, reprojection_errors(extrinsic, intrinsic, points, tracks), 0.0)
    return err.sum(axis=0) / np.maximum(mask.sum(axis=0), 1)


def _adjust(extrinsic, k_net, size, tri: Triangulated, colors, options: BAOptions, counts: dict):
    """pycolmap's BA of the triangulated tracks, then the points it could not fit (an
    observation behind its camera or beyond `max_error`) dropped and, if any were, BA
    again without them (they pulled on the cameras in the first round). Returns the
    adjusted arrays and the kept tracks and colours; `counts` gets the number dropped."""
    from rvggt_jax.ba.adjust import run_bundle_adjustment

    s = len(extrinsic)
    names = [f"frame_{i:03d}" for i in range(s)]  # pycolmap's own copy: names only label it
    ba = dict(refine_focal=options.refine_focal, loss=options.loss, max_iterations=options.max_iterations,
              camera_model=options.camera_model, shared_camera=options.shared_camera)
    adjusted, _ = run_bundle_adjustment(names, extrinsic, k_net, [size] * s, tri.points, tri.tracks, tri.mask,
                                        colors, **ba)
    err = reprojection_errors(adjusted.extrinsic, adjusted.intrinsic, adjusted.points, tri.tracks)
    fit = np.flatnonzero(~np.any(tri.mask & ~(err <= options.max_error), axis=0))
    counts["points_dropped_after_ba"] = len(tri) - len(fit)
    if len(fit) < options.min_points:
        raise BAError(f"bundle adjustment did not converge to a usable model: {len(fit)} of {len(tri)} points fit "
                      f"within --ba-max-error {options.max_error:g} px afterwards (at least {options.min_points} "
                      f"needed); the tracks are too poor for these cameras")
    if len(fit) < len(tri):
        tri = Triangulated(points=tri.points[fit], tracks=tri.tracks[:, fit], mask=tri.mask[:, fit],
                           index=tri.index[fit])
        colors = colors[fit]
        first = dataclasses.replace(adjusted, points=adjusted.points[fit])
        second, _ = run_bundle_adjustment(names, first.extrinsic, first.intrinsic, [size] * s, first.points,
                                          tri.tracks, tri.mask, colors, **ba)
        # the second round starts from the first's solution without the points it could not
        # fit; from poor cameras it can still diverge (seen: errors of 1e150 px on a model
        # whose cameras are nearly all alike). Then the first round's solution is the answer.
        e1 = mean_reprojection_error(first.extrinsic, first.intrinsic, first.points, tri.tracks, tri.mask)
        e2 = mean_reprojection_error(second.extrinsic, second.intrinsic, second.points, tri.tracks, tri.mask)
        if np.isfinite(e2) and e2 <= e1:
            adjusted = second
        else:
            adjusted = first
            counts["second_round_discarded"] = True
    return adjusted, tri, colors


def refine(recon, track_fn: TrackFn, options: BAOptions = BAOptions()) -> BAOutcome:
    """Bundle-adjust `recon` (a `rvggt_jax.app.pipeline.Reconstruction`): query points in
    `options.query_frames` frames, tracked by `track_fn` (see `rvggt_jax.ba.tracks`),
    filtered, triangulated with the predicted cameras, then pycolmap's BA. `BAError`
    (a message saying which option helps) for fewer than 2 frames or fewer than
    `options.min_points` surviving points."""
    options.check()
    images = np.asarray(recon.images, np.float32)
    s, _, h, w = images.shape
    if s < 2:
        raise BAError(f"bundle adjustment needs at least 2 frames; got {s}")
    qframes = choose_query_frames(s, options.query_frames)
    per_frame = -(-options.query_points // len(qframes))
    queries = [query_points(images[j], recon.depth_conf[j], recon.valid[j], per_frame, options.keypoints)
               for j in qframes]
    tracks = track_from_query_frames(track_fn, images, queries, qframes)
    keep = filter_tracks(tracks, (h, w), recon.valid, vis_threshold=options.vis_threshold,
                         conf_threshold=options.conf_threshold)
    k_net = np.asarray(recon.network_intrinsic, np.float64)
    tri = triangulate_tracks(recon.extrinsic, k_net, tracks.points, keep, max_error=options.max_error,
                             min_angle_deg=options.min_angle)
    counts = dict(query_points=len(tracks), observations_kept=int(keep.sum()),
                  tracks_with_2_views=int((keep.sum(axis=0) >= 2).sum()), points=len(tri),
                  observations=int(tri.mask.sum()))
    if len(tri) < options.min_points:
        raise BAError(
            f"too few tracks for bundle adjustment: {len(tri)} point(s) triangulated (at least {options.min_points} "
            f"needed) from {len(tracks)} query points, {counts['tracks_with_2_views']} of them seen in 2+ frames "
            f"after the visibility/confidence filters (points need inlier views whose rays meet at "
            f"{options.min_angle:g} degrees or more); try more --ba-query-points, lower --ba-vis-threshold / "
            f"--ba-conf-threshold, or a larger --ba-max-error")
    # a point's colour: its query pixel's
    qf = tracks.query_frame[tri.index]
    qxy = tracks.points[qf, tri.index]
    col = np.clip(qxy[:, 0].astype(int), 0, w - 1)
    row = np.clip(qxy[:, 1].astype(int), 0, h - 1)
    colors = (np.clip(images[qf, :, row, col], 0, 1) * 255 + 0.5).astype(np.uint8)
    adjusted, tri, colors = _adjust(recon.extrinsic, k_net, (w, h), tri, colors, options, counts)
    counts.update(points=len(tri), observations=int(tri.mask.sum()))
    err_before = mean_reprojection_error(recon.extrinsic, k_net, tri.points, tri.tracks, tri.mask)
    pe_before = _point_errors(recon.extrinsic, k_net, tri.points, tri.tracks, tri.mask)
    err_after = mean_reprojection_error(adjusted.extrinsic, adjusted.intrinsic, adjusted.points, tri.tracks,
                                        tri.mask)
    pe_after = _point_errors(adjusted.extrinsic, adjusted.intrinsic, adjusted.points, tri.tracks, tri.mask)
    to_original = np.asarray(recon.intrinsic, np.float64) @ np.linalg.inv(k_net)  # [S, 3, 3] affine pixel maps
    hom = np.concatenate([tri.tracks, np.ones(tri.tracks.shape[:2] + (1,))], axis=-1)
    return BAOutcome(
        extrinsic=adjusted.extrinsic, intrinsic=to_original @ adjusted.intrinsic,
        network_intrinsic=adjusted.intrinsic, points=adjusted.points, colors=colors,
        tracks=np.einsum("sij,snj->sni", to_original, hom)[..., :2], network_tracks=tri.tracks, mask=tri.mask,
        errors_before=pe_before, errors_after=pe_after, error_before=err_before, error_after=err_after,
        counts=counts, query_frames=tuple(qframes), summary=adjusted.summary, usable=adjusted.usable)


def _finite(obj):
    """`obj` with non-finite floats as None: standard JSON has no NaN or Infinity."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def write_outputs(out_dir: str | os.PathLike, outcome: BAOutcome, names: Sequence[str],
                  sizes: Sequence[tuple[int, int]], options: BAOptions = BAOptions(),
                  meta: dict[str, Any] | None = None) -> dict:
    """Write the BA result in `out_dir` (original-image pixels):

        sparse_ba/{cameras,images,points3D}.txt  COLMAP text model with tracks
                                                 (`rvggt_jax.io.colmap.write_colmap_text_with_tracks`)
        sparse_ba/bin/*.bin                      the same model written by pycolmap
        cameras_ba.json                          the refined cameras (`rvggt_jax.io.cameras`)
        points_ba.ply                            the refined points, with `error` (mean
                                                 reprojection error, pixels) and
                                                 `track_length` per point
        ba_report.json                           reprojection errors before / after, counts,
                                                 options

    names [S] image names (spaces become '_' in the COLMAP model); sizes [S] (width,
    height) of the original images. Returns the report."""
    from rvggt_jax.ba.adjust import build_pycolmap_reconstruction
    from rvggt_jax.io.cameras import write_cameras_json
    from rvggt_jax.io.colmap import write_colmap_text_with_tracks
    from rvggt_jax.io.ply import write_ply

    out = Path(out_dir)
    colmap_names = [n.replace(" ", "_") for n in names]
    sparse = out / SPARSE_DIR
    cams = dict(camera_model=options.camera_model, shared_camera=options.shared_camera)
    write_colmap_text_with_tracks(sparse, colmap_names, outcome.extrinsic, outcome.intrinsic, sizes,
                                  outcome.points, outcome.colors, outcome.tracks, outcome.mask,
                                  errors=outcome.errors_after, **cams)
    rec = build_pycolmap_reconstruction(colmap_names, outcome.extrinsic, outcome.intrinsic, sizes, outcome.points,
                                        outcome.tracks, outcome.mask, outcome.colors, **cams)
    rec.update_point_3d_errors()
    (sparse / "bin").mkdir(parents=True, exist_ok=True)
    rec.write(str(sparse / "bin"))
    write_cameras_json(out / CAMERAS_NAME, list(names), outcome.extrinsic, outcome.intrinsic, sizes,
                       meta=dict(bundle_adjusted=True))
    write_ply(out / POINTS_NAME, outcome.points, outcome.colors,
              extra=dict(error=outcome.errors_after.astype(np.float32),
                         track_length=outcome.mask.sum(axis=0).astype(np.int32)))
    report = dict(
        mean_reprojection_error_before_px=outcome.error_before,
        mean_reprojection_error_after_px=outcome.error_after,
        pixels="network input (the model's resolution)",
        reduction=(outcome.error_before / outcome.error_after) if outcome.error_after > 0 else None,
        **outcome.counts, query_frames=list(outcome.query_frames),
        pycolmap_mean_reprojection_error_px=float(rec.compute_mean_reprojection_error()),
        pycolmap_pixels="original images", solver=outcome.summary, solution_usable=outcome.usable,
        options=dataclasses.asdict(options), **(meta or {}))
    (out / REPORT_NAME).write_text(json.dumps(_finite(report), indent=1, allow_nan=False) + "\n")
    return report
