"""The checks of a forward's inputs: images, query points, and a parameter tree against
the layout its config implies. Only static facts (rank, shape, dtype, paths) are errors, so
every check also works on tracers under `jax.jit`; each error is an `InputError` naming the
problem."""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from rvggt_jax.config import VGGTConfig
from rvggt_jax.errors import InputError
from rvggt_jax.model.input_range import warn_if_out_of_range
from rvggt_jax.model.params import Params, expected_param_paths, flatten_params


def _is_float(x: Any) -> bool:
    return jnp.issubdtype(jnp.result_type(x), jnp.floating)


def check_images(images: Any, config: VGGTConfig) -> jax.Array:
    """Validate and batch images: [S, 3, H, W] or [B, S, 3, H, W], float in [0, 1] or
    uint8 in [0, 255] -> [B, S, 3, H, W] (float32, or uint8 kept as it is: the program
    scales it, `unit_images`). Only static facts (rank, shape, dtype) are errors, so
    this also works on tracers under jit; float values outside [0, 1] or NaN are an
    `InputRangeWarning` (`warn_if_out_of_range`: at once for concrete arrays, from inside
    the program under jit)."""
    if isinstance(images, (list, tuple)):
        images = _stack_frames(images)
    shape = tuple(np.shape(images))
    if len(shape) not in (4, 5):
        raise InputError(f"images must be [S,3,H,W] or [B,S,3,H,W]; got rank {len(shape)} shape {shape}")
    dtype = jnp.result_type(images)
    if not (_is_float(images) or dtype == jnp.uint8):
        raise InputError(f"images must be a float array in [0, 1] or a uint8 array in [0, 255]; got dtype {dtype}")
    # a float image is legal whatever its values: only a warning (concrete arrays now, under
    # jit from inside the program); uint8 is in range by its type
    warn_if_out_of_range(images)
    if len(shape) == 4:
        images = images[None]
        shape = (1,) + shape
    b, s, c, h, w = shape
    if c != 3:
        raise InputError(f"images must have 3 (RGB) channels in axis -3; got {c} (shape {shape})")
    ps = config.patch_size
    if h % ps or w % ps:
        raise InputError(f"image height and width must be multiples of the patch size {ps}; got {h} x {w}")
    if min(b, s, h, w) == 0:
        raise InputError(f"images has an empty axis: shape {shape}")
    # uint8 stays uint8 into the program: a quarter of float32's argument bytes (0.57 of
    # 2.27 GiB at 1000 frames of 392 x 518), scaled where the patch embed reads it
    return jnp.asarray(images, jnp.uint8 if dtype == jnp.uint8 else jnp.float32)


def _stack_frames(frames: list | tuple) -> jax.Array:
    """A list of S frames [3, H, W] (arrays, or tracers under jit) -> one array [S, 3, H, W];
    `InputError` when they are no frames or differ in shape."""
    shapes = [tuple(np.shape(f)) if hasattr(f, "shape") else None for f in frames]
    if not frames or None in shapes or len(set(shapes)) != 1:
        got = "an empty list" if not frames else f"a list of shapes {shapes[:4]}{' ...' if len(shapes) > 4 else ''}"
        raise InputError(f"images must be one array [S,3,H,W] or [B,S,3,H,W] (or a list of arrays [3,H,W] "
                         f"of one shape); got {got}")
    return jnp.stack(frames)


QUERY_HELP = "query_points are pixel (x, y) in frame 0 of the network input, shape [N, 2] or [B, N, 2]"


def as_query_points(query_points: Any) -> jax.Array:
    """Query points as users write them -> [N, 2] or [B, N, 2] float32.

    A query point is a pixel (x, y) in frame 0 of the network input (the preprocessed
    image, e.g. 518 x 392, not the original photo): x to the right, y down, continuous.
    Lists, tuples, NumPy and JAX arrays of ints or floats are accepted (inside `jax.jit`
    a list arrives as a list of scalars); anything else is an `InputError` saying what
    was given."""
    if query_points is None or isinstance(query_points, (str, bytes, dict, set)):
        raise InputError(f"{QUERY_HELP}; got a {type(query_points).__name__}")
    try:
        qp = jnp.asarray(query_points)
    except (TypeError, ValueError) as e:
        raise InputError(f"{QUERY_HELP}; cannot read a {type(query_points).__name__} as numbers "
                         f"({' '.join(str(e).split())[:200]})") from None
    if qp.ndim not in (2, 3) or qp.shape[-1] != 2:
        raise InputError(f"{QUERY_HELP}; got shape {tuple(qp.shape)}")
    if qp.dtype == jnp.bool_ or not (jnp.issubdtype(qp.dtype, jnp.floating) or jnp.issubdtype(qp.dtype, jnp.integer)):
        raise InputError(f"{QUERY_HELP}; got dtype {qp.dtype}")
    if qp.shape[-2] == 0:
        raise InputError(f"{QUERY_HELP}; got no points (shape {tuple(qp.shape)}): pass at least one, "
                         f"or query_points=None for no tracks")
    _check_finite_points(qp)
    return qp.astype(jnp.float32)


def _check_finite_points(qp: jax.Array) -> None:
    """`InputError` naming the first NaN/inf point of `qp` [N, 2] or [B, N, 2] (a NaN
    point would poison the other points' tracks and every visibility). Traced values are
    unknown until the program runs: not checked."""
    try:
        host = np.asarray(qp)
    except jax.errors.TracerArrayConversionError:
        return
    bad = np.argwhere(~np.isfinite(host).all(-1))
    if len(bad):
        at = tuple(int(i) for i in bad[0])
        index = at[0] if len(at) == 1 else at
        raise InputError(f"{QUERY_HELP}; point {index} is {host[at].tolist()} ({len(bad)} non-finite in all): "
                         f"every coordinate must be a finite number")


def check_query_points(query_points: Any, batch: int) -> jax.Array:
    """`as_query_points`, then batched: [N, 2] or [B, N, 2] -> [B, N, 2] float32."""
    qp = as_query_points(query_points)
    if qp.ndim == 2:
        qp = qp[None]
    if qp.shape[0] != batch:
        if qp.shape[0] != 1:
            raise InputError(f"query_points batch {qp.shape[0]} does not match images batch {batch}")
        qp = jnp.broadcast_to(qp, (batch,) + qp.shape[1:])
    return qp


def check_params(params: Params, config: VGGTConfig) -> None:
    """Catch a config that does not describe these params before shapes fail deep inside:
    every parameter the config implies must be in the tree, with its shape (a static
    check of paths and shapes against the converter's layout; no tracing cost). A tree
    without `track_head` is a model without the track head (as `skip_track` loads it);
    extra entries are left alone."""
    try:
        width = params["aggregator"]["camera_token"].shape[-1]
    except (KeyError, TypeError) as e:
        raise InputError("params are not a converted VGGT tree (no aggregator.camera_token); "
                         f"{_layout_hint(config, _expected_params(config, True))}") from e
    if width != config.embed_dim:
        raise InputError(f"params have embed_dim {width} but config says {config.embed_dim}")
    want = _expected_params(config, "track_head" not in params)
    have = flatten_params(params)
    missing = [p for p in want if p not in have]
    wrong = [(p, tuple(np.shape(have[p])), s) for p, s in want.items()
             if p in have and tuple(np.shape(have[p])) != s]
    if not (missing or wrong):
        return
    lines = []
    if missing:
        present = {p[:i] for p in have for i in range(1, len(p) + 1)}
        roots = list(dict.fromkeys(next(p[:i] for i in range(1, len(p) + 1) if p[:i] not in present)
                                   for p in missing))
        lines.append("params lack " + "; ".join(_describe_missing(r, want) for r in roots[:8])
                     + (f"; and {len(roots) - 8} more" if len(roots) > 8 else ""))
    if wrong:
        lines.append("params with the wrong shape: " + "; ".join(
            f"{'.'.join(p)} {have_s}, expected {want_s}" for p, have_s, want_s in wrong[:8])
            + (f"; and {len(wrong) - 8} more" if len(wrong) > 8 else ""))
    parent = roots[0][:-1] if missing else wrong[0][0][:-1]
    raise InputError(". ".join(lines) + ". " + _layout_hint(config, want, parent))


@functools.lru_cache(maxsize=16)
def _expected_params(config: VGGTConfig, skip_track: bool) -> dict[tuple[str, ...], tuple[int, ...]]:
    """{path: shape} of the converted tree `config` implies (cached: a config is hashable)."""
    return expected_param_paths(config, skip_track=skip_track)


def _describe_missing(root: tuple[str, ...], want: dict) -> str:
    under = [p for p in want if p[:len(root)] == root]
    if len(under) == 1 and under[0] == root:
        return f"{'.'.join(root)} (shape {want[root]})"
    return f"{'.'.join(root)} (a sub-tree of {len(under)} parameters, e.g. {'.'.join(under[0])} {want[under[0]]})"


def _layout_hint(config: VGGTConfig, want: dict, parent: tuple[str, ...] = ()) -> str:
    """Which keys the config's layout expects at `parent` (top level by default)."""
    keys = sorted({p[len(parent)] for p in want if p[:len(parent)] == parent and len(p) > len(parent)})
    where = ".".join(parent) or "the top level"
    return (f"the converted VGGT layout for this config (embed_dim {config.embed_dim}, depth {config.depth}; "
            f"rvggt_jax.weights.converter.expected_param_shapes(config), as load_pretrained returns it) "
            f"has at {where}: {', '.join(keys)}")


def check_inputs(params: Params, images: Any, config: VGGTConfig, query_points: Any = None
                 ) -> tuple[jax.Array, jax.Array | None]:
    """The checks of a forward's inputs (config, params, images, query points): images as
    [B, S, 3, H, W], query points as [B, N, 2] or None; `InputError` naming the problem."""
    config.validate()
    check_params(params, config)
    images = check_images(images, config)
    if query_points is not None:
        if not config.enable_track or "track_head" not in params:
            raise InputError("query_points given but this model has no track head")
        query_points = check_query_points(query_points, images.shape[0])
    return images, query_points
