"""Upstream VGGT (PyTorch) checkpoints -> rvggt-jax parameter pytrees.

- `upstream_state_dict_shapes(config)`: every upstream key and its shape.
- `RULES` / `find_rule` / `apply_rule`: the explicit key -> pytree-path conversion table.
- `convert_state_dict`, `load_safetensors`: convert (with one `CheckpointError` for all
  problems); `expected_param_shapes(config)`: our converted tree of `ShapeDtypeStruct`s.
- `main(argv)`: the `python -m convert SRC DST` command line.
"""

from convert.convert import (
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
from convert.rules import RULES, Rule, apply_rule, find_rule
from convert.shapes import upstream_state_dict_shapes
from rvggt_jax.checkpoint import CheckpointError


def main(argv=None) -> int:
    """`python -m convert SRC DST ...`; returns the exit status."""
    from convert.cli import main as _main

    return _main(argv)


__all__ = [
    "CheckpointError",
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
    "main",
    "unflatten_params",
    "upstream_state_dict_shapes",
]
