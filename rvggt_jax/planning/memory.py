"""Memory of a forward pass before running it: XLA's own buffer assignment.

    rep = rvggt_jax.memory_report(config.with_compression("regime").with_dtype("bfloat16"),
                                  frames=1000, height=392, width=518, target="h200")
    rep.total_bytes, rep.temp_bytes, rep.fits, str(rep)

The forward is lowered and compiled for abstract inputs (`jax.ShapeDtypeStruct`) on the
default backend (or `backend`), or for a named accelerator that need not be here
(`target`: XLA's GPU and TPU compilers run on this host, `rvggt_jax.planning.targets`):
nothing runs and no weights are needed, so 1000 frames of VGGT-1B can be planned on a
laptop. Peak = arguments + outputs + temporaries - aliased, the figure XLA allocates for
the program (the device also holds its runtime and, for a CPU, the Python process).

The images are donated to the program (`jax.jit(rvggt_forward, donate_argnums=1)`), as
`rvggt reconstruct` runs it: once the patch embed has read them, XLA may reuse their
buffer. With float32 images it writes the float32 point map there (`alias_bytes`). Kept,
they are held to the program's end: XLA:TPU refuses `regime` at 1000 frames of 392 x 518
with float32 images on a v6e (2.3 GiB over its HBM), and fits it donated
(docs/accelerators.md). `donate_images=False` plans the program a plain `jax.jit` makes.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
import warnings
from typing import Any, Callable

import jax
import jax.numpy as jnp

from rvggt_jax.config import VGGTConfig
from rvggt_jax.planning.targets import MEMORY_LIMIT_ENV, GiB, get_target, host_memory_bytes

# what the attention kernels leave in a lowered program (docs/accelerators.md)
KERNEL_MARKS = (("__cudnn$fmha", "cudnn"), ("tpu_custom_call", "tpu_flash"))


@dataclasses.dataclass(frozen=True)
class MemoryReport:
    """XLA's memory plan of one compiled forward, in bytes (per device over a mesh).

    With a target: `target` (its name), `memory_bytes` (what the plan is held against,
    `memory_what` says what that is), `device_kind` (the device XLA compiled for: which
    description), `attention` (the kernel in the program: "cudnn", "tpu_flash" or
    "blocked"), `fits` and `headroom_bytes`. XLA:TPU refuses a program larger than its
    HBM: such a report has `needed_bytes` (the figure of XLA's message, to 0.01 GiB) and
    None for the four parts, which XLA never assigned. A program XLA:TPU compiles for
    a chip fits its HBM (`compiler_checked`): XLA:TPU's memory analysis counts more
    temporaries than its memory-space assignment then places at once (at 1000 frames of
    `regime` on a v6e: arguments + outputs + temporaries 33.3 GiB, the chip's program
    and arguments 21.8 GiB; docs/accelerators.md, note (3)), so its total is an upper bound there.
    `peak_bytes`: XLA's heap-simulator peak of the scheduled program, where the
    compiler reports one. `fallback`: the XLA options the plan compiled with instead of
    the target's own after these failed without a device, and why (None: the target's).
    """

    frames: int
    height: int
    width: int
    batch: int
    dtype: str
    param_dtype: str
    preset: str
    argument_bytes: int | None  # parameters + images (+ query points)
    output_bytes: int | None
    temp_bytes: int | None
    alias_bytes: int | None
    compile_seconds: float
    # the compiled forward itself, callable as compiled(params, images [B, S, 3, H, W],
    # config): a run after the check need not compile again
    compiled: Any = dataclasses.field(default=None, compare=False, repr=False)
    target: str | None = None
    memory_bytes: int | None = None
    memory_what: str = ""
    device_kind: str | None = None
    attention: str | None = None
    devices: int = 1
    needed_bytes: int | None = None
    image_dtype: str = "float32"  # the images' dtype in the program (uint8: 1/4 of the bytes)
    peak_bytes: int | None = None
    compiler_checked: bool = False  # compiled by a compiler that refuses what exceeds the memory
    fallback: str | None = None
    # the target's own memory when `memory_bytes` is another the plan is held against
    # (`rvggt plan --memory-gb`); None: memory_bytes is the target's
    own_memory_bytes: int | None = None
    low_memory: bool = False  # planned in the low-memory mode (`VGGTConfig.low_memory`)
    # ((name, total bytes), ...) of the programs of a forward run in parts
    # (`model.low_memory`): the figures above are the largest part's
    parts: tuple = ()
    images_donated: bool = True  # the program may reuse the images' buffer (donate_argnums=1)

    @property
    def exhausted(self) -> bool:
        """Whether XLA refused to compile the program for lack of memory (XLA:TPU)."""
        return self.needed_bytes is not None

    @property
    def total_bytes(self) -> int:
        """Peak bytes XLA plans for the program: arguments + outputs + temporaries - aliased
        (XLA's figure of what it needed when it refused the program)."""
        if self.exhausted:
            return self.needed_bytes
        return self.argument_bytes + self.output_bytes + self.temp_bytes - self.alias_bytes

    @property
    def fits(self) -> bool | None:
        """Whether the plan fits the target's memory (None: no target, or its memory unknown)."""
        if self.exhausted:
            return False
        if self.compiler_checked:
            return True
        return None if self.memory_bytes is None else self.total_bytes <= self.memory_bytes

    @property
    def headroom_bytes(self) -> int | None:
        """The target's memory less the plan (negative: short by that much)."""
        return None if self.memory_bytes is None else self.memory_bytes - self.total_bytes

    def __str__(self) -> str:
        gb = 1e9
        per = f" on each of {self.devices} devices" if self.devices > 1 else ""
        head = (f"{self.preset} {self.dtype} (params {self.param_dtype}), {self.batch} x {self.frames} frames of "
                f"{self.height} x {self.width}{' uint8' if self.image_dtype == 'uint8' else ''}: "
                f"{self.total_bytes / gb:.1f} GB{per}")
        if self.exhausted:
            body = " (XLA refused it: more than the device's memory)"
        elif self.compiler_checked:
            body = (f" (arguments {self.argument_bytes / gb:.1f}, outputs {self.output_bytes / gb:.1f}, "
                    f"temporaries {self.temp_bytes / gb:.1f}, an upper bound: the compiler placed it in the "
                    f"device's memory)")
        else:
            body = (f" (arguments {self.argument_bytes / gb:.1f}, outputs {self.output_bytes / gb:.1f}, "
                    f"temporaries {self.temp_bytes / gb:.1f})")
        if self.target is None:
            return head + body
        verdict = {True: "fits", False: "does not fit", None: "memory unknown"}[self.fits]
        have = "" if self.memory_bytes is None else f" of {self.memory_bytes / GiB:.1f} GiB"
        return head + body + f" for {self.target}{have}: {verdict}"


def abstract_params(config: VGGTConfig, *, with_track: bool = False, param_dtype: Any = "float32") -> dict:
    """The converted parameter tree of `config` as `jax.ShapeDtypeStruct` leaves (the
    aggregator's in `param_dtype`, as `load_pretrained(..., param_dtype=...)` loads it; in
    the low-memory mode the camera head's too: `VGGTConfig.half_weight_heads`)."""
    from rvggt_jax.weights.converter import expected_param_shapes
    from rvggt_jax.weights.checkpoint import cast_params

    tree = expected_param_shapes(config, skip_track=not (with_track and config.enable_track))
    return cast_params(tree, param_dtype, heads=config.half_weight_heads)


def attention_kernel(program_text: str) -> str:
    """The attention kernel a lowered or compiled program holds: "cudnn", "tpu_flash" or
    "blocked" (neither custom call)."""
    return next((name for mark, name in KERNEL_MARKS if mark in program_text), "blocked")


def memory_report(config: VGGTConfig, frames: int, height: int, width: int, *, batch: int = 1,
                  dtype: Any = None, param_dtype: Any = None, query_points: int = 0,
                  backend: str | None = None, mesh: Any = None, target: Any = None,
                  devices: int = 1, image_dtype: Any = "float32", donate_images: bool = True,
                  progress: Callable[[str], None] | None = None) -> MemoryReport:
    """XLA's memory analysis of `jax.jit(rvggt_forward)` for `batch` x `frames` images of
    `height` x `width` (multiples of the patch size) under `config`, without running it.

    dtype: the compute dtype (default `config.dtype`); param_dtype: the aggregator's
    weight dtype (default: the compute dtype). query_points > 0 includes the track head.
    image_dtype: "float32" (images in [0, 1]) or "uint8" (the form `rvggt reconstruct`
    passes, `io.images.network_images`: a quarter of the argument bytes).
    donate_images: plan `jax.jit(rvggt_forward, donate_argnums=1)`, as the tool runs it
    (the module's docstring); False: a plain `jax.jit`, the images held to the end.
    mesh: plan `sharded_forward` over this mesh's "frames" axis instead (the figures are
    then per device: replicated parameters, this device's frames and exchanges).
    target: a name of `rvggt_jax.planning.targets.TARGETS` ("h200", "tpu-v6e", "cpu", ...)
    or a `Target`: compile for it, here, without the device (the `[plan]` extra), over
    `devices` of them (frames split as with `mesh`), and hold the plan against its memory
    (`fits`). Raises `UnknownTargetError` naming the choices, `CompilerMissingError`
    saying what to install. progress: called with a line when a target's compile is
    retried (XLA:GPU's Triton gemm tiling failure: `targets.gemm_fallback`).
    """
    from rvggt_jax.errors import InputError

    if min(frames, height, width, batch) <= 0:
        raise InputError(f"frames, height, width and batch must be positive; got {frames}, {height}, {width}, {batch}")
    ps = config.patch_size
    if height % ps or width % ps:
        raise InputError(f"image height and width must be multiples of the patch size {ps}; got {height} x {width}")
    if target is not None and (mesh is not None or backend is not None):
        raise ValueError("give a target, or a mesh / backend, not both")
    if target is None and devices != 1:
        raise ValueError("devices > 1 needs a target (or pass a mesh)")
    if dtype is not None:
        config = config.with_dtype(dtype)
    param_dtype = config.dtype if param_dtype is None else jnp.dtype(param_dtype).name
    with_track = query_points > 0
    params = abstract_params(config, with_track=with_track, param_dtype=param_dtype)
    image_dtype = jnp.dtype(image_dtype)
    if image_dtype not in (jnp.dtype(jnp.float32), jnp.dtype(jnp.uint8)):
        raise InputError(f"image_dtype must be float32 or uint8; got {image_dtype.name}")
    images = jax.ShapeDtypeStruct((batch, frames, 3, height, width), image_dtype)
    queries = jax.ShapeDtypeStruct((batch, query_points, 2), jnp.float32) if with_track else None
    fields = dict(frames=frames, height=height, width=width, batch=batch, dtype=config.dtype, image_dtype=image_dtype.name,
                  param_dtype=param_dtype, preset=config.compression.name, low_memory=config.low_memory,
                  images_donated=donate_images)
    from rvggt_jax.model.low_memory import runs_in_parts

    if backend is None and runs_in_parts(config, with_track, mesh is None and devices == 1):
        return _parts_report(config, params, images, fields, None if target is None else get_target(target),
                             progress)
    if target is not None:
        return _target_report(config, params, images, queries, get_target(target), devices, fields, progress)
    t0 = time.perf_counter()
    compiled = _lower(params, images, config, queries, mesh, backend, donate=donate_images).compile()
    return _report(compiled, time.perf_counter() - t0, fields)


@contextlib.contextmanager
def unused_donation_allowed():
    """Silences JAX's warning that no output can take the donated images' buffer: a
    program without a float32 point map has no output of their size, and the donation
    then costs nothing (the plans are the same: uint8 images on a v6e, docs/accelerators.md)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Some donated buffers were not usable")
        yield


def _lower(params, images, config, queries, mesh, backend=None, device=None, donate=True):
    """The forward lowered for the abstract inputs: on `device` (inputs placed there), as
    `sharded_forward` over `mesh`, or on `backend` / the default backend; `donate`: the
    images donated (`donate_argnums=1`)."""
    from rvggt_jax.model.forward import rvggt_forward

    donated = (1,) if donate else ()
    if mesh is not None:
        return _sharded_lowering(params, images, config, queries, mesh, donated)
    extra = () if queries is None else (queries,)
    if device is not None:
        where = jax.sharding.SingleDeviceSharding(device)
        params, images, extra = jax.tree.map(
            lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=where), (params, images, extra))
    jitted = jax.jit(rvggt_forward, donate_argnums=donated, **({"backend": backend} if backend else {}))
    with unused_donation_allowed():
        return jitted.lower(params, images, config, *extra)


def _report(compiled, seconds: float, fields: dict, **more) -> MemoryReport:
    m = compiled.memory_analysis()
    return MemoryReport(**fields, argument_bytes=int(m.argument_size_in_bytes),
                        output_bytes=int(m.output_size_in_bytes), temp_bytes=int(m.temp_size_in_bytes),
                        alias_bytes=int(m.alias_size_in_bytes), compile_seconds=seconds, compiled=compiled,
                        peak_bytes=_peak_bytes(compiled), **more)


def _peak_bytes(compiled) -> int | None:
    """XLA's heap-simulator peak of a compiled program: jaxlib's memory stats hold it, but
    `Compiled.memory_analysis()` does not return it in JAX 0.10 (a private path, None
    when it moves or the compiler reports none)."""
    try:
        peak = int(compiled._executable.xla_extension_executable().get_compiled_memory_stats().peak_memory_in_bytes)
    except Exception:  # noqa: BLE001 - a private path: absent in other JAX versions
        return None
    return peak or None


def _target_report(config, params, images, queries, target, devices: int, fields: dict,
                   progress=None) -> MemoryReport:
    """`memory_report` for `target` (a `Target`) over `devices` of its devices."""
    import numpy as np

    from rvggt_jax.parallel.sharded import FRAMES_AXIS
    from rvggt_jax.planning.targets import target_devices

    devs = target_devices(target, devices)
    mesh = None if devices == 1 else jax.sharding.Mesh(np.asarray(devs), (FRAMES_AXIS,),
                                                       axis_types=(jax.sharding.AxisType.Auto,))
    have, what = target.memory()
    t0 = time.perf_counter()
    lowered = _lower(params, images, config, queries, mesh, device=devs[0], donate=fields["images_donated"])
    more = dict(target=target.name, memory_bytes=have, memory_what=what, device_kind=devs[0].device_kind,
                devices=devices, attention=attention_kernel(lowered.as_text()))
    try:
        compiled, more["fallback"] = _compile_for(lowered, target, progress)
    except Exception as e:  # noqa: BLE001 - XLA's runtime error types move between versions
        return _exhausted_report(e, fields, more, have, t0)
    # (XLA:TPU compiles a program for a chip only when it fits the chip's HBM)
    return _report(compiled, time.perf_counter() - t0, fields, compiler_checked=target.platform == "tpu", **more)


def _exhausted_report(error: Exception, fields: dict, more: dict, have, t0: float,
                      part: str | None = None) -> MemoryReport:
    """The report of a program (or of the low-memory mode's `part`) that the target's
    compiler refused for exceeding the chip's memory; `error` raised again when it is
    anything else."""
    from rvggt_jax.planning.targets import exhausted_hbm

    exhausted = exhausted_hbm(str(error))
    if exhausted is None:
        raise error
    needed, available = exhausted
    return MemoryReport(**fields, argument_bytes=None, output_bytes=None, temp_bytes=None, alias_bytes=None,
                        compile_seconds=time.perf_counter() - t0, needed_bytes=needed,
                        **({} if part is None else {"parts": ((part, needed),)}),
                        **{**more, "memory_bytes": have or available})


def _parts_report(config, params, images, fields: dict, target=None, progress=None) -> MemoryReport:
    """`memory_report` of the low-memory mode's forward in parts (`model.low_memory`): each
    part compiled, the largest one's figures, every part's total in `parts`. A card runs
    one part at a time, so it must hold the largest, not the sum."""
    from rvggt_jax.model.low_memory import lowered_parts
    from rvggt_jax.planning.targets import target_devices

    t0 = time.perf_counter()
    device = None if target is None else target_devices(target, 1)[0]
    with unused_donation_allowed():
        lowered = lowered_parts(params, images, config, device=device)
    more: dict = {}
    if target is not None:
        have, what = target.memory()
        more = dict(target=target.name, memory_bytes=have, memory_what=what, device_kind=device.device_kind,
                    attention=attention_kernel(lowered["part 2"].as_text()), compiler_checked=target.platform == "tpu")
    reports = {}
    for name, lo in lowered.items():
        if target is None:
            compiled, fallback = lo.compile(), None
        else:
            try:
                compiled, fallback = _compile_for(lo, target, progress)
            except Exception as e:  # noqa: BLE001 - XLA's runtime error types move between versions
                # (XLA:TPU refuses a part that exceeds the chip: the run cannot fit)
                return _exhausted_report(e, fields, {**more, "compiler_checked": False}, have, t0, part=name)
        reports[name] = _report(compiled, 0.0, fields, fallback=fallback, **more)
    largest = max(reports.values(), key=lambda r: r.total_bytes)
    return dataclasses.replace(largest, compile_seconds=time.perf_counter() - t0, compiled=None,
                               parts=tuple((name, r.total_bytes) for name, r in reports.items()),
                               peak_bytes=largest.peak_bytes)


def _compile_for(lowered, target, progress=None) -> tuple[Any, str | None]:
    """(compiled, fallback): `lowered` compiled with `target`'s options, or, when XLA:GPU
    cannot tile a Triton gemm without the device, compiled again without Triton gemms (the
    fallback says so; a run on the card autotunes its gemms instead)."""
    try:
        return lowered.compile(compiler_options=target.options() or None), None
    except Exception as e:  # noqa: BLE001 - XLA's runtime error types move between versions
        from rvggt_jax.planning.targets import gemm_fallback

        options = gemm_fallback(target, str(e))
        if options is None:
            raise
    if progress is not None:
        progress("  XLA:GPU could not tile a Triton gemm without the device; compiling again with "
                 "xla_gpu_enable_triton_gemm=false (cuBLAS gemms) ...")
    fallback = ("xla_gpu_enable_triton_gemm=false: XLA:GPU could not tile a Triton gemm without the device (\""
                "Couldn't find output tile sizes\"); planned with cuBLAS gemms, whose workspaces count as "
                "temporaries (a run on the card autotunes its gemms)")
    return lowered.compile(compiler_options=options), fallback


def _sharded_lowering(params, images, config, queries, mesh, donated=(1,)):
    """`sharded_forward` over `mesh` lowered for abstract inputs placed as
    `rvggt_jax.parallel.sharded.input_shardings` places them; compiled, the program takes
    (params, images, config[, query_points])."""
    import functools

    from rvggt_jax.parallel.sharded import input_shardings, sharded_forward

    replicated, split = input_shardings(mesh, images.shape[1])
    params = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=replicated), params)
    images = jax.ShapeDtypeStruct(images.shape, images.dtype, sharding=split)
    extra = () if queries is None else (jax.ShapeDtypeStruct(queries.shape, queries.dtype, sharding=replicated),)
    with unused_donation_allowed():
        return jax.jit(functools.partial(sharded_forward, mesh=mesh), donate_argnums=donated).lower(
            params, images, config, *extra)


# ---------------------------------------------------------------------------------------
# Will it fit? (used by `rvggt reconstruct` before it runs anything)
# ---------------------------------------------------------------------------------------


class InsufficientMemoryError(RuntimeError):
    """A forward that XLA plans to need more memory than the device has."""


def device_memory_bytes() -> tuple[int | None, str]:
    """(bytes, what) of the memory a forward can use: $RVGGT_MEMORY_LIMIT_GB when set,
    else the default JAX device's limit (an accelerator), else the host's available RAM
    (CPU); (None, ...) when unknown."""
    import os

    if os.environ.get(MEMORY_LIMIT_ENV):
        return host_memory_bytes()  # the limit
    try:
        dev = jax.devices()[0]
        stats = dev.memory_stats() if hasattr(dev, "memory_stats") else None
        if stats and stats.get("bytes_limit"):
            return int(stats["bytes_limit"]), f"this {dev.platform.upper()} ({dev.device_kind})"
    except Exception:  # noqa: BLE001 - a backend without memory stats: fall back to the host
        pass
    return host_memory_bytes()


def check_fits(config: VGGTConfig, frames: int, height: int, width: int, *, param_dtype: Any = None,
               batch: int = 1, mesh: Any = None, image_dtype: Any = "float32") -> MemoryReport:
    """`memory_report` of the forward (over `mesh`'s devices when given: the figure is
    then per device), raising `InsufficientMemoryError` with what to change when it needs
    more than `device_memory_bytes()`. Returns the report (with the compiled forward)
    when it fits."""
    rep = memory_report(config, frames, height, width, batch=batch, param_dtype=param_dtype, mesh=mesh,
                        image_dtype=image_dtype)
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
