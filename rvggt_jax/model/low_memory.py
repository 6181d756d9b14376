"""The low-memory mode's forward in parts, for a card that one program overfills (issue
54: VGGT-1B on 1000 frames of 392 x 518 within 16 GiB).

One program (`rvggt_forward` under `VGGTConfig.with_low_memory`) keeps what the DPT heads
read on the device until the heads run at the end: layers 4 and 11 projected (3 GiB at
1000 frames), alive beside the aggregator's working set from layer 11 on, and the heads'
outputs (2.3 GiB in 16 bits). Here the same computation runs as programs one after
another, each holding only its own buffers:

    part 1  patch embed, layers 0..split            -> layers <= split projected (4, 11)
    part 2  patch embed, every layer, camera head   -> layers > split projected (17, 23),
                                                       the poses
    heads   the DPT heads on a chunk of frames      -> that chunk's depth and points

Between the parts the projected layers wait on the host (`jax.device_get`); the heads take
them back a chunk of frames at a time, and their outputs come back a chunk at a time. Part
2 computes layers 0..split again (half the aggregator's work once more) instead of taking
part 1's residual stream: see `second_part`. The values are the one program's: the same
ops on the same values (the heads' frame groups differ, which moves a 16-bit output by one
unit in its last place now and then).

    out = low_memory_forward(params, images, config.with_low_memory())   # numpy outputs

`lowered_parts` lowers the parts for abstract inputs (`rvggt plan --low-memory`, which
plans the largest). Measured with XLA:GPU's deviceless plan for an H100 (regime, bf16,
uint8 images, 1000 frames of 392 x 518): part 1 12.90 GiB, part 2 14.50, heads 0.85,
against 19.58 GiB for the one program (docs/memory_layout.md).
"""

from __future__ import annotations

import functools
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.config import VGGTConfig
from rvggt_jax.model import remat
from rvggt_jax.model.aggregator import aggregator_layers, aggregator_start
from rvggt_jax.model.forward import _head_projections, config_scope, heads_in_float32
from rvggt_jax.model.heads.camera import camera_head
from rvggt_jax.model.heads.dpt import dense_heads
from rvggt_jax.model.inputs import check_inputs
from rvggt_jax.model.kept import ProjectedLayer
from rvggt_jax.model.params import Params
from rvggt_jax.ops.bits import HalfBuffer

# Frames the heads' program takes at a time: VGGT-1B's four projected layers of 64
# frames of 392 x 518 are 0.3 GiB in bfloat16, its 16-bit outputs 0.15 GiB.
HEAD_CHUNK_FRAMES = 64


def split_layer(config: VGGTConfig) -> int:
    """Where part 1 ends: the second layer the DPT heads read (VGGT-1B: 11). The layers
    read before it are the wide projected ones (fine DPT levels); after it they are kept
    reassembled (coarse levels: a quarter of the values)."""
    return sorted(config.dpt_head.intermediate_layer_idx)[1]


def runs_in_parts(config: VGGTConfig, with_track: bool = False, one_device: bool = True) -> bool:
    """Whether `rvggt` runs (and `rvggt plan` plans) this forward in parts: the low-memory
    mode on one device, as `check_config` accepts it."""
    if not (config.low_memory and one_device):
        return False
    try:
        check_config(config, with_track)
    except ValueError:
        return False
    return True


def check_config(config: VGGTConfig, with_track: bool = False) -> None:
    """The three-part run is the low-memory mode's: one device, camera and depth heads, no
    tracks or extra outputs (ValueError naming what is not)."""
    problems = []
    if not config.low_memory:
        problems.append("the config is not in the low-memory mode (config.with_low_memory())")
    if not (config.enable_camera and config.enable_depth):
        problems.append("it needs the camera and depth heads")
    if with_track:
        problems.append("it runs no track head (query points)")
    if config.return_layers or config.return_saliency or config.return_images or config.return_descriptors:
        problems.append("it returns no extra outputs (config.with_outputs)")
    if config.remat != "none":
        problems.append("it is an inference mode (remat)")
    if problems:
        raise ValueError("the three-part low-memory forward: " + "; ".join(problems))


def _enabled(config: VGGTConfig) -> dict[str, bool]:
    """{DPT head: whether the config runs it}."""
    return {"depth_head": config.enable_depth, "point_head": config.enable_point}


def _projections(params: Params, config: VGGTConfig, image_hw: tuple[int, int]):
    grid = config.token_grid(image_hw)
    per_group = functools.partial(remat.checkpoint, config=config, part="head")
    return _head_projections(params, config, grid, False, _enabled(config), per_group)


def _float32_heads(params: Params) -> Params:
    return {name: (sub if name == "aggregator" else heads_in_float32(sub)) for name, sub in params.items()}


def first_part(params: Params, images: jax.Array, config: VGGTConfig) -> dict[int, ProjectedLayer]:
    """Patch embed and layers 0..`split_layer` of images [B, S, 3, H, W] -> {layer:
    `ProjectedLayer`} of the projected layers among them (VGGT-1B: 4 and 11)."""
    return _aggregator_part(params, images, config, late=False)[0]


def second_part(params: Params, images: jax.Array, config: VGGTConfig
                ) -> tuple[dict[int, ProjectedLayer], list[jax.Array]]:
    """Every layer of images [B, S, 3, H, W] again, keeping only the layers after
    `split_layer`, and the camera head -> ({layer: `ProjectedLayer`} of the projected
    layers after the split; the pose encodings [B, S, 9] of every camera iteration).

    Part 2 recomputes layers 0..split rather than take part 1's residual stream: a
    program given the stream held it twice (the argument and the copy XLA:GPU's loops
    update: 17.5 GiB at 1000 frames of VGGT-1B on an H100 against 16), a program that
    makes it holds it once."""
    return _aggregator_part(params, images, config, late=True)


def _aggregator_part(params: Params, images: jax.Array, config: VGGTConfig, late: bool):
    images, _ = check_inputs(params, images, config, None)
    hw = images.shape[-2:]
    split = split_layer(config)
    with config_scope(config):
        params = _float32_heads(params)
        project = {i: p for i, p in _projections(params, config, hw).items() if (i > split) == late}
        stream, _, saliency = aggregator_start(params["aggregator"], images, config)
        out = aggregator_layers(params["aggregator"], stream, config, (), project, hw, saliency,
                                layers=None if late else range(split + 1))
        poses = None
        if late:
            poses = camera_head(params["camera_head"], out[config.depth - 1].token(0)[:, :, None], config.camera_head)
    return {i: _portable(layer) for i, layer in out.items()}, poses


def heads_part(params: Params, layers: dict[int, ProjectedLayer], config: VGGTConfig, image_hw: tuple[int, int]
               ) -> dict[str, jax.Array]:
    """The DPT heads on the frames the projected `layers` hold (a chunk of them) -> depth,
    depth_conf, world_points, world_points_conf of those frames."""
    grid = config.token_grid(image_hw)
    per_group = functools.partial(remat.checkpoint, config=config, part="head")
    with config_scope(config):
        heads = {name: heads_in_float32(params[name]) for name, on in _enabled(config).items() if on}
        layers = {i: _restored(layer, config.compute_dtype) for i, layer in layers.items()}
        return dense_heads(heads, layers, config.dpt_head, grid, per_group, half_outputs=config.low_memory)


def _portable(layer: ProjectedLayer) -> ProjectedLayer:
    """A projected layer as a program returns it: a 16-bit buffer as its bits alone (its
    derivatives' shadow, dead in a forward, would be made whole as an output)."""
    buf = layer.buf.bits if isinstance(layer.buf, HalfBuffer) else layer.buf
    return ProjectedLayer(buf, layer.columns, layer.batch)


def _restored(layer: ProjectedLayer, dtype) -> ProjectedLayer:
    """`_portable`'s inverse: bits back in a `HalfBuffer` of the 16-bit compute `dtype`."""
    buf = layer.buf
    if buf.dtype == jnp.uint16:
        buf = HalfBuffer(buf, jnp.zeros(buf.shape, dtype))
    return ProjectedLayer(buf, layer.columns, layer.batch)


def chunk_starts(frames: int, chunk: int) -> list[int]:
    """Starts of chunks of `chunk` frames covering `frames`: the last one ends at the end
    (it overlaps the one before rather than being shorter: one compiled program)."""
    if frames <= chunk:
        return [0]
    return sorted({min(i, frames - chunk) for i in range(0, frames, chunk)})


def _take_frames(layer: ProjectedLayer, start: int, count: int, batch: int) -> ProjectedLayer:
    """Frames [start, start + count) of each batch element of a host-side projected layer."""
    def part(a):
        a = np.asarray(a)
        return a.reshape((batch, -1) + a.shape[1:])[:, start:start + count].reshape((-1,) + a.shape[1:])

    return ProjectedLayer(jax.tree.map(part, layer.buf), layer.columns, (batch, count))


class Programs:
    """The three jitted parts for one config and image size (`jax.jit` caches one program
    per input shape)."""

    def __init__(self, config: VGGTConfig, image_hw: tuple[int, int]):
        self.config, self.image_hw = config, tuple(image_hw)
        # (the images are not donated: no output has their shape, so XLA could not reuse them)
        self.first = jax.jit(functools.partial(first_part, config=config))
        self.second = jax.jit(functools.partial(second_part, config=config))
        self.heads = jax.jit(functools.partial(heads_part, config=config, image_hw=self.image_hw))


def low_memory_forward(params: Params, images, config: VGGTConfig, *, chunk: int = HEAD_CHUNK_FRAMES,
                       on_part: Callable[[str], Any] | None = None) -> dict[str, Any]:
    """`rvggt_forward(params, images, config)` of the low-memory mode (`check_config`),
    run as the module docstring says: numpy outputs pose_enc, pose_enc_list, depth,
    depth_conf, world_points, world_points_conf (those of the enabled heads), for images
    [B, S, 3, H, W] (or [S, 3, H, W]: a batch of one is added). `on_part(name)` is called
    before each part (progress)."""
    check_config(config)
    images = jnp.asarray(images)
    if images.ndim == 4:
        images = images[None]
    programs = Programs(config, images.shape[-2:])
    note = on_part or (lambda _: None)
    b, s = images.shape[:2]
    note("part 1: patch embed and the first layers")
    early = jax.device_get(programs.first(params, images))
    note("part 2: every layer again, the last ones kept, and the camera head")
    late, poses = programs.second(params, images)
    layers = {**early, **jax.device_get(late)}
    out: dict[str, Any] = {"pose_enc_list": [np.asarray(p) for p in jax.device_get(poses)]}
    out["pose_enc"] = out["pose_enc_list"][-1]
    count = min(chunk, s)
    parts: dict[str, list] = {}
    starts = chunk_starts(s, count)
    for n, start in enumerate(starts):
        note(f"heads: frames {start}-{start + count - 1} ({n + 1} of {len(starts)})")
        chunk_out = jax.device_get(programs.heads(params, {i: _take_frames(layer, start, count, b)
                                                          for i, layer in layers.items()}))
        for name, value in chunk_out.items():
            parts.setdefault(name, []).append(np.asarray(value))
    for name, values in parts.items():
        out[name] = _join(values, starts, count, s)
    return out


def _join(values: list[np.ndarray], starts: list[int], count: int, frames: int) -> np.ndarray:
    """Chunks [B, count, ...] starting at `starts` -> [B, frames, ...] (where the last
    overlaps the one before, both hold the same values)."""
    full = np.empty(values[0].shape[:1] + (frames,) + values[0].shape[2:], values[0].dtype)
    for v, start in zip(values, starts):
        full[:, start:start + v.shape[1]] = v
    return full


def lowered_parts(params: Params, images: jax.ShapeDtypeStruct, config: VGGTConfig, *,
                  chunk: int = HEAD_CHUNK_FRAMES, device: Any = None) -> dict[str, Any]:
    """The three parts lowered for abstract (or concrete) `params` and images [B, S, 3, H,
    W] (`jax.ShapeDtypeStruct`s; on `device` when given, a deviceless target's too):
    {"part 1": ..., "part 2": ..., "heads": ...}, each a `jax.stages.Lowered` to compile
    and plan (`planning.memory`). Nothing runs."""
    check_config(config)
    where = None if device is None else jax.sharding.SingleDeviceSharding(device)

    def placed(tree):
        return jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=where), tree)

    b, s = images.shape[:2]
    programs = Programs(config, images.shape[-2:])
    params, images = placed(params), placed(images)
    early = jax.eval_shape(programs.first, params, images)
    late, _ = jax.eval_shape(programs.second, params, images)
    count = min(chunk, s)

    def chunk_of(layer):
        return ProjectedLayer(jax.tree.map(lambda a: jax.ShapeDtypeStruct((b * count,) + a.shape[1:], a.dtype),
                                           layer.buf), layer.columns, (b, count))

    layers = placed({i: chunk_of(layer) for i, layer in {**early, **late}.items()})
    return {"part 1": programs.first.lower(params, images), "part 2": programs.second.lower(params, images),
            "heads": programs.heads.lower(params, layers)}
