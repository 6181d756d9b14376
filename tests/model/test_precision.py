"""float32 means float32 on every platform: a float32 config runs every matmul and
convolution at "highest" (on an H200 the platform's default, TF32, moved the tiny
fixture's outputs by up to 1.5e-3, over the 1e-4 of parity; docs/benchmarks.md "GPU
check"), the backward of a train step too; a bfloat16 config leaves JAX's own setting.
Checked on the lowered programs, whose precision attributes every compiler reads (a CPU
computes float32 in full either way, so values here cannot show it)."""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import pytest

import rvggt_jax
from rvggt_jax import train
from rvggt_jax.config import VGGTConfig
from rvggt_jax.model.forward import rvggt_forward
from tests.helpers.micro import micro_config

PRODUCT = re.compile(r"stablehlo\.(?:dot_general|convolution)\b[^\n]*")


def _precisions(text: str) -> list[str]:
    """The precision of each matmul / convolution of a lowered program: "HIGHEST",
    "DEFAULT", ... (the first operand's; None when the op names none)."""
    found = []
    for op in PRODUCT.findall(text):
        m = re.search(r"precision = \[(\w+)", op) or re.search(r"precision_config = \[#stablehlo<precision (\w+)", op)
        found.append(m.group(1) if m else None)
    assert found, "no matmul found: the pattern no longer matches the lowered text"
    return found


def _forward_text(params, images, config) -> str:
    return jax.jit(rvggt_forward, static_argnums=2).lower(params, images, config).as_text()


def test_precision_follows_the_dtype_unless_given():
    assert VGGTConfig().dot_precision == "highest"
    assert VGGTConfig().with_dtype("bfloat16").dot_precision is None  # JAX's own default
    assert VGGTConfig().with_precision("default").dot_precision == "default"
    assert VGGTConfig().with_dtype("bfloat16").with_precision("highest").dot_precision == "highest"
    config = VGGTConfig().with_precision("high")
    assert VGGTConfig.from_dict(config.to_dict()) == config
    with pytest.raises(ValueError, match="matmul_precision must be None or one of"):
        VGGTConfig().with_precision("tf32")


def test_a_float32_forward_runs_every_product_at_highest(tiny, golden):
    params, config = tiny
    images = golden["images"]
    assert set(_precisions(_forward_text(params, images, config))) == {"HIGHEST"}
    # asked for the platform's default, only the products that name their own remain HIGHEST
    fast = _precisions(_forward_text(params, images, config.with_precision("default")))
    assert fast.count("DEFAULT") > len(fast) // 2


def test_a_bfloat16_forward_leaves_jaxs_own_precision(tiny, golden):
    params, config = tiny
    config = config.with_dtype("bfloat16")
    assert "DEFAULT" in _precisions(_forward_text(params, golden["images"], config))
    with jax.default_matmul_precision("highest"):  # a user's global setting stays in force
        assert set(_precisions(_forward_text(params, golden["images"], config))) == {"HIGHEST"}


def test_a_gradient_taken_outside_the_forward_keeps_its_precision():
    # the blocked attention's backward is a custom VJP, traced by jax.grad after the
    # forward's own scope has closed: it runs at the precision its forward saw
    config = micro_config(enable_point=False, enable_track=False)
    params = rvggt_jax.init_params(config, 0)
    images = jnp.zeros((1, 2, 3, 28, 28), jnp.float32)

    def loss(p):
        return rvggt_forward(p, images, config)["depth"].sum()

    precisions = _precisions(jax.jit(jax.grad(loss)).lower(params).as_text())
    assert set(precisions) == {"HIGHEST"}, {p: precisions.count(p) for p in set(precisions)}


def test_a_float32_train_step_runs_its_backward_at_highest():
    config = micro_config(enable_point=False, enable_track=False)
    tc = train.TrainConfig(learning_rate=1e-3, warmup_steps=1, total_steps=2)
    state = train.init_state(rvggt_jax.init_params(config, 0), tc)
    batch = train.stack([train.synthetic_example(2, (28, 28), seed=0)])
    step = train.make_train_step(config, tc, donate=False)
    text = step.lower(state, batch).as_text(debug_info=True)
    precisions = _precisions(text)
    assert set(precisions) == {"HIGHEST"}, {p: precisions.count(p) for p in set(precisions)}
    assert "transpose(jvp(" in text  # the backward is in it


def test_the_flax_parts_run_at_their_configs_precision():
    # each part of `model.modules` runs under its config's kernel and precision, as the
    # whole forward does
    from rvggt_jax.model.modules import Aggregator, DPTHead

    config = micro_config(enable_point=False, enable_track=False)
    params = rvggt_jax.init_params(config, 0)
    images = jnp.zeros((1, 2, 3, 28, 28), jnp.float32)
    layers = jax.eval_shape(lambda p: Aggregator(config).apply({"params": p}, images), params["aggregator"])
    head = jax.jit(lambda p, agg: DPTHead(config, output="depth").apply({"params": p}, agg, (28, 28)))
    for c, want in ((config, {"HIGHEST"}), (config.with_precision("default"), {"DEFAULT", "HIGHEST"})):
        backbone = jax.jit(lambda p, x: Aggregator(c).apply({"params": p}, x))
        assert set(_precisions(backbone.lower(params["aggregator"], images).as_text())) == want
    assert set(_precisions(head.lower(params["depth_head"], layers).as_text())) == {"HIGHEST"}
