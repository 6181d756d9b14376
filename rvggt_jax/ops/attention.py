"""The one attention op of the model: every attention (frame, global, compressed with the
size bias, DINO, camera trunk, tracker) calls `attention`; ring attention (`ops/ring.py`)
calls `attention_with_lse` for each share of the keys, the same kernels with their
log-sum-exp.

    out = attention(q, k, v)                       # softmax(q k^T / sqrt(D)) v
    out = attention(q, k, v, key_bias=log_g)       # + an additive bias per key [B, Nk]

It picks its kernel by name (`implementation`), like MaxText's attention op, each kernel
a module of `ops/kernels/` (the names: `kernels/names.py`):

  "auto"       (the default) the kernel of the platform the program is compiled for,
               `kernel_for(platform, dtype, head_dim)`: cuDNN for 16-bit operands on an
               NVIDIA GPU, the Pallas flash kernel on a TPU, the blocked kernel on a CPU
               and for float32 on a GPU. The choice is made when the program is lowered
               (`jax.lax.platform_dependent`), from the devices it is compiled for, not
               from the host's default backend: a program traced on a CPU host and
               compiled for an H200 takes cuDNN.
  "blocked"    `kernels/blocked.py`: one (batch, head) pair and a cache-sized block of
               query rows at a time; memory bounded whatever the number of keys and the
               dtype, on any platform.
  "cudnn"      `kernels/fused.py`: cuDNN's flash kernel, the key bias folded into the
               operands (16-bit operands only); "xla" is its plain XLA form (forms all
               logits: for checks, not long sequences).
  "tpu_flash"  `kernels/tpu_flash.py`: the Pallas TPU flash kernel, the bias folded in.

The name is data: `VGGTConfig.attention` reaches every aggregator attention through
`layers.BlockConfig.kernel` (and the compressed layers' config); the float32 heads take
"auto". `KERNELS_BY_NAME` is the table, `kernel_for` resolves "auto" for a compile target.
"auto" includes a branch only for the platforms this installation can compile for (cuDNN
when JAX's CUDA plugin and cuDNN are installed, the TPU kernel when libtpu is): a CPU-only
install traces the blocked kernel alone.

JAX's private and experimental API (the Pallas TPU kernel, cuDNN's rules for the
log-sum-exp form, the cuDNN version check of "auto") is feature-checked before use
(`kernels.fused.missing_private_api`: the module, the attributes, the signatures as
called): on a JAX where it is missing or changed, the kernel that needs it is replaced
by the blocked kernel with a RuntimeWarning that names what is missing.

Precision: q, k, v in the compute dtype (float32 or bfloat16); logits, softmax
statistics and the value accumulation in float32; the result in q's dtype.

Gradients: every kernel's backward is O(N d) in memory. The blocked kernel's is a
`jax.custom_vjp` (flash attention's backward: each query block's weights recomputed from
q, k and the saved log-sum-exp; the key bias gets its gradient); cuDNN's and the Pallas
TPU kernel's are their own fused backwards, which the op reaches unchanged.
`attention_with_lse` is differentiable in both outputs (ring attention's fold takes the
log-sum-exp's gradient).
"""

from __future__ import annotations

import functools
import importlib.util
import math
import warnings
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.ops.kernels import blocked
from rvggt_jax.ops.kernels.blocked import blocked_attention
from rvggt_jax.ops.kernels.fused import (CUDNN_MAX_HEAD_DIM, CUDNN_MODULE, cudnn_lse_missing, fused_attention,
                                         fused_attention_with_lse, missing_private_api)
from rvggt_jax.ops.kernels.names import HALF_ONLY, KERNELS
from rvggt_jax.ops.kernels.tpu_flash import flash_missing as tpu_flash_missing
from rvggt_jax.ops.kernels.tpu_flash import lse_missing as tpu_lse_missing
from rvggt_jax.ops.kernels.tpu_flash import tpu_flash_attention, tpu_flash_attention_with_lse

IMPLEMENTATIONS = KERNELS

# A key bias this negative removes the key: exp(NEG_BIAS - max) is exactly 0 in float32,
# and, being finite, a row whose keys are all removed can never turn into NaN.
NEG_BIAS = -1.0e4

def check_kernel(name: str, dtype: Any = None) -> str:
    """`name` if it is a kernel (and takes `dtype`, when given), else a ValueError naming
    the choices."""
    if name not in KERNELS:
        raise ValueError(f"attention kernel (implementation) must be one of {KERNELS}; got {name!r}")
    if dtype is not None and name in HALF_ONLY and not _is_half(dtype):
        raise ValueError(f"the {name!r} attention kernel takes bfloat16/float16 only; got {jnp.dtype(dtype).name} "
                         f"(for float32 use 'auto' or 'blocked'; choices: {KERNELS})")
    return name


def kernel_for(platform: str, dtype: Any, head_dim: int) -> str:
    """The kernel "auto" takes in a program compiled for `platform` ("cpu", "cuda",
    "rocm", "tpu") with operands of `dtype` and head dimension `head_dim`."""
    if platform == "cuda" and _is_half(dtype) and head_dim + 2 <= CUDNN_MAX_HEAD_DIM:
        return "cudnn"
    if platform == "tpu" and head_dim + 2 <= 128:
        return "tpu_flash"
    # CPUs; float32 on a GPU (cuDNN takes none); ROCm: the blocked kernel, memory bounded
    return "blocked"


@functools.cache
def compilable_platforms() -> tuple[str, ...]:
    """The platforms besides the CPU that this installation can compile for, each of whose
    kernels can be traced here: "cuda" with JAX's CUDA plugin and cuDNN's libraries,
    "tpu" with libtpu (the `[plan]` extra installs both)."""
    platforms = []
    # cuDNN's presence is asked of JAX's private cuDNN module (JAX's own cuDNN attention
    # asks it when traced); a JAX without that function cannot say, and "auto" then takes
    # the blocked kernel on NVIDIA GPUs too: said where a CUDA plugin is installed
    missing = missing_private_api(CUDNN_MODULE, (("check_cudnn_version", 0, ()),))
    if missing is None:
        from jax._src.cudnn.fused_attention_stablehlo import check_cudnn_version
        try:
            check_cudnn_version()
            platforms.append("cuda")
        except Exception:  # noqa: BLE001 - no CUDA plugin or no cuDNN: nothing to compile for
            pass
    elif _cuda_plugin_installed():
        warnings.warn(f"this JAX ({jax.__version__}) cannot be asked whether cuDNN is installed ({missing}; "
                      "written against JAX 0.10-0.11): 'auto' attention takes the blocked kernel on NVIDIA GPUs "
                      "(memory bounded, slower); implementation='cudnn' still asks for cuDNN",
                      RuntimeWarning, stacklevel=2)
    if importlib.util.find_spec("libtpu") is not None:
        platforms.append("tpu")
    return tuple(platforms)


def _cuda_plugin_installed() -> bool:
    for name in ("jax_cuda12_plugin", "jax_cuda13_plugin"):
        try:
            if importlib.util.find_spec(name) is not None:
                return True
        except (ImportError, ValueError):  # a stand-in in sys.modules (app.xla_cpu): not for this process
            pass
    return False


def attention(q: jax.Array, k: jax.Array, v: jax.Array, key_bias: jax.Array | None = None, *,
              scale: float | None = None, implementation: str = "auto",
              block_bytes: int | None = None) -> jax.Array:
    """softmax(q k^T * scale + key_bias) v over tokens.

    q [B, Nq, H, D], k [B, Nk, H, D], v [B, Nk, H, Dv]; key_bias None or [B, Nk] (added
    to every query's logits; NEG_BIAS removes a key). Returns [B, Nq, H, Dv] in q's
    dtype. `scale` defaults to 1/sqrt(D); `implementation` names the kernel (`KERNELS`).
    """
    _check(implementation, q, k, v, key_bias)
    scale = 1.0 / math.sqrt(q.shape[-1]) if scale is None else float(scale)
    bias32 = None if key_bias is None else key_bias.astype(jnp.float32)
    block_bytes = blocked.LOGITS_BLOCK_BYTES if block_bytes is None else block_bytes
    return _dispatch(implementation, q, lambda name: functools.partial(
        KERNELS_BY_NAME[_usable(name)], q, k, v, bias32, scale, block_bytes))


def _usable(name: str) -> str:
    """Kernel `name`, or the blocked kernel (with a warning saying what is missing) where
    this JAX lacks what `name` calls of JAX's experimental or private modules (`_missing`)."""
    missing = _missing(name)
    if missing is None:
        return name
    warnings.warn(f"this JAX ({jax.__version__}) lacks what the {name!r} attention kernel calls ({missing}; "
                  "written against JAX 0.10-0.11): the blocked kernel runs instead (memory bounded, slower)",
                  RuntimeWarning, stacklevel=4)
    return "blocked"


@functools.cache
def _missing(name: str) -> str | None:
    """What of JAX's experimental or private API kernel `name`'s forward calls this JAX
    lacks, or None (cuDNN's forward is `jax.nn.dot_product_attention`, public)."""
    return tpu_flash_missing() if name == "tpu_flash" else None


def _check(implementation: str, q, k, v, key_bias) -> None:
    """The kernel name (for these operands' dtype) and the operands' shapes."""
    check_kernel(implementation, q.dtype)
    _check_operands(q, k, v, key_bias)


def _dispatch(implementation: str, q: jax.Array, run):
    """`run(name)()` for the kernel `implementation` names; for "auto", the kernel of each
    platform this installation can compile for (`kernel_for`), chosen when the program is
    lowered (`jax.lax.platform_dependent`)."""
    if implementation != "auto":
        return run(check_kernel(implementation, q.dtype))()
    branches = {}
    for platform in compilable_platforms():
        name = kernel_for(platform, q.dtype, q.shape[-1])
        if name != "blocked":
            branches[platform] = run(name)
    if not branches:
        return run("blocked")()
    return jax.lax.platform_dependent(cpu=run("blocked"), default=run("blocked"), **branches)


def attention_with_lse(q: jax.Array, k: jax.Array, v: jax.Array, key_bias: jax.Array | None, scale: float,
                       block_bytes: int | None = None, out_dtype: Any = None, *,
                       implementation: str = "auto") -> tuple[jax.Array, jax.Array]:
    """(attention [B, Nq, H, Dv] in `out_dtype` (default q's), the log-sum-exp of every
    query's logits [B, Nq, H] float32): what ring attention folds partial results with.
    The kernel is chosen as in `attention`, each in its log-sum-exp form: the blocked
    kernel's own; cuDNN's statistics (`kernels/fused.py`: JAX's cuDNN rules under a VJP
    that takes the log-sum-exp's cotangent); the Pallas TPU kernel's
    (`kernels/tpu_flash.py`, the same for its backward kernels). Differentiable in both
    outputs."""
    _check(implementation, q, k, v, key_bias)
    block_bytes = blocked.LOGITS_BLOCK_BYTES if block_bytes is None else block_bytes
    bias32 = None if key_bias is None else key_bias.astype(jnp.float32)
    out_dtype = q.dtype if out_dtype is None else out_dtype
    return _dispatch(implementation, q, lambda name: functools.partial(
        _with_lse, name, q, k, v, bias32, float(scale), block_bytes, out_dtype))


def _with_lse(name: str, q, k, v, bias32, scale: float, block_bytes: int, out_dtype):
    """Kernel `name`'s (attention in `out_dtype`, lse) on checked operands. The
    accelerator kernels' log-sum-exp forms call JAX-private functions: on a JAX without
    them, the blocked kernel (memory bounded, slower), with a warning."""
    if name != "blocked" and not _lse_available(name):
        missing = _lse_missing(name) or "its private functions"
        warnings.warn(f"this JAX ({jax.__version__}) lacks what the {name!r} kernel's log-sum-exp form calls "
                      f"({missing}; written against JAX 0.10-0.11): ring attention takes the blocked kernel",
                      RuntimeWarning, stacklevel=3)
        name = "blocked"
    out, lse = KERNELS_WITH_LSE_BY_NAME[name](q, k, v, bias32, scale, block_bytes, out_dtype)
    return out.astype(out_dtype), lse


def _lse_available(name: str) -> bool:
    return _lse_missing(name) is None


@functools.cache
def _lse_missing(name: str) -> str | None:
    """What of JAX's private API kernel `name`'s log-sum-exp form calls this JAX lacks, or
    None ("xla" and "blocked" call none)."""
    if name == "tpu_flash":
        return tpu_lse_missing()
    return cudnn_lse_missing() if name == "cudnn" else None


def _blocked(q, k, v, bias32, scale: float, block_bytes: int, out_dtype: Any = None):
    """The blocked kernel's (out, lse), its 16-bit operands held as bits only in a program
    compiled for a CPU (`blocked_attention`; the branch is chosen when the program is
    lowered for its platform, as `bits.on_cpu` does)."""
    return jax.lax.platform_dependent(
        cpu=lambda: blocked_attention(q, k, v, bias32, scale, block_bytes, out_dtype),
        default=lambda: blocked_attention(q, k, v, bias32, scale, block_bytes, out_dtype, bits=False))


# Each kernel by name, on checked operands (q, k, v, the float32 key bias or None, scale,
# the blocked kernel's logits block bytes): the attention in q's dtype ...
KERNELS_BY_NAME = {
    "blocked": lambda q, k, v, b, scale, bb: _blocked(q, k, v, b, scale, bb)[0].astype(q.dtype),
    "cudnn": lambda q, k, v, b, scale, bb: fused_attention(q, k, v, b, scale, "cudnn", NEG_BIAS),
    "xla": lambda q, k, v, b, scale, bb: fused_attention(q, k, v, b, scale, "xla", NEG_BIAS),
    "tpu_flash": lambda q, k, v, b, scale, bb: tpu_flash_attention(q, k, v, b, scale, NEG_BIAS),
}
# ... and with its log-sum-exp (plus the output dtype): (out, lse [B, Nq, H] float32)
KERNELS_WITH_LSE_BY_NAME = {
    "blocked": lambda q, k, v, b, scale, bb, dt: _blocked(q, k, v, b, scale, bb, dt),
    "cudnn": lambda q, k, v, b, scale, bb, dt: fused_attention_with_lse(q, k, v, b, scale, "cudnn", NEG_BIAS),
    "xla": lambda q, k, v, b, scale, bb, dt: fused_attention_with_lse(q, k, v, b, scale, "xla", NEG_BIAS),
    "tpu_flash": lambda q, k, v, b, scale, bb, dt: tpu_flash_attention_with_lse(q, k, v, b, scale, NEG_BIAS),
}


def _is_half(dtype: Any) -> bool:
    return jnp.dtype(dtype) in (jnp.dtype(jnp.bfloat16), jnp.dtype(jnp.float16))


def _check_operands(q, k, v, key_bias) -> None:
    if q.ndim != 4 or k.ndim != 4 or v.ndim != 4:
        raise ValueError(f"attention takes [B, N, H, D] operands; got {q.shape}, {k.shape}, {v.shape}")
    b, _, h, d = q.shape
    if k.shape[:3] != (b, k.shape[1], h) or v.shape[:3] != k.shape[:3] or k.shape[-1] != d:
        raise ValueError(f"attention operands disagree: q {q.shape}, k {k.shape}, v {v.shape}")
    if key_bias is not None and key_bias.shape != (b, k.shape[1]):
        raise ValueError(f"key_bias must be [B, Nk] = {(b, k.shape[1])}; got {key_bias.shape}")


def log_sizes(sizes: jax.Array, valid: jax.Array | None = None) -> jax.Array:
    """The size bias log g [B, Nk] (float32): log of the group sizes, NEG_BIAS for empty
    slots (g = 0)."""
    lg = jnp.log(jnp.maximum(sizes.astype(jnp.float32), 1.0))
    if valid is not None:
        lg = jnp.where(valid, lg, np.float32(NEG_BIAS))
    return lg
