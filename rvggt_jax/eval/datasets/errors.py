"""`DatasetError`, the one error of the dataset readers, and `need_file`.

A leaf: it imports nothing of this package, so the Scene (`rvggt_jax.eval.datasets.base`,
which re-exports both) and the file readers it uses (`rvggt_jax.eval.datasets.ply`) can
both import it without an import cycle.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["DatasetError", "need_file"]


class DatasetError(ValueError):
    """A dataset folder is missing something or is malformed; the message names the file."""


def need_file(path: Path, what: str) -> Path:
    """`path` if it is a file, else a DatasetError naming it and what it should hold."""
    if not path.is_file():
        raise DatasetError(f"missing {what}: {path}")
    return path
