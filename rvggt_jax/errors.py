"""The package's input error, in a module of its own so that parts that never touch the
model (`rvggt_jax.sequence`) raise the same exception as the model's input checks."""

from __future__ import annotations

__all__ = ["InputError"]


class InputError(ValueError):
    """Images, query points, or other inputs the package cannot take (the message says
    which, and what would be accepted)."""
