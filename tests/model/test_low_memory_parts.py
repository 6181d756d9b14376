"""The low-memory mode's forward in parts (`rvggt_jax.model.low_memory`): part 1 (patch
embed, layers 0..11), part 2 (patch embed and every layer again, the camera head), the DPT
heads a chunk of frames at a time, the projected layers on the host in between. Its
outputs are the one-program low-memory forward's; `memory_report` plans the largest part."""

import dataclasses

import jax
import numpy as np
import pytest

from rvggt_jax import rvggt_forward
from rvggt_jax.model import low_memory
from rvggt_jax.planning.memory import memory_report

OUTPUTS = ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf")


def one_unit_apart(a, b, dtype) -> bool:
    """a and b (float64 or float32 arrays of `dtype` values) at most one unit of `dtype`'s last
    place apart: the same ops on the same values, in frame groups of another size (the DPT
    heads' fusions then round a 16-bit output differently now and then)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return bool(np.all(np.abs(a - b) <= np.spacing(np.abs(a).astype(dtype)).astype(np.float64)))


@pytest.fixture(scope="module")
def regime(tiny):
    params, config = tiny
    return params, dataclasses.replace(config.with_compression("regime"), enable_track=False).with_low_memory()


def test_parts_equal_the_one_program(regime, golden):
    # 3 frames in chunks of 2: the second chunk overlaps the first (frames 1-2)
    params, config = regime
    images = golden["images"]
    ref = jax.device_get(jax.jit(rvggt_forward, static_argnums=2)(params, images, config))
    seen = []
    got = low_memory.low_memory_forward(params, images, config, chunk=2, on_part=seen.append)
    assert seen[:2] == ["part 1: patch embed and the first layers",
                        "part 2: every layer again, the last ones kept, and the camera head"]
    assert seen[2:] == ["heads: frames 0-1 (1 of 2)", "heads: frames 1-2 (2 of 2)"]
    for key in OUTPUTS:
        a, b = np.asarray(ref[key], np.float64), np.asarray(got[key], np.float64)
        assert got[key].dtype == ref[key].dtype and a.shape == b.shape, key
        assert one_unit_apart(a, b, ref[key].dtype), key
    assert len(got["pose_enc_list"]) == len(ref["pose_enc_list"])
    np.testing.assert_array_equal(got["pose_enc_list"][0], np.asarray(ref["pose_enc_list"][0]))
    assert low_memory.split_layer(config) == 11
    # `rvggt reconstruct --low-memory` runs it (`app.pipeline.run_model`, float32 outputs)
    from rvggt_jax.app.pipeline import run_model

    tool = run_model(params, images[0], config)
    for key in ("pose_enc", "depth", "world_points"):
        assert tool[key].dtype == np.float32 and one_unit_apart(tool[key], got[key][0], got[key].dtype), key


def test_the_plan_is_the_largest_part(regime, golden):
    params, config = regime
    s, _, h, w = golden["images"].shape[1:]
    rep = memory_report(config, s, h, w)
    assert [name for name, _ in rep.parts] == ["part 1", "part 2", "heads"]
    assert rep.total_bytes == max(b for _, b in rep.parts) and rep.compiled is None
    assert rep.low_memory and all(b > 0 for _, b in rep.parts)


@pytest.mark.parametrize("change, problem", [
    (lambda c: c.with_low_memory(False), "not in the low-memory mode"),
    (lambda c: c.with_outputs(layers=(4,)), "no extra outputs"),
    (lambda c: dataclasses.replace(c, enable_depth=False), "camera and depth heads"),
])
def test_what_does_not_run_in_parts_is_named(regime, change, problem):
    _, config = regime
    with pytest.raises(ValueError, match=problem):
        low_memory.check_config(change(config))
    assert not low_memory.runs_in_parts(change(config))
    assert low_memory.runs_in_parts(config) and not low_memory.runs_in_parts(config, one_device=False)
    assert not low_memory.runs_in_parts(config, with_track=True)


def test_chunks_cover_every_frame_once_with_one_shape():
    assert low_memory.chunk_starts(3, 2) == [0, 1]
    assert low_memory.chunk_starts(64, 64) == [0]
    assert low_memory.chunk_starts(130, 64) == [0, 64, 66]
    assert low_memory.chunk_starts(2, 64) == [0]


def test_the_time_estimate_counts_the_recomputed_layers(regime):
    from rvggt_jax.planning.target_time import device_flops

    _, config = regime
    one = device_flops(config.with_low_memory(False), 100, 112, 154)["aggregator"]
    parts = device_flops(config, 100, 112, 154)["aggregator"]
    assert parts == pytest.approx(one * (1 + 12 / 24))
    assert device_flops(config, 100, 112, 154, devices=2)["aggregator"] < one  # (a split: one program)


def test_bf16_parts_within_twice_upstreams_own_deviation(tiny, golden):
    """The mode as issue 54 plans it (bfloat16 weights and compute, dense), run in parts,
    against the float32 fixture: within twice upstream's own bf16 deviation, as the
    one-program mode (tests/model/test_low_memory.py)."""
    from rvggt_jax.weights.checkpoint import cast_params
    from tests.helpers import rel_err
    from tests.helpers.tolerances import UPSTREAM_BF16

    params, config = tiny
    low = dataclasses.replace(config, enable_track=False).with_dtype("bfloat16").with_low_memory()
    out = low_memory.low_memory_forward(cast_params(params, "bfloat16", heads=low.half_weight_heads),
                                        golden["images"], low)
    for key in OUTPUTS:
        err = rel_err(np.asarray(out[key], np.float32), golden[key])
        assert err <= 2 * UPSTREAM_BF16[key], (key, err)
