"""Every output file of one reconstruction, in one folder (`export_reconstruction`),
each written by the module of its format:

    points.ply                `io.ply`: confidence-filtered points, image colours,
                              per-point `confidence` and source `frame`
    scene.glb                 `io.glb`: points + camera frustums (glTF, y up)
    thumbnails/<stem>.jpg     `io.plots`: the network input, small (for `rvggt view`)
    cameras.json              `io.cameras`: per-image camera in the ORIGINAL image's
                              pixels, plus the network-input camera under "network"
    sparse/{cameras,images,points3D}.txt   `io.colmap`: COLMAP text model (original
                              pixels); points3D.txt holds a random subset of points.ply
    depth/<stem>.png          `io.depth`: 16-bit depth of the network input (scale in
                              depth/depth_scale.json)
    depth_preview/<stem>.png  `io.depth`: coloured depth (near = bright)
    trajectory.png            `io.plots`: camera centres from above
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from rvggt_jax.io.cameras import write_cameras_json
from rvggt_jax.io.colmap import write_colmap_text
from rvggt_jax.io.depth import write_depth_pngs
from rvggt_jax.io.plots import write_thumbnails, write_trajectory_png
from rvggt_jax.io.ply import write_ply

__all__ = ["export_reconstruction", "unique_stems"]

PathLike = str | os.PathLike

CAMERAS_CONVENTION = ("extrinsic: 3x4 world-to-camera, OpenCV axes (x right, y down, z forward); "
                      "intrinsic: pinhole in the original image's pixels (network: in the network input's)")


def export_reconstruction(out_dir: PathLike, recon, *, max_colmap_points: int | None = 100_000,
                          meta: Mapping[str, Any] | None = None, write_scene: bool = True) -> dict[str, Any]:
    """Write every file of `recon` (a `rvggt_jax.app.pipeline.Reconstruction`) to `out_dir`
    (layout in the module docstring). points3D.txt holds a random subset of at most
    `max_colmap_points` points (None: all); `meta` goes into cameras.json; scene.glb only
    with `write_scene`. COLMAP names cannot hold spaces: they are written with '_'
    instead (listed in the summary's `colmap_renamed`).
    Returns a summary dict (paths, point counts, threshold used)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = list(recon.names)
    s, _, h, w = recon.images.shape
    cloud, cloud_rgb = recon.points, recon.colors
    write_ply(out / "points.ply", cloud, cloud_rgb, extra=dict(confidence=recon.confidences, frame=recon.frames))

    extra = [dict(network=dict(intrinsic=recon.network_intrinsic[i].tolist(), width=w, height=h)) for i in range(s)]
    write_cameras_json(out / "cameras.json", names, recon.extrinsic, recon.intrinsic, recon.sizes, extra=extra,
                       meta={"convention": CAMERAS_CONVENTION, **(meta or {})})

    if max_colmap_points is not None and len(cloud) > max_colmap_points:
        sel = np.sort(np.random.default_rng(1).choice(len(cloud), size=max_colmap_points, replace=False))
        cpts, crgb = cloud[sel], cloud_rgb[sel]
    else:
        cpts, crgb = cloud, cloud_rgb
    colmap_names = [n.replace(" ", "_") for n in names]
    write_colmap_text(out / "sparse", colmap_names, recon.extrinsic, recon.intrinsic, recon.sizes, cpts, crgb)

    if write_scene:
        from rvggt_jax.io.glb import write_glb

        write_glb(out / "scene.glb", cloud, cloud_rgb, recon.extrinsic, recon.intrinsic, recon.sizes)

    stems = unique_stems(names)
    write_thumbnails(out / "thumbnails", stems, recon.images, recon.valid)
    scale = write_depth_pngs(out / "depth", stems, recon.depth, recon.valid, preview_folder=out / "depth_preview")
    step = max(1, len(cloud) // 20000)  # the plot needs no more points
    write_trajectory_png(out / "trajectory.png", recon.extrinsic, cloud[::step], cloud_rgb[::step])
    return dict(out_dir=str(out), frames=s, points=int(len(cloud)), colmap_points=int(len(cpts)),
                max_colmap_points=max_colmap_points,
                conf_threshold=recon.conf_threshold, depth_scale=scale, stems=stems,
                colmap_renamed=[(a, b) for a, b in zip(names, colmap_names) if a != b])


def unique_stems(names: Sequence[str]) -> list[str]:
    """File stems usable as output names: unique, path-safe (`a.png`, `a.jpg` -> `a_png`, `a_jpg`)."""
    stems = [re.sub(r"[^\w.\-]+", "_", Path(n).stem) or "image" for n in names]
    dup = {s for s in stems if stems.count(s) > 1}
    out = []
    for n, s in zip(names, stems):
        out.append(re.sub(r"[^\w.\-]+", "_", Path(n).name.replace(".", "_")) if s in dup else s)
    seen: dict[str, int] = {}
    for i, s in enumerate(out):
        if s in seen:
            seen[s] += 1
            out[i] = f"{s}_{seen[s]}"
        else:
            seen[s] = 0
    return out
