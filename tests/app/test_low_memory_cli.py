"""`rvggt reconstruct --low-memory`: the option reaches the model (the config's low-memory
mode, the camera head's weights in the compute dtype), and the pipeline hands its 16-bit
outputs on in float32. No forward is compiled here: tests/model/test_low_memory.py holds
the mode's parity, tests/app/test_plan_command.py its plan."""

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.app.cli import build_parser, reconstruct_options
from rvggt_jax.app.model_runner import model_for
from rvggt_jax.app.options import ReconstructOptions
from rvggt_jax.app.pipeline import run_model
from tests.helpers import TINY


def test_the_option_reaches_the_config_and_the_weights():
    args = build_parser().parse_args(["reconstruct", "in", "--weights", "w", "--out", "o", "--low-memory"])
    assert reconstruct_options(args).low_memory
    plain = build_parser().parse_args(["reconstruct", "in", "--weights", "w", "--out", "o"])
    assert not reconstruct_options(plain).low_memory
    params, config = model_for(TINY, "tiny", ReconstructOptions(low_memory=True, dtype="bfloat16"))
    assert config.low_memory and config.dtype == "bfloat16" and config.half_weight_heads == ("camera_head",)
    dtypes = lambda tree: {leaf.dtype for leaf in jax.tree.leaves(tree)}  # noqa: E731
    assert dtypes(params["camera_head"]) == {jnp.dtype(jnp.bfloat16)}
    assert dtypes(params["depth_head"]) == {jnp.dtype(jnp.float32)}  # (the DPT heads' stay float32)
    _, default = model_for(TINY, "tiny", ReconstructOptions())
    assert not default.low_memory


def test_16_bit_outputs_come_back_in_float32():
    _, config = model_for(TINY, "tiny", ReconstructOptions(low_memory=True))
    s, h, w = 2, 28, 28
    half = {"pose_enc": jnp.ones((1, s, 9), jnp.float32), "depth": jnp.full((1, s, h, w, 1), 1.5, jnp.float16),
            "depth_conf": jnp.full((1, s, h, w), 2.0, jnp.bfloat16)}

    def compiled(params, batch, cfg):
        assert batch.shape == (1, s, 3, h, w) and cfg is config
        return half

    out = run_model({}, np.zeros((s, 3, h, w), np.float32), config, compiled=compiled)
    assert {k: v.dtype for k, v in out.items()} == {k: np.dtype(np.float32) for k in half}
    assert out["depth"].shape == (s, h, w, 1) and np.all(out["depth"] == 1.5) and np.all(out["depth_conf"] == 2.0)
