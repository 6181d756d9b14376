"""Gradients through the compressed global blocks (issue 25, item 1): with the blocked
attention kernel (its custom VJP) against the same block whose every attention call is a
plain float32 reference attention differentiated by JAX, at 1e-5: a K/V-downsampled layer
and a merged layer with the size bias (the op-level checks: tests/ops/test_attention_grad.py)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rvggt_jax.ops import attention as attn
from tests.helpers.attention_reference import differentiable_reference as reference, rel

TOL = 1e-5

def _layer_gradients(monkeypatch, preset, layer, kernel):
    from rvggt_jax.compression import Geometry, global_block, init_state
    from rvggt_jax.config import VGGTConfig
    from tests.helpers.compression_reference import global_positions, random_block_params

    s, h, w_, ns, c = 4, 5, 7, 5, 32
    cfg = VGGTConfig(embed_dim=c, num_heads=2).with_compression(preset)
    params = random_block_params(jax.random.PRNGKey(0), c, 2)
    rng = np.random.default_rng(layer)
    x = jnp.asarray(rng.standard_normal((1, s * (ns + h * w_), c)), jnp.float32)
    sal = jnp.asarray(rng.random((1, s, h * w_)), jnp.float32)
    wo = jnp.asarray(rng.standard_normal(x.shape), jnp.float32)
    pos = global_positions(s, h, w_)
    if kernel == "reference":  # every attention call of the block: the plain reference
        for name in attn.KERNELS_BY_NAME:  # (the kernel table: whichever "auto" resolves to)
            monkeypatch.setitem(attn.KERNELS_BY_NAME, name,
                                lambda q, k, v, b, scale, bb: reference(q, k, v, b, scale)[0].astype(q.dtype))

    def loss(p, x):
        state = init_state(cfg.compression, sal, Geometry(s, h, w_, ns))
        return jnp.sum(global_block(p, x, pos, layer, cfg, state)[0] * wo)

    grads = jax.jit(jax.grad(loss, (0, 1)))(params, x)
    monkeypatch.undo()
    return grads


@pytest.mark.parametrize("preset, layer, what", [
    ("kv_only", 0, "K/V-downsampled"),  # kept sub-grid K/V + dynamic slots (removed: NEG_BIAS)
    ("regime", 0, "merged, size bias"),  # merged queries and keys with the log g bias; K/V
])                                       # downsampled too, invalid slots masked
def test_compressed_block_gradient_equals_reference(monkeypatch, preset, layer, what):
    from rvggt_jax.compression import Geometry, layer_plan
    from rvggt_jax.config import VGGTConfig

    plan = layer_plan(VGGTConfig(embed_dim=32, num_heads=2).with_compression(preset).compression, layer,
                      Geometry(4, 5, 7, 5))
    assert plan.kind == ("kv" if preset == "kv_only" else "merge") and plan.n_kv < 4 * 40  # a compressed layer
    ours = _layer_gradients(monkeypatch, preset, layer, "blocked")
    want = _layer_gradients(monkeypatch, preset, layer, "reference")
    flat_o, flat_w = jax.tree.leaves(ours), jax.tree.leaves(want)
    errs = [rel(a, b) for a, b in zip(flat_o, flat_w)]
    assert max(errs) <= TOL, (what, max(errs))
    assert all(np.any(np.asarray(g)) for g in flat_w)  # every gradient reaches its leaf
