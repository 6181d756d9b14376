"""The Pallas TPU flash attention kernel (`jax.experimental.pallas.ops.tpu.flash_attention`)
with the key bias folded into the operands, as for cuDNN (`fused.fold_key_bias`).

The kernel tiles sequences in blocks of 128 rows: queries and keys are padded to a
multiple of that, and padded keys are removed through the folded bias column (NEG_BIAS,
exactly 0 after the softmax), so a bias column is always present. The head dimension
(D + the bias columns) is padded to a multiple of 8; the kernel takes any head dimension
up to 128. It carries its own backward (flash attention's, blockwise: O(N d) memory).
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp

from rvggt_jax.ops.kernels.fused import fold_key_bias, missing_private_api

# the kernel's sequence block (its BlockSizes defaults) and largest unpadded head dim
BLOCK = 128
MAX_HEAD_DIM = 128
HEAD_MULTIPLE = 8

# What this module calls in JAX's experimental Pallas kernel, and how: (function,
# positional arguments, keyword names), checked against the signatures
# (`fused.missing_private_api`). Written against JAX 0.10.2; the same in 0.11.
PALLAS_MODULE = "jax.experimental.pallas.ops.tpu.flash_attention"
FLASH_CALLS = (("flash_attention", 3, ("sm_scale",)),)
_BWD = ("block_q_major", "block_k_major", "block_k", "sm_scale", "causal", "mask_value", "debug")
LSE_CALLS = (("_flash_attention_impl", 13, ()), ("_flash_attention_bwd_dkv", 9, _BWD + ("block_q",)),
             ("_flash_attention_bwd_dq", 9, _BWD), ("BlockSizes.get_default", 5, ()))
LSE_ATTRS = ("DEFAULT_MASK_VALUE",)


def tpu_flash_attention(q: jax.Array, k: jax.Array, v: jax.Array, key_bias: jax.Array | None, scale: float,
                        neg_bias: float) -> jax.Array:
    """q [B, Nq, H, D], k [B, Nk, H, D], v [B, Nk, H, Dv], key_bias [B, Nk] float32 or
    None -> [B, Nq, H, Dv] in q's dtype; `neg_bias` is the bias that removes a key."""
    from jax.experimental.pallas.ops.tpu import flash_attention as pallas_flash

    qf, kf, vf = _operands(q, k, v, key_bias, scale, neg_bias)
    out = pallas_flash.flash_attention(qf, kf, vf, sm_scale=scale)
    return out.transpose(0, 2, 1, 3)[:, :q.shape[1], :, :v.shape[-1]].astype(q.dtype)


def _operands(q, k, v, key_bias, scale, neg_bias):
    """The kernel's operands [B, H, N, Dp]: rows padded to BLOCK (padded keys removed by
    `neg_bias` in the bias), the bias folded in (`fold_key_bias`), the head dimension
    padded to HEAD_MULTIPLE."""
    b, nq = q.shape[:2]
    nk = k.shape[1]
    pq, pk = BLOCK * math.ceil(nq / BLOCK) - nq, BLOCK * math.ceil(nk / BLOCK) - nk
    bias = jnp.zeros((b, nk), jnp.float32) if key_bias is None else key_bias.astype(jnp.float32)
    bias = jnp.pad(bias, ((0, 0), (0, pk)), constant_values=neg_bias)

    def pad_rows(x, n):
        return jnp.pad(x, ((0, 0), (0, n), (0, 0), (0, 0)))

    qf, kf, vf = fold_key_bias(pad_rows(q, pq), pad_rows(k, pk), pad_rows(v, pk), bias, scale, HEAD_MULTIPLE)
    if qf.shape[-1] > MAX_HEAD_DIM:
        raise ValueError(f"the TPU flash kernel takes head dims up to {MAX_HEAD_DIM} (with the bias columns); "
                         f"got {qf.shape[-1]}")
    return tuple(x.transpose(0, 2, 1, 3) for x in (qf, kf, vf))


def tpu_flash_attention_with_lse(q: jax.Array, k: jax.Array, v: jax.Array, key_bias: jax.Array | None, scale: float,
                                 neg_bias: float) -> tuple[jax.Array, jax.Array]:
    """`tpu_flash_attention` and the log-sum-exp of every query's logits: (out
    [B, Nq, H, Dv] in q's dtype, lse [B, Nq, H] float32), what ring attention folds
    partial results with. Differentiable in both outputs (`_flash_with_lse`)."""
    nq = q.shape[1]
    out, lse = _flash_with_lse(*_operands(q, k, v, key_bias, scale, neg_bias), scale)
    return out.transpose(0, 2, 1, 3)[:, :nq, :, :v.shape[-1]].astype(q.dtype), lse.transpose(0, 2, 1)[:, :nq]


def flash_missing() -> str | None:
    """What of the Pallas kernel's entry point `tpu_flash_attention` calls this JAX lacks
    (None: all there); `ops.attention` then takes the blocked kernel, with a warning."""
    return missing_private_api(PALLAS_MODULE, FLASH_CALLS)


def lse_missing() -> str | None:
    """What of the Pallas kernel's private functions `_flash_with_lse` calls this JAX
    lacks (None: all there); `ops.attention` then gives the ring the blocked kernel."""
    return missing_private_api(PALLAS_MODULE, LSE_CALLS, LSE_ATTRS)


def lse_available() -> bool:
    """Whether this JAX has the Pallas kernel's functions `_flash_with_lse` calls, as it
    calls them (`lse_missing`)."""
    return lse_missing() is None


@functools.partial(jax.custom_vjp, nondiff_argnums=(3,))
def _flash_with_lse(q, k, v, scale):
    """The Pallas kernel on [B, H, N, D] operands with its softmax statistics: (out,
    lse [B, H, Nq] float32). The kernel's own entry point returns them only undifferentiated
    (`save_residuals`); its backward kernels take the row term di = rowsum(out * dout)
    as an argument, and an lse cotangent enters exactly there (below)."""
    return _forward(q, k, v, scale)[:2]


def _forward(q, k, v, scale):
    from jax.experimental.pallas.ops.tpu import flash_attention as pallas_flash

    sizes = _block_sizes()
    o, l, m = pallas_flash._flash_attention_impl(  # noqa: SLF001 - the kernel with its statistics
        q, k, v, None, None, True, False, scale, sizes.block_b, sizes.block_q, sizes.block_k_major, sizes.block_k,
        False)
    return o, m + jnp.log(l), l, m


def _flash_with_lse_fwd(q, k, v, scale):
    o, lse, l, m = _forward(q, k, v, scale)
    return (o, lse), (q, k, v, o, l, m)


def _flash_with_lse_bwd(scale, res, cotangents):
    """d lse_i / d s_ij = p_ij, so an lse cotangent g adds p_ij * g_i to the logits'
    cotangent p_ij * (dp_ij - di_i): the kernels' di becomes di - g."""
    from jax.experimental.pallas.ops.tpu import flash_attention as pallas_flash

    q, k, v, o, l, m = res
    do, dlse = cotangents
    sizes = _block_sizes()
    di = jnp.sum(o.astype(jnp.float32) * do.astype(jnp.float32), axis=-1) - dlse.astype(jnp.float32)
    mask = pallas_flash.DEFAULT_MASK_VALUE
    dk, dv = pallas_flash._flash_attention_bwd_dkv(  # noqa: SLF001
        q, k, v, None, None, l, m, do, di, block_q_major=sizes.block_q_major_dkv, block_k_major=sizes.block_k_major_dkv,
        block_k=sizes.block_k_dkv, block_q=sizes.block_q_dkv, sm_scale=scale, causal=False, mask_value=mask,
        debug=False)
    dq, _ = pallas_flash._flash_attention_bwd_dq(  # noqa: SLF001
        q, k, v, None, None, l, m, do, di, block_q_major=sizes.block_q_dq, block_k_major=sizes.block_k_major_dq,
        block_k=sizes.block_k_dq, sm_scale=scale, causal=False, mask_value=mask, debug=False)
    return dq, dk, dv


_flash_with_lse.defvjp(_flash_with_lse_fwd, _flash_with_lse_bwd)


def _block_sizes():
    from jax.experimental.pallas.ops.tpu import flash_attention as pallas_flash

    # the kernel's defaults (every block 128 rows), forward and backward
    return pallas_flash.BlockSizes.get_default(1, 1, BLOCK, BLOCK, BLOCK)
