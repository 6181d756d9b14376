"""The frame layout of the program being traced (`rvggt_jax.ops.shards`): outside a split
every frame is on this device; `split_frames` (what `parallel/` enters inside its
`shard_map`) is what the model's code reads, it is checked against the frames the code
holds, and it ends with its block, an exception included. The model reads it: a dense
global block traced inside a split attends around the ring of devices, and outside one it
does not. Traced on an abstract mesh, so no devices are needed (the 4-device numerics are
tests/parallel/test_sharded.py's)."""

from __future__ import annotations

import jax
import jax.extend
import jax.numpy as jnp
import pytest
from jax.sharding import AbstractMesh, AxisType
from jax.sharding import PartitionSpec as P

import rvggt_jax
from rvggt_jax.model import layers
from rvggt_jax.ops.shards import FRAMES_AXIS, FrameShards, frame_layout, split_frames
from tests.helpers.micro import micro_config


def test_outside_a_split_every_frame_is_here():
    assert frame_layout(5) == FrameShards.single(5)
    assert frame_layout(frames=7) == FrameShards.single(7)
    assert not frame_layout(3).sharded
    with pytest.raises(ValueError, match="frame count"):
        frame_layout()


def test_a_split_is_read_checked_and_ended():
    split = FrameShards(7, 4, FRAMES_AXIS)  # 2 a device, padded to 8
    with split_frames(split):
        assert frame_layout(2) is split
        assert frame_layout(frames=7) is split
        with pytest.raises(ValueError, match="3 frames on this device, but the frames are split as 7 over 4"):
            frame_layout(3)
        with pytest.raises(ValueError, match="a sequence of 8 frames, but the split is of 7"):
            frame_layout(frames=8)
    assert frame_layout(2) == FrameShards.single(2)
    with pytest.raises(RuntimeError, match="inside"):
        with split_frames(split):
            raise RuntimeError("inside")
    assert not frame_layout(2).sharded


def _primitives(jaxpr) -> set[str]:
    names = set()
    for eqn in jaxpr.eqns:
        names.add(eqn.primitive.name)
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            names |= _primitives(sub)
    return names


def test_the_dense_global_block_reads_the_split():
    config = micro_config()
    block = rvggt_jax.init_params(config, 0)["aggregator"]["global_blocks"]["0"]
    per_frame = config.patch_start_idx + 4  # a 2 x 2 patch grid
    frames, devices = 4, 2
    x = jax.ShapeDtypeStruct((1, frames * per_frame, config.embed_dim), jnp.float32)
    pos = jnp.zeros((1, frames * per_frame, 2), jnp.int32)
    mesh = AbstractMesh((devices,), (FRAMES_AXIS,), axis_types=(AxisType.Auto,))

    def traced(split: FrameShards | None) -> set[str]:
        def body(x, pos):
            if split is None:
                return layers.dense_global_block(block, x, pos, config, per_frame)
            with split_frames(split):
                return layers.dense_global_block(block, x, pos, config, per_frame)

        fn = jax.shard_map(body, mesh=mesh, in_specs=(P(None, FRAMES_AXIS), P(None, FRAMES_AXIS)),
                           out_specs=P(None, FRAMES_AXIS), check_vma=False)
        return _primitives(jax.make_jaxpr(fn)(x, pos).jaxpr)

    assert "ppermute" in traced(FrameShards(frames, devices, FRAMES_AXIS))  # keys around the ring
    assert "ppermute" not in traced(None)  # each device's frames alone
    with pytest.raises(ValueError, match="2 frames on this device, but the frames are split as 6 over 2"):
        traced(FrameShards(frames + 2, devices, FRAMES_AXIS))  # 3 a device, but each holds 2
