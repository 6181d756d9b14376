"""What a converted (Orbax) checkpoint folder holds before it is restored, and what to say
when it does not fit or cannot be read:

- `stored_shapes(ckpt_dir)`: {path tuple: shape} from Orbax's `_METADATA` file (one small
  JSON read; Orbax's own metadata call opens every array and takes ~1 s).
- `contradiction(config, shapes)`: the one sentence a config.json that contradicts its
  tensors deserves ("config.json says embed_dim 2048; the tensors are 32 wide").
- `restore_error(ckpt_dir, e)`: a failed restore as one error; an unreadable chunk as one
  line naming the parameter.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path
from typing import Mapping

from rvggt_jax.config import VGGTConfig
from rvggt_jax.weights.errors import CheckpointError, CheckpointFileError

__all__ = ["contradiction", "quiet_closed_loop_stragglers", "restore_error", "stored_shapes"]

_WIDTH_KEY = "aggregator.camera_token"  # [1, 2, 1, embed_dim], in upstream's and our tree alike
_BLOCK = re.compile(r"^aggregator\.frame_blocks\.(\d+)\.")


def stored_shapes(ckpt_dir: Path) -> dict[tuple, tuple[int, ...]] | None:
    """{path tuple: shape} of the arrays in the Orbax folder `ckpt_dir`, from its
    `_METADATA`; None when that file is absent or not in the layout known here (the
    restore then checks the shapes itself)."""
    try:
        tree = json.loads((ckpt_dir / "_METADATA").read_text())["tree_metadata"]
        out = {}
        for entry in tree.values():
            path = tuple(str(k["key"]) for k in entry["key_metadata"])
            shape = entry["value_metadata"].get("write_shape")
            if shape is None:  # saved from numpy leaves: the shape is in the array's zarr header
                shape = _zarr_shape(ckpt_dir / ".".join(path))
            out[path] = tuple(int(d) for d in shape)
        return out
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _zarr_shape(array_dir: Path) -> list[int]:
    """The shape in a zarr v2 (`.zarray`) or v3 (`zarr.json`) array header."""
    for name in (".zarray", "zarr.json"):
        if (array_dir / name).is_file():
            return json.loads((array_dir / name).read_text())["shape"]
    raise KeyError(f"no zarr header in {array_dir}")


def contradiction(config: VGGTConfig, shapes: Mapping[str, tuple]) -> str | None:
    """The plain reason a config.json does not fit tensors of `shapes` ({dotted name:
    shape}, upstream keys or our paths): its embed_dim or depth against the tensors'. None
    when both agree (the mismatch is elsewhere: the detail list says where)."""
    width = shapes.get(_WIDTH_KEY)
    if width and width[-1] != config.embed_dim:
        return f"config.json says embed_dim {config.embed_dim}; the tensors are {width[-1]} wide"
    blocks = {int(m.group(1)) for k in shapes if (m := _BLOCK.match(k))}
    if blocks and len(blocks) != config.depth:
        return f"config.json says depth {config.depth}; the tensors hold {len(blocks)} frame blocks"
    return None


def restore_error(ckpt_dir: Path, e: Exception) -> Exception:
    """The error to raise for an Orbax restore of `ckpt_dir` that failed with `e`: a chunk
    tensorstore could not read (it names the file, under `ckpt_dir/<parameter>/`) is a
    one-line `CheckpointFileError` naming the parameter; a tree or shape Orbax found
    different from config.json's (when `stored_shapes` could not tell beforehand) a
    `CheckpointError` with the first lines of Orbax's account."""
    quiet_closed_loop_stragglers()  # (again: a test runner may have reset the hook)
    text = str(e)
    m = re.search(re.escape(str(ckpt_dir)) + r"/([^/'\"\s]+)", text)
    if m:
        line = next((ln for ln in text.splitlines() if m.group(1) in ln and "rror" in ln), "")
        why = f" ({' '.join(line.split())[:300]})" if line else ""
        return CheckpointFileError(
            f"converted checkpoint {ckpt_dir.parent}: parameter {m.group(1)} cannot be read{why}: "
            f"its file under {ckpt_dir / m.group(1)} is truncated or corrupt; convert the checkpoint again")
    lines = [ln for ln in text.splitlines() if ln.strip()]
    if isinstance(e, ValueError):
        more = [f"... and {len(lines) - 10} more lines"] if len(lines) > 10 else []
        return CheckpointError("\n".join([f"converted checkpoint {ckpt_dir.parent} does not match its config.json:",
                                          *(" ".join(ln.split())[:300] for ln in lines[:10]), *more]))
    return CheckpointFileError(f"converted checkpoint {ckpt_dir.parent} cannot be read ({type(e).__name__}: "
                               f"{' '.join(text.split())[:300]}); convert the checkpoint again")


def quiet_closed_loop_stragglers() -> None:
    """After a failed restore, Orbax's remaining reads finish on threads whose asyncio loop
    is gone, each reporting an unraisable `RuntimeError('Event loop is closed')`
    (thousands of tracebacks, some before the error reaches us, most after it): drop
    those, pass on the rest. Installed before each restore, kept for the process."""
    previous = sys.unraisablehook
    if getattr(previous, "_rvggt_closed_loop_filter", False):
        return

    def hook(u):
        if isinstance(u.exc_value, RuntimeError) and str(u.exc_value) == "Event loop is closed":
            return
        previous(u)

    hook._rvggt_closed_loop_filter = True
    sys.unraisablehook = hook
