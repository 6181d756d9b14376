"""The output folder of a run: checked before any slow step, never mixed with an
earlier run, and a user's own files in it never deleted.

- `prepare_output(out, overwrite)`: create `out` (or fail now, not after inference);
  refuse a non-empty folder unless `overwrite`; with `overwrite`, delete exactly the
  files the previous run listed in its manifest, and nothing else.
- `Manifest(out)`: snapshot the folder, then `write()` records every file created or
  changed since, in `out/MANIFEST_NAME` (written even when the run fails half-way, so the
  next `--overwrite` can clean it up).
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path
from typing import Iterator

__all__ = ["LOCK_NAME", "MANIFEST_NAME", "Manifest", "OutputDirError", "output_lock", "prepare_output"]

MANIFEST_NAME = ".rvggt-manifest.json"
LOCK_NAME = ".rvggt-lock"  # held (flock) by the run writing the folder; never listed or counted


class OutputDirError(ValueError):
    """An output folder that cannot be used (the message says why and what to do)."""


def _files(root: Path) -> dict[str, tuple[int, int]]:
    """Every file under `root` (relative POSIX path) -> (mtime_ns, size)."""
    out = {}
    for dirpath, _, names in os.walk(root):
        for n in names:
            if n == LOCK_NAME and Path(dirpath) == root:
                continue
            p = Path(dirpath) / n
            try:
                st = p.stat()
            except OSError:
                continue
            out[p.relative_to(root).as_posix()] = (st.st_mtime_ns, st.st_size)
    return out


def _check_path(out: str | os.PathLike) -> Path:
    """`out` as a Path; `OutputDirError` when it is a file, or a file stands in its path."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OutputDirError(f"output path exists and is not a folder: {out}")
    blocker = _first_existing_file_ancestor(out.parent)
    if blocker is not None:
        raise OutputDirError(f"cannot create output folder {out}: {blocker} is a file, not a folder")
    return out


def _first_existing_file_ancestor(p: Path) -> Path | None:
    for q in [p, *p.parents]:
        if q.exists():
            return None if q.is_dir() else q
    return None


def _remove_previous(out: Path) -> int:
    """Delete the files the previous run's manifest lists (only files inside `out`),
    then the folders that became empty; returns how many files were deleted."""
    mf = out / MANIFEST_NAME
    try:
        listed = json.loads(mf.read_text())["files"]
    except (OSError, ValueError, KeyError, TypeError):
        listed = []
    root = out.resolve()
    removed, dirs = 0, set()
    for rel in listed:
        p = (out / rel)
        try:
            if not p.resolve().is_relative_to(root) or not p.is_file():
                continue  # a manifest entry pointing outside, or already gone
            p.unlink()
            removed += 1
            dirs.update(q for q in p.parents if q != out and q.resolve().is_relative_to(root))
        except OSError:
            continue
    for d in sorted(dirs, key=lambda q: len(q.parts), reverse=True):
        try:
            d.rmdir()  # only when empty: a user's file keeps its folder
        except OSError:
            pass
    mf.unlink(missing_ok=True)
    return removed


def prepare_output(out: str | os.PathLike, overwrite: bool = False) -> int:
    """Make `out` ready to receive a run's files, before anything slow happens.

    Creates it (with parents) and checks that a file can be written in it. A folder
    that already holds entries is refused unless `overwrite`; then the files listed in
    the previous run's manifest are deleted (returned: how many) and nothing else.
    Raises OutputDirError with a one-line reason."""
    out = _check_path(out)
    removed = 0
    if out.is_dir():
        entries = sorted(e for e in os.listdir(out) if e != LOCK_NAME)
        if entries and not overwrite:
            ours = (out / MANIFEST_NAME).is_file()
            raise OutputDirError(
                f"output folder {out} is not empty ({len(entries)} entr{'y' if len(entries) == 1 else 'ies'}"
                f"{', from an earlier run' if ours else ''}): pass --overwrite to replace "
                f"{'that run' if ours else 'files of the same names'} (your other files stay), or choose another folder")
        if entries:
            removed = _remove_previous(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=out, prefix=".rvggt-write-test-"):
            pass
    except OSError as e:
        raise OutputDirError(f"cannot write to output folder {out}: {e.strerror or e}") from None
    return removed


@contextlib.contextmanager
def output_lock(out: str | os.PathLike) -> Iterator[None]:
    """Hold the folder `out` (created if needed) for one run: an exclusive `flock` on
    `out/LOCK_NAME`, so that a second run into the same folder is refused at once
    (`OutputDirError` naming the other run's process) instead of mixing its files with
    this run's. The lock file stays (empty of meaning once unlocked): removing it could
    let a third run lock a new file while a second holds the old one."""
    out = _check_path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        fd = os.open(out / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as e:
        raise OutputDirError(f"cannot create output folder {out}: {e.strerror or e}") from None
    try:
        try:
            import fcntl
        except ImportError:  # not POSIX: no lock (the emptiness check still applies)
            fcntl = None
        if fcntl is not None:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 32, 0).decode(errors="replace").strip()
                raise OutputDirError(f"another rvggt run{f' (process {holder})' if holder else ''} is writing to "
                                     f"{out}: wait for it to end, or choose another folder") from None
            os.ftruncate(fd, 0)
            os.pwrite(fd, str(os.getpid()).encode(), 0)
        yield
    finally:
        os.close(fd)  # releases the lock


def remove_if_unused(out: str | os.PathLike) -> None:
    """Remove `out` when it holds nothing but a lock file (a run that failed before
    writing anything leaves no folder behind)."""
    out = Path(out)
    try:
        if set(os.listdir(out)) <= {LOCK_NAME}:
            (out / LOCK_NAME).unlink(missing_ok=True)
            out.rmdir()
    except OSError:
        pass


class Manifest:
    """Records which files of `out` a run wrote: everything new or changed between
    construction and `write()` (the manifest file itself excluded)."""

    def __init__(self, out: str | os.PathLike, carry: bool = False):
        """carry: also list the files the previous manifest in `out` lists that still
        exist (a resumed run: what the stopped run wrote stays its to delete)."""
        self.out = Path(out)
        self.before = _files(self.out)
        self.carried: set[str] = set()
        if carry:
            try:
                self.carried = set(json.loads((self.out / MANIFEST_NAME).read_text())["files"])
            except (OSError, ValueError, KeyError, TypeError):
                self.carried = set()

    def written(self) -> list[str]:
        now = _files(self.out)
        return sorted(k for k, v in now.items()
                      if k != MANIFEST_NAME and (self.before.get(k) != v or k in self.carried))

    def write(self) -> list[str]:
        """Record the files written since construction; a run that wrote nothing (it
        failed before any output) leaves no manifest, so the folder stays reusable."""
        files = self.written()
        if not files:
            (self.out / MANIFEST_NAME).unlink(missing_ok=True)
            return files
        (self.out / MANIFEST_NAME).write_text(json.dumps(
            dict(note="files written by the last rvggt run here; `--overwrite` deletes exactly these", files=files),
            indent=1) + "\n")
        return files
