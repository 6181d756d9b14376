"""COLMAP model, text and binary: `cameras.txt` / `.bin` (one camera per image, or one
shared by all; PINHOLE, SIMPLE_PINHOLE or SIMPLE_RADIAL: `colmap_cameras`),
`images.txt` / `.bin` (world-to-camera quaternion `QW QX QY QZ` + translation, no 2D
points), `points3D.txt` / `.bin` (points with colour, error 0 and an empty track), in the
layout of COLMAP's documentation ("Output format"). Readable by COLMAP, pycolmap,
nerfstudio's COLMAP loader and gsplat's (which read the binary files).

COLMAP's quaternions are scalar-first (qw, qx, qy, qz); `rvggt_jax.geometry` (the one
quaternion implementation) is scalar-last (x, y, z, w), as upstream VGGT: `colmap_qvec`
and `colmap_rotation` convert.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from rvggt_jax.io.cameras import check_cameras
from rvggt_jax.io.ply import colors_u8

__all__ = ["CAMERA_MODELS", "ColmapCameras", "colmap_cameras", "colmap_qvec", "colmap_rotation",
           "write_colmap_binary", "write_colmap_text", "write_colmap_text_with_tracks"]

PathLike = str | os.PathLike

# The camera models written: name -> COLMAP's model id (src/colmap/sensor/models.h) and
# parameters. VGGT's cameras are pinholes; SIMPLE_RADIAL (radial k = 0) is for tools that
# start their own calibration from it.
CAMERA_MODELS = {"SIMPLE_PINHOLE": (0, ("f", "cx", "cy")), "PINHOLE": (1, ("fx", "fy", "cx", "cy")),
                 "SIMPLE_RADIAL": (2, ("f", "cx", "cy", "k"))}


@dataclass(frozen=True, eq=False)
class ColmapCameras:
    """The cameras of a COLMAP model of S images: C = S cameras, or 1 shared.

    model: a name of `CAMERA_MODELS`; sizes: C (width, height); params [C, P] float64 in
    the model's parameter order; camera_ids [S] int, the id (1..C) of each image's camera."""

    model: str
    sizes: tuple[tuple[int, int], ...]
    params: np.ndarray
    camera_ids: np.ndarray


def colmap_cameras(intrinsics: np.ndarray, sizes: Sequence[tuple[int, int]], model: str = "PINHOLE",
                   shared: bool = False) -> ColmapCameras:
    """COLMAP cameras of pinholes intrinsics [S, 3, 3] with sizes [S] of (width, height).
    SIMPLE_PINHOLE and SIMPLE_RADIAL take f = (fx + fy) / 2 (and k = 0). `shared`: one
    camera for all images, each parameter the median over the images (a video's frames,
    one phone's photos); a ValueError naming two of the sizes when the images differ."""
    if model not in CAMERA_MODELS:
        raise ValueError(f"unknown COLMAP camera model {model!r}; known: {', '.join(CAMERA_MODELS)}")
    k = np.asarray(intrinsics, np.float64).reshape(-1, 3, 3)
    sizes = tuple((int(w), int(h)) for w, h in sizes)
    if len(sizes) != len(k):
        raise ValueError(f"{len(k)} intrinsics need {len(k)} sizes; got {len(sizes)}")
    fx, fy, cx, cy = k[:, 0, 0], k[:, 1, 1], k[:, 0, 2], k[:, 1, 2]
    f = (fx + fy) / 2
    params = {"PINHOLE": [fx, fy, cx, cy], "SIMPLE_PINHOLE": [f, cx, cy],
              "SIMPLE_RADIAL": [f, cx, cy, np.zeros_like(f)]}[model]
    params = np.stack(params, axis=1)  # [S, P]
    if not shared:
        return ColmapCameras(model, sizes, params, np.arange(1, len(k) + 1))
    other = next((sz for sz in sizes if sz != sizes[0]), None)
    if other is not None:
        raise ValueError(f"one shared camera needs images of one size; got {sizes[0][0]}x{sizes[0][1]} and "
                         f"{other[0]}x{other[1]}")
    return ColmapCameras(model, sizes[:1], np.median(params, axis=0, keepdims=True), np.ones(len(k), int))


def _geometry():
    # (imported when first used: rvggt_jax.geometry imports JAX, and the command line reads
    # CAMERA_MODELS to build its parser, before any model runs)
    from rvggt_jax import geometry

    return geometry


def colmap_qvec(rotation: np.ndarray) -> np.ndarray:
    """COLMAP's unit quaternion (qw, qx, qy, qz), qw >= 0, of a rotation [3, 3] (float64)."""
    x, y, z, w = _geometry().mat_to_quat(np.asarray(rotation, dtype=np.float64))
    q = np.array([w, x, y, z])
    return q / np.linalg.norm(q)


def colmap_rotation(qvec) -> np.ndarray:
    """Rotation [3, 3] (float64) of a COLMAP quaternion (qw, qx, qy, qz), any norm."""
    w, x, y, z = np.asarray(qvec, dtype=np.float64)
    return _geometry().quat_to_mat(np.array([x, y, z, w]))


def _fmt(x: float) -> str:
    return repr(float(x))


def _model_folder(folder: PathLike, names: Sequence[str], extrinsics: np.ndarray, intrinsics: np.ndarray,
                  sizes: Sequence[tuple[int, int]], camera_model: str,
                  shared_camera: bool) -> tuple[Path, np.ndarray, ColmapCameras]:
    """The checks the model writers make, then their folder (created): -> (folder,
    extrinsics [S, 3, 4] as `check_cameras` returns them, the cameras `colmap_cameras`)."""
    e, k = check_cameras(names, extrinsics, intrinsics, sizes)
    cams = colmap_cameras(k, sizes, camera_model, shared_camera)
    for name in names:
        if any(ch.isspace() for ch in name):
            raise ValueError(f"COLMAP image names cannot contain spaces: {name!r}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    return folder, e, cams


def _write_cameras_txt(folder: Path, cams: ColmapCameras) -> None:
    lines = ["# Camera list with one line of data per camera:",
             "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
             f"# Number of cameras: {len(cams.sizes)}"]
    for c, ((w, h), params) in enumerate(zip(cams.sizes, cams.params)):
        lines.append(" ".join([str(c + 1), cams.model, str(w), str(h), *map(_fmt, params)]))
    (folder / "cameras.txt").write_text("\n".join(lines) + "\n")


def _image_line(i: int, e: np.ndarray, cams: ColmapCameras, name: str) -> str:
    """images.txt's first line of image i (id i + 1): pose e [3, 4], camera, name."""
    q = colmap_qvec(_geometry().nearest_rotation(e[:, :3]))
    return " ".join([str(i + 1), *map(_fmt, q), *map(_fmt, e[:, 3]), str(int(cams.camera_ids[i])), name])


def write_colmap_text(folder: PathLike, names: Sequence[str], extrinsics: np.ndarray, intrinsics: np.ndarray,
                      sizes: Sequence[tuple[int, int]], points: np.ndarray | None = None,
                      colors: np.ndarray | None = None, *, camera_model: str = "PINHOLE",
                      shared_camera: bool = False) -> None:
    """COLMAP text model in `folder` (created): cameras.txt, images.txt, points3D.txt.

    names [S] image file names (COLMAP needs them without spaces); extrinsics [S, 3, 4]
    world-to-camera; intrinsics [S, 3, 3]; sizes [S] of (width, height) in the pixels
    of `intrinsics`; points [N, 3], colors [N, 3] (uint8 or float in [0, 1]). Image ids
    are 1..S; camera ids 1..S (camera i belongs to image i), or, with `shared_camera`,
    camera 1 for all (`colmap_cameras`: `camera_model`, the median intrinsics); points
    have ids 1..N, error 0 and no track.
    """
    folder, e, cams = _model_folder(folder, names, extrinsics, intrinsics, sizes, camera_model, shared_camera)
    s = len(names)
    _write_cameras_txt(folder, cams)

    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)",
             f"# Number of images: {s}, mean observations per image: 0"]
    for i in range(s):
        lines.append(_image_line(i, e[i], cams, names[i]))
        lines.append("")
    (folder / "images.txt").write_text("\n".join(lines) + "\n")

    pts = np.zeros((0, 3)) if points is None else np.asarray(points, dtype=np.float64)
    cols = colors_u8(colors, len(pts))
    with open(folder / "points3D.txt", "w") as f:
        f.write("# 3D point list with one line of data per point:\n"
                "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
                f"# Number of points: {len(pts)}, mean track length: 0\n")
        f.writelines(
            f"{j + 1} {p[0]:.7g} {p[1]:.7g} {p[2]:.7g} {c[0]} {c[1]} {c[2]} 0\n"
            for j, (p, c) in enumerate(zip(pts, cols))
        )


def write_colmap_text_with_tracks(folder: PathLike, names: Sequence[str], extrinsics: np.ndarray,
                                  intrinsics: np.ndarray, sizes: Sequence[tuple[int, int]], points: np.ndarray,
                                  colors: np.ndarray | None, tracks: np.ndarray, mask: np.ndarray,
                                  errors: np.ndarray | None = None, *, camera_model: str = "PINHOLE",
                                  shared_camera: bool = False) -> None:
    """COLMAP text model with tracks (as bundle adjustment produces it): as
    `write_colmap_text`, plus the observations.

    points [N, 3], colors [N, 3]; tracks [S, N, 2] pixel (x, y) of point j in image i
    (in the pixels of `intrinsics`, continuous: the image spans [0, W] x [0, H], as
    COLMAP's), mask [S, N] bool the observations that exist; errors [N] each point's
    mean reprojection error in pixels (default 0). Image i's POINTS2D are its
    observations in point order, so point j's TRACK lists (i + 1, its rank among image
    i's observations)."""
    folder, e, cams = _model_folder(folder, names, extrinsics, intrinsics, sizes, camera_model, shared_camera)
    _write_cameras_txt(folder, cams)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n, s = len(pts), len(names)
    tr = np.asarray(tracks, dtype=np.float64)
    m = np.asarray(mask, dtype=bool)
    if tr.shape != (s, n, 2) or m.shape != (s, n):
        raise ValueError(f"tracks must be [S, N, 2] and mask [S, N] = {(s, n)}; got {tr.shape}, {m.shape}")
    err = np.zeros(n) if errors is None else np.asarray(errors, dtype=np.float64).reshape(n)
    cols = colors_u8(colors, n)
    idx = np.cumsum(m, axis=1) - 1  # [S, N] rank of each observation among its image's 2D points

    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)",
             f"# Number of images: {s}, mean observations per image: {m.sum() / max(s, 1):.6g}"]
    for i in range(s):
        lines.append(_image_line(i, e[i], cams, names[i]))
        lines.append(" ".join(f"{_fmt(tr[i, j, 0])} {_fmt(tr[i, j, 1])} {j + 1}" for j in np.flatnonzero(m[i])))
    (folder / "images.txt").write_text("\n".join(lines) + "\n")

    length = m.sum(axis=0)
    with open(folder / "points3D.txt", "w") as f:
        f.write("# 3D point list with one line of data per point:\n"
                "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
                f"# Number of points: {n}, mean track length: {length.mean() if n else 0:.6g}\n")
        for j in range(n):
            p, c = pts[j], cols[j]
            track = " ".join(f"{i + 1} {idx[i, j]}" for i in np.flatnonzero(m[:, j]))
            f.write(f"{j + 1} {_fmt(p[0])} {_fmt(p[1])} {_fmt(p[2])} {c[0]} {c[1]} {c[2]} {_fmt(err[j])} {track}\n")


def write_colmap_binary(folder: PathLike, names: Sequence[str], extrinsics: np.ndarray, intrinsics: np.ndarray,
                        sizes: Sequence[tuple[int, int]], points: np.ndarray | None = None,
                        colors: np.ndarray | None = None, *, camera_model: str = "PINHOLE",
                        shared_camera: bool = False) -> None:
    """COLMAP binary model in `folder` (created): cameras.bin, images.bin, points3D.bin,
    the same model as `write_colmap_text` (its arguments; ids as there).
    Little-endian, as COLMAP writes it: cameras (id int32, model int32, width, height
    uint64, params float64), images (id uint32, qvec, tvec float64, camera id uint32,
    name NUL-terminated, 0 2D points uint64), points (id uint64, xyz float64, rgb uint8,
    error float64, track length uint64 = 0)."""
    folder, e, cams = _model_folder(folder, names, extrinsics, intrinsics, sizes, camera_model, shared_camera)
    s = len(names)
    model_id, param_names = CAMERA_MODELS[cams.model]
    with open(folder / "cameras.bin", "wb") as f:
        f.write(struct.pack("<Q", len(cams.sizes)))
        for c, ((w, h), params) in enumerate(zip(cams.sizes, cams.params)):
            f.write(struct.pack(f"<iiQQ{len(param_names)}d", c + 1, model_id, w, h, *params))
    with open(folder / "images.bin", "wb") as f:
        f.write(struct.pack("<Q", s))
        for i in range(s):
            q = colmap_qvec(_geometry().nearest_rotation(e[i, :, :3]))
            f.write(struct.pack("<I7dI", i + 1, *q, *e[i, :, 3], int(cams.camera_ids[i])))
            f.write(names[i].encode("utf-8") + b"\0" + struct.pack("<Q", 0))
    pts = np.zeros((0, 3)) if points is None else np.asarray(points, dtype=np.float64).reshape(-1, 3)
    cols = colors_u8(colors, len(pts))
    record = np.dtype([("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3), ("error", "<f8"), ("track", "<u8")])
    table = np.zeros(len(pts), record)  # one packed record per point (no padding: 51 bytes)
    table["id"] = np.arange(1, len(pts) + 1)
    table["xyz"], table["rgb"] = pts, cols
    with open(folder / "points3D.bin", "wb") as f:
        f.write(struct.pack("<Q", len(pts)))
        f.write(table.tobytes())
