"""One train step over many devices: scenes in parallel, frames around the ring, FSDP.

    layout = train_layout(devices=8, batch=4, frames=16, frames_per_device=8)  # data 4 x frames 2
    mesh = train_mesh(layout)                         # jax.make_mesh, axes ("data", "frames")
    step = make_sharded_train_step(config, tc, mesh, fsdp=layout.fsdp)
    state = place_state(train.init_state(params, tc), mesh, fsdp=layout.fsdp)
    state, metrics = step(state, place_batch(batch, mesh))

The mesh has two axes (`jax.make_mesh`, axis types Auto):

- "data" (D devices): the batch's scenes. Batch arrays [B, S, ...] are split along B, B / D
  scenes per device group; every scene's forward and loss terms stay in its group.
- "frames" (F devices): the frames of one scene, split as the inference does
  (`sharded_forward`'s `forward_frames` under `shard_map`): each device holds S / F
  frames' tokens, the global attention passes K/V around the ring, the camera trunk runs
  on gathered camera tokens. Batch arrays are split along S too.

The loss is taken on the global [B, S, ...] outputs (outside the `shard_map`), so every
mean divides by the whole batch's count, as on one device; `jit` makes the sums over
devices. Gradients of the replicated parameters are summed over both axes by the
`shard_map`'s transpose (a psum of each device's share), which is the one-device
gradient of the whole batch's loss: no averaging by hand.

Parameters and the optimiser state are replicated, or with `fsdp=True` split over every
device of the mesh (both axes, `state_shardings`): each leaf along its largest dimension
that the device count divides (leaves with none stay replicated). XLA gathers them for
the forward (the `shard_map` takes them replicated), reduce-scatters their gradients and
runs AdamW on each device's share: the state at rest is 1 / (D x F) per device; during
the step the gathered parameters (not the gradient's or Adam's copies) are whole.

The result equals `make_train_step` on one device up to float summation order
(tests/parallel/test_sharded_train.py: 1e-5 on 4 host devices).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable

import jax
from jax.sharding import AxisType, Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from rvggt_jax.config import VGGTConfig
from rvggt_jax.errors import InputError
from rvggt_jax.model.forward import forward_frames
from rvggt_jax.model.inputs import check_inputs
from rvggt_jax.parallel.sharded import FRAMES_AXIS, frame_shards, split_frames
from rvggt_jax.train.step import TrainConfig, TrainState, divisors, train_step_fn

DATA_AXIS = "data"
AXES = (DATA_AXIS, FRAMES_AXIS)


@dataclasses.dataclass(frozen=True)
class TrainLayout:
    """How a train step's devices are used: `data` device groups take B / data scenes
    each, `frames` devices share each scene's frames; `fsdp` splits the parameters and
    optimiser state over all `data * frames` devices."""

    data: int = 1
    frames: int = 1
    fsdp: bool = False

    @property
    def devices(self) -> int:
        return self.data * self.frames

    def describe(self) -> str:
        state = "parameters + optimiser state split over all devices (FSDP)" if self.fsdp else "parameters replicated"
        return f"{self.devices} devices: mesh data {self.data} x frames {self.frames}; {state}"


def train_layout(devices: int, batch: int, frames: int, frames_per_device: int | None = None, *,
                 accumulate: int = 1, fsdp: bool = False, available: int | None = None) -> TrainLayout:
    """The mesh of `devices` devices for batches of `batch` scenes of `frames` frames
    (`rvggt finetune --devices N --frames-per-device K`): the frames axis has
    frames / frames_per_device devices (default `frames_per_device = frames`: 1, every
    scene on one device), the data axis the rest, devices / that. The data axis must
    divide the scenes of each micro-batch, batch / accumulate. An `InputError` says what
    would work when the numbers do not fit. `available`: the devices there are (default
    `len(jax.devices())`)."""
    available = len(jax.devices()) if available is None else available
    if devices < 1 or batch < 1 or frames < 1 or accumulate < 1:
        raise InputError(f"devices, batch, frames and accumulate must be >= 1; got {devices}, {batch}, {frames}, "
                         f"{accumulate}")
    if batch % accumulate:
        raise InputError(f"--accumulate {accumulate} must divide --batch {batch}: use --accumulate in "
                         f"{divisors(batch)}")
    micro = batch // accumulate
    fpd = frames if frames_per_device is None else frames_per_device
    if fpd < 1 or frames % fpd:
        raise InputError(f"--frames-per-device {fpd} must divide --frames {frames} (each device takes the same "
                         f"number of a scene's frames): use one of {divisors(frames)}")
    frame_devices = frames // fpd
    # every (data, frames) split of these devices that fits the batch and the frames
    fits = [(d, devices // d) for d in divisors(devices) if micro % d == 0 and frames % (devices // d) == 0]
    if devices % frame_devices == 0 and micro % (devices // frame_devices) == 0:
        if devices > available:
            raise InputError(f"--devices {devices}: there are {available} device(s) "
                             f"({jax.default_backend().upper()}); use --devices 1 to {available}")
        return TrainLayout(devices // frame_devices, frame_devices, fsdp)

    unit = "scenes per micro-batch (--batch / --accumulate)" if accumulate > 1 else "scenes per batch (--batch)"
    if devices % frame_devices:
        problem = (f"--devices {devices} is not a multiple of the {frame_devices} devices that share each scene's "
                   f"frames (--frames {frames} / --frames-per-device {fpd})")
    else:
        data = devices // frame_devices
        problem = (f"--devices {devices} does not divide the batch: {frame_devices} device(s) per scene leave "
                   f"{data} on axis \"data\", which needs a multiple of {data} {unit}; there are {micro}")
    would = []
    if fits:
        would.append("--frames-per-device " + " or ".join(
            f"{frames // f} (data {d} x frames {f})" for d, f in fits))
    counts = sorted({d * frame_devices for d in divisors(micro) if d * frame_devices <= available})
    if counts:
        would.append(f"--devices {' or '.join(map(str, counts))} (at --frames-per-device {fpd})")
    if devices % frame_devices == 0:
        need = (devices // frame_devices) * accumulate
        would.append(f"--batch a multiple of {need} ({', '.join(str(need * k) for k in (1, 2, 3))}, ...)")
    raise InputError(f"{problem}. Would work: " + "; ".join(would))


def train_mesh(layout: TrainLayout, devices: list | None = None) -> Mesh:
    """The ("data", "frames") mesh of `layout` over the first `layout.devices` devices
    (`jax.make_mesh`; Auto axes: the step's loss and optimiser run as XLA partitions them)."""
    devices = jax.devices() if devices is None else devices
    if layout.devices > len(devices):
        raise InputError(f"the layout needs {layout.devices} devices; there are {len(devices)}")
    return jax.make_mesh((layout.data, layout.frames), AXES, devices=devices[:layout.devices],
                         axis_types=(AxisType.Auto, AxisType.Auto))


def _auto(mesh: Mesh) -> Mesh:
    """`mesh` with Auto axes. The step's loss reshapes and slices [B, S, ...] arrays split
    over both axes, which explicit axes (JAX's sharding-in-types) would refuse; the values
    are the same."""
    if set(mesh.axis_names) != set(AXES):
        raise InputError(f"a train mesh has the axes {AXES} (train_mesh); this one has {tuple(mesh.axis_names)}")
    if all(t == AxisType.Auto for t in mesh.axis_types):
        return mesh
    return Mesh(mesh.devices, mesh.axis_names, axis_types=(AxisType.Auto,) * len(mesh.axis_names))


# ---------------------------------------------------------------------------------------
# where things live
# ---------------------------------------------------------------------------------------


def leaf_spec(shape: tuple[int, ...], devices: int) -> P:
    """FSDP: the spec splitting a leaf of `shape` over both mesh axes along its largest
    dimension that `devices` divides (the first of equal ones); P() when none does."""
    best = None
    for i, n in enumerate(shape):
        if n % devices == 0 and (best is None or n > shape[best]):
            best = i
    if best is None:
        return P()
    return P(*([None] * best + [AXES]))


def state_shardings(tree: Any, mesh: Mesh, fsdp: bool) -> Any:
    """NamedShardings for a train state (or any tree of arrays): replicated, or with
    `fsdp` split by `leaf_spec` (AdamW's moments have their parameters' shapes, so they
    are split as their parameters; the step counters stay replicated)."""
    mesh = _auto(mesh)
    if not fsdp:
        return jax.tree.map(lambda _: NamedSharding(mesh, P()), tree)
    return jax.tree.map(lambda a: NamedSharding(mesh, leaf_spec(tuple(a.shape), mesh.size)), tree)


def batch_shardings(batch: dict, mesh: Mesh) -> dict:
    """Every batch leaf [B, S, ...] split over "data" (B) and "frames" (S)."""
    mesh = _auto(mesh)
    return jax.tree.map(lambda _: NamedSharding(mesh, P(DATA_AXIS, FRAMES_AXIS)), batch)


def place_state(state: TrainState, mesh: Mesh, fsdp: bool = False) -> TrainState:
    """`state` on the mesh's devices (`state_shardings`)."""
    return jax.device_put(state, state_shardings(state, mesh, fsdp))


def place_batch(batch: dict, mesh: Mesh) -> dict:
    """`batch` (host arrays, e.g. `train.stack`'s) split over the mesh: each device gets
    only its scenes' frames."""
    check_batch(batch, mesh)
    return jax.device_put(batch, batch_shardings(batch, mesh))


def check_batch(batch: dict, mesh: Mesh) -> None:
    """An `InputError` when the batch's scenes or frames do not split evenly over the
    mesh (B by "data", S by "frames")."""
    b, s = batch["images"].shape[:2]
    d, f = mesh.shape[DATA_AXIS], mesh.shape[FRAMES_AXIS]
    if b % d:
        raise InputError(f"a batch of {b} scenes does not split over {d} devices on axis \"data\": use a multiple "
                         f"of {d} scenes, or a data axis in {divisors(b)}")
    if s % f:
        raise InputError(f"{s} frames do not split over {f} devices on axis \"frames\": use a multiple of {f} "
                         f"frames, or a frames axis in {divisors(s)}")


# ---------------------------------------------------------------------------------------
# the step
# ---------------------------------------------------------------------------------------


def sharded_train_forward(params: Any, images: jax.Array, query_points: jax.Array | None, *,
                          config: VGGTConfig, mesh: Mesh) -> dict[str, Any]:
    """`rvggt_forward` with the scenes split over "data" and the frames over "frames".

    images [B, S, 3, H, W] (B divisible by the data axis, S by the frames axis: no
    padding frames, whose outputs the loss would have to mask); query_points [B, N, 2] or
    None. Returns the forward's outputs, every per-frame array [B, S, ...] split as the
    images. Inside, each device runs `forward_frames` on its [B / D, S / F] block: the
    inference path's frame sharding (ring attention, gathered camera trunk); the data
    axis is independent copies. Differentiable: the ring attention has its backward, the
    gathers' transposes are reduce-scatters, and the replicated parameters' cotangents
    are summed over both axes by the `shard_map`'s transpose."""
    images, query_points = check_inputs(params, images, config, query_points)
    check_batch({"images": images}, mesh)
    shards = frame_shards(mesh, images.shape[1])
    block = P(DATA_AXIS, FRAMES_AXIS)

    def local(params, images, *qp):
        with split_frames(shards):
            return forward_frames(params, images, config, qp[0] if qp else None)

    extra = () if query_points is None else (query_points,)
    # check_vma=False as the inference's shard_map: its collectives (ring permutes, a
    # psum of one non-zero term) are written for device-varying values
    return jax.shard_map(local, mesh=mesh, in_specs=(P(), block) + (P(DATA_AXIS),) * len(extra),
                         out_specs=block, check_vma=False)(params, images, *extra)


def make_sharded_train_step(config: VGGTConfig, tc: TrainConfig, mesh: Mesh, *, fsdp: bool = False,
                            donate: bool = True) -> Callable[[TrainState, dict], tuple[TrainState, dict]]:
    """`make_train_step` over `mesh` (axes "data", "frames": `train_mesh`): `step(state,
    batch) -> (state, metrics)`, one `jax.jit`. state: as `place_state(state, mesh,
    fsdp)` lays it out (other layouts are moved there); batch: leaves [B, S, ...] with
    B divisible by the data axis (by it times `tc.accumulate` with gradient accumulation)
    and S by the frames axis (`place_batch`). The returned state keeps the layout;
    metrics are replicated scalars. Same values as the one-device step (float summation
    order aside)."""
    mesh = _auto(mesh)
    body = train_step_fn(config, tc, forward=functools.partial(sharded_train_forward, config=config, mesh=mesh))

    def constrain(tree, shardings):
        return jax.tree.map(jax.lax.with_sharding_constraint, tree, shardings)

    def step(state: TrainState, batch: dict) -> tuple[TrainState, dict]:
        # the layouts, whatever the arguments': XLA plans the program around them (the
        # FSDP state split, the batch split over both axes)
        state = constrain(state, state_shardings(state, mesh, fsdp))
        batch = constrain(batch, batch_shardings(batch, mesh))
        new, metrics = body(state, batch)
        return constrain(new, state_shardings(new, mesh, fsdp)), metrics

    return jax.jit(step, donate_argnums=(0,) if donate else ())
