"""Writers (and readers, for checking) of the files a reconstruction produces.

Every camera is given as in VGGT: `extrinsic [3, 4]` world-to-camera (OpenCV axes:
x right, y down, z forward) and `intrinsic [3, 3]` pinhole in pixels, continuous
pixel coordinates (the image spans `[0, W] x [0, H]`, as COLMAP).

Files (see `export_reconstruction` for the folder layout):
- `write_ply` (`rvggt_jax.io.ply`): binary little-endian PLY, `x y z` float32 +
  `red green blue` uint8 (+ `confidence` float32 and `frame` int32 in points.ply).
- `write_colmap_text`: COLMAP text model `cameras.txt` (one PINHOLE camera per
  image), `images.txt` (world-to-camera quaternion + translation, empty 2D-point
  line), `points3D.txt` (points with colour, error 0 and an empty track). Readable by
  COLMAP (`colmap model_converter`), pycolmap and nerfstudio's COLMAP loader.
- `write_cameras_json`: `{"frames": [{"image", "extrinsic", "intrinsic", "width", "height"}]}`.
- `write_depth_pngs`: 16-bit PNG depth maps, `depth = value * scale` with one `scale`
  for all frames (in `depth_scale.json`), 0 where there is no depth; plus colour previews.
- `write_trajectory_png`: camera centres seen from above, drawn with Pillow.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from PIL import Image, ImageDraw

from rvggt_jax.io.ply import colors_u8, read_ply, read_ply_properties, write_ply

__all__ = [
    "camera_centers",
    "colorize",
    "export_reconstruction",
    "read_colmap_text",
    "read_depth_png",
    "read_ply",
    "read_ply_properties",
    "rotmat_to_qvec",
    "qvec_to_rotmat",
    "sanitize_cameras",
    "select_points",
    "unique_stems",
    "write_cameras_json",
    "write_colmap_text",
    "write_depth_pngs",
    "write_ply",
    "write_trajectory_png",
]

PathLike = str | os.PathLike


# ---------------------------------------------------------------------------------------
# PLY
# ---------------------------------------------------------------------------------------

_colors_u8 = colors_u8


# ---------------------------------------------------------------------------------------
# Rotations
# ---------------------------------------------------------------------------------------


def rotmat_to_qvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrix [3, 3] -> unit quaternion (qw, qx, qy, qz) with qw >= 0 (COLMAP order)."""
    R = np.asarray(R, dtype=np.float64)
    m00, m01, m02 = R[0]
    m10, m11, m12 = R[1]
    m20, m21, m22 = R[2]
    trace = m00 + m11 + m22
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = np.array([0.25 * s, (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s])
    elif m00 > m11 and m00 > m22:
        s = 2.0 * np.sqrt(1.0 + m00 - m11 - m22)
        q = np.array([(m21 - m12) / s, 0.25 * s, (m01 + m10) / s, (m02 + m20) / s])
    elif m11 > m22:
        s = 2.0 * np.sqrt(1.0 + m11 - m00 - m22)
        q = np.array([(m02 - m20) / s, (m01 + m10) / s, 0.25 * s, (m12 + m21) / s])
    else:
        s = 2.0 * np.sqrt(1.0 + m22 - m00 - m11)
        q = np.array([(m10 - m01) / s, (m02 + m20) / s, (m12 + m21) / s, 0.25 * s])
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def qvec_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Quaternion (qw, qx, qy, qz) -> rotation matrix [3, 3]."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _orthonormalize(R: np.ndarray) -> np.ndarray:
    """Nearest rotation (SVD), so that slightly non-orthogonal predictions still give a
    valid quaternion."""
    u, _, vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    r = u @ vt
    if np.linalg.det(r) < 0:
        u[:, -1] *= -1
        r = u @ vt
    return r


def camera_centers(extrinsics: np.ndarray) -> np.ndarray:
    """World positions of the cameras: extrinsics [S, 3, 4] world-to-camera -> [S, 3] (-R^T t)."""
    e = np.asarray(extrinsics, dtype=np.float64)
    return -np.einsum("sji,sj->si", e[:, :3, :3], e[:, :3, 3])


def sanitize_cameras(extrinsic: np.ndarray, intrinsic: np.ndarray, image_hw: tuple[int, int],
                     default_fov_deg: float = 60.0) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Make predicted cameras writable: extrinsic [S, 3, 4], intrinsic [S, 3, 3] ->
    copies with unusable values replaced, and a message per kind of replacement.

    A focal length that is not finite and positive (e.g. a predicted field of view of
    0, as random weights give) takes the other axis' focal when that one is usable,
    else the focal of a `default_fov_deg` horizontal field of view; non-finite
    rotations become the identity (re-orthonormalised otherwise) and non-finite
    translations 0. The principal point is the image centre `(W/2, H/2)` if not finite.
    """
    e = np.array(extrinsic, dtype=np.float64, copy=True)
    k = np.array(intrinsic, dtype=np.float64, copy=True)
    h, w = image_hw
    msgs: dict[str, list[int]] = {}

    def note(msg, i):
        msgs.setdefault(msg, []).append(i)

    def usable(f):
        return bool(np.isfinite(f) and f > 0 and f < 1e6 * max(h, w))

    for i in range(len(e)):
        fx, fy = k[i, 0, 0], k[i, 1, 1]
        if not usable(fx) or not usable(fy):
            default = (w / 2) / np.tan(np.radians(default_fov_deg) / 2)
            good = fx if usable(fx) else fy if usable(fy) else default
            note("unusable predicted focal length replaced" + ("" if usable(fx) or usable(fy) else
                 f" by a {default_fov_deg:g} degree field of view"), i)
            k[i, 0, 0] = fx if usable(fx) else good
            k[i, 1, 1] = fy if usable(fy) else good
        if not np.isfinite(k[i, :2, 2]).all():
            k[i, 0, 2], k[i, 1, 2] = w / 2, h / 2
            note("non-finite principal point replaced by the image centre", i)
        if not np.isfinite(e[i, :, :3]).all():
            e[i, :, :3] = np.eye(3)
            note("non-finite rotation replaced by the identity", i)
        else:
            e[i, :, :3] = _orthonormalize(e[i, :, :3])
        if not np.isfinite(e[i, :, 3]).all():
            e[i, :, 3] = 0.0
            note("non-finite translation replaced by 0", i)
    return e, k, [f"{m} (frame{'s' if len(ix) > 1 else ''} {', '.join(map(str, ix))})" for m, ix in msgs.items()]


# ---------------------------------------------------------------------------------------
# COLMAP text model
# ---------------------------------------------------------------------------------------


def _check_cameras(names: Sequence[str], extrinsics, intrinsics, sizes) -> tuple[np.ndarray, np.ndarray]:
    e = np.asarray(extrinsics, dtype=np.float64)
    k = np.asarray(intrinsics, dtype=np.float64)
    s = len(names)
    if e.shape != (s, 3, 4) or k.shape != (s, 3, 3) or len(sizes) != s:
        raise ValueError(f"{s} names need extrinsics [S,3,4], intrinsics [S,3,3], S sizes; "
                         f"got {e.shape}, {k.shape}, {len(sizes)}")
    return e, k


def _fmt(x: float) -> str:
    return repr(float(x))


def write_colmap_text(folder: PathLike, names: Sequence[str], extrinsics: np.ndarray, intrinsics: np.ndarray,
                      sizes: Sequence[tuple[int, int]], points: np.ndarray | None = None,
                      colors: np.ndarray | None = None) -> None:
    """COLMAP text model in `folder` (created): cameras.txt, images.txt, points3D.txt.

    names [S] image file names (COLMAP needs them without spaces); extrinsics [S, 3, 4]
    world-to-camera; intrinsics [S, 3, 3]; sizes [S] of (width, height) in the pixels
    of `intrinsics`; points [N, 3], colors [N, 3] (uint8 or float in [0, 1]). Camera
    and image ids are 1..S (camera i belongs to image i); points have ids 1..N, error
    0 and no track.
    """
    e, k = _check_cameras(names, extrinsics, intrinsics, sizes)
    for name in names:
        if any(ch.isspace() for ch in name):
            raise ValueError(f"COLMAP image names cannot contain spaces: {name!r}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    s = len(names)

    lines = ["# Camera list with one line of data per camera:",
             "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
             f"# Number of cameras: {s}"]
    for i in range(s):
        w, h = sizes[i]
        fx, fy, cx, cy = k[i, 0, 0], k[i, 1, 1], k[i, 0, 2], k[i, 1, 2]
        lines.append(f"{i + 1} PINHOLE {int(w)} {int(h)} {_fmt(fx)} {_fmt(fy)} {_fmt(cx)} {_fmt(cy)}")
    (folder / "cameras.txt").write_text("\n".join(lines) + "\n")

    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)",
             f"# Number of images: {s}, mean observations per image: 0"]
    for i in range(s):
        q = rotmat_to_qvec(_orthonormalize(e[i, :, :3]))
        t = e[i, :, 3]
        lines.append(" ".join([str(i + 1), *map(_fmt, q), *map(_fmt, t), str(i + 1), names[i]]))
        lines.append("")
    (folder / "images.txt").write_text("\n".join(lines) + "\n")

    pts = np.zeros((0, 3)) if points is None else np.asarray(points, dtype=np.float64)
    cols = _colors_u8(colors, len(pts))
    with open(folder / "points3D.txt", "w") as f:
        f.write("# 3D point list with one line of data per point:\n"
                "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
                f"# Number of points: {len(pts)}, mean track length: 0\n")
        f.writelines(
            f"{j + 1} {p[0]:.7g} {p[1]:.7g} {p[2]:.7g} {c[0]} {c[1]} {c[2]} 0\n"
            for j, (p, c) in enumerate(zip(pts, cols))
        )


def read_colmap_text(folder: PathLike) -> dict[str, Any]:
    """Parse a COLMAP text model (the subset `write_colmap_text` writes, following
    COLMAP's own reader: '#' comments, two lines per image) -> {"cameras": {id: {model,
    width, height, params}}, "images": {id: {qvec, tvec, camera_id, name, points2d}},
    "points": {id: {xyz, rgb, error, track}}}."""
    folder = Path(folder)
    cameras = {}
    for line in (folder / "cameras.txt").read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        it = line.split(" ")
        cameras[int(it[0])] = dict(model=it[1], width=int(it[2]), height=int(it[3]),
                                   params=np.array([float(v) for v in it[4:]]))
    images = {}
    lines = (folder / "images.txt").read_text().split("\n")
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        i += 1
        if not line or line.startswith("#"):
            continue
        it = line.split(" ")
        if len(it) != 10:
            raise ValueError(f"images.txt: bad image line {line!r}")
        if i >= len(lines):
            raise ValueError("images.txt: missing POINTS2D line")
        pts2d = lines[i].split()
        i += 1
        images[int(it[0])] = dict(qvec=np.array([float(v) for v in it[1:5]]), tvec=np.array([float(v) for v in it[5:8]]),
                                  camera_id=int(it[8]), name=it[9], points2d=pts2d)
    points = {}
    for line in (folder / "points3D.txt").read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        it = line.split()
        points[int(it[0])] = dict(xyz=np.array([float(v) for v in it[1:4]]), rgb=np.array([int(v) for v in it[4:7]]),
                                  error=float(it[7]), track=[int(v) for v in it[8:]])
    return dict(cameras=cameras, images=images, points=points)


# ---------------------------------------------------------------------------------------
# cameras.json
# ---------------------------------------------------------------------------------------


def write_cameras_json(path: PathLike, names: Sequence[str], extrinsics: np.ndarray, intrinsics: np.ndarray,
                       sizes: Sequence[tuple[int, int]], extra: Sequence[Mapping[str, Any]] | None = None,
                       meta: Mapping[str, Any] | None = None) -> None:
    """`{"frames": [{"image", "extrinsic" (3x4 world-to-camera, OpenCV), "intrinsic"
    (3x3), "width", "height"} + extra[i]], **meta}` as JSON."""
    e, k = _check_cameras(names, extrinsics, intrinsics, sizes)
    frames = []
    for i, name in enumerate(names):
        fr = dict(image=name, extrinsic=e[i].tolist(), intrinsic=k[i].tolist(),
                  width=int(sizes[i][0]), height=int(sizes[i][1]))
        if extra is not None:
            fr.update(extra[i])
        frames.append(fr)
    doc = dict(meta or {})
    doc["frames"] = frames
    text = _json_rows(doc)
    with open(path, "w") as f:
        f.write(text + "\n")


def _json_rows(obj: Any, indent: str = "") -> str:
    """JSON with lists of numbers on one line (one matrix row per line)."""
    inner = indent + " "
    if isinstance(obj, Mapping):
        if not obj:
            return "{}"
        items = [f"{inner}{json.dumps(str(k))}: {_json_rows(v, inner)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + "\n" + indent + "}"
    if isinstance(obj, (list, tuple)):
        if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in obj):
            return json.dumps(list(obj))
        return "[\n" + ",\n".join(inner + _json_rows(v, inner) for v in obj) + "\n" + indent + "]"
    return json.dumps(obj)


# ---------------------------------------------------------------------------------------
# Depth maps
# ---------------------------------------------------------------------------------------

# A perceptually ordered ramp (dark blue -> teal -> yellow), anchors interpolated linearly.
_RAMP = np.array([
    [0.050, 0.030, 0.330], [0.230, 0.200, 0.620], [0.130, 0.450, 0.560], [0.120, 0.620, 0.480],
    [0.380, 0.780, 0.300], [0.800, 0.870, 0.150], [0.990, 0.910, 0.140],
])


def colorize(values: np.ndarray, vmin: float, vmax: float, invalid: np.ndarray | None = None) -> np.ndarray:
    """Scalar image [H, W] -> RGB uint8 [H, W, 3] on a blue-to-yellow ramp (vmin blue);
    `invalid` pixels black."""
    v = np.asarray(values, dtype=np.float64)
    t = np.clip((v - vmin) / max(vmax - vmin, 1e-12), 0.0, 1.0)
    t = np.where(np.isfinite(t), t, 0.0) * (len(_RAMP) - 1)
    i0 = np.clip(np.floor(t).astype(int), 0, len(_RAMP) - 2)
    f = (t - i0)[..., None]
    rgb = _RAMP[i0] * (1 - f) + _RAMP[i0 + 1] * f
    out = (rgb * 255 + 0.5).astype(np.uint8)
    if invalid is not None:
        out[invalid] = 0
    return out


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


def write_depth_pngs(folder: PathLike, stems: Sequence[str], depth: np.ndarray, valid: np.ndarray | None = None,
                     preview_folder: PathLike | None = None) -> float:
    """16-bit depth PNGs `folder/<stem>.png` and `folder/depth_scale.json`; colour
    previews `preview_folder/<stem>.png` (if given).

    depth [S, H, W] (or [S, H, W, 1]); valid [S, H, W] bool (default: finite and > 0).
    One scale for every frame: `depth = png_value * scale`, with the largest valid depth
    at 65535; 0 marks pixels without depth. Returns the scale.
    """
    d = np.asarray(depth, dtype=np.float64)
    if d.ndim == 4 and d.shape[-1] == 1:
        d = d[..., 0]
    if d.ndim != 3 or d.shape[0] != len(stems):
        raise ValueError(f"depth must be [S, H, W] with S = {len(stems)}; got {np.shape(depth)}")
    ok = np.isfinite(d) & (d > 0)
    if valid is not None:
        ok &= np.asarray(valid, dtype=bool)
    dmax = float(d[ok].max()) if ok.any() else 1.0
    scale = dmax / 65535.0
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for i, stem in enumerate(stems):
        q = np.where(ok[i], np.clip(np.round(d[i] / scale), 1, 65535), 0).astype(np.uint16)
        Image.fromarray(q).save(folder / f"{stem}.png")
    with open(folder / "depth_scale.json", "w") as f:
        json.dump(dict(scale=scale, formula="depth = png_value * scale (16-bit PNG); 0 = no depth",
                       units="the model's depth units (scene scale normalised by the model, not metres)",
                       max_depth=dmax, frames=list(stems)), f, indent=1)
        f.write("\n")
    if preview_folder is not None:
        pf = Path(preview_folder)
        pf.mkdir(parents=True, exist_ok=True)
        for i, stem in enumerate(stems):
            vals = d[i][ok[i]]
            lo, hi = (np.percentile(vals, [2, 98]) if vals.size else (0.0, 1.0))
            # near = bright: colour inverse depth ranks
            img = colorize(-d[i], -hi, -lo, invalid=~ok[i])
            Image.fromarray(img).save(pf / f"{stem}.png")
    return scale


def read_depth_png(path: PathLike, scale: float | None = None) -> np.ndarray:
    """Depth [H, W] float32 from a `write_depth_pngs` file; `scale` defaults to the one
    in the `depth_scale.json` beside it. 0 = no depth."""
    path = Path(path)
    if scale is None:
        scale = json.loads((path.parent / "depth_scale.json").read_text())["scale"]
    with Image.open(path) as im:
        v = np.asarray(im).astype(np.float64)
    return (v * scale).astype(np.float32)


# ---------------------------------------------------------------------------------------
# Trajectory plot
# ---------------------------------------------------------------------------------------


def _top_view_basis(extrinsics: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two world axes spanning the ground plane: 'up' is the mean of the cameras' up
    (-y) axes; the first axis follows the first camera's right (x) axis."""
    e = np.asarray(extrinsics, dtype=np.float64)
    ups = -e[:, 1, :3]  # row 1 of R = camera y axis in world coordinates
    up = ups.mean(0)
    if np.linalg.norm(up) < 1e-6:
        up = ups[0]
    up /= np.linalg.norm(up)
    a = e[0, 0, :3] - up * (e[0, 0, :3] @ up)
    if np.linalg.norm(a) < 1e-6:
        a = np.cross(up, [1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.cross(up, [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)  # a x b = up: seen from above, not mirrored; ~ the first camera's forward
    return a, b


def write_trajectory_png(path: PathLike, extrinsics: np.ndarray, points: np.ndarray | None = None,
                         colors: np.ndarray | None = None, names: Sequence[str] | None = None,
                         size: int = 640, title: str = "camera trajectory (top view)") -> None:
    """Top view of the camera centres [S] in order (first green, last red, a tick for
    each viewing direction, labelled with the frame index) over an optional point
    cloud points [N, 3] / colors [N, 3]. `names` is accepted for symmetry with the
    other writers; labels are indices (the order of cameras.json)."""
    e = np.asarray(extrinsics, dtype=np.float64)
    centers = camera_centers(e)
    ax_a, ax_b = _top_view_basis(e)
    c2 = np.stack([centers @ ax_a, centers @ ax_b], axis=1)
    fwd = np.stack([e[:, 2, :3] @ ax_a, e[:, 2, :3] @ ax_b], axis=1)

    p2 = None
    if points is not None and len(points):
        pts = np.asarray(points, dtype=np.float64)
        p2 = np.stack([pts @ ax_a, pts @ ax_b], axis=1)
        keep = np.all(np.isfinite(p2), axis=1)
        p2 = p2[keep]
        colors = None if colors is None else _colors_u8(np.asarray(colors)[keep], len(p2))
    ext = c2 if p2 is None or not len(p2) else np.concatenate(
        [c2, np.percentile(p2, [2, 98], axis=0)], axis=0)
    lo, hi = ext.min(0), ext.max(0)
    span = float(max(hi[0] - lo[0], hi[1] - lo[1], 1e-6))
    spacing = span / max(len(c2), 2)
    lo -= 0.1 * span + 0.3 * spacing
    hi += 0.1 * span + 0.3 * spacing
    span = float(max(hi[0] - lo[0], hi[1] - lo[1]))
    mid = (lo + hi) / 2
    margin, top = 20, 28
    inner = size - 2 * margin

    def to_px(xy: np.ndarray) -> np.ndarray:
        u = margin + (xy[..., 0] - mid[0]) / span * inner + inner / 2
        v = top + (size - top - margin) / 2 - (xy[..., 1] - mid[1]) / span * inner  # forward = up on the page
        return np.stack([u, v], axis=-1)

    img = Image.new("RGB", (size, size + top - margin), (255, 255, 255))
    dr = ImageDraw.Draw(img)
    dr.text((margin, 6), title, fill=(0, 0, 0))
    if p2 is not None and len(p2):
        px = np.round(to_px(p2)).astype(int)
        ok = (px[:, 0] >= 0) & (px[:, 0] < img.width) & (px[:, 1] >= top) & (px[:, 1] < img.height)
        arr = np.asarray(img).copy()
        col = colors if colors is not None else np.full((len(p2), 3), 160, np.uint8)
        col = (0.7 * col.astype(np.float64) + 0.3 * 255).astype(np.uint8)  # faded behind the cameras
        arr[px[ok, 1], px[ok, 0]] = col[ok]
        img = Image.fromarray(arr)
        dr = ImageDraw.Draw(img)
    cp = to_px(c2)
    if len(cp) > 1:
        dr.line([tuple(p) for p in cp], fill=(90, 90, 90), width=2)
    tick = 0.06 * inner
    n = len(cp)
    for i, (p, f) in enumerate(zip(cp, fwd)):
        fn = np.linalg.norm(f)
        col = (30, 160, 60) if i == 0 else (200, 40, 40) if i == n - 1 else (40, 80, 200)
        if fn > 1e-9:
            q = p + np.array([f[0], -f[1]]) / fn * tick
            dr.line([tuple(p), tuple(q)], fill=col, width=2)
        r = 5
        dr.ellipse([p[0] - r, p[1] - r, p[0] + r, p[1] + r], fill=col, outline=(0, 0, 0))
        if n <= 30 or i % max(1, n // 30) == 0:
            dr.text((p[0] + 7, p[1] - 6), str(i), fill=(0, 0, 0))
    img.save(path)


# ---------------------------------------------------------------------------------------
# Whole reconstruction
# ---------------------------------------------------------------------------------------


def select_points(points: np.ndarray, conf: np.ndarray, colors: np.ndarray, valid: np.ndarray | None,
                  threshold: str | float = "50%", max_points: int | None = None,
                  seed: int = 0, return_index: bool = False) -> tuple:
    """Filter a point map by confidence.

    points [S, H, W, 3], conf [S, H, W], colors [S, H, W, 3] uint8, valid [S, H, W]
    (image content, not padding). `threshold`: a number X keeps points with
    conf >= X (VGGT's confidences are 1 + exp(.) >= 1); a string "P%" keeps points at
    or above the P-th percentile of the confidences of valid pixels ("0%" keeps all).
    Non-finite points are dropped. At most `max_points` are kept (uniform random
    subset, fixed seed). Returns points [N, 3] float32, colors [N, 3] uint8 and the
    absolute confidence threshold used; with `return_index`, also the kept points'
    flat indices [N] into [S * H * W] (frame = index // (H * W)).
    """
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    cf = np.asarray(conf, dtype=np.float32).reshape(-1)
    col = np.asarray(colors).reshape(-1, 3)
    ok = np.all(np.isfinite(pts), axis=1) & np.isfinite(cf)
    if valid is not None:
        ok &= np.asarray(valid, dtype=bool).reshape(-1)
    thr = parse_threshold(threshold)
    if isinstance(thr, tuple):
        abs_thr = float(np.percentile(cf[ok], thr[0])) if ok.any() else 0.0
    else:
        abs_thr = float(thr)
    ok &= cf >= abs_thr
    idx = np.flatnonzero(ok)
    if max_points is not None and len(idx) > max_points:
        idx = np.sort(np.random.default_rng(seed).choice(idx, size=max_points, replace=False))
    if return_index:
        return pts[idx], col[idx].astype(np.uint8), abs_thr, idx
    return pts[idx], col[idx].astype(np.uint8), abs_thr


def parse_threshold(threshold: str | float) -> float | tuple[float]:
    """`"P%"` -> (P,) (a percentile in [0, 100]); a number or numeric string -> float.
    NaN and infinities are refused (a NaN threshold would keep no point, silently)."""
    value = _parse_threshold(threshold)
    if not np.all(np.isfinite(value)):
        raise ValueError(f"bad confidence threshold {threshold!r}: must be a finite number or a percentage like '50%'")
    return value


def _parse_threshold(threshold: str | float) -> float | tuple[float]:
    if isinstance(threshold, str):
        s = threshold.strip()
        if s.endswith("%"):
            try:
                p = float(s[:-1])
            except ValueError:
                raise ValueError(f"bad confidence threshold {threshold!r}: expected a number or a percentage like '50%'") from None
            if not 0.0 <= p <= 100.0:
                raise ValueError(f"confidence percentile must be in [0, 100]; got {threshold!r}")
            return (p,)
        try:
            return float(s)
        except ValueError:
            raise ValueError(f"bad confidence threshold {threshold!r}: expected a number or a percentage like '50%'") from None
    return float(threshold)


def export_reconstruction(out_dir: PathLike, names: Sequence[str], images: np.ndarray, infos: Sequence[Any],
                          extrinsic: np.ndarray, intrinsic: np.ndarray, depth: np.ndarray, depth_conf: np.ndarray,
                          world_points: np.ndarray | None = None, world_points_conf: np.ndarray | None = None,
                          points_from: str = "depth", conf_threshold: str | float = "50%",
                          max_points: int | None = 2_000_000, max_colmap_points: int | None = 100_000,
                          meta: Mapping[str, Any] | None = None, write_scene: bool = True) -> dict[str, Any]:
    """Write every output of one reconstruction (one batch element) to `out_dir`:

        points.ply                point cloud (confidence-filtered, image colours,
                                  per-point `confidence` and source `frame`)
        scene.glb                 points + camera frustums (glTF, y up; `write_scene`)
        thumbnails/<stem>.jpg     the network input, small (for `rvggt view`)
        cameras.json              per-image camera, in the ORIGINAL image's pixels,
                                  plus the network-input camera under "network"
        sparse/{cameras,images,points3D}.txt     COLMAP text model (original pixels);
                                  points3D.txt holds a random subset of points.ply of at
                                  most `max_colmap_points` (None: all of them)
        depth/<stem>.png          16-bit depth of the network input (scale in depth/depth_scale.json)
        depth_preview/<stem>.png  coloured depth (near = bright)
        trajectory.png            camera centres from above

    names [S] image file names; images [S, 3, H, W] in [0, 1] (the network input);
    infos [S] `ImageInfo` (or None: network pixels are the original pixels); extrinsic
    [S, 3, 4] world-to-camera; intrinsic [S, 3, 3] in network pixels; depth
    [S, H, W(, 1)], depth_conf [S, H, W]; world_points [S, H, W, 3] and
    world_points_conf [S, H, W] for `points_from="pointmap"`. `points_from="depth"`
    unprojects the depth maps with the predicted cameras (upstream's default).
    COLMAP names cannot hold spaces: they are written with '_' instead (listed in the
    summary's `colmap_renamed`).
    Returns a summary dict (paths, point counts, threshold used).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    images = np.asarray(images, dtype=np.float32)
    s, _, h, w = images.shape
    extrinsic = np.asarray(extrinsic, dtype=np.float64)
    intrinsic = np.asarray(intrinsic, dtype=np.float64)
    depth = np.asarray(depth, dtype=np.float32)
    if depth.ndim == 4:
        depth = depth[..., 0]
    if infos is None:
        infos = [None] * s
    valid = np.stack([np.ones((h, w), bool) if info is None else info.valid_mask(h, w) for info in infos])
    colors = (np.clip(images.transpose(0, 2, 3, 1), 0, 1) * 255 + 0.5).astype(np.uint8)

    if points_from == "depth":
        pts = _unproject(depth, extrinsic, intrinsic)
        conf = np.asarray(depth_conf, dtype=np.float32)
        pvalid = valid & (depth > 1e-8)
    elif points_from == "pointmap":
        if world_points is None or world_points_conf is None:
            raise ValueError("points_from='pointmap' needs world_points and world_points_conf")
        pts = np.asarray(world_points, dtype=np.float32)
        conf = np.asarray(world_points_conf, dtype=np.float32)
        pvalid = valid
    else:
        raise ValueError(f"points_from must be 'depth' or 'pointmap'; got {points_from!r}")
    cloud, cloud_rgb, thr, idx = select_points(pts, conf, colors, pvalid, conf_threshold, max_points,
                                               return_index=True)
    cloud_conf = conf.reshape(-1)[idx].astype(np.float32)
    cloud_frame = (idx // (h * w)).astype(np.int32)
    write_ply(out / "points.ply", cloud, cloud_rgb, extra=dict(confidence=cloud_conf, frame=cloud_frame))

    orig_k = np.stack([intrinsic[i] if info is None else info.intrinsic_to_original(intrinsic[i])
                       for i, info in enumerate(infos)])
    sizes = [(w, h) if info is None else (info.width, info.height) for info in infos]
    extra = [dict(network=dict(intrinsic=intrinsic[i].tolist(), width=w, height=h)) for i in range(s)]
    json_meta = dict(convention="extrinsic: 3x4 world-to-camera, OpenCV axes (x right, y down, z forward); "
                                "intrinsic: pinhole in the original image's pixels (network: in the network input's)")
    json_meta.update(meta or {})
    write_cameras_json(out / "cameras.json", names, extrinsic, orig_k, sizes, extra=extra, meta=json_meta)

    if max_colmap_points is not None and len(cloud) > max_colmap_points:
        sel = np.sort(np.random.default_rng(1).choice(len(cloud), size=max_colmap_points, replace=False))
        cpts, crgb = cloud[sel], cloud_rgb[sel]
    else:
        cpts, crgb = cloud, cloud_rgb
    colmap_names = [n.replace(" ", "_") for n in names]
    write_colmap_text(out / "sparse", colmap_names, extrinsic, orig_k, sizes, cpts, crgb)

    if write_scene:
        from rvggt_jax.io.glb import write_glb

        write_glb(out / "scene.glb", cloud, cloud_rgb, extrinsic, orig_k, sizes)

    stems = unique_stems(names)
    write_thumbnails(out / "thumbnails", stems, images, valid)
    scale = write_depth_pngs(out / "depth", stems, depth, valid, preview_folder=out / "depth_preview")
    traj_pts = cloud[:: max(1, len(cloud) // 20000)]
    traj_rgb = cloud_rgb[:: max(1, len(cloud) // 20000)]
    write_trajectory_png(out / "trajectory.png", extrinsic, traj_pts, traj_rgb)
    return dict(out_dir=str(out), frames=s, points=int(len(cloud)), colmap_points=int(len(cpts)),
                max_colmap_points=max_colmap_points,
                conf_threshold=thr, depth_scale=scale, stems=stems,
                colmap_renamed=[(a, b) for a, b in zip(names, colmap_names) if a != b])


def write_thumbnails(folder: PathLike, stems: Sequence[str], images: np.ndarray, valid: np.ndarray,
                     max_side: int = 256) -> None:
    """`folder/<stem>.jpg`: each network input image [S, 3, H, W] in [0, 1], cut to its
    content box (valid [S, H, W], padding left out) and shrunk to `max_side` pixels."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for i, stem in enumerate(stems):
        rows, cols = np.flatnonzero(valid[i].any(1)), np.flatnonzero(valid[i].any(0))
        arr = images[i].transpose(1, 2, 0)
        if len(rows) and len(cols):
            arr = arr[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
        im = Image.fromarray((np.clip(arr, 0, 1) * 255 + 0.5).astype(np.uint8))
        im.thumbnail((max_side, max_side))
        im.save(folder / f"{stem}.jpg", quality=90)


def _unproject(depth: np.ndarray, extrinsic: np.ndarray, intrinsic: np.ndarray) -> np.ndarray:
    """World points [S, H, W, 3] of depth [S, H, W]: upstream's unprojection (pixel
    (col, row) at integer coordinates), via `rvggt_jax.geometry`."""
    from rvggt_jax.geometry import unproject_depth_map_to_point_map

    return np.asarray(unproject_depth_map_to_point_map(depth, extrinsic, intrinsic), dtype=np.float32)
