"""Weights: upstream VGGT (PyTorch) checkpoints -> rvggt-jax parameter pytrees, and loading them.

- `upstream_state_dict_shapes(config)`: every upstream key and its shape.
- `RULES` / `find_rule` / `apply_rule`: the explicit key -> pytree-path conversion table.
- `CheckpointError`, `CheckpointFileError` (`rvggt_jax.weights.errors`, shared with `rvggt_jax.weights.checkpoint`).
- `convert_state_dict`, `load_safetensors`: convert (with one `CheckpointError` for all
  problems); `expected_param_shapes(config)`: our converted tree of `ShapeDtypeStruct`s.

Loading, in submodules not imported here: `rvggt_jax.weights.pretrained.load_pretrained`
(a hub repo id or a local path; `rvggt_jax.load_pretrained`), which uses
`rvggt_jax.weights.hub` (repo ids: download, convert once) and
`rvggt_jax.weights.checkpoint` (local checkpoints, Orbax save/load).
"""

from rvggt_jax.weights.converter import (
    MappingSource,
    SafetensorsSource,
    TensorSource,
    check_source,
    convert_state_dict,
    expected_param_paths,
    expected_param_shapes,
    flatten_params,
    load_safetensors,
    unflatten_params,
)
from rvggt_jax.weights.errors import CheckpointError, CheckpointFileError
from rvggt_jax.model.param_rules import RULES, Rule, apply_rule, find_rule
from rvggt_jax.model.params import upstream_state_dict_shapes



__all__ = [
    "CheckpointError",
    "CheckpointFileError",
    "MappingSource",
    "RULES",
    "Rule",
    "SafetensorsSource",
    "TensorSource",
    "apply_rule",
    "check_source",
    "convert_state_dict",
    "expected_param_paths",
    "expected_param_shapes",
    "find_rule",
    "flatten_params",
    "load_safetensors",
    "unflatten_params",
    "upstream_state_dict_shapes",
]
