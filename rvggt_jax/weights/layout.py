"""The layout of the converted parameter tree: every path and shape a config implies,
derived through the rule table (`rules.py`) from upstream's state-dict shapes
(`shapes.py`). The model checks a tree against it (`model.inputs.check_params`) and the
converter and checkpoints build on it; like those two modules it imports only `config`
of the package, so the model may use it."""

from __future__ import annotations

from typing import Any, Mapping

from rvggt_jax.config import VGGTConfig
from rvggt_jax.weights.rules import Path as TreePath
from rvggt_jax.weights.rules import converted_shapes, find_rule
from rvggt_jax.weights.shapes import upstream_state_dict_shapes

__all__ = ["expected_param_paths", "flatten_params"]


def flatten_params(params: Mapping[str, Any], prefix: TreePath = ()) -> dict[TreePath, Any]:
    """Nested dicts -> {path tuple: leaf}."""
    flat: dict[TreePath, Any] = {}
    for k, v in params.items():
        if isinstance(v, Mapping):
            flat.update(flatten_params(v, prefix + (k,)))
        else:
            flat[prefix + (k,)] = v
    return flat


def expected_param_paths(config: VGGTConfig, *, skip_track: bool = False) -> dict[TreePath, tuple[int, ...]]:
    """{our path tuple: converted shape} for `config`, derived through the rule table."""
    flat: dict[TreePath, tuple[int, ...]] = {}
    for key, shape in upstream_state_dict_shapes(config, skip_track=skip_track).items():
        rule = find_rule(key)
        if rule is None:
            raise ValueError(f"no conversion rule for upstream key {key}")
        for path, s in converted_shapes(rule.kind, key, shape):
            if path in flat:
                raise ValueError(f"conversion rules write {'.'.join(path)} twice")
            flat[path] = s
    return flat
