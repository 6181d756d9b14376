"""Upstream VGGT (PyTorch) checkpoints -> rvggt-jax parameter pytrees.

- `upstream_state_dict_shapes(config)`: every upstream key and its shape.
- `RULES` / `find_rule` / `apply_rule`: the explicit key -> pytree-path conversion table.
- `CheckpointError`, `CheckpointFileError` (`errors.py`, shared with `rvggt_jax.checkpoint`).
- `convert_state_dict`, `load_safetensors`: convert (with one `CheckpointError` for all
  problems); `expected_param_shapes(config)`: our converted tree of `ShapeDtypeStruct`s.
- `main(argv)`: the `python -m rvggt_jax.convert SRC DST` command line.
"""

from rvggt_jax.convert.convert import (
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
from rvggt_jax.convert.errors import CheckpointError, CheckpointFileError
from rvggt_jax.convert.rules import RULES, Rule, apply_rule, find_rule
from rvggt_jax.convert.shapes import upstream_state_dict_shapes


def main(argv=None) -> int:
    """`python -m rvggt_jax.convert SRC DST ...`; returns the exit status."""
    from rvggt_jax.convert.cli import main as _main

    return _main(argv)


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
    "main",
    "unflatten_params",
    "upstream_state_dict_shapes",
]
