"""Every output file of one reconstruction, in one folder (`export_reconstruction`),
each written by the module of its format:

    points.ply                `io.ply`: confidence-filtered points, image colours,
                              per-point `confidence` and source `frame`
    scene.glb                 `io.glb`: points + camera frustums (glTF, y up)
    thumbnails/<stem>.jpg     `io.plots`: the network input, small (for `rvggt view`)
    cameras.json              `io.cameras`: per-image camera in the ORIGINAL image's
                              pixels, plus the network-input camera under "network"
    sparse/{cameras,images,points3D}.txt and .bin   `io.colmap`: the COLMAP model, text
                              and binary (original pixels; a camera per image or one
                              shared, PINHOLE by default); points3D holds a random
                              subset of points.ply
    transforms.json           `io.transforms`: nerfstudio's format (cameras, the images
                              under images/, points.ply as splatfacto's initial points)
    images/<name>             the input images under their COLMAP names (hard links, or
                              copies across file systems): what nerfstudio and gsplat
                              read next to the model (only when the image paths are given)
    depth/<stem>.png          `io.depth`: 16-bit depth of the network input (scale in
                              depth/depth_scale.json)
    depth_preview/<stem>.png  `io.depth`: coloured depth (near = bright)
    trajectory.png            `io.plots`: camera centres from above
    predictions.npz           `io.raw`: the model's predictions under upstream's names
                              (only with `save_raw`)
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from rvggt_jax.io.cameras import write_cameras_json
from rvggt_jax.io.colmap import colmap_cameras, write_colmap_binary, write_colmap_text
from rvggt_jax.io.depth import write_depth_pngs
from rvggt_jax.io.plots import write_thumbnails, write_trajectory_png
from rvggt_jax.io.ply import write_ply
from rvggt_jax.io.raw import RAW_NAME, write_predictions
from rvggt_jax.io.transforms import write_transforms_json

__all__ = ["IMAGES_DIR", "export_reconstruction", "link_images", "unique_stems"]

PathLike = str | os.PathLike

CAMERAS_CONVENTION = ("extrinsic: 3x4 world-to-camera, OpenCV axes (x right, y down, z forward); "
                      "intrinsic: pinhole in the original image's pixels (network: in the network input's)")


def export_reconstruction(out_dir: PathLike, recon, *, max_colmap_points: int | None = 100_000,
                          meta: Mapping[str, Any] | None = None, write_scene: bool = True,
                          image_paths: Sequence[PathLike] | None = None, camera_model: str = "PINHOLE",
                          shared_camera: bool = False, save_raw: bool = False,
                          model_outputs: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Write every file of `recon` (a `rvggt_jax.app.pipeline.Reconstruction`) to `out_dir`
    (layout in the module docstring). points3D holds a random subset of at most
    `max_colmap_points` points (None: all); `meta` goes into cameras.json; scene.glb only
    with `write_scene`. COLMAP names cannot hold spaces: they are written with '_'
    instead (listed in the summary's `colmap_renamed`). `image_paths` [S], the image
    files of `recon.names`: linked into images/ (transforms.json refers to them there;
    without them it names the images by their COLMAP names, relative to `out_dir`).
    `camera_model` / `shared_camera`: the COLMAP model's cameras (`io.colmap.colmap_cameras`;
    a shared camera needs images of one size, checked before anything is written).
    `save_raw`: also predictions.npz (`io.raw.write_predictions`), with `model_outputs`,
    the run's model outputs (pose_enc, world_points, world_points_conf).
    Returns a summary dict (paths, point counts, threshold used)."""
    colmap_cameras(recon.intrinsic, recon.sizes, camera_model, shared_camera)  # (raises before any file)
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
    cams = dict(camera_model=camera_model, shared_camera=shared_camera)
    write_colmap_text(out / "sparse", colmap_names, recon.extrinsic, recon.intrinsic, recon.sizes, cpts, crgb, **cams)
    write_colmap_binary(out / "sparse", colmap_names, recon.extrinsic, recon.intrinsic, recon.sizes, cpts, crgb,
                        **cams)
    if image_paths is not None:
        if len(image_paths) != s:
            raise ValueError(f"{s} images need {s} image paths; got {len(image_paths)}")
        link_images(out / IMAGES_DIR, image_paths, colmap_names)
        file_paths = [f"{IMAGES_DIR}/{n}" for n in colmap_names]
    else:
        file_paths = colmap_names
    write_transforms_json(out / "transforms.json", file_paths, recon.extrinsic, recon.intrinsic, recon.sizes,
                          ply_file_path="points.ply")

    if write_scene:
        from rvggt_jax.io.glb import write_glb

        write_glb(out / "scene.glb", cloud, cloud_rgb, recon.extrinsic, recon.intrinsic, recon.sizes)

    stems = unique_stems(names)
    write_thumbnails(out / "thumbnails", stems, recon.images, recon.valid)
    scale = write_depth_pngs(out / "depth", stems, recon.depth, recon.valid, preview_folder=out / "depth_preview")
    step = max(1, len(cloud) // 20000)  # the plot needs no more points
    write_trajectory_png(out / "trajectory.png", recon.extrinsic, cloud[::step], cloud_rgb[::step])
    if save_raw:
        write_predictions(out / RAW_NAME, recon, model_outputs)
    return dict(out_dir=str(out), frames=s, points=int(len(cloud)), colmap_points=int(len(cpts)),
                max_colmap_points=max_colmap_points,
                conf_threshold=recon.conf_threshold, depth_scale=scale, stems=stems,
                colmap_renamed=[(a, b) for a, b in zip(names, colmap_names) if a != b],
                raw=RAW_NAME if save_raw else None)


IMAGES_DIR = "images"  # where COLMAP-format readers (gsplat, nerfstudio) look for the images


def link_images(folder: Path, paths: Sequence[PathLike], names: Sequence[str]) -> None:
    """`folder/names[i]` = the file `paths[i]`: a hard link (no copy, and deleting it
    leaves the original), or a copy where the two are on different file systems. An
    entry already there (an earlier run) is replaced."""
    import shutil

    folder.mkdir(parents=True, exist_ok=True)
    for src, name in zip(paths, names):
        dst = folder / name
        src = Path(src)
        if dst.exists() and os.path.samefile(src, dst):
            continue
        tmp = folder / f".{name}.tmp"
        tmp.unlink(missing_ok=True)
        try:
            os.link(src, tmp)
        except OSError:
            shutil.copyfile(src, tmp)
        os.replace(tmp, dst)


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
