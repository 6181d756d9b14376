"""JAX's private and experimental API behind feature checks (issue 54): where a function the
kernels call is missing, its module does not import or its signature changed, the kernel
that needs it gives way to the blocked kernel, with a RuntimeWarning naming what is
missing, and the result is the blocked kernel's. Simulated by monkeypatching JAX's own
modules; on this CPU the cuDNN and Pallas TPU kernels cannot run, so a missing fallback
fails here."""

from __future__ import annotations

import importlib
import sys
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

from rvggt_jax.ops import attention as attn
from rvggt_jax.ops.kernels import fused, tpu_flash


@pytest.fixture(autouse=True)
def fresh_checks():
    """The attention op caches what the checks find: cleared before and after each test
    (each one changes what they find)."""
    caches = (attn._missing, attn._lse_missing, attn.compilable_platforms)
    for cache in caches:
        cache.cache_clear()
    yield
    for cache in caches:
        cache.cache_clear()


def _operands(dtype, seed=0):
    """q [1, 6, 2, 8], k / v [1, 10, 2, 8], a key bias [1, 10] with a removed key."""
    rng = np.random.default_rng(seed)
    q, k, v = (jnp.asarray(rng.standard_normal(s), dtype) for s in ((1, 6, 2, 8), (1, 10, 2, 8), (1, 10, 2, 8)))
    bias = jnp.asarray(rng.standard_normal((1, 10)), jnp.float32).at[0, 3].set(attn.NEG_BIAS)
    return q, k, v, bias


def _same(a, b):
    np.testing.assert_array_equal(np.asarray(a, np.float32), np.asarray(b, np.float32))


def test_every_check_passes_on_this_jax():
    # the checks must not refuse what is there (else every GPU and TPU would run blocked)
    assert fused.cudnn_lse_missing() is None
    assert tpu_flash.flash_missing() is None and tpu_flash.lse_missing() is None


def test_checker_names_a_missing_module_attribute_and_signature(monkeypatch):
    mod = importlib.import_module(fused.CUDNN_MODULE)
    assert fused.missing_private_api(fused.CUDNN_MODULE + "_gone").startswith(fused.CUDNN_MODULE + "_gone does not")
    assert fused.missing_private_api(fused.CUDNN_MODULE, attrs=("MaskType.NOT_A_MASK",)) == \
        f"{fused.CUDNN_MODULE} has no MaskType.NOT_A_MASK"
    missing = fused.missing_private_api(fused.CUDNN_MODULE, (("check_cudnn_version", 1, ()),))
    assert missing and "check_cudnn_version() does not take 1 positional" in missing
    monkeypatch.setattr(mod, "check_cudnn_version", lambda: 90000)  # a lambda's signature is read too
    assert fused.missing_private_api(fused.CUDNN_MODULE, (("check_cudnn_version", 0, ()),)) is None


def _ring_falls_back(name, dtype, match):
    """attention_with_lse(implementation=name) warns `match` and equals the blocked kernel."""
    q, k, v, bias = _operands(dtype)
    with pytest.warns(RuntimeWarning, match=match):
        out, lse = attn.attention_with_lse(q, k, v, bias, 0.3, implementation=name)
    ref, ref_lse = attn.attention_with_lse(q, k, v, bias, 0.3, implementation="blocked")
    _same(out, ref)
    _same(lse, ref_lse)


def test_cudnn_lse_without_a_rule_takes_the_blocked_kernel(monkeypatch):
    monkeypatch.delattr(importlib.import_module(fused.CUDNN_MODULE), "_dot_product_attention_bwd_rule")
    assert "has no _dot_product_attention_bwd_rule" in fused.cudnn_lse_missing()
    assert not fused.cudnn_lse_available()
    _ring_falls_back("cudnn", jnp.bfloat16, "has no _dot_product_attention_bwd_rule.*blocked kernel")


def test_cudnn_lse_when_the_module_does_not_import_takes_the_blocked_kernel(monkeypatch):
    monkeypatch.setitem(sys.modules, fused.CUDNN_MODULE, None)  # `import` raises ModuleNotFoundError
    assert "does not import" in fused.cudnn_lse_missing()
    _ring_falls_back("cudnn", jnp.bfloat16, "fused_attention_stablehlo does not import")


def test_cudnn_lse_with_a_changed_signature_takes_the_blocked_kernel(monkeypatch):
    def fwd_rule(query, key, value, bias, *, scale, cudnn_version):  # fewer arguments than this code passes
        raise AssertionError("called despite the check")

    monkeypatch.setattr(importlib.import_module(fused.CUDNN_MODULE), "_dot_product_attention_fwd_rule", fwd_rule)
    assert "_dot_product_attention_fwd_rule(query, key, value, bias, *, scale, cudnn_version) does not take" in \
        fused.cudnn_lse_missing()
    _ring_falls_back("cudnn", jnp.bfloat16, "does not take 10 positional")


def test_tpu_kernel_without_its_entry_point_takes_the_blocked_kernel(monkeypatch):
    monkeypatch.delattr(importlib.import_module(tpu_flash.PALLAS_MODULE), "flash_attention")
    q, k, v, bias = _operands(jnp.float32)
    with pytest.warns(RuntimeWarning, match="'tpu_flash' attention kernel.*has no flash_attention"):
        out = attn.attention(q, k, v, bias, implementation="tpu_flash")
    _same(out, attn.attention(q, k, v, bias, implementation="blocked"))


def test_tpu_lse_without_a_backward_kernel_takes_the_blocked_kernel(monkeypatch):
    monkeypatch.delattr(importlib.import_module(tpu_flash.PALLAS_MODULE), "_flash_attention_bwd_dq")
    assert not tpu_flash.lse_available() and tpu_flash.flash_missing() is None
    _ring_falls_back("tpu_flash", jnp.float32, "has no _flash_attention_bwd_dq")


def test_auto_without_the_cudnn_version_check_warns_where_a_cuda_plugin_is(monkeypatch):
    monkeypatch.setitem(sys.modules, fused.CUDNN_MODULE, None)
    monkeypatch.setattr(attn, "_cuda_plugin_installed", lambda: True)
    with pytest.warns(RuntimeWarning, match="cannot be asked whether cuDNN is installed"):
        assert "cuda" not in attn.compilable_platforms()
    # without a CUDA plugin there is nothing to say
    attn.compilable_platforms.cache_clear()
    monkeypatch.setattr(attn, "_cuda_plugin_installed", lambda: False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert "cuda" not in attn.compilable_platforms()
