"""The attention kernel is chosen for the platform a program is compiled for (issue 24):
lowered here, on a CPU host, for an H200 and a TPU v6e without either (the `[plan]`
extra), the programs hold cuDNN's and the Pallas TPU kernel; the CPU program holds
neither. Explicit kernels, their checks, and the TPU kernel's folded bias and padding
against the reference (Pallas' interpreter, on this CPU)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rvggt_jax.ops import attention as attn
from rvggt_jax.ops.kernels import fused, tpu_flash
from tests.helpers.attention_reference import reference_attention
from tests.helpers.deviceless import device, on

CUDNN = "__cudnn$fmha"  # cuDNN's fused attention custom call
TPU_KERNEL = "tpu_custom_call"  # a Mosaic (Pallas TPU) kernel


def _lowered(fn, dev, dtype, nq=40, nk=56, h=2, d=16):
    args = [on(dev, (1, n, h, d), dtype) if dev is not None else jax.ShapeDtypeStruct((1, n, h, d), dtype)
            for n in (nq, nk, nk)]
    bias = (jax.ShapeDtypeStruct((1, nk), jnp.float32) if dev is None else on(dev, (1, nk), jnp.float32))
    return jax.jit(fn).lower(*args, bias).as_text()


def _auto(q, k, v, b):
    return attn.attention(q, k, v, b)


def test_auto_table():
    assert attn.kernel_for("cuda", jnp.bfloat16, 64) == "cudnn"
    assert attn.kernel_for("cuda", jnp.float32, 64) == "blocked"  # cuDNN takes no float32
    assert attn.kernel_for("tpu", jnp.float32, 64) == "tpu_flash"
    assert attn.kernel_for("cpu", jnp.bfloat16, 64) == "blocked"
    assert attn.kernel_for("cuda", jnp.bfloat16, 127) == "blocked"  # + the bias columns: over cuDNN's 128


def test_the_plan_extra_makes_both_accelerators_compilable():
    # CI installs the extra: a missing plugin must fail here, not skip the checks below
    assert set(attn.compilable_platforms()) == {"cuda", "tpu"}


def test_gpu_program_takes_cudnn_for_bfloat16_and_no_cpu_workaround():
    text = _lowered(_auto, device("h200"), jnp.bfloat16)
    assert CUDNN in text and TPU_KERNEL not in text
    assert "ui16" not in text  # the XLA:CPU bit views stay out of the GPU program


def test_gpu_gradient_takes_cudnn_at_odd_token_counts():
    """A train step differentiates attention; JAX's cuDNN wrapper refuses odd sequence
    lengths there (a frame of 224 x 294 has 341 tokens): the gradient is taken at counts
    padded by `fused.even_lengths`. Without it this lowering raises "Unsupported sequence
    length Q 11, KV 13"."""
    dev = device("h200")
    for with_bias in (False, True):
        def loss(q, k, v, b):
            return attn.attention(q, k, v, b if with_bias else None).astype(jnp.float32).sum()

        args = [on(dev, (1, n, 2, 16), jnp.bfloat16) for n in (11, 13, 13)]
        bias = on(dev, (1, 13), jnp.float32)
        text = jax.jit(jax.grad(loss, argnums=(0, 1, 2))).lower(*args, bias).as_text()
        assert CUDNN in text and CUDNN + "SoftmaxBackward" in text, with_bias
        assert "1x12x2x" in text and "1x14x2x" in text  # differentiated at even counts
        # the forward alone keeps its odd counts (no copies): only its cuDNN call
        forward = jax.jit(loss).lower(*args, bias).as_text()
        assert CUDNN in forward and "1x12x2x" not in forward and "1x14x2x" not in forward


@pytest.mark.parametrize("with_bias", [False, True])
def test_even_lengths_leaves_attention_unchanged(with_bias):
    rng = np.random.default_rng(0)
    q, k, v = (rng.standard_normal((2, n, 2, 8)).astype(np.float32) for n in (11, 13, 13))
    bias = rng.standard_normal((2, 13)).astype(np.float32) if with_bias else None
    qp, kp, vp, bp = fused.even_lengths(jnp.asarray(q), jnp.asarray(k), jnp.asarray(v),
                                        None if bias is None else jnp.asarray(bias), attn.NEG_BIAS)
    assert (qp.shape[1], kp.shape[1], vp.shape[1], bp.shape) == (12, 14, 14, (2, 14))
    got = reference_attention(qp, kp, vp, np.asarray(bp)[:, None, None, :])[:, :11]
    want = reference_attention(q, k, v, None if bias is None else bias[:, None, None, :])
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    even = fused.even_lengths(*(jnp.asarray(a[:, :10]) for a in (q, k, v)), None, attn.NEG_BIAS)
    assert [a.shape[1] for a in even[:3]] == [10, 10, 10] and even[3] is None  # even: untouched


@pytest.mark.parametrize("with_bias", [False, True])
def test_odd_lengths_gradient_equals_autodiff(with_bias):
    """The odd-count path's gradient (taken at padded counts) against autodiff of the
    unpadded attention, float32 on this CPU ("xla": the same plumbing as "cudnn")."""
    rng = np.random.default_rng(1)
    q, k, v = (jnp.asarray(rng.standard_normal((2, n, 2, 8)), jnp.float32) for n in (11, 13, 13))
    bias = jnp.asarray(rng.standard_normal((2, 13)), jnp.float32) if with_bias else None
    w = jnp.asarray(rng.standard_normal((2, 11, 2, 8)), jnp.float32)
    scale = 8 ** -0.5

    def loss(fn):
        return lambda q, k, v, b: (fn(q, k, v, b) * w).sum()

    odd = loss(lambda q, k, v, b: fused.odd_lengths(q, k, v, b, scale, attn.NEG_BIAS, "xla"))
    plain = loss(lambda q, k, v, b: fused.fused_attention(q, k, v, b, scale, "xla", attn.NEG_BIAS))
    argnums = (0, 1, 2, 3) if with_bias else (0, 1, 2)
    got = jax.grad(odd, argnums=argnums)(q, k, v, bias)
    want = jax.grad(plain, argnums=argnums)(q, k, v, bias)
    for a, b in zip(got, want):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(odd(q, k, v, bias), plain(q, k, v, bias), rtol=1e-6)


def test_gpu_program_in_float32_takes_the_bounded_blocked_kernel():
    text = _lowered(_auto, device("h200"), jnp.float32)
    assert CUDNN not in text and TPU_KERNEL not in text


def test_tpu_program_takes_the_pallas_kernel():
    for dtype in (jnp.float32, jnp.bfloat16):
        text = _lowered(_auto, device("tpu-v6e"), dtype)
        assert TPU_KERNEL in text and CUDNN not in text and "ui16" not in text


def test_cpu_program_keeps_the_blocked_kernel_and_its_bit_views():
    # small logits blocks: the kernel's loop, whose 16-bit operands it reads as bits
    text = _lowered(lambda q, k, v, b: attn.attention(q, k, v, b, block_bytes=4096), None, jnp.bfloat16)
    assert CUDNN not in text and TPU_KERNEL not in text
    assert "ui16" in text


def test_an_argument_overrides_auto():
    assert CUDNN not in _lowered(lambda q, k, v, b: attn.attention(q, k, v, b, implementation="blocked"),
                                 device("h200"), jnp.bfloat16)
    assert CUDNN in _lowered(lambda q, k, v, b: attn.attention(q, k, v, b, implementation="cudnn"),
                             device("h200"), jnp.bfloat16)


def test_bad_kernels_are_named():
    q = jnp.zeros((1, 4, 1, 8), jnp.float32)
    with pytest.raises(ValueError, match="bfloat16/float16 only.*'auto'"):
        attn.attention(q, q, q, implementation="cudnn")
    with pytest.raises(ValueError, match="tpu_flash"):
        attn.attention(q, q, q, implementation="flash")


def test_the_kernel_is_data_not_a_scope():
    # no context variable: the name travels in the block's config (and VGGTConfig.attention)
    assert not hasattr(attn, "kernel_scope") and not hasattr(attn, "current_kernel")
    from rvggt_jax.model.layers import BlockConfig

    assert BlockConfig(2).kernel == "auto"
    q = jnp.asarray(np.random.default_rng(0).standard_normal((1, 5, 1, 8)), jnp.float32)
    np.testing.assert_allclose(attn.attention(q, q, q), reference_attention(q, q, q), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("dtype, tol", [(jnp.float32, 2e-6), (jnp.bfloat16, 2e-2)])
@pytest.mark.parametrize("with_bias", [False, True])
def test_tpu_kernel_folds_the_bias_and_pads(monkeypatch, dtype, tol, with_bias):
    # Pallas' interpreter runs the TPU kernel on this CPU: odd lengths (padded to 128
    # rows, padded keys removed by the bias column), a size bias with empty slots
    from jax.experimental import pallas as pl

    call = pl.pallas_call
    monkeypatch.setattr(pl, "pallas_call", lambda *a, **k: call(*a, **{**k, "interpret": True}))
    rng = np.random.default_rng(1)
    q, k, v = (rng.standard_normal((2, n, 2, 16)).astype(np.float32) for n in (50, 130, 130))
    sizes = np.floor(4 * rng.random((2, 130)))
    bias = attn.log_sizes(jnp.asarray(sizes), jnp.asarray(sizes > 0)) if with_bias else None
    out = tpu_flash.tpu_flash_attention(*(jnp.asarray(x, dtype) for x in (q, k, v)), bias, 0.25, attn.NEG_BIAS)
    assert out.shape == (2, 50, 2, 16) and out.dtype == dtype
    cast = [np.asarray(jnp.asarray(x, dtype).astype(jnp.float32)) for x in (q, k, v)]
    ref = reference_attention(*cast, None if bias is None else np.asarray(bias)[:, None, None, :])  # 1/sqrt(16) = 0.25
    np.testing.assert_allclose(np.asarray(out.astype(jnp.float32)), ref, rtol=tol, atol=tol)


def _forward_text(tiny, dev, dtype, kernel="auto"):
    from rvggt_jax.model.forward import rvggt_forward
    from rvggt_jax.planning.memory import abstract_params

    _, config = tiny
    cfg = config.with_compression("regime").with_dtype(dtype).with_attention(kernel)
    params = jax.tree.map(lambda a: on(dev, a.shape, a.dtype), abstract_params(cfg, param_dtype=dtype))
    images = on(dev, (1, 3, 3, 28, 42), jnp.float32)
    return jax.jit(rvggt_forward, static_argnums=2).lower(params, images, cfg).as_text()


def test_whole_forward_for_each_target(tiny):
    # regime: the frame, global, merged (size bias) and K/V-downsampled layers, DINO and
    # the camera trunk all take the target's kernel
    gpu = _forward_text(tiny, device("h200"), "bfloat16")
    assert gpu.count(CUDNN) >= 4 and TPU_KERNEL not in gpu
    tpu = _forward_text(tiny, device("tpu-v6e"), "float32")
    assert tpu.count(TPU_KERNEL) >= 3 and CUDNN not in tpu
    assert CUDNN not in _forward_text(tiny, device("h200"), "bfloat16", "blocked")
    # a 16-bit-only kernel runs the aggregator's attention (DINO, frame, global, merged,
    # K/V layers); the float32 heads take "auto" (they would refuse cuDNN)
    assert _forward_text(tiny, device("h200"), "bfloat16", "cudnn").count(CUDNN) >= 4


@pytest.mark.parametrize("kernel, dtype, message", [
    ("cudnn", "float32", "bfloat16 only"), ("flash", "bfloat16", "must be one of"),
])
def test_config_names_a_kernel_the_target_cannot_run(tiny, kernel, dtype, message):
    _, config = tiny
    with pytest.raises(ValueError, match=message):
        config.with_dtype(dtype).with_attention(kernel)
