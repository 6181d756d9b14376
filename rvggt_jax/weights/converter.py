"""Upstream VGGT state dict -> our parameter pytree (nested dicts of float32 arrays).

`load_safetensors` streams a `.safetensors` file tensor by tensor (peak memory about the
size of the file: each tensor is read, re-laid-out and the upstream copy dropped before
the next one is read). Both entry points check the whole checkpoint against
`upstream_state_dict_shapes(config)` *before* converting anything and raise one
`CheckpointError` listing every missing, unexpected, mis-shaped and non-float tensor.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Protocol, runtime_checkable

import ml_dtypes  # noqa: F401  (registers bfloat16 & co with numpy, needed for BF16 files)
import numpy as np

from rvggt_jax.config import VGGTConfig
from rvggt_jax.weights.errors import CheckpointError, CheckpointFileError, unreadable_message
from rvggt_jax.weights.integrity import check_finite
from rvggt_jax.model.param_rules import Path as TreePath
from rvggt_jax.model.param_rules import apply_rule, converted_shapes, find_rule
from rvggt_jax.model.params import expected_param_paths, flatten_params  # noqa: F401 (re-exported)
from rvggt_jax.model.params import upstream_state_dict_shapes
from rvggt_jax.model.params import Params

TRACK_PREFIX = "track_head."
PARAM_DTYPE = np.float32


# ---- tensor sources ------------------------------------------------------------------------


@runtime_checkable
class TensorSource(Protocol):
    """Lazy access to a state dict: metadata first, each tensor loaded on request."""

    def keys(self) -> Iterable[str]: ...

    def shape(self, key: str) -> tuple[int, ...]: ...

    def dtype(self, key: str) -> Any: ...  # a numpy dtype or a safetensors dtype string

    def get(self, key: str) -> np.ndarray: ...


class MappingSource:
    """A `Mapping[str, array-like]` as a `TensorSource` (values are read via `np.asarray`)."""

    def __init__(self, tensors: Mapping[str, Any]):
        self._t = tensors

    def keys(self) -> Iterable[str]:
        return list(self._t.keys())

    def shape(self, key: str) -> tuple[int, ...]:
        return tuple(int(d) for d in np.shape(self._t[key]))

    def dtype(self, key: str) -> Any:
        v = self._t[key]
        return np.dtype(v.dtype) if hasattr(v, "dtype") else np.asarray(v).dtype

    def get(self, key: str) -> np.ndarray:
        return np.asarray(self._t[key])


class SafetensorsSource:
    """A `.safetensors` file opened with `safe_open(framework="numpy")`; use as a context
    manager. Shapes and dtypes come from the header, tensors are read one at a time.

    `safe_open` memory-maps the file and `get_tensor` copies out of the map, so the
    pages read stay resident (and count in the process's RSS) until the map is closed:
    the file is therefore re-opened after every `remap_bytes` read, which keeps the
    peak at about one file size (our converted copy) instead of two."""

    def __init__(self, path: str | Path, *, remap_bytes: int = 64 << 20):
        self.path = Path(path)
        self.remap_bytes = remap_bytes
        self._ctx = self._f = None
        try:
            self._open()
            self._meta = {k: (self.shape_of(k), self._f.get_slice(k).get_dtype()) for k in self._f.keys()}
        except Exception as e:  # SafetensorError (truncated header, bad JSON, ...) names no file
            self.close()
            raise CheckpointFileError(unreadable_message(self.path, e)) from None

    def _open(self) -> None:
        from safetensors import safe_open

        self._ctx = safe_open(str(self.path), framework="numpy")
        self._f = self._ctx.__enter__()
        self._since_open = 0

    def shape_of(self, key: str) -> tuple[int, ...]:
        return tuple(int(d) for d in self._f.get_slice(key).get_shape())

    def __enter__(self) -> "SafetensorsSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._ctx is not None:
            self._ctx.__exit__(None, None, None)
            self._ctx = self._f = None

    def keys(self) -> Iterable[str]:
        return list(self._meta)

    def shape(self, key: str) -> tuple[int, ...]:
        return self._meta[key][0]

    def dtype(self, key: str) -> str:
        return self._meta[key][1]  # "F32", "BF16", "I64", ...

    def get(self, key: str) -> np.ndarray:
        if self._f is None:
            self._open()
        try:
            x = self._f.get_tensor(key)
        except Exception as e:  # data shorter than the header says: truncated
            raise CheckpointFileError(unreadable_message(self.path, e)) from None
        self._since_open += x.nbytes
        if self._since_open >= self.remap_bytes:
            self.close()  # drop the map (and its resident pages); reopened on the next get
        return x


def _is_floating(dtype: Any) -> bool:
    if isinstance(dtype, str):  # safetensors dtype code
        return dtype.startswith("F") or dtype == "BF16"
    try:
        ml_dtypes.finfo(np.dtype(dtype))
        return True
    except (TypeError, ValueError):
        return False


def _as_source(tensors: Mapping[str, Any] | TensorSource) -> TensorSource:
    if isinstance(tensors, Mapping):
        return MappingSource(tensors)
    if isinstance(tensors, TensorSource):
        return tensors
    raise TypeError(f"expected a Mapping[str, array] or a TensorSource, got {type(tensors).__name__}")


# ---- checking --------------------------------------------------------------------------------


def check_source(source: TensorSource, config: VGGTConfig, *, skip_track: bool = False) -> list[str]:
    """Keys of `source` to convert, in file order; raises one `CheckpointError` naming every
    missing, unexpected, mis-shaped and non-floating tensor (reads metadata only)."""
    expected = upstream_state_dict_shapes(config, skip_track=skip_track)
    keys = [k for k in source.keys() if not (skip_track and k.startswith(TRACK_PREFIX))]
    present = set(keys)
    missing = [(k, s) for k, s in expected.items() if k not in present]
    unexpected, mismatched, bad_dtype = [], [], []
    for k in keys:
        if k not in expected:
            unexpected.append(k)
            continue
        if find_rule(k) is None:  # a gap in the rule table, not in the checkpoint
            unexpected.append(f"{k} (no conversion rule)")
            continue
        shape = source.shape(k)
        if shape != expected[k]:
            mismatched.append((k, shape, expected[k]))
        dt = source.dtype(k)
        if not _is_floating(dt):
            bad_dtype.append((k, str(dt)))
    if missing or unexpected or mismatched or bad_dtype:
        from rvggt_jax.weights.orbax_meta import contradiction

        summary = contradiction(config, {k: source.shape(k) for k in keys}) if mismatched or missing else None
        raise CheckpointError(missing=missing, unexpected=unexpected, mismatched=mismatched, bad_dtype=bad_dtype,
                              summary=summary)
    return keys


# ---- trees -----------------------------------------------------------------------------------


def _insert(tree: dict, path: TreePath, leaf: Any) -> None:
    node = tree
    for p in path[:-1]:
        node = node.setdefault(p, {})
        if not isinstance(node, dict):
            raise ValueError(f"conversion rules put a leaf and a subtree at {'.'.join(path)}")
    if path[-1] in node:
        raise ValueError(f"conversion rules write {'.'.join(path)} twice")
    node[path[-1]] = leaf


def unflatten_params(flat: Mapping[TreePath, Any]) -> Params:
    tree: Params = {}
    for path, leaf in flat.items():
        _insert(tree, path, leaf)
    return tree


def expected_param_shapes(config: VGGTConfig, *, skip_track: bool = False) -> Params:
    """Our converted pytree for `config` with `jax.ShapeDtypeStruct(shape, float32)` leaves
    (for `jax.eval_shape`, Orbax restore targets, or `.shape` checks)."""
    import jax

    flat = expected_param_paths(config, skip_track=skip_track)
    return unflatten_params({p: jax.ShapeDtypeStruct(s, PARAM_DTYPE) for p, s in flat.items()})


# ---- conversion ------------------------------------------------------------------------------


def _to_param(x: np.ndarray) -> np.ndarray:
    """float32, C-contiguous, owning its memory when it had to be re-laid-out."""
    return np.ascontiguousarray(x, dtype=PARAM_DTYPE)


def convert_source(
    source: TensorSource,
    config: VGGTConfig,
    *,
    skip_track: bool = False,
    progress: bool = False,
    leaf_fn: Callable[[np.ndarray], Any] | None = None,
) -> Params:
    """Check then convert every tensor of `source`, one at a time.

    `leaf_fn` (e.g. `jax.device_put`) is applied to each converted leaf as soon as it
    exists, so the upstream copy and our numpy copy can be dropped right away. A tensor
    holding NaN or inf raises `NonFiniteWeightError` naming it."""
    keys = check_source(source, config, skip_track=skip_track)
    from tqdm.auto import tqdm

    tree: Params = {}
    with tqdm(total=len(keys), disable=not progress, unit="tensor", desc="converting") as bar:
        for key in keys:
            rule = find_rule(key)
            x = source.get(key)
            for path, y in apply_rule(rule.kind, key, x):
                y = _to_param(y)
                check_finite(y, f"{'.'.join(path)} (upstream {key})", getattr(source, "path", None))
                _insert(tree, path, leaf_fn(y) if leaf_fn is not None else y)
                del y
            del x
            bar.update(1)
    return tree


def convert_state_dict(
    tensors: Mapping[str, Any] | TensorSource,
    config: VGGTConfig | None = None,
    *,
    skip_track: bool = False,
    progress: bool = False,
) -> Params:
    """Upstream state dict -> our params pytree (nested dicts of float32 numpy arrays).

    `tensors`: a `Mapping[str, array-like]` (e.g. a dict of numpy arrays; values are
    fetched once each during conversion, so a lazy mapping works) or a `TensorSource`.
    `config` defaults to `VGGTConfig()` (VGGT-1B). `skip_track=True` ignores every
    `track_head.*` tensor and leaves the track head out of the result.
    Raises `CheckpointError` listing every missing / unexpected / mis-shaped / non-float key.
    """
    return convert_source(_as_source(tensors), config or VGGTConfig(), skip_track=skip_track, progress=progress)


def load_safetensors(
    path: str | Path,
    config: VGGTConfig | None = None,
    *,
    skip_track: bool = False,
    progress: bool = False,
    leaf_fn: Callable[[np.ndarray], Any] | None = None,
) -> Params:
    """Stream-convert an upstream `.safetensors` checkpoint to our params pytree.

    Peak memory is about the file size (tensor by tensor via
    `safetensors.safe_open(framework="numpy")`). See `convert_state_dict` for the checks."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such safetensors file: {path}")
    with SafetensorsSource(path) as src:
        return convert_source(src, config or VGGTConfig(), skip_track=skip_track, progress=progress, leaf_fn=leaf_fn)
