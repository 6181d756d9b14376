"""What the user sees on the terminal: messages on stdout (`say`, unless quiet) and
`rvggt: warning: ...` lines on stderr (`warn`), written without tearing a progress bar."""

from __future__ import annotations

import sys
from typing import Any

from rvggt_jax.app.messages import one_line

PROG = "rvggt"


def _write(text: str, file) -> None:
    """Print a line without tearing an active progress bar."""
    try:
        from tqdm.auto import tqdm

        tqdm.write(text, file=file)
        file.flush()
    except ImportError:  # pragma: no cover
        print(text, file=file, flush=True)


def say(quiet: bool, *parts: Any) -> None:
    if not quiet:
        _write(" ".join(map(str, parts)), sys.stdout)


def warn(msg: str) -> None:
    _write(f"{PROG}: warning: {one_line(msg, 1000)}", sys.stderr)
