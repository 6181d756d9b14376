"""The attention op's backward (issue 25, item 1): the blocked kernel's custom VJP (flash
attention's backward, O(N d) memory) against autodiff of a plain float32 reference
attention, at 1e-5: dense, `attention_with_lse` with its log-sum-exp output
differentiated, removed keys, bfloat16; XLA's plan of the gradient growing linearly with
N; the GPU and TPU gradient programs taking cuDNN's and the Pallas kernel's own
backwards. The ring's backward on host devices: tests/parallel/test_sharded.py (it needs
4 devices); a K/V-downsampled and a merged (size-bias) global block:
tests/compression/test_block_grad.py."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rvggt_jax.ops import attention as attn
from rvggt_jax.ops.kernels import blocked
from tests.helpers.attention_reference import differentiable_reference as reference, rel
from tests.helpers.deviceless import device, on

TOL = 1e-5


def _operands(b=2, nq=37, nk=45, h=3, d=8, dv=5, seed=0):
    """Odd sizes (padded query blocks), Dv != D, a log-group-size bias with removed keys."""
    rng = np.random.default_rng(seed)
    q, k, v = (jnp.asarray(rng.standard_normal(s), jnp.float32) for s in ((b, nq, h, d), (b, nk, h, d), (b, nk, h, dv)))
    sizes = np.floor(1 + 6 * rng.random((b, nk)))
    valid = rng.random((b, nk)) > 0.2
    bias = attn.log_sizes(jnp.asarray(sizes), jnp.asarray(valid))
    w = jnp.asarray(rng.standard_normal((b, nq, h, dv)), jnp.float32)  # a loss direction
    return q, k, v, bias, w


@pytest.mark.parametrize("block_bytes, with_bias", [(None, False), (4096, True), (1, True)])
def test_blocked_gradient_equals_reference_autodiff(block_bytes, with_bias):
    q, k, v, bias, w = _operands()
    bias = bias if with_bias else None
    argnums = (0, 1, 2, 3) if with_bias else (0, 1, 2)

    def ours(q, k, v, b):
        return jnp.sum(attn.attention(q, k, v, b, implementation="blocked", block_bytes=block_bytes) * w)

    got = jax.jit(jax.grad(ours, argnums))(q, k, v, bias)
    want = jax.jit(jax.grad(lambda q, k, v, b: jnp.sum(reference(q, k, v, b)[0] * w), argnums))(q, k, v, bias)
    for name, g, r in zip("qkvb", got, want):
        assert g.shape == r.shape and g.dtype == jnp.float32
        assert rel(g, r) <= TOL, (name, rel(g, r))
    if with_bias:  # removed keys: no gradient to their bias, nor to their K and V
        removed = np.asarray(bias) == attn.NEG_BIAS
        assert removed.any() and not np.any(np.asarray(got[3])[removed])
        assert not np.any(np.asarray(got[2])[removed])


@pytest.mark.parametrize("block_bytes", [None, 4096])
def test_attention_with_lse_passes_both_cotangents(block_bytes):
    # the ring's combine differentiates through the log-sum-exp: its cotangent enters dS
    q, k, v, bias, w = _operands(seed=1)
    wl = jnp.asarray(np.random.default_rng(2).standard_normal(q.shape[:3]), jnp.float32)

    def loss(fn):
        def f(q, k, v, b):
            out, lse = fn(q, k, v, b)
            return jnp.sum(out * w) + jnp.sum(jnp.sin(lse) * wl)
        return f

    ours = loss(lambda q, k, v, b: attn.attention_with_lse(q, k, v, b, 0.3, block_bytes, jnp.float32))
    got = jax.jit(jax.grad(ours, (0, 1, 2, 3)))(q, k, v, bias)
    want = jax.jit(jax.grad(loss(lambda q, k, v, b: reference(q, k, v, b, 0.3)), (0, 1, 2, 3)))(q, k, v, bias)
    for name, g, r in zip("qkvb", got, want):
        assert rel(g, r) <= TOL, (name, rel(g, r))
    # the lse term matters: without it the q gradient would differ
    only_out = jax.jit(jax.grad(loss(lambda q, k, v, b: (reference(q, k, v, b, 0.3)[0], jnp.zeros(q.shape[:3])))))(
        q, k, v, bias)
    assert rel(only_out, want[0]) > 1e-2


def test_forward_values_unchanged_by_the_custom_vjp():
    # the primal of the custom VJP is the kernel's forward as it was: bitwise
    q, k, v, bias, _ = _operands(seed=3)
    for bb in (blocked.LOGITS_BLOCK_BYTES, 4096):
        new = jax.jit(lambda *a: blocked.blocked_attention(*a, 0.25, bb, bits=False))(q, k, v, bias)
        old = jax.jit(lambda *a: blocked._forward(*a, 0.25, bb, None, False))(q, k, v, bias)
        for a, b in zip(new, old):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_bfloat16_gradients_in_the_operands_dtype():
    q, k, v, bias, w = _operands(nq=64, nk=80, d=16, dv=16, seed=4)
    qb, kb, vb = (t.astype(jnp.bfloat16) for t in (q, k, v))

    def ours(q, k, v, b):
        return jnp.sum(attn.attention(q, k, v, b, implementation="blocked", block_bytes=2048).astype(jnp.float32) * w)

    got = jax.jit(jax.grad(ours, (0, 1, 2, 3)))(qb, kb, vb, bias)
    assert [g.dtype for g in got] == [jnp.bfloat16] * 3 + [jnp.float32]
    cast = [t.astype(jnp.float32) for t in (qb, kb, vb)]
    want = jax.jit(jax.grad(lambda q, k, v, b: jnp.sum(reference(q, k, v, b)[0] * w), (0, 1, 2, 3)))(*cast, bias)
    for name, g, r in zip("qkvb", got, want):  # bf16 weights, dS and results: ~1e-2
        assert rel(g, r) <= 3e-2, (name, rel(g, r))


# ---- memory: XLA's plan of the gradient -------------------------------------------------

def _grad_temp_bytes(n: int, fn) -> int:
    """XLA:CPU's temporaries of jit(grad(fn)) over q, k, v [1, n, 1, 64] and a bias [1, n]
    (compiled, not run)."""
    args = [jax.ShapeDtypeStruct((1, n, 1, 64), jnp.float32)] * 3 + [jax.ShapeDtypeStruct((1, n), jnp.float32)]
    c = jax.jit(jax.grad(lambda *a: jnp.sum(fn(*a)), (0, 1, 2, 3))).lower(*args).compile()
    return c.memory_analysis().temp_size_in_bytes


def test_gradient_memory_grows_linearly_with_tokens():
    # 256 KiB logits blocks, so that the O(N d) terms show (at the default 24 MiB block the
    # plan is flat: ~48 MiB at 2048 tokens, ~59 MiB at 8192)
    bb = 2**18

    def ours(q, k, v, b):
        return attn.attention(q, k, v, b, implementation="blocked", block_bytes=bb)

    small, large = _grad_temp_bytes(2048, ours), _grad_temp_bytes(8192, ours)
    assert large / small <= 4.5, (small, large)  # linear (+ a constant), not quadratic (16)
    assert large <= 8192 * 64 * 4 * 8 + 8 * bb  # a few [N, d] arrays and blocks: ~10.6 MiB
    # autodiff of the forward loop (what the custom VJP replaces) keeps every block's weights
    before = _grad_temp_bytes(2048, lambda q, k, v, b: blocked._forward(q, k, v, b, 0.125, bb)[0])
    assert before > 8 * small


# ---- GPU and TPU: their kernels' own backwards ------------------------------------------

def _grad_text(dev, dtype):
    args = [on(dev, (1, n, 2, 16), dtype) for n in (40, 56, 56)] + [on(dev, (1, 56), jnp.float32)]

    def loss(q, k, v, b):
        return jnp.sum(attn.attention(q, k, v, b).astype(jnp.float32))

    return jax.jit(jax.grad(loss, (0, 1, 2, 3))).lower(*args).as_text()


def test_gpu_gradient_takes_cudnn_backward():
    text = _grad_text(device("h200"), jnp.bfloat16)
    assert "__cudnn$fmhaSoftmaxBackward" in text
    assert "stablehlo.while" not in text  # no blocked loop (nor its logits) in the program


def test_tpu_gradient_takes_the_pallas_backward():
    text = _grad_text(device("tpu-v6e"), jnp.float32)
    assert text.count("tpu_custom_call") >= 3  # forward, dK/dV and dQ kernels
    assert "stablehlo.while" not in text


# ---- the log-sum-exp forms of the accelerator kernels (ring attention's shares) ---------

def _lse_loss(fn, w, wl):
    def f(q, k, v, b):
        out, lse = fn(q, k, v, b)
        return jnp.sum(out.astype(jnp.float32) * w) + jnp.sum(jnp.sin(lse) * wl)
    return f


@pytest.mark.parametrize("kernel", ["xla", "tpu_flash"])
def test_accelerator_kernels_with_lse_pass_both_cotangents(monkeypatch, kernel):
    # "xla": cuDNN's interface (forward with its statistics; a backward from the output it
    # is given) in plain XLA, so the VJP that feeds the lse cotangent through a spare v
    # column is checked here; "tpu_flash": the Pallas kernels in Pallas' interpreter
    if kernel == "tpu_flash":
        from jax.experimental import pallas as pl

        call = pl.pallas_call
        monkeypatch.setattr(pl, "pallas_call", lambda *a, **k: call(*a, **{**k, "interpret": True}))
    q, k, v, bias, w = _operands(b=1, nq=37, nk=45, h=2, d=8, dv=8, seed=5)
    wl = jnp.asarray(np.random.default_rng(6).standard_normal(q.shape[:3]), jnp.float32)
    ours = _lse_loss(lambda q, k, v, b: attn.attention_with_lse(q, k, v, b, 0.3, out_dtype=jnp.float32,
                                                                implementation=kernel), w, wl)
    out, lse = jax.jit(lambda *a: attn.attention_with_lse(*a, 0.3, implementation=kernel))(q, k, v, bias)
    ref_out, ref_lse = reference(q, k, v, bias, 0.3)
    assert out.shape == q.shape[:3] + (8,) and lse.shape == q.shape[:3] and lse.dtype == jnp.float32
    assert rel(out, ref_out) <= TOL and rel(lse, ref_lse) <= TOL
    got = jax.jit(jax.grad(ours, (0, 1, 2, 3)))(q, k, v, bias)
    want = jax.jit(jax.grad(_lse_loss(lambda q, k, v, b: reference(q, k, v, b, 0.3), w, wl), (0, 1, 2, 3)))(
        q, k, v, bias)
    for name, g, r in zip("qkvb", got, want):
        assert g.shape == r.shape and rel(g, r) <= TOL, (name, rel(g, r))


def _lse_grad_text(dev, dtype):
    args = [on(dev, (1, n, 2, 64), dtype) for n in (40, 57, 57)] + [on(dev, (1, 57), jnp.float32)]

    def loss(q, k, v, b):
        out, lse = attn.attention_with_lse(q, k, v, b, 0.125, out_dtype=jnp.float32)
        return jnp.sum(out) + jnp.sum(lse)

    return jax.jit(jax.grad(loss, (0, 1, 2, 3))).lower(*args).as_text()


def test_ring_shares_take_the_accelerator_kernels_with_their_backwards():
    gpu = _lse_grad_text(device("h200"), jnp.bfloat16)
    backward = gpu.count("__cudnn$fmhaSoftmaxBackward")
    assert backward >= 1 and gpu.count("__cudnn$fmhaSoftmax") > backward  # and the forward
    assert "stablehlo.while" not in gpu
    tpu = _lse_grad_text(device("tpu-v6e"), jnp.float32)
    assert tpu.count("tpu_custom_call") >= 3 and "stablehlo.while" not in tpu


def _ring_grad_text(target, dtype):
    """The gradient of ring attention over 2 devices of `target` that are not here
    (lowered, not compiled): queries and key shares split over a "frames" mesh, 5
    replicated extra keys."""
    from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

    from rvggt_jax.ops.ring import ring_attention
    from rvggt_jax.ops.shards import FrameShards
    from rvggt_jax.planning.targets import target_devices

    mesh = Mesh(np.array(target_devices(target, 2)), ("frames",))
    shards = FrameShards(2, 2, "frames")
    row, rep = NamedSharding(mesh, P(None, "frames")), NamedSharding(mesh, P())
    args = ([jax.ShapeDtypeStruct((1, 2 * 48, 2, 64), dtype, sharding=row)] * 3
            + [jax.ShapeDtypeStruct((1, 2 * 48), jnp.float32, sharding=row)]
            + [jax.ShapeDtypeStruct((1, 5, 2, 64), dtype, sharding=rep)] * 2
            + [jax.ShapeDtypeStruct((1, 5), jnp.float32, sharding=rep)])

    def loss(q, k, v, b, ek, ev, eb):
        fn = jax.shard_map(lambda *a: ring_attention(*a[:4], shards, (a[4:],)), mesh=mesh,
                           in_specs=(P(None, "frames"),) * 4 + (P(),) * 3, out_specs=P(None, "frames"),
                           check_vma=False)
        return jnp.sum(fn(q, k, v, b, ek, ev, eb).astype(jnp.float32))

    return jax.jit(jax.grad(loss, range(7))).lower(*args).as_text()


def test_the_ring_on_accelerators_takes_their_kernels_for_every_share():
    # the own share, the share passed in the ring's loop, the extra keys: three forward
    # calls and three backward calls of the kernel
    gpu = _ring_grad_text("h200", jnp.bfloat16)
    assert gpu.count("__cudnn$fmhaSoftmaxBackward") >= 3
    assert gpu.count("__cudnn$fmhaSoftmax") - gpu.count("__cudnn$fmhaSoftmaxBackward") >= 3
    tpu = _ring_grad_text("tpu-v6e", jnp.float32)
    assert tpu.count("tpu_custom_call") >= 9  # forward, dK/dV and dQ per share


def test_a_jax_without_the_private_kernels_takes_the_blocked_one(monkeypatch):
    # the log-sum-exp forms call JAX-private functions; where they are missing the ring
    # says so and runs the blocked kernel (same values)
    monkeypatch.setattr(attn, "_lse_available", lambda name: False)
    q, k, v, bias, _ = _operands(seed=7)
    with pytest.warns(RuntimeWarning, match="blocked kernel"):
        out, lse = attn.attention_with_lse(q, k, v, bias, 0.3, implementation="xla")
    ref, ref_lse = attn.attention_with_lse(q, k, v, bias, 0.3, implementation="blocked")
    np.testing.assert_array_equal(np.asarray(out), np.asarray(ref))
    np.testing.assert_array_equal(np.asarray(lse), np.asarray(ref_lse))
    # this JAX (the one the project pins) has them
    from rvggt_jax.ops.kernels import fused, tpu_flash

    assert fused.cudnn_lse_available() and tpu_flash.lse_available()
