"""The outputs of a chunked run (`rvggt_jax.app.long_sequence`), written chunk by chunk.

Every frame takes its camera, depth and points from the chunk the trajectory assigned it
to (`Trajectory.frame_chunk`), moved into the first chunk's frame by that chunk's Sim(3)
(depth scaled by it). Two passes over the cached chunks, each holding one chunk:

1. the largest depth (one 16-bit scale for every depth PNG) and a histogram of the
   confidences (a "P%" threshold over all frames, to 0.1% of its value);
2. per chunk: its images decoded again (colours, thumbnails), its depth PNGs, and its
   confident points into a `VoxelCloud` (at most --max-points, voxel-averaged).

The cameras (O(S) small matrices) are written at the end, in the usual formats.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from rvggt_jax.app.console import say

__all__ = ["ConfidenceHistogram", "export_chunked"]

MAX_COLMAP_POINTS = 100_000


class ConfidenceHistogram:
    """Percentiles of a stream of positive confidences from log-spaced bins (0.1% wide,
    1e-3 to 1e9): O(1) memory for any number of pixels. Values outside the range are
    counted in the end bins."""

    LO, HI, BINS = 1e-3, 1e9, 27_632  # log(1e12) / log(1.001)

    def __init__(self):
        self.counts = np.zeros(self.BINS, np.int64)
        self._log_lo, self._step = math.log(self.LO), (math.log(self.HI) - math.log(self.LO)) / self.BINS

    def add(self, values) -> None:
        v = np.asarray(values, np.float64).reshape(-1)
        v = v[np.isfinite(v)]
        idx = np.clip(((np.log(np.maximum(v, self.LO)) - self._log_lo) / self._step).astype(np.int64), 0,
                      self.BINS - 1)
        self.counts += np.bincount(idx, minlength=self.BINS)

    def percentile(self, p: float) -> float:
        """The lower edge of the bin holding the p-th percentile (keeps at least the
        values at or above it); 0 when nothing was added."""
        total = int(self.counts.sum())
        if total == 0:
            return 0.0
        rank = p / 100.0 * (total - 1)
        b = int(np.searchsorted(np.cumsum(self.counts), rank, side="right"))
        return 0.0 if b == 0 and p == 0 else float(math.exp(self._log_lo + min(b, self.BINS - 1) * self._step))


def _frames_by_chunk(trajectory, store, n_chunks: int) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(chunk k, its frames [n] that take their outputs from it, their rows in chunk k)."""
    out = []
    for k in range(n_chunks):
        frames = np.flatnonzero(trajectory.frame_chunk == k)
        if len(frames):
            chunk_frames = np.asarray(store.array(k, "frames"))
            rows = np.searchsorted(chunk_frames, frames)
            out.append((k, frames, rows))
    return out


def _depth_and_conf(run, store, k: int, rows: np.ndarray, scale: float):
    """World-unit depth [n, H, W], confidence [n, H, W] and the pixels with a point
    [n, H, W] (image content, positive finite depth) of chunk k's `rows`."""
    depth = np.asarray(store.array(k, "depth")[rows], np.float64) * scale
    conf = np.asarray(store.array(k, "confidence")[rows], np.float32)
    valid = np.asarray(store.array(k, "valid")[rows], bool)
    ok = valid & np.isfinite(depth) & (depth > 1e-8) & np.isfinite(conf)
    if run.options.points_from == "pointmap":
        ok = valid & np.isfinite(conf)
    return depth, conf, valid, ok


def export_chunked(out_dir: Path, run, store, trajectory, source: Path, weights) -> dict:
    """Write every output of the chunked run `run` (its cached chunks in `store`, aligned
    into `trajectory`) to `out_dir`; returns the summary `rvggt reconstruct` prints."""
    from rvggt_jax.app.pipeline import parse_threshold
    from rvggt_jax.io.depth import write_depth_frames, write_depth_scale
    from rvggt_jax.io.export import unique_stems
    from rvggt_jax.io.plots import write_thumbnails
    from rvggt_jax.sequence import VoxelCloud

    options = run.options
    names = [p.name for p in run.paths]
    stems = unique_stems(names)
    groups = _frames_by_chunk(trajectory, store, len(trajectory.chunk_sim3))

    # pass 1: one depth scale for the PNGs, the confidence threshold over all frames
    hist, dmax = ConfidenceHistogram(), 0.0
    for k, frames, rows in groups:
        depth, conf, valid, ok = _depth_and_conf(run, store, k, rows, trajectory.chunk_sim3[k].scale)
        hist.add(conf[ok])
        good = valid & np.isfinite(depth) & (depth > 0)
        if good.any():
            dmax = max(dmax, float(depth[good].max()))
    thr = parse_threshold(options.conf_threshold)
    threshold = hist.percentile(thr[0]) if isinstance(thr, tuple) else float(thr)
    depth_scale = (dmax if dmax > 0 else 1.0) / 65535.0

    # pass 2: per chunk, its frames' files and points
    cloud = VoxelCloud(options.max_points or 2_000_000)
    infos: dict[int, object] = {}
    for k, frames, rows in groups:
        sim3 = trajectory.chunk_sim3[k]
        depth, conf, valid, ok = _depth_and_conf(run, store, k, rows, sim3.scale)
        images, loaded = run._load(list(frames))
        infos.update(zip(frames.tolist(), loaded))
        chunk_stems = [stems[f] for f in frames]
        write_depth_frames(out_dir / "depth", chunk_stems, depth, valid, depth_scale,
                           preview_folder=out_dir / "depth_preview")
        write_thumbnails(out_dir / "thumbnails", chunk_stems, images, valid)
        points = store.load(k, points_from=options.points_from).points[rows]
        keep = ok & (conf >= threshold) & np.isfinite(points).all(axis=-1)
        colors = (np.clip(images.transpose(0, 2, 3, 1), 0, 1) * 255 + 0.5).astype(np.uint8)
        frame_ids = np.broadcast_to(frames[:, None, None], keep.shape)
        cloud.add(sim3.apply(points[keep]), colors[keep], conf[keep], frame_ids[keep])
    write_depth_scale(out_dir / "depth", depth_scale, dmax, stems)
    cloud_points, cloud_colors, cloud_conf, cloud_frames = cloud.result()
    summary = _write_cameras_and_cloud(out_dir, run, trajectory, infos, names, cloud_points, cloud_colors, cloud_conf,
                                       cloud_frames, source, weights)
    summary.update(conf_threshold=threshold, depth_scale=depth_scale, stems=stems, voxel=cloud.voxel)
    return summary


def _write_cameras_and_cloud(out_dir: Path, run, trajectory, infos: dict, names: list[str], points, colors, conf,
                             frames, source: Path, weights) -> dict:
    from rvggt_jax.eval.datasets.kitti import write_kitti_poses
    from rvggt_jax.io.cameras import write_cameras_json
    from rvggt_jax.io.colmap import write_colmap_binary, write_colmap_text
    from rvggt_jax.io.export import CAMERAS_CONVENTION, IMAGES_DIR, link_images
    from rvggt_jax.io.glb import write_glb
    from rvggt_jax.io.plots import write_trajectory_png
    from rvggt_jax.io.ply import write_ply
    from rvggt_jax.io.transforms import write_transforms_json

    options = run.options
    h, w = run.hw
    s = len(names)
    ext = trajectory.extrinsics
    k_net = trajectory.intrinsics
    k_orig = np.stack([infos[i].intrinsic_to_original(k_net[i]) for i in range(s)])
    sizes = tuple((infos[i].width, infos[i].height) for i in range(s))
    write_ply(out_dir / "points.ply", points, colors, extra=dict(confidence=conf, frame=frames))
    extra = [dict(network=dict(intrinsic=k_net[i].tolist(), width=w, height=h), chunk=int(trajectory.frame_chunk[i]))
             for i in range(s)]
    meta = dict(convention=CAMERAS_CONVENTION, source=str(source), weights=str(weights),
                preset=run.config.compression.name, mode=options.mode, conf_threshold=str(options.conf_threshold),
                points_from=options.points_from, exif_orientation=options.exif_orientation,
                chunk_frames=run.chunk_frames, overlap=run.overlap, loop_closure=options.loop_closure,
                loops=len(trajectory.loops), chunk_sim3=[dict(scale=g.scale, rotation=g.rotation.tolist(),
                                                              translation=g.translation.tolist())
                                                         for g in trajectory.chunk_sim3])
    write_cameras_json(out_dir / "cameras.json", names, ext, k_orig, sizes, extra=extra, meta=meta)
    if not options.all_colmap_points and len(points) > MAX_COLMAP_POINTS:
        sel = np.sort(np.random.default_rng(1).choice(len(points), size=MAX_COLMAP_POINTS, replace=False))
        cpts, crgb = points[sel], colors[sel]
    else:
        cpts, crgb = points, colors
    colmap_names = [n.replace(" ", "_") for n in names]
    cams = dict(camera_model=options.camera_type, shared_camera=options.shared_camera)
    write_colmap_text(out_dir / "sparse", colmap_names, ext, k_orig, sizes, cpts, crgb, **cams)
    write_colmap_binary(out_dir / "sparse", colmap_names, ext, k_orig, sizes, cpts, crgb, **cams)
    link_images(out_dir / IMAGES_DIR, run.paths, colmap_names)
    write_transforms_json(out_dir / "transforms.json", [f"{IMAGES_DIR}/{n}" for n in colmap_names], ext, k_orig,
                          sizes, ply_file_path="points.ply")
    # evo reads this directly: `evo_ape kitti gt.txt poses_kitti.txt -as` (Sim(3)-aligned)
    write_kitti_poses(out_dir / "poses_kitti.txt", ext)
    write_glb(out_dir / "scene.glb", points, colors, ext, k_orig, sizes)
    step = max(1, len(points) // 20000)
    write_trajectory_png(out_dir / "trajectory.png", ext, points[::step], colors[::step])
    say(options.quiet, f"point cloud: {len(points)} points (voxel-averaged, at most {options.max_points})")
    return dict(out_dir=str(out_dir), frames=s, points=int(len(points)), colmap_points=int(len(cpts)),
                max_colmap_points=None if options.all_colmap_points else MAX_COLMAP_POINTS,
                colmap_renamed=[(a, b) for a, b in zip(names, colmap_names) if a != b],
                loops=len(trajectory.loops))
