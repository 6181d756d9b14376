"""The DPT heads' convolutions, NHWC: nn.Conv2d (a 1x1 one as a matmul) and the
transposed conv whose stride is its kernel (a matmul and a reshape)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from rvggt_jax.model import layers
from rvggt_jax.model.params import Params
from rvggt_jax.ops.ordering import relu_unwritten


def conv2d(p: Params, x: jax.Array, stride: int = 1, padding: int | None = None) -> jax.Array:
    """nn.Conv2d with a square kernel: x [N, H, W, I], kernel [kh, kw, I, O] -> [N, H', W', O].
    `padding` defaults to 'same' for odd kernels (kh // 2), as every conv of the head."""
    kh = p["kernel"].shape[0]
    pad = kh // 2 if padding is None else padding
    if kh == 1 and stride == 1 and pad == 0:
        # a 1x1 conv is a per-pixel matmul (~8x faster as one on a CPU)
        return layers.linear(_as_linear(p), x)
    y = jax.lax.conv_general_dilated(
        x, p["kernel"], window_strides=(stride, stride), padding=((pad, pad), (pad, pad)),
        dimension_numbers=("NHWC", "HWIO", "NHWC"), precision=jax.lax.Precision.HIGHEST)
    if "bias" in p:
        y = y + p["bias"]
    return y


# Output channels up to which `relu_pointwise` reduces instead of multiplying matrices.
POINTWISE_REDUCE_MAX_OUT = 8


def relu_pointwise(p: Params, x: jax.Array) -> jax.Array:
    """conv2d(p, relu(x)) for a 1x1 kernel [1, 1, I, O]: x [..., I] -> [..., O] in x's
    dtype, products and sums in float32.

    With few outputs (O <= POINTWISE_REDUCE_MAX_OUT: the heads' last conv, 32 -> 2 or 4)
    it is a multiply-reduce over the I channels, one pass over x with the ReLU, rather
    than a matmul by a 2- or 4-column matrix (half the time of a head's last stage on a
    CPU: docs/history/cpu_speed.md)."""
    kernel = p["kernel"]
    if kernel.shape[:2] != (1, 1):
        raise ValueError(f"relu_pointwise takes a 1x1 kernel, got {kernel.shape[:2]}")
    if kernel.shape[-1] > POINTWISE_REDUCE_MAX_OUT:
        return conv2d(p, jax.nn.relu(x))
    w = kernel[0, 0].astype(jnp.float32)  # [I, O]
    # (a ReLU whose zero is made from the weights: no map of zeros is written out for it)
    y = jnp.sum(relu_unwritten(x.astype(jnp.float32), w)[..., :, None] * w, axis=-2)
    if "bias" in p:
        y = y + p["bias"].astype(jnp.float32)
    return y.astype(x.dtype)


def _as_linear(p: Params) -> Params:
    out = {"kernel": p["kernel"][0, 0]}
    if "bias" in p:
        out["bias"] = p["bias"]
    return out


def conv_transpose_patchwise(p: Params, x: jax.Array) -> jax.Array:
    """nn.ConvTranspose2d whose stride equals its kernel size (k) and padding is 0: every
    input pixel paints its own k x k output block, so it is one matmul and a reshape.

    x [N, h, w, I], kernel [k, k, I, O] (torch weight [I, O, k, k] permuted (2, 3, 0, 1))
    -> [N, k*h, k*w, O]; output (k*i + a, k*j + b) = x(i, j) @ kernel[a, b] + bias."""
    k = p["kernel"].shape[0]
    n, h, w, _ = x.shape
    y = jnp.einsum("nijc,abco->niajbo", x, p["kernel"], precision=jax.lax.Precision.HIGHEST)
    return y.reshape(n, h * k, w * k, -1) + p["bias"]
