"""A warning for images outside the network's input range: `warn_if_out_of_range`.

The model takes images in [0, 1]; a float image in 0..255 (a forgotten `/ 255`) or with
NaN runs without error and gives a wrong answer. A float image is legal, so only its
values tell: concrete arrays (NumPy, JAX arrays outside `jax.jit`) are checked at once;
under `jax.jit` the check is part of the compiled program (three fused reductions, a
further pass only for images holding NaN, and a `jax.debug.callback` that warns on the host), so it
costs no second compile and no host sync in the caller.

Except with JAX's persistent compilation cache on (`jax_compilation_cache_dir` set, as
`rvggt` sets it): JAX never writes a program holding a host callback to that cache (the
callback's address is baked into it), so the check would silently cost a full compile in
every new process, minutes for VGGT-1B on a GPU. There the traced program goes without
it; check concrete images before the call (`warn_if_out_of_range(images)`), as the
pipeline does.
"""

from __future__ import annotations

import functools
import warnings
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["InputRangeWarning", "warn_if_out_of_range", "range_message", "program_check_enabled"]

LOW, HIGH = 0.0, 1.0


class InputRangeWarning(UserWarning):
    """Images with values outside [0, 1] or NaN: the model's outputs are not meaningful."""


def range_message(lo: float, hi: float, nans: int) -> str | None:
    """The warning text for images of min `lo`, max `hi` (NaN ignored) and `nans` NaN
    values; None when they are in range."""
    problems = []
    if nans:
        problems.append(f"{int(nans)} NaN value(s)")
    if lo <= hi and (lo < LOW or hi > HIGH):  # (lo > hi: every value is NaN)
        problems.append(f"values in [{lo:.4g}, {hi:.4g}]")
    if not problems:
        return None
    hint = " (0..255 pixel values? divide by 255)" if hi > 2.0 else ""
    return (f"images have {' and '.join(problems)}; the model expects float RGB in [{LOW:g}, {HIGH:g}]"
            f"{hint}: its outputs will not be meaningful")


def _warn(lo, hi, nans) -> None:
    msg = range_message(float(lo), float(hi), int(nans))
    if msg is not None:
        warnings.warn(msg, InputRangeWarning, stacklevel=2)


def _stats(xp, x):
    """(min, max ignoring NaN, NaN count); an all-NaN array has min +inf / max -inf."""
    nan = xp.isnan(x)
    return (xp.min(xp.where(nan, xp.inf, x)), xp.max(xp.where(nan, -xp.inf, x)), xp.sum(nan))


def _traced_stats(x: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """`_stats` of a traced array: the NaN count, then plain min and max (XLA fuses the
    three reductions into one pass), and only for an array holding NaN the NaN-aware pass
    (a `lax.cond`). The count is explicit because XLA's CPU min/max do not propagate NaN
    for every shape (a [2, 3, 28, 28] array with one NaN: finite min and max, no warning).
    (`_stats` traced as it is makes three more passes over the images, each materialising
    a select or an int32 mask; in a 64-frame forward they overlapped other work, and the
    wall time did not measurably change.)"""
    nans = jnp.sum(jnp.isnan(x), dtype=jnp.int32)
    return jax.lax.cond(nans > 0, lambda: _stats(jnp, x), lambda: (jnp.min(x), jnp.max(x), nans))


@functools.lru_cache(maxsize=None)
def _has_client(platform: str) -> bool:
    try:
        return bool(jax.devices(platform))
    except RuntimeError:
        return False


def program_check_enabled() -> bool:
    """Whether a traced forward holds the range check: not when JAX's persistent
    compilation cache is on (it does not store programs with host callbacks)."""
    return not (jax.config.jax_enable_compilation_cache and jax.config.jax_compilation_cache_dir)


def _in_program(images: jax.Array) -> None:
    """The check as part of the traced program (see `program_check_enabled`). A host
    callback can only be lowered for a platform this process has a client for; a program
    lowered for another one (a deviceless compile for a GPU or TPU, `rvggt plan`) goes
    without the check, chosen per platform at lowering time (`lax.platform_dependent`),
    so it still lowers."""
    if not program_check_enabled():
        return

    def check(x):
        jax.debug.callback(_warn, *_traced_stats(x.astype(jnp.float32)))

    def skip(x):
        return None

    jax.lax.platform_dependent(images, default=skip,
                               **{p: check for p in ("cpu", "cuda", "rocm", "tpu") if _has_client(p)})


def warn_if_out_of_range(images: Any) -> None:
    """Warn (`InputRangeWarning`) when float `images` (any shape) hold values outside
    [0, 1] or NaN. Concrete arrays are checked now; a tracer (under `jax.jit`, `grad`,
    `shard_map`) gets the check inside its program, reported by `jax.debug.callback` when
    the program runs, unless the persistent compilation cache is on
    (`program_check_enabled`). Integer images are not checked (their scaling is the
    caller's)."""
    if not jnp.issubdtype(jnp.result_type(images), jnp.floating) or 0 in np.shape(images):
        return  # (an empty array is the shape check's to refuse)
    if isinstance(images, jax.core.Tracer):
        _in_program(images)
        return
    if isinstance(images, jax.Array):
        # (eagerly even when a traced function closes over the array: under a trace, jnp
        # on a concrete array would be staged into the program)
        with jax.ensure_compile_time_eval():
            lo, hi, nans = jax.device_get(_stats(jnp, images.astype(jnp.float32)))
    else:
        lo, hi, nans = _stats(np, np.asarray(images, np.float32))
    msg = range_message(float(lo), float(hi), int(nans))
    if msg is not None:
        warnings.warn(msg, InputRangeWarning, stacklevel=5)  # the caller of rvggt_forward
