"""Upsampling in the DPT heads: align-corners bilinear resizing (torch's
`F.interpolate(mode="bilinear", align_corners=True)`), and each upsampling fused with the
3x3 convolution that follows it, so that the convolution's channel mix runs at the low
resolution.

- `resized_conv3x3`: a bilinear upsampling (and the positional map) then a 3x3 conv.
  Every step is linear and the resize is separable, so each of the kernel's 9 taps reads
  the resized map at a shifted row and column, which is the resize with shifted source
  indices: mixing the channels before the resize does the 9 C O multiply-adds per input
  pixel instead of per output pixel (~4x fewer for a 2x upsampling, ~3x for 1.75x).
- `patchwise_conv3x3`: a transposed conv whose stride is its kernel (each input pixel
  paints a k x k block) then a 3x3 conv: composing the kernels, each output pixel sums
  <= 2 x 2 input pixels' products instead of 9 upsampled ones.

Equal up to float rounding; docs/benchmarks.md has the measurements.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.model.heads.conv import conv2d
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


def resize_then_conv3x3(p: Params, size: tuple[int, int], pos: jax.Array | np.ndarray | None = None
                        ) -> Callable[[jax.Array], jax.Array]:
    """The composition `resized_conv3x3` computes, as written: x [N, h, w, C] ->
    conv2d(p, resize_bilinear_align_corners(x, size) + pos) (every output pixel convolved
    at the high resolution)."""
    def plain(x):
        y = resize_bilinear_align_corners(x, size)
        return conv2d(p, y if pos is None else y + jnp.asarray(pos, y.dtype))
    return plain


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
    so it resizes and convolves as written (docs/history/cpu_speed.md measures both)."""
    kernel = p["kernel"]
    if kernel.shape[:2] != (3, 3):
        raise ValueError(f"resized_conv3x3 takes a 3x3 kernel, got {kernel.shape[:2]}")
    c, o = kernel.shape[2:]
    if pos is not None and tuple(pos.shape) != tuple(size) + (c,):
        raise ValueError(f"the positional map is {tuple(pos.shape)}, the resized map {tuple(size) + (c,)}")
    height, width = size

    if c < o:
        return resize_then_conv3x3(p, size, pos)

    if pos is None:
        offset = p["bias"] if "bias" in p else jnp.zeros((o,), kernel.dtype)
    else:
        offset = conv2d(p, jnp.asarray(pos, kernel.dtype)[None])[0]  # (bias included)
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


def _shift(x: jax.Array, axis: int, s: int) -> jax.Array:
    """out[i] = x[i + s] along `axis` (s in -1, 0, 1), zero where i + s is outside."""
    if s == 0:
        return x
    n = x.shape[axis]
    kept = jax.lax.slice_in_dim(x, max(s, 0), n + min(s, 0), axis=axis)
    pad = [(0, 0)] * x.ndim
    pad[axis] = (max(-s, 0), max(s, 0))
    return jnp.pad(kept, pad)


def _source_rows(k: int) -> np.ndarray:
    """For a k x k patchwise upsampling followed by a 3x3 conv, [k + 2, k, 3]: for each
    (output sub-row a, source row shift s) pair that any tap reaches (sub-rows 0..k-1 from
    the input pixel itself, s = 0; sub-row 0 from the pixel above, s = -1; sub-row k-1
    from the one below, s = +1), 1 at (upsampled sub-row (a + dy) % k, tap dy + 1) for each
    tap dy whose row (a + dy) // k is that shift. (Columns are the same.)"""
    pairs = [(a, 0) for a in range(k)] + [(0, -1), (k - 1, 1)]
    select = np.zeros((k + 2, k, 3), np.float32)
    for p, (a, s) in enumerate(pairs):
        for dy in (-1, 0, 1):
            if (a + dy) // k == s:
                select[p, (a + dy) % k, dy + 1] = 1
    return select


def patchwise_conv3x3(up: Params, conv: Params, hw: tuple[int, int]) -> Callable[[jax.Array], jax.Array]:
    """x [N, h, w, I] (hw = (h, w)) -> conv3x3(patchwise upsampling of x) [N, k h, k w, O], zero
    padding 1: the DPT head's x4 / x2 transposed convs (stride = kernel k, `up`: kernel
    [k, k, I, M], bias [M]) and the 3x3 `layer{1,2}_rn` after them (`conv`: [3, 3, M, O]).

    Every upsampled pixel is one input pixel's matmul, so each output pixel's 9 taps
    read at most 2 x 2 input pixels: composing the two kernels, an output pixel is the sum
    of <= 4 [I, O] products instead of 9 [M, O] ones (plus the upsampling's I x M): per
    input pixel (k + 2)^2 products against 9 k^2 + k^2 (x4: 36 against 160). Returns the
    function of x; the composed kernels and the bias map are made once, here (outside a
    frame loop)."""
    kt, k3 = up["kernel"], conv["kernel"]
    k = kt.shape[0]
    if k < 2 or kt.shape[:2] != (k, k) or k3.shape[:2] != (3, 3):
        raise ValueError(f"patchwise_conv3x3 takes a k x k upsampling (k >= 2) and a 3x3 conv, "
                         f"got kernels {kt.shape} and {k3.shape}")
    hp = jax.lax.Precision.HIGHEST
    select = _source_rows(k)
    # [pair_y, pair_x, I, O]: sum over the taps of sub-pixel kernel @ tap kernel
    taps = jnp.einsum("abim,yxmo->aybxio", kt, k3, precision=hp)  # [k, 3, k, 3, I, O]
    composed = jnp.einsum("pay,qbx,aybxio->pqio", select, select, taps, precision=hp)
    o = k3.shape[-1]
    h, w = hw

    def valid(size: int) -> np.ndarray:  # [size, 3]: output index i reads i + dy inside
        idx = np.arange(size)[:, None] + np.arange(-1, 2)[None]
        return ((idx >= 0) & (idx < size)).astype(np.float32)

    # the upsampling's bias through the taps that land inside (fewer at the border), and
    # the conv's own bias: [k h, k w, O]
    bias_taps = jnp.einsum("m,yxmo->yxo", up["bias"], k3, precision=hp)
    offset = jnp.einsum("Yy,Xx,yxo->YXo", valid(k * h), valid(k * w), bias_taps, precision=hp)
    if "bias" in conv:
        offset = offset + conv["bias"]

    def fused(x: jax.Array) -> jax.Array:
        n = x.shape[0]
        if x.shape[1:3] != (h, w):
            raise ValueError(f"patchwise_conv3x3 was made for {h} x {w} maps, got {x.shape[1:3]}")
        z = jnp.einsum("nhwi,pqio->nhwpqo", x, composed, precision=hp)  # [N, h, w, k+2, k+2, O]
        # row pairs -> sub-rows: the pixel's own k, then the row above's into sub-row 0
        # and the row below's into sub-row k-1 (zero beyond the map)
        def gather(z, pix_axis, pair_axis):
            own = jax.lax.slice_in_dim(z, 0, k, axis=pair_axis)
            above = _shift(jax.lax.slice_in_dim(z, k, k + 1, axis=pair_axis), pix_axis, -1)
            below = _shift(jax.lax.slice_in_dim(z, k + 1, k + 2, axis=pair_axis), pix_axis, 1)
            middle = [jnp.zeros_like(above)] * (k - 2)
            return own + jnp.concatenate([above] + middle + [below], axis=pair_axis)
        y = gather(gather(z, 1, 3), 2, 4)  # [N, h, w, k, k, O]
        return y.transpose(0, 1, 3, 2, 4, 5).reshape(n, k * h, k * w, o) + offset

    return fused
