"""Align-corners bilinear resizing (torch's `F.interpolate(mode="bilinear",
align_corners=True)`) and the DPT head's last upsampling fused with the 3x3 convolution
that follows it.

The dense DPT head upsamples its fused map [N, h, w, C] to the image size [H, W]
(about 1.75x per axis), adds the positional map and runs a 3x3 convolution C -> O there.
Every step is linear, and bilinear resizing is separable, so the same output comes from
convolving at the lower resolution: each of the kernel's 3 x 3 taps reads the resized
map shifted by (dy, dx), which is the resize with shifted source rows / columns. Mixing
the channels before the resize does the 9 C O multiply-adds per input pixel instead of
per output pixel (~3x fewer). Equal up to float rounding; docs/benchmarks.md has the
measurements.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.model.params import Params


def align_corners_axis(in_size: int, out_size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Source indices (lower, upper) and upper weight for align-corners linear resizing,
    with torch's float32 arithmetic (scale (in-1)/(out-1), lower = floor(scale * i))."""
    scale = np.float32((in_size - 1) / (out_size - 1)) if out_size > 1 else np.float32(0.0)
    src = scale * np.arange(out_size, dtype=np.float32)
    lo = np.minimum(src.astype(np.int64), in_size - 1)
    hi = np.minimum(lo + 1, in_size - 1)
    return lo, hi, (src - lo.astype(np.float32)).astype(np.float32)


def _lerp(x: jax.Array, axis: int, lo: np.ndarray, hi: np.ndarray, w_lo: np.ndarray, w_hi: np.ndarray) -> jax.Array:
    """x resampled along `axis`: x[lo] * w_lo + x[hi] * w_hi, one entry per output index."""
    shape = [1] * x.ndim
    shape[axis] = len(lo)
    return (jnp.take(x, lo, axis=axis) * jnp.asarray(w_lo.reshape(shape))
            + jnp.take(x, hi, axis=axis) * jnp.asarray(w_hi.reshape(shape)))


def resize_bilinear_align_corners(x: jax.Array, size: tuple[int, int]) -> jax.Array:
    """torch `F.interpolate(mode="bilinear", align_corners=True)` on NHWC: corner pixels of
    input and output coincide. (jax.image.resize uses half-pixel centres instead.)
    x [N, H, W, C] -> [N, size[0], size[1], C]."""
    def along(x, axis, out_size):
        lo, hi, wt = align_corners_axis(x.shape[axis], out_size)
        return _lerp(x, axis, lo, hi, 1 - wt, wt)

    return along(along(x, 2, size[1]), 1, size[0])


def shifted_taps(in_size: int, out_size: int) -> list[tuple[np.ndarray, ...]]:
    """For the 3 offsets d = -1, 0, 1 of a 3x3 kernel: (lo, hi, w_lo, w_hi) [out_size]
    reading output index i + d of the align-corners resize from the input, with both
    weights 0 where i + d falls outside [0, out_size) (the convolution's zero padding)."""
    lo, hi, wt = align_corners_axis(in_size, out_size)
    taps = []
    for d in (-1, 0, 1):
        idx = np.arange(out_size) + d
        inside = (idx >= 0) & (idx < out_size)
        j = np.clip(idx, 0, out_size - 1)
        taps.append((lo[j], hi[j], np.where(inside, 1 - wt[j], 0).astype(np.float32),
                     np.where(inside, wt[j], 0).astype(np.float32)))
    return taps


def _conv3x3(p: Params, x: jax.Array) -> jax.Array:
    """[N, H, W, C] -> [N, H, W, O], zero padding 1, no bias."""
    return jax.lax.conv_general_dilated(x, p["kernel"], (1, 1), ((1, 1), (1, 1)),
                                        dimension_numbers=("NHWC", "HWIO", "NHWC"),
                                        precision=jax.lax.Precision.HIGHEST)


def resized_conv3x3(p: Params, size: tuple[int, int], pos: jax.Array | np.ndarray | None = None
                    ) -> Callable[[jax.Array], jax.Array]:
    """x [N, h, w, C] -> conv3x3(resize_bilinear_align_corners(x, size) + pos) + bias
    [N, size[0], size[1], O], zero padding 1 (output_conv2's first conv after the head's
    last upsampling). p: kernel [3, 3, C, O] (and bias); pos [size[0], size[1], C] or None.

    Returns the function of x, to be made once outside a loop over frames: with C >= O
    (VGGT-1B's 128 -> 32) it holds the input-free part, the convolved positional map plus
    the bias, and convolves at the low resolution: x's channels mixed into the 9 taps' O
    outputs per input pixel, each tap then resized with its shifted rows and columns.
    With C < O (the 8 -> 32 of narrow models) mixing first widens the map 9 O / C times,
    so it resizes and convolves as written (docs/benchmarks.md measures both)."""
    kernel = p["kernel"]
    if kernel.shape[:2] != (3, 3):
        raise ValueError(f"resized_conv3x3 takes a 3x3 kernel, got {kernel.shape[:2]}")
    c, o = kernel.shape[2:]
    if pos is not None and tuple(pos.shape) != tuple(size) + (c,):
        raise ValueError(f"the positional map is {tuple(pos.shape)}, the resized map {tuple(size) + (c,)}")
    bias = p["bias"] if "bias" in p else jnp.zeros((o,), kernel.dtype)
    height, width = size

    if c < o:
        def plain(x):
            y = resize_bilinear_align_corners(x, size)
            return _conv3x3(p, y if pos is None else y + jnp.asarray(pos, y.dtype)) + bias
        return plain

    offset = bias if pos is None else _conv3x3(p, jnp.asarray(pos, kernel.dtype)[None])[0] + bias
    # [C, (dx, dy, O)]: one matmul gives every tap's contribution of a pixel
    k = jnp.transpose(kernel, (2, 1, 0, 3)).reshape(c, 9 * o)

    def fused(x):
        n, h, w, _ = x.shape
        cols, rows = shifted_taps(w, width), shifted_taps(h, height)
        mixed = jnp.einsum("nhwc,ck->nhwk", x, k, precision=jax.lax.Precision.HIGHEST).reshape(n, h, w, 3, 3 * o)
        # the column shifts dx = -1, 0, 1 resized and summed: [N, h, W, (dy, O)]
        z = sum(_lerp(mixed[:, :, :, b], 2, *cols[b]) for b in range(3)).reshape(n, h, width, 3, o)
        out = offset
        for a in range(3):  # the row shifts dy = -1, 0, 1
            out = out + _lerp(z[:, :, :, a], 1, *rows[a])
        return out

    return fused
