"""The DPT heads' convolutions, NHWC: nn.Conv2d (a 1x1 one as a matmul) and the
transposed conv whose stride is its kernel (a matmul and a reshape)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from rvggt_jax.model import layers
from rvggt_jax.model.params import Params
from rvggt_jax.ops.ordering import zeros_from


def conv2d(p: Params, x: jax.Array, stride: int = 1, padding: int | None = None) -> jax.Array:
    """nn.Conv2d with a square kernel: x [N, H, W, I], kernel [kh, kw, I, O] -> [N, H', W', O].
    `padding` defaults to 'same' for odd kernels (kh // 2), as every conv of the head."""
    kh = p["kernel"].shape[0]
    pad = kh // 2 if padding is None else padding
    if kh == 1 and stride == 1 and pad == 0:
        # A 1x1 conv is a per-pixel matmul; XLA:CPU runs it ~8x faster as one.
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
    it is a multiply-reduce over the I channels, which XLA fuses with the ReLU into one
    pass over x. As a matmul, the ReLU'd map is written out, read again, and multiplied
    by a 2- or 4-column matrix, which XLA:CPU's matmul runs at ~20 GFLOP/s: a head's last
    stage (3x3 conv, ReLU, 1x1) over 64 frames of 168 x 224 took 72 ms (2 outputs) and 80
    ms (4) that way, 39 and 42 ms this way (docs/benchmarks.md). The ReLU keeps torch's
    zero gradient at 0 (`_relu_against`)."""
    kernel = p["kernel"]
    if kernel.shape[:2] != (1, 1):
        raise ValueError(f"relu_pointwise takes a 1x1 kernel, got {kernel.shape[:2]}")
    if kernel.shape[-1] > POINTWISE_REDUCE_MAX_OUT:
        return conv2d(p, jax.nn.relu(x))
    w = kernel[0, 0].astype(jnp.float32)  # [I, O]
    y = jnp.sum(_relu_against(x.astype(jnp.float32), zeros_from(w.shape[:1], jnp.float32, w))[..., :, None] * w,
                axis=-2)
    if "bias" in p:
        y = y + p["bias"].astype(jnp.float32)
    return y.astype(x.dtype)


@jax.custom_jvp
def _relu_against(x: jax.Array, zero: jax.Array) -> jax.Array:
    """jax.nn.relu(x) for x [..., I], against zero [I], a zero vector made from another
    value (`zeros_from`). XLA:CPU's YNNPACK fusion of the 3x3 conv, the ReLU and the
    multiply-reduce takes a scalar constant's broadcast as an operand that another op
    writes out, one [frames, H, W, I] map of zeros per frame group (0.5 ms each, 32 per
    head at 64 frames of 168 x 224); a vector operand it broadcasts itself. The gradient
    is jax.nn.relu's: none at 0, as torch's."""
    return jnp.maximum(x, zero)


@_relu_against.defjvp
def _relu_against_jvp(primals, tangents):
    x, zero = primals
    tx, _ = tangents
    return _relu_against(x, zero), jnp.where(x > zero, tx, jnp.zeros_like(tx))


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
