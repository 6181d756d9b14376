"""The DPT head's additive positional map: sin/cos of a centred uv grid whose
half-diagonal is 1 (upstream's `create_uv_grid` + `position_grid_to_embed`, times 0.1).
A shape-only constant, computed in numpy."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

POS_EMBED_RATIO = 0.1
POS_EMBED_OMEGA0 = 100.0


def uv_grid(width: int, height: int, aspect_ratio: float) -> np.ndarray:
    """[height, width, 2] (u, v) pixel-centre coordinates of a plane whose half-diagonal is 1
    and whose width:height is `aspect_ratio`; float32, as upstream's `create_uv_grid`."""
    diag = (aspect_ratio ** 2 + 1.0) ** 0.5
    span_x, span_y = aspect_ratio / diag, 1.0 / diag
    xs = np.linspace(-span_x * (width - 1) / width, span_x * (width - 1) / width, width)
    ys = np.linspace(-span_y * (height - 1) / height, span_y * (height - 1) / height, height)
    uu, vv = np.meshgrid(xs.astype(np.float32), ys.astype(np.float32), indexing="xy")
    return np.stack([uu, vv], axis=-1)


def _sincos_1d(dim: int, pos: np.ndarray, omega0: float) -> np.ndarray:
    """[M] positions -> [M, dim]: sin then cos of pos * omega0^(-2i/dim), i < dim/2.
    Upstream forms the products in float64 from float32 positions."""
    omega = 1.0 / omega0 ** (np.arange(dim // 2, dtype=np.float64) / (dim / 2.0))
    angles = pos.astype(np.float64)[:, None] * omega[None, :]
    return np.concatenate([np.sin(angles), np.cos(angles)], axis=1).astype(np.float32)


def pos_embed_map(height: int, width: int, channels: int, aspect_ratio: float) -> np.ndarray:
    """The additive positional map [height, width, channels] (already times 0.1): channels
    [0, C/2) embed u, [C/2, C) embed v. A shape-only constant, so computed in numpy."""
    if channels % 4:
        raise ValueError(f"the DPT positional embedding needs channels % 4 == 0, got {channels}")
    grid = uv_grid(width, height, aspect_ratio).reshape(-1, 2)
    emb = np.concatenate([_sincos_1d(channels // 2, grid[:, 0], POS_EMBED_OMEGA0),
                          _sincos_1d(channels // 2, grid[:, 1], POS_EMBED_OMEGA0)], axis=-1)
    return (emb.reshape(height, width, channels) * np.float32(POS_EMBED_RATIO)).astype(np.float32)


def add_pos_embed(x: jax.Array, image_hw: tuple[int, int]) -> jax.Array:
    """x [N, h, w, C] + the positional map of an h x w grid with the image's aspect ratio."""
    _, h, w, c = x.shape
    return x + jnp.asarray(pos_embed_map(h, w, c, image_hw[1] / image_hw[0]))
