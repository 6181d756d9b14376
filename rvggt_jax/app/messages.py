"""The one error format of every `rvggt` command:

    rvggt: error: <what went wrong, one line>
      <details, if any, indented two spaces: one per line>

`format_error` builds it; `CLIError` is a failure to report that way (exit status `code`).
"""

from __future__ import annotations

from typing import Any

__all__ = ["CLIError", "MAX_DETAIL_LINES", "format_error", "one_line"]

MAX_DETAIL_LINES = 250  # CheckpointError lists up to 50 keys in each of 4 sections


class CLIError(Exception):
    """A failure reported as `rvggt: error: <first line>` (+ indented detail lines)."""

    def __init__(self, message: str, code: int = 1):
        super().__init__(message)
        self.code = code


def one_line(msg: Any, limit: int = 400) -> str:
    """`msg` on one line, cut to about `limit` characters."""
    text = " ".join(str(msg).split())
    return text if len(text) <= limit else text[: limit - 3].rstrip() + "..."


def format_error(prog: str, message: str) -> str:
    """`prog: error: <first line of message>` and its further lines indented two
    spaces (at most MAX_DETAIL_LINES of them, then a count of the rest)."""
    lines = [ln.rstrip() for ln in str(message).strip().splitlines() if ln.strip()] or ["unknown error"]
    out = [f"{prog}: error: {one_line(lines[0], 1000)}"]
    rest = lines[1:]
    out += ["  " + ln for ln in rest[:MAX_DETAIL_LINES]]
    if len(rest) > MAX_DETAIL_LINES:
        out.append(f"  ... and {len(rest) - MAX_DETAIL_LINES} more lines")
    return "\n".join(out)
