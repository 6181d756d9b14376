"""Are the numbers loaded the numbers meant? Two checks on a checkpoint's arrays, both on
the host with numpy, one array at a time as the arrays are loaded (an accelerator's array
is copied to the host one at a time for them; jitted reductions would cost a compile per
shape, seconds in all):

- finite: a NaN or inf weight makes every output NaN or constant without an error, so
  every load refuses one (`NonFiniteWeightError`, naming the tensor). 3-6 GB/s here
  (numpy's min and max, which propagate NaN, over each array): 15 ms for the tiny
  checkpoint, 1-2 s for VGGT-1B's 5.0 GB (its load takes ~28 s).
- digests: `save_orbax` records the SHA-256 of every array's float32 bytes in
  `digests.json` beside `config.json` (Orbax's zarr chunks carry no checksum of ours, so
  a flipped byte would load as a wrong weight). A load verifies them (`DigestMismatchError`
  naming the parameters) when asked (`verify=True`), and otherwise once per copy: a
  `.verified` marker records the sizes and mtimes of the files it verified, and while they
  are unchanged the hashing is skipped. 0.6-0.8 GB/s: 11 ms for the tiny checkpoint,
  ~7-8 s for VGGT-1B, at conversion and at the first load of each copy; later loads only
  stat the files (~80 ms for 5,400 files). A checkpoint written before digests existed
  (no `digests.json`) loads as before, unverified and without a warning.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from rvggt_jax.weights.errors import CheckpointFileError

__all__ = ["DIGESTS_NAME", "DigestMismatchError", "NonFiniteWeightError", "VERIFIED_NAME", "array_digest",
           "check_finite", "check_loaded", "write_digests"]

DIGESTS_NAME = "digests.json"
VERIFIED_NAME = ".verified"
_ALGORITHM = "sha256"
_NAMED = 5  # parameters named in an error message; the rest are counted


class NonFiniteWeightError(CheckpointFileError):
    """A checkpoint array holding NaN or inf (a damaged file, or diverged training)."""


class DigestMismatchError(CheckpointFileError):
    """A converted checkpoint whose arrays differ from the digests recorded when it was written."""


def host_array(leaf: Any) -> np.ndarray:
    """`leaf` (numpy or `jax.Array`) as a numpy array, without keeping a host copy on the
    `jax.Array` (`np.asarray` would cache one on an accelerator's array): a CPU array is
    viewed in place, an accelerator's is copied through the CPU device."""
    if isinstance(leaf, np.ndarray):
        return leaf
    import jax

    if isinstance(leaf, jax.Array) and any(d.platform != "cpu" for d in leaf.devices()):
        try:
            leaf = jax.device_put(leaf, jax.devices("cpu")[0])
        except RuntimeError:  # no CPU backend (JAX_PLATFORMS without cpu): the cached copy it is
            pass
    return np.asarray(leaf)


def nonfinite_count(x: np.ndarray) -> int:
    """How many entries of the float array `x` (any shape) are NaN or +-inf."""
    if x.size == 0:
        return 0
    if np.isfinite(x.min()) and np.isfinite(x.max()):  # NaN propagates; +-inf is the min or max
        return 0
    return int(x.size - np.count_nonzero(np.isfinite(x)))


def check_finite(x: np.ndarray, name: str, where: str | Path | None = None) -> None:
    """Raise `NonFiniteWeightError` naming `name` (and the checkpoint `where`) when the
    float array `x` holds NaN or inf."""
    n = nonfinite_count(x)
    if n:
        raise NonFiniteWeightError(_nonfinite_message([(name, n, x.size)], where))


def _nonfinite_message(bad: list[tuple[str, int, int]], where: str | Path | None) -> str:
    name, n, size = bad[0]
    head = (f"checkpoint {where}: " if where is not None else "") + (
        f"parameter {name} holds {n} NaN/inf value{'s' if n != 1 else ''} (of {size}): the file is damaged "
        f"or the weights diverged; refusing to load it")
    more = [f"also {nm}: {k} of {s}" for nm, k, s in bad[1:_NAMED]]
    if len(bad) > _NAMED:
        more.append(f"... and {len(bad) - _NAMED} more parameters")
    return "\n".join([head, *more])


def array_digest(x: np.ndarray) -> str:
    """Hex SHA-256 of the array's float32 bytes in C order (any shape)."""
    x = np.ascontiguousarray(x, dtype=np.float32)
    return hashlib.new(_ALGORITHM, x.reshape(-1).view(np.uint8)).hexdigest()


def write_digests(root: Path, flat: Mapping[tuple, Any]) -> None:
    """`root/digests.json`: {dotted path: digest} of the flat tree `flat` ({path tuple:
    array}); any `.verified` marker of an earlier copy is removed."""
    digests = {".".join(p): array_digest(host_array(v)) for p, v in flat.items()}
    (root / VERIFIED_NAME).unlink(missing_ok=True)
    (root / DIGESTS_NAME).write_text(json.dumps({"algorithm": _ALGORITHM, "dtype": "float32",
                                                 "params": digests}, indent=0, sort_keys=True))


def _fingerprint(root: Path, ckpt_dir: Path) -> str:
    """Digest of the (relative path, size, mtime) of every file of `ckpt_dir` and of
    `root/digests.json`: changes when any of them is rewritten, truncated or replaced."""
    entries = []
    for path in [str(root / DIGESTS_NAME)] + [os.path.join(d, f) for d, _, fs in os.walk(ckpt_dir) for f in fs]:
        st = os.stat(path)
        entries.append(f"{os.path.relpath(path, root)}\0{st.st_size}\0{st.st_mtime_ns}\n")
    return hashlib.sha256("".join(sorted(entries)).encode()).hexdigest()


def _verified(root: Path, ckpt_dir: Path, complete: bool) -> bool:
    try:
        mark = json.loads((root / VERIFIED_NAME).read_text())
        return mark["fingerprint"] == _fingerprint(root, ckpt_dir) and (mark["complete"] or not complete)
    except (OSError, ValueError, KeyError, TypeError):
        return False


def check_loaded(flat: Mapping[tuple, Any], root: Path, ckpt_dir: Path, *, verify: bool = False,
                 complete: bool = True) -> None:
    """Check the arrays just loaded from the Orbax folder `ckpt_dir` (its `config.json`
    and `digests.json` in `root`): all finite, and equal to the recorded digests when
    `verify` or when this copy has not been verified since its files last changed.
    `flat` is {path tuple: array}; `complete` says it holds every parameter of the
    checkpoint (a marker written after a partial load, e.g. without the track head, does
    not spare the next complete one). Raises `DigestMismatchError` / `NonFiniteWeightError`."""
    recorded = None
    if (root / DIGESTS_NAME).is_file() and (verify or not _verified(root, ckpt_dir, complete)):
        try:
            recorded = json.loads((root / DIGESTS_NAME).read_text())["params"]
        except (ValueError, KeyError, TypeError) as e:
            raise DigestMismatchError(f"checkpoint {root}: {DIGESTS_NAME} is unreadable ({e}); "
                                      f"convert it again") from None
    wrong, nonfinite = [], []
    for path, leaf in flat.items():
        name = ".".join(path)
        x = host_array(leaf)
        if recorded is not None and recorded.get(name) != array_digest(x):
            wrong.append(name)
        n = nonfinite_count(x)
        if n:
            nonfinite.append((name, n, x.size))
    if wrong:
        more = [f"also {n}" for n in wrong[1:_NAMED]]
        if len(wrong) > _NAMED:
            more.append(f"... and {len(wrong) - _NAMED} more")
        raise DigestMismatchError("\n".join([
            f"checkpoint {root}: parameter {wrong[0]} differs from the digest recorded when it was converted "
            f"({len(wrong)} parameter{'s' if len(wrong) != 1 else ''} in all): the files are damaged; convert it again",
            *more]))
    if nonfinite:
        raise NonFiniteWeightError(_nonfinite_message(nonfinite, root))
    if recorded is not None:
        try:
            (root / VERIFIED_NAME).write_text(json.dumps({"fingerprint": _fingerprint(root, ckpt_dir),
                                                          "complete": complete}))
        except OSError:  # a read-only copy is verified on every load instead
            pass
