"""Accelerators to plan for without having one: XLA's own GPU and TPU compilers run on this
host ("deviceless" compilation; the `[plan]` extra installs them).

    dev = target_device("h200")            # an abstract device: inputs are placed on it
    TARGETS["tpu-v6e"].memory_bytes        # what a plan for it is held against

A GPU is described to XLA by a target description (`gpu_specs/*.txtpb`, XLA's own files,
see gpu_specs/README.md); a TPU by libtpu's topology name. A program's memory plan barely
depends on a card's details beyond its memory, so a card XLA ships no description of is
planned with the nearest one it does ship (the same chip family) and the result is held
against the card's own memory (`Target.described_by` says which description is used).
Nothing here changes `os.environ`: the `rvggt plan` command sets JAX_PLATFORMS=cpu.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import re
from importlib import resources
from typing import Any

from rvggt_jax.planning import peaks
from rvggt_jax.planning.peaks import Link, Peaks

__all__ = ["CompilerMissingError", "TARGETS", "Target", "UnknownTargetError", "description_text",
           "exhausted_hbm", "gemm_fallback", "get_target", "host_memory_bytes", "target_device", "target_devices"]

GiB = 2 ** 30
PLATFORMS = ("cuda", "tpu", "cpu")
MEMORY_LIMIT_ENV = "RVGGT_MEMORY_LIMIT_GB"
INSTALL_HINT = 'pip install "rvggt-jax[plan]"'
# the package that holds each platform's compiler (the `[plan]` extra installs both)
# XLA's compiler per platform: either CUDA plugin (12 from the [plan] extra, 13 on newer
# images) carries the CUDA compiler
PLUGIN_MODULES = {"cuda": ("jax_cuda12_plugin", "jax_cuda13_plugin"), "tpu": ("libtpu",)}


class UnknownTargetError(ValueError):
    """A target name that is not in `TARGETS` (nor an alias of one)."""


class CompilerMissingError(RuntimeError):
    """XLA's compiler for a target's platform is not installed (or cannot describe it)."""


@dataclasses.dataclass(frozen=True)
class Target:
    """One accelerator to plan for.

    name: the canonical name ("h200"); aliases: other names it answers to (matched after
    `normalize`, so "H200" and "tpu_v6e" need no alias of their own).
    platform: "cuda", "tpu" or "cpu" (this host).
    memory_bytes: what a plan is held against: a GPU's memory, the HBM XLA:TPU lets a
    program use; None for "cpu" (this machine's available RAM, read when asked).
    description: a GPU's XLA target description, a file of gpu_specs/ (or an absolute path).
    tpu_type: a TPU's libtpu type ("v6e", "v5e", "v5p"); chip_config its chip
    configuration ("megacore" for v5p: two cores as one device).
    compiler_options: XLA options every compile for the target takes, as (name, value)
    pairs (`options()` gives the dict `Lowered.compile(compiler_options=...)` takes).
    note: why this description (a card XLA has none of) or what the memory is.
    peak: the vendor's peak dense FLOP/s of one GPU or chip per way this project runs a
    product (`Peaks`; None: unknown, and for "cpu", whose rate `planning.estimate` measures).
    link: what the device sends to its neighbour in a ring, one way (`Link`; None: unknown,
    and for "cpu", whose host devices share one memory).
    """

    name: str
    title: str
    platform: str
    memory_bytes: int | None
    description: str | None = None
    tpu_type: str | None = None
    chip_config: str = "default"
    aliases: tuple[str, ...] = ()
    compiler_options: tuple[tuple[str, Any], ...] = ()
    note: str = ""
    peak: "Peaks | None" = None
    link: "Link | None" = None

    def __post_init__(self):
        if self.platform not in PLATFORMS:
            raise ValueError(f"target {self.name!r}: platform must be one of {PLATFORMS}; got {self.platform!r}")
        if (self.platform == "cuda") != (self.description is not None):
            raise ValueError(f"target {self.name!r}: a GPU target, and only one, names its XLA description")
        if (self.platform == "tpu") != (self.tpu_type is not None):
            raise ValueError(f"target {self.name!r}: a TPU target, and only one, names its libtpu type")
        if self.memory_bytes is not None and self.memory_bytes <= 0:
            raise ValueError(f"target {self.name!r}: memory_bytes must be positive; got {self.memory_bytes}")

    @property
    def described_by(self) -> str:
        """What XLA compiles for: the description file, the TPU type, or this host."""
        if self.platform == "cuda":
            return f"XLA's {self.description}"
        if self.platform == "tpu":
            return f"libtpu's {self.tpu_type}"
        return "this host's CPU"

    def options(self) -> dict[str, Any]:
        """`compiler_options` as the dict `jax.stages.Lowered.compile` takes."""
        return dict(self.compiler_options)

    def memory(self) -> tuple[int | None, str]:
        """(bytes, what) a plan is held against: the target's memory, or for "cpu" this
        machine's available RAM (None when unknown)."""
        if self.memory_bytes is not None:
            return self.memory_bytes, self.title
        return host_memory_bytes()


# XLA's GPU compiler (jaxlib 0.10.2) cannot tile a small float32 Triton gemm of the DPT
# head for sm_80 / sm_86 without a device ("Couldn't find output tile sizes that satisfy
# hlo"): Ampere plans take cuBLAS gemms instead (their workspaces count as temporaries).
NO_TRITON_GEMM = (("xla_gpu_enable_triton_gemm", False),)
# The same failure on other GPUs, for other programs (a small config's DPT head on an H100):
# the compile is retried with NO_TRITON_GEMM (`gemm_fallback`), as the Ampere plans take it.
TRITON_TILING_FAILURE = "Couldn't find output tile sizes"


def gemm_fallback(target: Target, message: str) -> dict[str, Any] | None:
    """The compiler options to compile again with after XLA:GPU failed with `message`:
    the target's options and NO_TRITON_GEMM when the failure is the Triton gemm tiling one
    (a deviceless compile does not autotune its gemms; a run on the card does, cuBLAS among
    the candidates), else None (nothing to retry: the target already takes them, or
    another error)."""
    options = target.options()
    if target.platform != "cuda" or TRITON_TILING_FAILURE not in message:
        return None
    if all(options.get(k) == v for k, v in NO_TRITON_GEMM):
        return None
    return {**options, **dict(NO_TRITON_GEMM)}


def _gpu(name, title, memory, description, aliases, note="", compiler_options=(), peak=None, link=None):
    return Target(name, title, "cuda", memory, description=description, aliases=aliases, note=note,
                  compiler_options=compiler_options, peak=peak, link=link)


def _tpu(name, title, memory, tpu_type, aliases, chip_config="default", peak=None, link=None):
    return Target(name, title, "tpu", memory, tpu_type=tpu_type, chip_config=chip_config, aliases=aliases,
                  note="memory: the HBM XLA:TPU lets one program use (it refuses larger ones)", peak=peak, link=link)


# Memory of the XLA-described cards: the description's own device_memory_size. TPU: the
# largest program XLA:TPU (libtpu 0.0.42) accepted for one chip, found by bisection to
# 1 MiB (its refusals print 15.75G, 31.25G and 95.74G available).
_AMPERE = "cuBLAS gemms (xla_gpu_enable_triton_gemm=false, see NO_TRITON_GEMM)"
_ALL = (
    _gpu("h100", "NVIDIA H100 SXM 80GB", 84942979072, "h100_sxm.txtpb", ("h100-sxm", "h100-80gb"), peak=peaks.HOPPER,
         link=peaks.NVLINK4),
    _gpu("h200", "NVIDIA H200 141GB", 151397597184, "h200.txtpb", ("h200-sxm",), peak=peaks.HOPPER,
         link=peaks.NVLINK4),
    _gpu("a100-40gb", "NVIDIA A100 SXM 40GB", 42331013120, "a100_sxm_40.txtpb", ("a100-40", "a100"),
         note=_AMPERE, compiler_options=NO_TRITON_GEMM, peak=peaks.A100, link=peaks.NVLINK3),
    _gpu("a100-80gb", "NVIDIA A100 SXM 80GB", 85100068864, "a100_sxm_80.txtpb", ("a100-80",),
         note=_AMPERE, compiler_options=NO_TRITON_GEMM, peak=peaks.A100, link=peaks.NVLINK3),
    _gpu("a6000", "NVIDIA RTX A6000 48GB", 51041271808, "a6000.txtpb", ("rtx-a6000",),
         note=_AMPERE, compiler_options=NO_TRITON_GEMM, peak=peaks.A6000, link=peaks.PCIE4),
    _gpu("rtx4090", "NVIDIA GeForce RTX 4090 24GB", 24 * GiB, "a6000.txtpb", ("4090", "rtx-4090", "gpu-24gb"),
         note="XLA ships no Ada (sm_89) description: planned with the RTX A6000's (Ampere GA102, sm_86, cuDNN "
              f"flash attention too) and {_AMPERE}, held against the card's 24 GiB",
         compiler_options=NO_TRITON_GEMM, peak=peaks.RTX4090, link=peaks.PCIE4),
    _gpu("rtx5090", "NVIDIA GeForce RTX 5090 32GB", 32 * GiB, "rtx6000pro.txtpb", ("5090", "rtx-5090", "gpu-32gb"),
         note="XLA ships no GeForce Blackwell description: planned with the RTX PRO 6000 Blackwell's (the same "
              "GB202 chip, sm_120), held against the card's 32 GiB", peak=peaks.RTX5090, link=peaks.PCIE5),
    _tpu("tpu-v5e", "TPU v5e (one chip)", 16908386304, "v5e", ("v5e", "v5litepod", "tpu-v5-lite"),
         peak=peaks.TPU_V5E, link=peaks.ICI_V5E),
    _tpu("tpu-v6e", "TPU v6e (one chip)", 33549328384, "v6e", ("v6e", "trillium"), peak=peaks.TPU_V6E,
         link=peaks.ICI_V6E),
    _tpu("tpu-v5p", "TPU v5p (one chip, megacore)", 102802489344, "v5p", ("v5p",), chip_config="megacore",
         peak=peaks.TPU_V5P, link=peaks.ICI_V5P),
    Target("cpu", "this machine's CPU", "cpu", None, aliases=("host",),
           note="memory: this machine's available RAM (RVGGT_MEMORY_LIMIT_GB overrides it)"),
)
TARGETS: dict[str, Target] = {t.name: t for t in _ALL}


def normalize(name: str) -> str:
    """A target name as looked up: lower case, "_" and spaces as "-", no "nvidia-" prefix."""
    key = re.sub(r"[\s_]+", "-", str(name).strip().lower())
    return key.removeprefix("nvidia-").removeprefix("geforce-")


_BY_NAME = {normalize(a): t for t in _ALL for a in (t.name, *t.aliases)}


def get_target(name: str | Target) -> Target:
    """The target called `name` (a name or alias of `TARGETS`, any case); a `Target` is
    returned as given. Raises `UnknownTargetError` listing the choices."""
    if isinstance(name, Target):
        return name
    target = _BY_NAME.get(normalize(name))
    if target is None:
        raise UnknownTargetError(f"unknown target {name!r}; choose one of: {', '.join(TARGETS)}")
    return target


def check_compiler(target: Target) -> None:
    """Raise `CompilerMissingError` (saying what to install) when XLA's compiler for
    `target`'s platform cannot be imported; for a GPU also when cuDNN is missing (the
    bfloat16 plan would then hold another attention kernel than the card runs)."""
    modules = PLUGIN_MODULES.get(target.platform)
    if modules is None:
        return
    errors = []
    for module in modules:
        try:
            importlib.import_module(module)
            break
        except ImportError as e:
            errors.append(f"{module}: {e}")
    else:
        raise CompilerMissingError(
            f"planning for {target.name} needs XLA's {target.platform.upper()} compiler (not installed: "
            f"{'; '.join(errors)}); install it with: {INSTALL_HINT}")
    if target.platform == "cuda":
        from rvggt_jax.ops.attention import compilable_platforms

        if "cuda" not in compilable_platforms():
            raise CompilerMissingError(
                f"planning for {target.name} needs cuDNN's libraries (its flash attention is what the card runs); "
                f"install them with: {INSTALL_HINT}")


def _tpu_shape(target: Target, n: int) -> tuple[str, tuple[int, int, int]]:
    """(libtpu topology name, chips per host) of a slice of `n` chips of `target`'s type:
    v5e / v6e 1x2, 2x2, 2x4, 4x4, ... (a host holds 2 x 4); v5p 2x1x1, 2x2x1, 2x2x2, 4x2x2,
    ... (a host holds 2 x 2 x 1)."""
    if n < 1 or n & (n - 1):
        raise ValueError(f"a TPU slice has a power of two chips; got {n}")
    three_d = target.tpu_type == "v5p"
    dims, host = ([1, 1, 1], (2, 2, 1)) if three_d else ([1, 1], (2, 4))
    for _ in range(n.bit_length() - 1):  # double the shortest side (v5p: the first, else the last)
        low = min(dims)
        i = dims.index(low) if three_d else len(dims) - 1 - dims[::-1].index(low)
        dims[i] *= 2
    bounds = tuple(min(d, h) for d, h in zip(dims, host)) + (1,) * (3 - len(dims))
    return f"{target.tpu_type}:{'x'.join(map(str, dims))}", bounds


def description_text(target: Target) -> str:
    """The text of a GPU target's XLA description: a file of gpu_specs/, or a path to one."""
    import os

    if os.path.isabs(target.description):
        with open(target.description) as f:
            return f.read()
    spec = resources.files("rvggt_jax.planning").joinpath("gpu_specs", target.description)
    if not spec.is_file():
        raise FileNotFoundError(f"target {target.name!r}: no description {target.description!r} in "
                                f"rvggt_jax/planning/gpu_specs/ (a broken install, or give an absolute path)")
    return spec.read_text()


@functools.cache
def _devices(target: Target, n: int) -> tuple[Any, ...]:
    """`target_devices` after its checks, cached per (target, n)."""
    import jax
    from jax.experimental import topologies

    if target.platform == "cpu":
        cpus = jax.devices("cpu")
        if n > len(cpus):
            raise ValueError(f"the cpu target has {len(cpus)} device(s) here, asked for {n} (more: "
                             f"XLA_FLAGS=--xla_force_host_platform_device_count={n} before JAX starts)")
        return tuple(cpus[:n])
    if target.platform == "cuda" and n > 8 and n % 8:
        raise ValueError(f"more than 8 GPUs must be whole hosts of 8; got {n}")
    shape, bounds = _tpu_shape(target, n) if target.platform == "tpu" else (None, None)
    text = description_text(target) if target.platform == "cuda" else None
    try:
        if target.platform == "cuda":
            # slices x hosts x GPUs per host: 8 GPUs to a host
            layout = f"1x1x{n}" if n <= 8 else f"1x{n // 8}x8"
            topo = topologies.get_topology_desc(platform="cuda", target_config=text, topology=layout)
        else:
            topo = topologies.get_topology_desc(platform="tpu", topology_name=shape,
                                                chip_config_name=target.chip_config, chips_per_host_bounds=bounds,
                                                num_slices=1, wrap=(False, False, False))
    except Exception as e:  # noqa: BLE001 - the plugin's own error types: say what to install
        raise CompilerMissingError(
            f"XLA's {target.platform.upper()} compiler could not describe {target.name} ({target.described_by}): "
            f"{' '.join(str(e).split())[:500]}; the compilers come with {INSTALL_HINT} (matching jaxlib's "
            f"version)") from e
    if len(topo.devices) != n:
        raise RuntimeError(f"{target.name}: asked XLA for {n} devices, got {len(topo.devices)}")
    return tuple(topo.devices)


def target_devices(name: str | Target, n: int = 1) -> tuple[Any, ...]:
    """`n` abstract devices of target `name` (one host's GPUs, a TPU slice of n chips;
    cached): place abstract inputs on them (`jax.ShapeDtypeStruct(..., sharding=...)`) and
    `jax.jit(f).lower(...).compile()` compiles for the target. For "cpu", this host's
    CPU devices."""
    target = get_target(name)
    if isinstance(n, bool) or int(n) != n or n < 1:
        raise ValueError(f"devices must be a positive integer; got {n!r}")
    check_compiler(target)  # every time: the devices are cached, the compilers may go
    return _devices(target, int(n))


def target_device(name: str | Target):
    """The abstract device of target `name` (cached): `target_devices(name, 1)[0]`."""
    return target_devices(name, 1)[0]


def host_memory_bytes() -> tuple[int | None, str]:
    """(bytes, what) of this machine's memory for a forward: $RVGGT_MEMORY_LIMIT_GB when
    set, else the available RAM, else the physical RAM; (None, ...) when unknown."""
    import os

    limit = os.environ.get(MEMORY_LIMIT_ENV)
    if limit:
        try:
            value = float(limit)
        except ValueError:
            raise ValueError(f"{MEMORY_LIMIT_ENV} must be a number of GB; got {limit!r}") from None
        return int(value * 1e9), f"the limit {MEMORY_LIMIT_ENV}={limit}"
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


_UNITS = {"": 1, "B": 1, "K": 2 ** 10, "M": 2 ** 20, "G": 2 ** 30, "T": 2 ** 40}
# XLA:TPU's refusal (libtpu 0.0.42): "RESOURCE_EXHAUSTED: Ran out of memory on HBM, the
# total memory required for HLO temporaries (20.00G) exceeds available HBM (15.75G)."
# (the figure is the whole program: arguments + outputs + temporaries); older libtpu
# said "Used 20.00G of 15.75G hbm".
_REQUIRED = re.compile(r"required[^()]*\(\s*([\d.]+)\s*([KMGT]?)(?:i?B)?\s*\)\s*exceeds available HBM\s*"
                       r"\(\s*([\d.]+)\s*([KMGT]?)(?:i?B)?\s*\)")
_USED = re.compile(r"Used\s+([\d.]+)\s*([KMGT]?)(?:i?B)?\s+of\s+([\d.]+)\s*([KMGT]?)(?:i?B)?\s+hbm", re.IGNORECASE)


def exhausted_hbm(message: str) -> tuple[int, int] | None:
    """(bytes needed, bytes available) from XLA:TPU's RESOURCE_EXHAUSTED message for a
    program larger than HBM (to the message's precision: 0.01 GiB), else None. Its units
    are binary: "20.00G" is 20 GiB."""
    text = str(message)
    if "RESOURCE_EXHAUSTED" not in text:
        return None
    m = _REQUIRED.search(text) or _USED.search(text)
    if m is None:
        return None
    need, need_unit, have, have_unit = m.groups()
    return round(float(need) * _UNITS[need_unit]), round(float(have) * _UNITS[have_unit])
