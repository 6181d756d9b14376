"""Network inputs of a scene and its ground truth at the network's resolution.

`network_images(paths, size)`: at the default size 518 this is the project's
upstream-exact `load_images_with_info(paths, "crop")` (width 518, height a multiple of
14, centre-cropped to <= 518: 518x392 for 4:3 frames, the paper's resolution). Other
sizes (small CPU runs, tests) apply the same rule with `size` in place of 518.

`gt_points_at_network(scene, i, info, hw)`: the ground-truth world point seen at each
network pixel, from the frame's depth map: the network pixel centre is mapped back to
the original image (`ImageInfo`), then to the nearest depth-map pixel, and that
pixel is unprojected with the depth camera. The ground-truth geometry is exact; only
the pixel correspondence is nearest-neighbour (as resizing the depth map would be).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = ["gt_points_at_network", "network_images"]

PATCH = 14


def network_images(paths: Sequence[Path], size: int = 518):
    """(images [S, 3, H, W] float32 in [0, 1], [ImageInfo]) for the model."""
    from rvggt_jax.io.images import TARGET_SIZE, ImageInfo, load_images_with_info

    if size == TARGET_SIZE:
        return load_images_with_info(paths, mode="crop")
    if size < PATCH or size % PATCH:
        raise ValueError(f"image size must be a positive multiple of {PATCH}; got {size}")
    from PIL import Image

    from rvggt_jax.io.images import _open_rgb

    arrays, infos = [], []
    for p in paths:
        img = _open_rgb(os.fspath(p))
        w, h = img.size
        nh = round(h * (size / w) / PATCH) * PATCH
        if nh < PATCH:
            raise ValueError(f"image {p} ({w}x{h}) is too thin for width {size}")
        arr = np.asarray(img.resize((size, nh), Image.Resampling.BICUBIC), np.uint8).transpose(2, 0, 1)
        arr = arr.astype(np.float32) / np.float32(255.0)
        oy = 0.0
        if nh > size:
            top = (nh - size) // 2
            arr, oy = arr[:, top:top + size], -float(top)
        arrays.append(arr)
        infos.append(ImageInfo(path=os.fspath(p), name=Path(p).name, width=w, height=h, sx=size / w, sy=nh / h,
                               ox=0.0, oy=oy, valid=(0, 0, arr.shape[2], arr.shape[1])))
    if len({a.shape for a in arrays}) > 1:
        raise ValueError("the frames of a scene must have one aspect ratio at this image size")
    return np.stack(arrays), infos


def gt_points_at_network(scene, i: int, info, hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth world points [H, W, 3] (float64) and validity [H, W] (depth > 0 and
    inside the image) at network resolution hw = (H, W) for frame i of `scene`."""
    depth = scene.depth(i)
    hd, wd = depth.shape
    h, w = hw
    u = (np.arange(w) + 0.5 - info.ox) / info.sx  # continuous original-image coordinates
    v = (np.arange(h) + 0.5 - info.oy) / info.sy
    cu = np.floor(u * wd / info.width).astype(np.int64)
    cv = np.floor(v * hd / info.height).astype(np.int64)
    inside = (cu >= 0) & (cu < wd)
    inside_v = (cv >= 0) & (cv < hd)
    cu, cv = np.clip(cu, 0, wd - 1), np.clip(cv, 0, hd - 1)
    d = depth[cv[:, None], cu[None, :]].astype(np.float64)
    valid = (d > 0) & np.isfinite(d) & inside_v[:, None] & inside[None, :]
    k = scene.depth_camera(i)
    x = (cu[None, :] - k[0, 2]) / k[0, 0] * d
    y = (cv[:, None] - k[1, 2]) / k[1, 1] * d
    cam = np.stack([x, y, d], axis=-1)
    e = scene.extrinsics[i]
    world = (cam - e[:, 3]) @ e[:, :3]  # R^T (p - t)
    return world, valid
