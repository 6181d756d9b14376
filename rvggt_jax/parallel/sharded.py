"""One forward pass split over devices by frames: `sharded_forward`.

    mesh = rvggt_jax.frames_mesh()                      # every local device on axis "frames"
    fwd = jax.jit(rvggt_jax.sharded_forward, static_argnames=("config", "mesh"))
    out = fwd(params, images, config, mesh)             # outputs sharded over frames

Each device holds its frames' tokens through the whole pass: patch embed, frame blocks,
per-token work and the depth/point heads are local; the global blocks exchange what
crosses frames (K/V, or the compressed sequence's matching and group sums: see
`compression/merged_layer.py` and docs/sharding.md); the camera trunk and the tracker's update
transformer, which attend across frames, run on gathered [B, S, ...] tokens. Parameters
are replicated. The result equals `rvggt_forward` up to float summation order.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from jax.sharding import AxisType, Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from rvggt_jax.config import VGGTConfig
from rvggt_jax.ops.shards import FRAMES_AXIS, FrameShards, split_frames
from rvggt_jax.model.layers import Params
from rvggt_jax.model.forward import forward_frames
from rvggt_jax.model.inputs import check_inputs


def frames_mesh(devices: int | None = None) -> Mesh:
    """A one-axis mesh named "frames" over the first `devices` devices (default: all)."""
    available = jax.devices()
    n = len(available) if devices is None else int(devices)
    if not 1 <= n <= len(available):
        raise ValueError(f"asked for {n} devices; this machine has {len(available)} "
                         f"{jax.default_backend().upper()} device(s)")
    return jax.make_mesh((n,), (FRAMES_AXIS,), devices=available[:n], axis_types=(AxisType.Auto,))


def frame_shards(mesh: Mesh, frames: int) -> FrameShards:
    """How `frames` frames sit on `mesh` (its "frames" axis)."""
    if FRAMES_AXIS not in mesh.axis_names:
        raise ValueError(f"the mesh needs an axis named {FRAMES_AXIS!r} to split frames over; "
                         f"it has {tuple(mesh.axis_names)}")
    n = mesh.shape[FRAMES_AXIS]
    return FrameShards(frames, n, FRAMES_AXIS) if n > 1 else FrameShards.single(frames)


def input_shardings(mesh: Mesh, frames: int) -> tuple[NamedSharding, NamedSharding]:
    """(parameters: replicated, images [B, S, 3, H, W]: split over "frames" when S divides
    the axis, else replicated, as the forward pads them) for `frames` frames on `mesh`."""
    shards = frame_shards(mesh, frames)
    even = shards.padded == shards.frames
    return NamedSharding(mesh, P()), NamedSharding(mesh, P(None, FRAMES_AXIS) if even else P())


def sharded_forward(params: Params, images: jax.Array, config: VGGTConfig, mesh: Mesh,
                    query_points: jax.Array | None = None, keep_padding: bool = False) -> dict[str, Any]:
    """`rvggt_forward` with the frames split over the mesh axis "frames".

    images [B, S, 3, H, W] (or [S, 3, H, W]); query_points as `rvggt_forward`. Returns
    its outputs, every per-frame array sharded over "frames" along S (axis 1;
    `patch_tokens` [B*S, h*w, C] along its first axis). S need not divide the number of
    devices: the sequence is padded with empty frames to whole shards, and no real
    token ever attends to, merges with or is normalised with a padding one. A JAX array
    cannot be sharded unevenly, so with such an S the S-frame outputs are laid out as
    XLA sees fit (replicated); `keep_padding=True` returns them padded to whole shards
    instead (S' = devices * ceil(S / devices) frames, still sharded), with
    "frame_mask" [S'] (True for the real frames).

    Traceable under `jax.jit` (config and mesh static), on concrete or abstract inputs
    (`jax.ShapeDtypeStruct`), so XLA's memory analysis of the sharded program is one
    `.lower(...).compile()` away."""
    images, query_points = check_inputs(params, images, config, query_points)
    b, s = images.shape[:2]
    shards = frame_shards(mesh, s)
    frames = P(None, FRAMES_AXIS)
    pad = shards.padded - s
    if pad and _explicit(mesh):
        # a user's frames-sharded images of uneven S cannot be padded in place on an
        # explicit mesh; padding a replicated copy is what the auto mesh does
        images = jax.sharding.reshard(images, NamedSharding(mesh, P()))
    if pad:
        images = jnp.pad(images, ((0, 0), (0, pad), (0, 0), (0, 0), (0, 0)))
    images = _constrain(images, NamedSharding(mesh, frames))

    def local(params, images, *qp):
        with split_frames(shards):
            out = forward_frames(params, images, config, qp[0] if qp else None)
        if "patch_tokens" in out:  # [B*S, ...]: frames along axis 1 like every other output
            out["patch_tokens"] = out["patch_tokens"].reshape((b, shards.local) + out["patch_tokens"].shape[1:])
        return out

    extra = () if query_points is None else (query_points,)
    out = jax.shard_map(local, mesh=mesh, in_specs=(P(), frames) + (P(),) * len(extra), out_specs=frames,
                        check_vma=False)(params, images, *extra)

    explicit = _explicit(mesh)
    if pad and not keep_padding:
        # S frames do not split evenly: on a mesh of explicit axes JAX refuses to slice a
        # frames-sharded axis to S (no even layout); replicated first, which is what XLA
        # picks on an auto mesh
        unsharded = NamedSharding(mesh, P())
        out = jax.tree.map(lambda a: (jax.sharding.reshard(a, unsharded) if explicit else a)[:, :s], out)
    if "patch_tokens" in out:
        pt = out["patch_tokens"]
        shape = (b * pt.shape[1],) + pt.shape[2:]
        if explicit:
            # [B, S, ...] -> [B*S, ...] interleaves the frames of B: laid out along "frames"
            # (when S was sharded), as the docstring promises; JAX moves what it must
            spec = P(FRAMES_AXIS) if (keep_padding or not pad) and b == 1 else P()
            out["patch_tokens"] = jnp.reshape(pt, shape, out_sharding=NamedSharding(mesh, spec))
        else:
            out["patch_tokens"] = pt.reshape(shape)
    if keep_padding:
        out["frame_mask"] = _constrain(jnp.arange(shards.padded) < s, NamedSharding(mesh, P(FRAMES_AXIS)))
    return out


def _explicit(mesh: Mesh) -> bool:
    """Whether the "frames" axis is explicit (`jax.make_mesh`'s default in recent JAX):
    then JAX's sharding-in-types rules apply to every op on frame-sharded arrays."""
    return mesh.axis_types[mesh.axis_names.index(FRAMES_AXIS)] == AxisType.Explicit


def _constrain(a: jax.Array, sharding: NamedSharding) -> jax.Array:
    """Ask for `sharding` (a reshard on a mesh of explicit axes)."""
    if _explicit(sharding.mesh):
        return jax.sharding.reshard(a, sharding)
    return jax.lax.with_sharding_constraint(a, sharding)
