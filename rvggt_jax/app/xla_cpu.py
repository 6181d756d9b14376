"""XLA:CPU settings: multi-threaded convolutions (the model needs them for speed), the
CPU backend on a host without accelerators (`use_cpu_without_accelerator`), and JAX's
CUDA plugin left unloaded in a CPU-only process (`leave_cuda_plugin_unloaded`: on a host
without a CUDA driver it logs native "Could not find cuda drivers" lines otherwise).

jaxlib 0.10 hands every f32 NHWC convolution to YNNPACK, which runs it on one thread:
the DPT heads' 3x3 convolutions then leave all other cores idle (measured: 1.0 cores
busy on a 2-core machine; the same conv through XLA's Eigen path runs 2x faster on 2
cores, and the whole forward ~10% faster). Matmuls keep YNNPACK, which is multi-threaded
and fast.

XLA reads its flags once, when the first JAX backend starts (the first computation, or
`jax.devices()`; `import jax` does not), so the flag must be in `XLA_FLAGS` before that.
`prefer_threaded_convolutions()` (also `rvggt_jax.prefer_threaded_convolutions`) appends
it, and only when all of these hold:
  - no JAX backend has started yet (otherwise it could not take effect);
  - `XLA_FLAGS` does not already set `--xla_cpu_experimental_ynn_fusion_type` (yours wins);
  - `RVGGT_XLA_CPU_CONV` is not `ynn` (the opt-out);
  - the installed jaxlib is a version this flag was verified on (an unknown XLA flag
    aborts the process, so other versions are left alone).
It changes only which CPU kernel runs a convolution, not what it computes (f32 either
way). `applied()` says whether it took effect in this process.

`import rvggt_jax` does not call it: importing the library leaves `os.environ` as it was.
The `rvggt` command calls it first thing (`rvggt_jax.app.cli.main`), and so do the
benchmarks that time CPU runs. A program of yours gets the same speed by calling it
before anything starts JAX:

    import rvggt_jax
    rvggt_jax.prefer_threaded_convolutions()   # then load weights, run the model, ...
"""

from __future__ import annotations

import os
import sys
import types

FLAG = "--xla_cpu_experimental_ynn_fusion_type=-individual_convolution"
FLAG_NAME = FLAG.split("=")[0]
VERIFIED_JAXLIB = ((0, 10),)  # (major, minor) versions known to have the flag
OPT_OUT_ENV = "RVGGT_XLA_CPU_CONV"

_applied = False


def _jaxlib_version() -> tuple[int, ...]:
    try:
        from jaxlib.version import __version__ as v
    except ImportError:  # pragma: no cover - jaxlib always ships it
        return ()
    return tuple(int(p) for p in v.split(".")[:2] if p.isdigit())


def _backends_started() -> bool:
    if "jax._src.xla_bridge" not in sys.modules:  # JAX not imported: none runs (and asking would import it)
        return False
    try:
        from jax._src import xla_bridge
    except ImportError:  # pragma: no cover
        return True
    started = getattr(xla_bridge, "backends_are_initialized", None)
    return True if started is None else bool(started())


def prefer_threaded_convolutions() -> bool:
    """Append FLAG to XLA_FLAGS when it is safe and useful (see the module doc): call it
    before anything starts a JAX backend. Returns whether it was appended by this call
    (False when a backend already runs, the flag is set already, `RVGGT_XLA_CPU_CONV=ynn`
    or the jaxlib version is not a verified one)."""
    global _applied
    flags = os.environ.get("XLA_FLAGS", "")
    if (FLAG_NAME in flags or os.environ.get(OPT_OUT_ENV, "").lower() == "ynn"
            or _jaxlib_version() not in VERIFIED_JAXLIB or _backends_started()):
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {FLAG}".strip()
    _applied = True
    return True


def applied() -> bool:
    """Whether the flag was set by rvggt_jax in this process."""
    return _applied


# Device nodes of the accelerators JAX's plugins drive on Linux: NVIDIA GPUs (WSL2: the
# /dev/dxg paravirtual GPU), AMD GPUs (ROCm), TPUs (/dev/accel*, or VFIO on some TPU VMs).
ACCELERATOR_NODES = ("/dev/nvidiactl", "/dev/dxg", "/dev/kfd", "/dev/accel0", "/dev/vfio")


def use_cpu_without_accelerator(nodes: tuple[str, ...] = ACCELERATOR_NODES) -> bool:
    """On a Linux host with none of the accelerators' device nodes, JAX on its CPU backend
    (JAX_PLATFORMS=cpu), unless the user chose platforms (JAX_PLATFORMS set) or a backend
    runs already. Without it JAX initialises every installed plugin first, and the
    `[plan]` extra's CUDA and TPU plugins each print a traceback on a machine without
    their device (the `rvggt` command calls it first thing). Returns whether it set it."""
    if os.environ.get("JAX_PLATFORMS") or not sys.platform.startswith("linux") or _backends_started():
        return False
    if any(os.path.exists(n) for n in nodes):
        return False
    return use_cpu_backend()


# JAX's CUDA plugin, as the `[plan]` extra installs it: its native modules, which
# `import jax` loads (jaxlib's gpu_solver / gpu_prng / gpu_linalg wrappers import them
# whatever JAX_PLATFORMS says), and its PJRT plugin, which JAX imports and initialises
# when the first backend starts. Without a CUDA driver each of their libraries logs
# "cudart_stub.cc:31] Could not find cuda drivers" through absl, to fd 2 before any
# logging is set up: no log level or Python handler reaches those lines, only not loading
# the libraries does.
CUDA_PLUGIN_PACKAGES = ("jax_cuda12_plugin", "jax_cuda13_plugin")
CUDA_PJRT_PLUGINS = ("jax_plugins.xla_cuda12", "jax_plugins.xla_cuda13")


def leave_cuda_plugin_unloaded() -> bool:
    """Keep JAX's CUDA plugin out of a process that runs on the CPU alone: when JAX_PLATFORMS
    names only "cpu" and JAX is not imported yet, its native packages cannot be imported
    (jaxlib then takes them as not installed) and its PJRT plugin module is a stub whose
    `initialize()` registers nothing. Returns whether it did. For commands that run on the
    CPU: `rvggt plan` compiles for GPUs with that plugin and must not call it."""
    platforms = {p.strip().lower() for p in os.environ.get("JAX_PLATFORMS", "").split(",") if p.strip()}
    if platforms != {"cpu"} or "jax" in sys.modules or "jaxlib" in sys.modules:
        return False  # (once imported, the plugin's libraries are loaded and logged already)
    for name in CUDA_PLUGIN_PACKAGES:
        sys.modules.setdefault(name, None)  # None: `import name` raises ModuleNotFoundError
    for name in CUDA_PJRT_PLUGINS:
        sys.modules.setdefault(name, _unused_plugin(name))
    return True


def _unused_plugin(name: str) -> types.ModuleType:
    """A stand-in for the PJRT plugin module `name` that JAX's plugin discovery imports and
    calls `initialize()` of: the real one would load the CUDA libraries (and log)."""
    module = types.ModuleType(name, "JAX's CUDA plugin, left unloaded by rvggt_jax.app.xla_cpu (CPU only).")
    module.initialize = lambda: None
    return module


def use_cpu_backend() -> bool:
    """JAX on its CPU backend (JAX_PLATFORMS=cpu) unless the user chose platforms (then
    nothing changes; returns whether it set it). Before JAX's backends start."""
    if os.environ.get("JAX_PLATFORMS"):
        return False
    os.environ["JAX_PLATFORMS"] = "cpu"
    if "jax" in sys.modules:  # (JAX read the environment when it was imported)
        sys.modules["jax"].config.update("jax_platforms", "cpu")
    return True
