"""The checkpoint errors, shared by the converter and the loaders (`rvggt_jax.weights.checkpoint`).

This module imports nothing from rvggt_jax, so both sides can import it at module level
without an import cycle.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

__all__ = ["CheckpointError", "CheckpointFileError", "unreadable_message"]

_LIST_LIMIT = 10  # per category in error messages (the counts line gives the totals)


class CheckpointError(ValueError):
    """A checkpoint that does not match the layout expected for its config.

    Carries every problem at once: `missing` [(key, expected shape)], `unexpected` [key],
    `mismatched` [(key, shape, expected shape)], `bad_dtype` [(key, dtype)]; `summary`, the
    plain reason when one is known (e.g. config.json's embed_dim against the tensors'), is
    the message's first line."""

    def __init__(
        self,
        message: str | None = None,
        *,
        missing: Sequence[tuple[str, tuple]] = (),
        unexpected: Sequence[str] = (),
        mismatched: Sequence[tuple[str, tuple, tuple]] = (),
        bad_dtype: Sequence[tuple[str, str]] = (),
        summary: str | None = None,
    ):
        self.missing = list(missing)
        self.unexpected = list(unexpected)
        self.mismatched = list(mismatched)
        self.bad_dtype = list(bad_dtype)
        self.summary = summary
        super().__init__(message or self._describe())

    def _describe(self) -> str:
        counts = (
            f"{len(self.missing)} missing, {len(self.unexpected)} unexpected, "
            f"{len(self.mismatched)} with the wrong shape, {len(self.bad_dtype)} not floating point"
        )
        lines = [f"checkpoint does not match the VGGT layout of its config: {counts}"]
        if self.summary:
            lines = [self.summary, lines[0]]

        def section(title: str, items: list, fmt) -> None:
            if not items:
                return
            lines.append(f"{title}:")
            lines.extend(f"  {fmt(it)}" for it in items[:_LIST_LIMIT])
            if len(items) > _LIST_LIMIT:
                lines.append(f"  ... and {len(items) - _LIST_LIMIT} more")

        section("missing", self.missing, lambda t: f"{t[0]} (expected shape {tuple(t[1])})")
        section("unexpected", self.unexpected, str)
        section("wrong shape", self.mismatched, lambda t: f"{t[0]}: {tuple(t[1])}, expected {tuple(t[2])}")
        section("not floating point", self.bad_dtype, lambda t: f"{t[0]}: {t[1]}")
        return "\n".join(lines)


class CheckpointFileError(ValueError):
    """A checkpoint file that cannot be read at all (truncated, corrupt, not safetensors)."""


def unreadable_message(path: str | Path, e: Exception) -> str:
    """One line: `path` is not a readable safetensors file, and why."""
    size = Path(path).stat().st_size if Path(path).is_file() else 0
    return (f"{path} is not a readable .safetensors file: truncated or corrupt ({size} bytes; "
            f"{type(e).__name__}: {' '.join(str(e).split())}); download it again")
