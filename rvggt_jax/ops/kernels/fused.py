"""Fused attention kernels (`jax.nn.dot_product_attention`: cuDNN's flash kernel, or its
plain XLA form), which take no per-key bias: the bias is folded into the operands.

    softmax(q k^T * scale + bias) v = softmax(q' k'^T * scale) v'[..., :Dv]
    q' = [q, 1.., 0..], k' = [k, bias / scale, 0..], v' = [v, 0..]

(two bias columns hi + lo in 16-bit dtypes); the head dimension is zero-padded to a
multiple of 8 for cuDNN (D = 64 + the bias column would be 65).
"""

from __future__ import annotations

import functools
import importlib
import inspect
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

# cuDNN's fused attention needs a head dimension that is a multiple of 8, at most 128.
CUDNN_HEAD_MULTIPLE = 8
CUDNN_MAX_HEAD_DIM = 128


def bias_columns(key_bias: jax.Array, dtype: Any) -> jax.Array:
    """A float32 key bias [B, Nk] as K columns [B, Nk, c] in `dtype`: one column in
    float32; in a 16-bit dtype a pair (hi, lo) whose sum is the bias to ~2^-16 relative.
    One bfloat16 column keeps 8 significant bits: the folded log g / scale of a group of
    100 (~37 at D = 64) would be rounded by up to 0.125, 0.016 in the logit, up to 1.6%
    of the group's weight."""
    dtype = jnp.dtype(dtype)
    if not (dtype.itemsize == 2 and jnp.issubdtype(dtype, jnp.floating)):
        return key_bias.astype(dtype)[..., None]
    hi = key_bias.astype(dtype)
    lo = (key_bias - hi.astype(jnp.float32)).astype(dtype)
    return jnp.stack([hi, lo], axis=-1)


def fold_key_bias(q: jax.Array, k: jax.Array, v: jax.Array, key_bias: jax.Array | None, scale: float,
                  multiple: int) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Fold an additive per-key bias into the operands and pad the head dimension:

        softmax(q k^T * scale + bias) v = softmax(q' k'^T * scale) v'[..., :Dv]
        q' = [q, 1.., 0..], k' = [k, bias / scale, 0..], v' = [v, 0..]

    (`bias_columns`: one bias column, or a hi/lo pair in 16-bit dtypes). q [B, Nq, H, D],
    k/v [B, Nk, H, D], key_bias [B, Nk] or None; every result has the head dimension
    (D + the bias columns, or Dv if larger) rounded up to a multiple of `multiple`."""
    if key_bias is not None:
        b, nk, h, _ = k.shape
        cols = bias_columns(key_bias.astype(jnp.float32) / np.float32(scale), k.dtype)  # [B, Nk, c]
        q = jnp.concatenate([q, jnp.ones(q.shape[:-1] + cols.shape[-1:], q.dtype)], axis=-1)
        k = jnp.concatenate([k, jnp.broadcast_to(cols[:, :, None, :], (b, nk, h, cols.shape[-1]))], axis=-1)
    dp = int(math.ceil(max(q.shape[-1], v.shape[-1]) / multiple) * multiple)

    def pad(x):
        return jnp.pad(x, ((0, 0), (0, 0), (0, 0), (0, dp - x.shape[-1])))

    return pad(q), pad(k), pad(v)


def even_lengths(q: jax.Array, k: jax.Array, v: jax.Array, key_bias: jax.Array | None, neg_bias: float
                 ) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array | None]:
    """Odd token counts made even for cuDNN's differentiated kernel: one zero query row
    more (the caller slices its output off) and one zero key/value more that `neg_bias`
    in the key bias removes (exp of it is exactly 0). The attention is unchanged. Shapes
    depend on shapes only."""
    nq, nk = q.shape[1], k.shape[1]
    if nq % 2:
        q = jnp.pad(q, ((0, 0), (0, 1), (0, 0), (0, 0)))
    if nk % 2:
        k = jnp.pad(k, ((0, 0), (0, 1), (0, 0), (0, 0)))
        v = jnp.pad(v, ((0, 0), (0, 1), (0, 0), (0, 0)))
        bias = jnp.zeros((k.shape[0], nk), jnp.float32) if key_bias is None else key_bias.astype(jnp.float32)
        key_bias = jnp.pad(bias, ((0, 0), (0, 1)), constant_values=neg_bias)
    return q, k, v, key_bias


def fused_attention(q: jax.Array, k: jax.Array, v: jax.Array, key_bias: jax.Array | None, scale: float,
                    implementation: str, neg_bias: float) -> jax.Array:
    """`jax.nn.dot_product_attention` with the key bias [B, Nk] (float32, or None) folded
    in: implementation "cudnn" (flash, head dims padded to CUDNN_HEAD_MULTIPLE) or "xla"
    (forms all logits). q [B, Nq, H, D], k [B, Nk, H, D], v [B, Nk, H, Dv] ->
    [B, Nq, H, Dv] in q's dtype.

    Odd token counts under cuDNN are differentiated through `even_lengths` (the extra
    key removed by `neg_bias`): JAX 0.10's cuDNN wrapper refuses odd sequence lengths when
    differentiating ("Unsupported sequence length Q 341, KV 341": a rule meant for calls
    with a bias, applied to every call because an absent bias is passed on as an empty
    array; docs/accelerators.md). A frame of 224 x 294 has 16 x 21 + 5 = 341 tokens. The
    forward alone keeps the odd counts (no copies: it is not refused)."""
    if implementation == "cudnn" and (q.shape[1] % 2 or k.shape[1] % 2):
        return odd_lengths(q, k, v, key_bias, scale, neg_bias, implementation)
    return _fused(q, k, v, key_bias, scale, implementation)


def _fused(q, k, v, key_bias, scale, implementation):
    dv = v.shape[-1]
    multiple = CUDNN_HEAD_MULTIPLE if implementation == "cudnn" else 1
    qf, kf, vf = fold_key_bias(q, k, v, key_bias, scale, multiple)
    if implementation == "cudnn" and qf.shape[-1] > CUDNN_MAX_HEAD_DIM:
        raise ValueError(f"cuDNN attention takes head dims up to {CUDNN_MAX_HEAD_DIM}; got {qf.shape[-1]}")
    out = jax.nn.dot_product_attention(qf, kf, vf, scale=scale, implementation=implementation)
    return out[..., :dv].astype(q.dtype)


@functools.partial(jax.custom_vjp, nondiff_argnums=(4, 5, 6))
def odd_lengths(q, k, v, key_bias, scale, neg_bias, implementation):
    """The fused attention at odd token counts: as they are in the forward; differentiated
    (a gradient's forward pass and its backward) at even counts (`even_lengths`). The
    model takes it for "cudnn"; "xla" checks it on a CPU."""
    return _fused(q, k, v, key_bias, scale, implementation)


def _even(q, k, v, key_bias, scale, neg_bias, implementation):
    q2, k2, v2, b2 = even_lengths(q, k, v, key_bias, neg_bias)
    return _fused(q2, k2, v2, b2, scale, implementation)[:, : q.shape[1]]


def _odd_lengths_fwd(q, k, v, key_bias, scale, neg_bias, implementation):
    # (jax.vjp's function is a pytree of the residuals)
    return jax.vjp(lambda *a: _even(*a, scale, neg_bias, implementation), q, k, v, key_bias)


def _odd_lengths_bwd(scale, neg_bias, implementation, vjp, g):
    return vjp(g)


odd_lengths.defvjp(_odd_lengths_fwd, _odd_lengths_bwd)


# ---------------------------------------------------------------------------------------
# With the log-sum-exp (ring attention's partial results). `jax.nn.dot_product_attention`
# returns no softmax statistics; JAX's cuDNN module does (`return_residual`), but its
# backward drops the statistics' cotangent, which ring attention's fold needs. So the
# forward and backward rules of that module are called here, under a VJP of our own.
# ---------------------------------------------------------------------------------------

def fused_attention_with_lse(q: jax.Array, k: jax.Array, v: jax.Array, key_bias: jax.Array | None, scale: float,
                             implementation: str, neg_bias: float) -> tuple[jax.Array, jax.Array]:
    """(attention [B, Nq, H, Dv] in q's dtype, the log-sum-exp of every query's logits
    [B, Nq, H] float32) with the key bias [B, Nk] folded in, differentiable in both.
    implementation "cudnn" (cuDNN's flash kernel and its statistics) or "xla" (the same
    interface in plain XLA, forming all logits: it checks the VJP below on a CPU).

    Token counts are made even (`even_lengths`: cuDNN's wrapper refuses odd ones when its
    statistics are returned), and the head dimension has a spare zero column in v (the
    VJP writes the lse cotangent there)."""
    nq, dv = q.shape[1], v.shape[-1]
    q, k, v, key_bias = even_lengths(q, k, v, key_bias, neg_bias)
    multiple = CUDNN_HEAD_MULTIPLE if implementation == "cudnn" else 1
    qf, kf, vf = fold_key_bias(q, k, v, key_bias, scale, multiple)
    if vf.shape[-1] == dv:  # no spare column: one more block of zero columns
        qf, kf, vf = (jnp.pad(x, ((0, 0), (0, 0), (0, 0), (0, multiple))) for x in (qf, kf, vf))
    if implementation == "cudnn" and qf.shape[-1] > CUDNN_MAX_HEAD_DIM:
        raise ValueError(f"cuDNN attention with its log-sum-exp takes head dims up to {CUDNN_MAX_HEAD_DIM} "
                         f"(with the bias columns and a spare one); got {qf.shape[-1]}")
    out, lse = _with_lse(qf, kf, vf, scale, dv, implementation)
    return out[:, :nq, :, :dv].astype(q.dtype), lse[:, :nq]


@functools.partial(jax.custom_vjp, nondiff_argnums=(3, 4, 5))
def _with_lse(q, k, v, scale, dv, implementation):
    """[B, N, H, Dp] operands (v's column `dv` zero) -> (out [B, Nq, H, Dp], lse
    [B, Nq, H] float32)."""
    return _with_lse_fwd(q, k, v, scale, dv, implementation)[0]


def _with_lse_fwd(q, k, v, scale, dv, implementation):
    out, stats = _LSE_KERNELS[implementation][0](q, k, v, scale)
    return (out, stats.transpose(0, 2, 1)), (q, k, v, out, stats)


def _with_lse_bwd(scale, dv, implementation, res, cotangents):
    """The kernel's backward forms the logits' cotangent p_ij (dout_i . v_j - di_i) with
    di_i = out_i . dout_i from the output it is given. An lse cotangent g adds p_ij g_i
    (d lse_i / d s_ij = p_ij). v's column `dv` is zero, so a value there in dout changes
    no dout_i . v_j; with g there in dout and -1 there in out, di_i becomes di_i - g_i.
    (With 16-bit operands g is held in dout's dtype, as dout itself is.)"""
    q, k, v, out, stats = res
    dout, dlse = cotangents
    dout = dout.at[..., dv].set(dlse.astype(dout.dtype))
    out = out.at[..., dv].set(-1)
    dq, dk, dvv = _LSE_KERNELS[implementation][1](q, k, v, out, stats, dout, scale)
    return dq, dk, dvv


_with_lse.defvjp(_with_lse_fwd, _with_lse_bwd)


# What `_cudnn_forward` and `_cudnn_backward` take from JAX's private cuDNN module, and
# how they call it: (function, positional arguments, keyword names), checked by binding the
# call to the function's signature (`missing_private_api`). Written against JAX 0.10.2;
# the same in 0.11 (docs/accelerators.md).
CUDNN_MODULE = "jax._src.cudnn.fused_attention_stablehlo"
CUDNN_LSE_CALLS = (
    ("_dot_product_attention_fwd_rule", 10, ("scale", "seed", "dropout_rate", "variadic_args", "mask_type", "layout",
                                             "sliding_window_length", "cudnn_version", "return_residual")),
    ("_dot_product_attention_bwd_rule", 11, ()),
    ("check_cudnn_version", 0, ()),
)
CUDNN_LSE_ATTRS = ("MaskType.NO_MASK", "AttentionLayout.BTNH")
_ABSENT = object()


def missing_private_api(module: str, calls: tuple[tuple[str, int, tuple[str, ...]], ...] = (),
                        attrs: tuple[str, ...] = ()) -> str | None:
    """What this code needs of a JAX-private `module` and does not find, in words, or None
    when all of it is there: the module itself, each dotted attribute of `attrs`, each
    function of `calls` (dotted name, number of positional arguments, keyword names) and
    whether its signature takes that call. A function whose signature cannot be read
    counts as taking it (nothing better is known)."""
    try:
        mod = importlib.import_module(module)
    except Exception as e:  # noqa: BLE001 - ImportError, or whatever the module raises on import
        return f"{module} does not import ({type(e).__name__}: {e})"

    def resolve(dotted):
        obj = mod
        for part in dotted.split("."):
            obj = getattr(obj, part, _ABSENT)
            if obj is _ABSENT:
                return _ABSENT
        return obj

    for dotted in attrs + tuple(c[0] for c in calls):
        if resolve(dotted) is _ABSENT:
            return f"{module} has no {dotted}"
    for name, positional, keywords in calls:
        try:
            sig = inspect.signature(resolve(name))
        except (TypeError, ValueError):
            continue
        try:
            sig.bind(*range(positional), **dict.fromkeys(keywords))
        except TypeError as e:
            taken = f"{positional} positional argument(s)" + (f" and {', '.join(keywords)}" if keywords else "")
            return f"{module}.{name}{sig} does not take {taken} ({e})"
    return None


def cudnn_lse_missing() -> str | None:
    """What of JAX's private cuDNN rules `fused_attention_with_lse` calls this JAX lacks
    (None: all there). `ops.attention` then gives the ring the blocked kernel, with a
    warning that says this."""
    return missing_private_api(CUDNN_MODULE, CUDNN_LSE_CALLS, CUDNN_LSE_ATTRS)


def cudnn_lse_available() -> bool:
    """Whether this JAX has the cuDNN rules `fused_attention_with_lse` calls, as it calls
    them (private to JAX: `cudnn_lse_missing`)."""
    return cudnn_lse_missing() is None


def _cudnn_rules():
    return importlib.import_module(CUDNN_MODULE)


def _cudnn_args(q, scale):
    cudnn = _cudnn_rules()
    empty = jnp.zeros(0, q.dtype)
    statics = dict(scale=scale, seed=42, dropout_rate=0.0, variadic_args=(False, False),
                   mask_type=cudnn.MaskType.NO_MASK, layout=cudnn.AttentionLayout.BTNH.value,
                   sliding_window_length=None)
    return cudnn, (empty,) * 7, statics  # bias, q/kv seqlens, q/kv offsets, page tables


def _cudnn_forward(q, k, v, scale):
    """cuDNN's flash forward in training mode: (out [B, N, H, D], stats [B, H, N] float32,
    the log-sum-exp of the scaled logits)."""
    cudnn, empties, statics = _cudnn_args(q, scale)
    (out, stats), _ = cudnn._dot_product_attention_fwd_rule(  # noqa: SLF001
        q, k, v, *empties, **statics, cudnn_version=cudnn.check_cudnn_version(), return_residual=True)
    return out, stats


def _cudnn_backward(q, k, v, out, stats, dout, scale):
    cudnn, empties, statics = _cudnn_args(q, scale)
    res = (q, k, v, *empties, stats, out)
    grads = cudnn._dot_product_attention_bwd_rule(  # noqa: SLF001
        *statics.values(), cudnn.check_cudnn_version(), False, res, dout)
    return grads[:3]


def _xla_forward(q, k, v, scale):
    s = jnp.einsum("bqhd,bkhd->bhqk", q.astype(jnp.float32), k.astype(jnp.float32)) * np.float32(scale)
    stats = jax.nn.logsumexp(s, axis=-1)
    out = jnp.einsum("bhqk,bkhd->bqhd", jnp.exp(s - stats[..., None]), v.astype(jnp.float32))
    return out.astype(q.dtype), stats


def _xla_backward(q, k, v, out, stats, dout, scale):
    """A flash-attention backward from (out, stats, dout), as cuDNN's computes it."""
    f32 = [x.astype(jnp.float32) for x in (q, k, v, out, dout)]
    q32, k32, v32, o32, do32 = f32
    s = jnp.einsum("bqhd,bkhd->bhqk", q32, k32) * np.float32(scale)
    p = jnp.exp(s - stats[..., None])
    di = jnp.einsum("bqhd,bqhd->bhq", o32, do32)
    ds = p * (jnp.einsum("bqhd,bkhd->bhqk", do32, v32) - di[..., None]) * np.float32(scale)
    dq = jnp.einsum("bhqk,bkhd->bqhd", ds, k32)
    dk = jnp.einsum("bhqk,bqhd->bkhd", ds, q32)
    dv = jnp.einsum("bhqk,bqhd->bkhd", p, do32)
    return dq.astype(q.dtype), dk.astype(k.dtype), dv.astype(v.dtype)


_LSE_KERNELS = {"cudnn": (_cudnn_forward, _cudnn_backward), "xla": (_xla_forward, _xla_backward)}
