"""Pictures for looking at a reconstruction: the colour ramp of depth previews
(`colorize`), the camera trajectory seen from above (`write_trajectory_png`, drawn with
Pillow) and the network-input thumbnails that `rvggt view` shows (`write_thumbnails`)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np
from PIL import Image, ImageDraw

from rvggt_jax.io.ply import colors_u8

__all__ = ["colorize", "write_thumbnails", "write_trajectory_png"]

PathLike = str | os.PathLike

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
    from rvggt_jax.geometry import camera_centers  # (JAX: imported when a plot is drawn)

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
        colors = None if colors is None else colors_u8(np.asarray(colors)[keep], len(p2))
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
