"""Small file helpers shared by the dataset formats: 16-bit depth PNGs, text matrices,
images, camera conversions."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from rvggt_jax.eval.datasets.base import DatasetError, need_file

__all__ = ["c2w_to_w2c", "read_depth_u16", "read_matrix", "save_image", "w2c_to_c2w", "write_depth_u16",
           "write_matrix"]


def read_depth_u16(path: Path, scale: float, invalid: int | None = None) -> np.ndarray:
    """16-bit depth PNG -> [H, W] float32 metres (value * scale); `invalid` (e.g. 7
    Scenes' 65535) and 0 become 0."""
    try:
        with Image.open(path) as im:
            v = np.asarray(im)
    except OSError as e:
        raise DatasetError(f"cannot read depth map {path}: {e}") from None
    if v.ndim != 2:
        raise DatasetError(f"depth map is not single-channel: {path} (shape {v.shape})")
    d = v.astype(np.float32) * np.float32(scale)
    if invalid is not None:
        d[v == invalid] = 0.0
    return d


def write_depth_u16(path: Path, depth: np.ndarray, scale: float, invalid: int = 0) -> None:
    """[H, W] metres -> 16-bit PNG of round(depth / scale); depth <= 0 -> `invalid`."""
    v = np.round(np.asarray(depth, np.float64) / scale)
    if (v > 65534).any():
        raise ValueError(f"depth beyond the 16-bit range at scale {scale}: {path}")
    out = np.where(np.asarray(depth) > 0, v, invalid).astype(np.uint16)
    Image.fromarray(out).save(path)


def read_matrix(path: Path, what: str, shape=(4, 4)) -> np.ndarray:
    """A whitespace-separated text matrix (e.g. a 4x4 pose) -> float64 array of `shape`."""
    need_file(path, what)
    try:
        a = np.array(path.read_text().split(), dtype=np.float64)
    except ValueError:
        raise DatasetError(f"malformed {what} (not numbers): {path}") from None
    if a.size != int(np.prod(shape)):
        raise DatasetError(f"{what} must hold {int(np.prod(shape))} numbers, found {a.size}: {path}")
    return a.reshape(shape)


def write_matrix(path: Path, m: np.ndarray) -> None:
    path.write_text("\n".join(" ".join(f"{x:.10g}" for x in row) for row in np.asarray(m)) + "\n")


def save_image(path: Path, rgb: np.ndarray) -> None:
    """[H, W, 3] uint8 -> file (format from the suffix; JPEG at quality 95)."""
    img = Image.fromarray(np.asarray(rgb, np.uint8))
    if path.suffix.lower() in (".jpg", ".jpeg"):
        img.save(path, quality=95)
    else:
        img.save(path)


def c2w_to_w2c(c2w: np.ndarray) -> np.ndarray:
    """[..., 4, 4] camera-to-world -> [..., 3, 4] world-to-camera (rigid inverse)."""
    r = np.swapaxes(c2w[..., :3, :3], -1, -2)
    t = -np.einsum("...ij,...j->...i", r, c2w[..., :3, 3])
    return np.concatenate([r, t[..., None]], axis=-1)


def w2c_to_c2w(w2c: np.ndarray) -> np.ndarray:
    """[..., 3|4, 4] world-to-camera -> [..., 4, 4] camera-to-world."""
    r = np.swapaxes(w2c[..., :3, :3], -1, -2)
    out = np.zeros(w2c.shape[:-2] + (4, 4))
    out[..., :3, :3] = r
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", r, w2c[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out
