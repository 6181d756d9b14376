"""Whitespace-separated text tables (trajectory files, timestamp lists, calibration
lines) read with errors that name the file and the line (a 4,000-line pose file with
one truncated line is otherwise hard to fix), and what the trajectory writers share."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rvggt_jax.eval.datasets.base import DatasetError, need_file

__all__ = ["as_extrinsics", "format_floats", "numbers", "read_rows"]


def read_rows(path: Path, what: str, fields: int | None = None) -> list[tuple[int, list[str]]]:
    """The lines of a text file that are neither blank nor `#` comments, split on
    whitespace, each with its 1-based line number. With `fields`, a line with another
    number of fields is a DatasetError naming `path:line`."""
    need_file(path, what)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise DatasetError(f"cannot read {what} {path}: {e}") from None
    rows = []
    for no, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        tokens = s.split()
        if fields is not None and len(tokens) != fields:
            raise DatasetError(f"{path}:{no}: {what} lines hold {fields} fields, this one {len(tokens)}: {s[:80]!r}")
        rows.append((no, tokens))
    return rows


def numbers(tokens: list[str], path: Path, line: int, what: str) -> np.ndarray:
    """`tokens` as float64 [N]; anything not a finite number is a DatasetError naming
    `path:line`."""
    try:
        a = np.array([float(t) for t in tokens], dtype=np.float64)
    except ValueError:
        raise DatasetError(f"{path}:{line}: {what}: not a number in {' '.join(tokens)[:80]!r}") from None
    if not np.isfinite(a).all():
        raise DatasetError(f"{path}:{line}: {what}: non-finite value in {' '.join(tokens)[:80]!r}")
    return a


def format_floats(values) -> str:
    """Floats joined by spaces, each as its shortest exact decimal (`repr`): a written
    file reads back bit for bit."""
    return " ".join(repr(float(v)) for v in np.asarray(values, np.float64).ravel())


def as_extrinsics(w2c) -> np.ndarray:
    """World-to-camera [S, 3, 4] or [S, 4, 4] (S >= 1, finite) as float64 [S, 3, 4];
    ValueError otherwise (a writer's input is a program's array, not a file)."""
    a = np.asarray(w2c, np.float64)
    if a.ndim != 3 or a.shape[1:] not in ((3, 4), (4, 4)) or len(a) < 1:
        raise ValueError(f"extrinsics must be [S, 3, 4] (or [S, 4, 4]) world-to-camera with S >= 1; got "
                         f"{list(a.shape)}")
    if not np.isfinite(a).all():
        raise ValueError("extrinsics hold non-finite values")
    return a[:, :3]
