"""Type aliases shared by the package (this module imports nothing of rvggt_jax, so any
module can import it without an import cycle)."""

from typing import Any, Mapping

__all__ = ["Params"]

# A parameter pytree: nested {name: sub-tree or array} in the converter's layout
# (rvggt_jax/weights/rules.py). Defined once here; every module imports this one.
Params = Mapping[str, Any]
