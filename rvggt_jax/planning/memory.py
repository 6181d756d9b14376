"""Memory of a forward pass before running it: XLA's own buffer assignment.

    rep = rvggt_jax.memory_report(config.with_compression("regime").with_dtype("bfloat16"),
                                  frames=1000, height=392, width=518)
    rep.total_bytes, rep.temp_bytes, str(rep)

The forward is lowered and compiled for abstract inputs (`jax.ShapeDtypeStruct`) on the
default backend (or `backend`): nothing runs and no weights are needed, so 1000 frames of
VGGT-1B can be planned on a laptop. Peak = arguments + outputs + temporaries - aliased,
the figure XLA allocates for the program (the device also holds its runtime and, for a
CPU, the Python process).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from rvggt_jax.config import VGGTConfig


@dataclasses.dataclass(frozen=True)
class MemoryReport:
    """XLA's memory plan of one compiled forward, in bytes."""

    frames: int
    height: int
    width: int
    batch: int
    dtype: str
    param_dtype: str
    preset: str
    argument_bytes: int  # parameters + images (+ query points)
    output_bytes: int
    temp_bytes: int
    alias_bytes: int
    compile_seconds: float
    # the compiled forward itself, callable as compiled(params, images [B, S, 3, H, W],
    # config): a run after the check need not compile again
    compiled: Any = dataclasses.field(default=None, compare=False, repr=False)

    @property
    def total_bytes(self) -> int:
        """Peak bytes XLA plans for the program: arguments + outputs + temporaries - aliased."""
        return self.argument_bytes + self.output_bytes + self.temp_bytes - self.alias_bytes

    def __str__(self) -> str:
        gb = 1e9
        return (f"{self.preset} {self.dtype} (params {self.param_dtype}), {self.batch} x {self.frames} frames of "
                f"{self.height} x {self.width}: {self.total_bytes / gb:.1f} GB (arguments "
                f"{self.argument_bytes / gb:.1f}, outputs {self.output_bytes / gb:.1f}, temporaries "
                f"{self.temp_bytes / gb:.1f})")


def abstract_params(config: VGGTConfig, *, with_track: bool = False, param_dtype: Any = "float32") -> dict:
    """The converted parameter tree of `config` as `jax.ShapeDtypeStruct` leaves (the
    aggregator's in `param_dtype`, as `load_pretrained(..., param_dtype=...)` loads it)."""
    from rvggt_jax.weights.converter import expected_param_shapes
    from rvggt_jax.weights.checkpoint import cast_params

    tree = expected_param_shapes(config, skip_track=not (with_track and config.enable_track))
    return cast_params(tree, param_dtype)


def memory_report(config: VGGTConfig, frames: int, height: int, width: int, *, batch: int = 1,
                  dtype: Any = None, param_dtype: Any = None, query_points: int = 0,
                  backend: str | None = None, mesh: Any = None) -> MemoryReport:
    """XLA's memory analysis of `jax.jit(rvggt_forward)` for `batch` x `frames` images of
    `height` x `width` (multiples of the patch size) under `config`, without running it.

    dtype: the compute dtype (default `config.dtype`); param_dtype: the aggregator's
    weight dtype (default: the compute dtype). query_points > 0 includes the track head.
    mesh: plan `sharded_forward` over this mesh's "frames" axis instead (the figures are
    then per device: replicated parameters, this device's frames and exchanges).
    """
    from rvggt_jax.model.forward import InputError, rvggt_forward

    import time

    if min(frames, height, width, batch) <= 0:
        raise InputError(f"frames, height, width and batch must be positive; got {frames}, {height}, {width}, {batch}")
    ps = config.patch_size
    if height % ps or width % ps:
        raise InputError(f"image height and width must be multiples of the patch size {ps}; got {height} x {width}")
    if dtype is not None:
        config = config.with_dtype(dtype)
    param_dtype = config.dtype if param_dtype is None else jnp.dtype(param_dtype).name
    with_track = query_points > 0
    params = abstract_params(config, with_track=with_track, param_dtype=param_dtype)
    images = jax.ShapeDtypeStruct((batch, frames, 3, height, width), jnp.float32)
    queries = jax.ShapeDtypeStruct((batch, query_points, 2), jnp.float32) if with_track else None
    t0 = time.perf_counter()
    if mesh is None:
        jitted = jax.jit(rvggt_forward, backend=backend) if backend else jax.jit(rvggt_forward)
        compiled = jitted.lower(params, images, config, *((queries,) if with_track else ())).compile()
    else:
        compiled = _sharded_plan(params, images, config, queries, mesh)
    m = compiled.memory_analysis()
    seconds = time.perf_counter() - t0
    return MemoryReport(
        frames=frames, height=height, width=width, batch=batch, dtype=config.dtype, param_dtype=param_dtype,
        preset=config.compression.name, argument_bytes=int(m.argument_size_in_bytes),
        output_bytes=int(m.output_size_in_bytes), temp_bytes=int(m.temp_size_in_bytes),
        alias_bytes=int(m.alias_size_in_bytes), compile_seconds=seconds, compiled=compiled)


def _sharded_plan(params, images, config, queries, mesh):
    """`sharded_forward` over `mesh` compiled for abstract inputs placed as
    `rvggt_jax.parallel.sharded.input_shardings` places them; the compiled program takes (params, images,
    config[, query_points])."""
    import functools

    from rvggt_jax.parallel.sharded import input_shardings, sharded_forward

    replicated, split = input_shardings(mesh, images.shape[1])
    params = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=replicated), params)
    images = jax.ShapeDtypeStruct(images.shape, images.dtype, sharding=split)
    extra = () if queries is None else (jax.ShapeDtypeStruct(queries.shape, queries.dtype, sharding=replicated),)
    return jax.jit(functools.partial(sharded_forward, mesh=mesh)).lower(params, images, config, *extra).compile()


# ---------------------------------------------------------------------------------------
# Will it fit? (used by `rvggt reconstruct` before it runs anything)
# ---------------------------------------------------------------------------------------

MEMORY_LIMIT_ENV = "RVGGT_MEMORY_LIMIT_GB"


class InsufficientMemoryError(RuntimeError):
    """A forward that XLA plans to need more memory than the device has."""


def device_memory_bytes() -> tuple[int | None, str]:
    """(bytes, what) of the memory a forward can use: $RVGGT_MEMORY_LIMIT_GB when set,
    else the default JAX device's limit (an accelerator), else the host's available RAM
    (CPU); (None, ...) when unknown."""
    import os

    limit = os.environ.get(MEMORY_LIMIT_ENV)
    if limit:
        try:
            value = float(limit)
        except ValueError:
            raise ValueError(f"{MEMORY_LIMIT_ENV} must be a number of GB; got {limit!r}") from None
        return int(value * 1e9), f"the limit {MEMORY_LIMIT_ENV}={limit}"
    try:
        dev = jax.devices()[0]
        stats = dev.memory_stats() if hasattr(dev, "memory_stats") else None
        if stats and stats.get("bytes_limit"):
            return int(stats["bytes_limit"]), f"this {dev.platform.upper()} ({dev.device_kind})"
    except Exception:  # noqa: BLE001 - a backend without memory stats: fall back to the host
        pass
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024, "this machine (available RAM)"
    except OSError:
        pass
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"), "this machine (RAM)"
    except (ValueError, OSError, AttributeError):
        return None, "this machine"


def check_fits(config: VGGTConfig, frames: int, height: int, width: int, *, param_dtype: Any = None,
               batch: int = 1, mesh: Any = None) -> MemoryReport:
    """`memory_report` of the forward (over `mesh`'s devices when given: the figure is
    then per device), raising `InsufficientMemoryError` with what to change when it needs
    more than `device_memory_bytes()`. Returns the report (with the compiled forward)
    when it fits."""
    rep = memory_report(config, frames, height, width, batch=batch, param_dtype=param_dtype, mesh=mesh)
    have, what = device_memory_bytes()
    if have is not None and rep.total_bytes > have:
        hints = []
        if config.compression.is_dense:
            hints.append("--preset regime")
        if config.dtype == "float32":
            hints.append("--dtype bfloat16")
        # memory grows about linearly with the frames once they dominate
        fit = max(1, int(frames * have / rep.total_bytes * 0.9))
        if fit < frames:
            hints.append(f"--max-frames {fit}")
        where = "" if mesh is None else f" on each of {mesh.devices.size} devices"
        raise InsufficientMemoryError(
            f"{frames} frames of {width}x{height} ({config.compression.name}, {config.dtype}) need "
            f"{rep.total_bytes / 1e9:.1f} GB{where}, {what} has {have / 1e9:.1f} GB; try "
            + ", ".join(hints))
    return rep
