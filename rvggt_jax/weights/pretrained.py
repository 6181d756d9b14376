"""`load_pretrained`: VGGT parameters from wherever they are named, a Hugging Face repo id
or a local checkpoint (`rvggt_jax.load_pretrained` is this function).

It is the one place that joins the two ways to a checkpoint: `rvggt_jax.weights.hub`
turns a repo id into a local (converted) folder, using `rvggt_jax.weights.checkpoint` to
convert it, and `rvggt_jax.weights.checkpoint.load_checkpoint` loads a local one. Neither
of them imports this module, so the three form no import cycle.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rvggt_jax.config import VGGTConfig
from rvggt_jax.weights.checkpoint import load_checkpoint
from rvggt_jax.weights.hub import is_repo_id, resolve_checkpoint

__all__ = ["BUNDLED", "bundled_path", "load_pretrained", "train_image_size"]

_EXAMPLES = Path(__file__).resolve().parents[1] / "examples_data"

BUNDLED = {
    # trained here from scratch on procedural scenes (rvggt_jax.train.small; its model card is
    # rvggt_jax/examples_data/rvggt_small/README.md)
    "rvggt-small": _EXAMPLES / "rvggt_small",
    # random weights, upstream's initialisation: the parity fixtures' model
    "tiny-random": _EXAMPLES / "tiny",
}
"""Reserved checkpoint names, resolved to folders shipped in the package (offline)."""


def train_image_size(model_dir: str | Path) -> tuple[int, int] | None:
    """The (H, W) a checkpoint folder's config.json says it was trained at
    ("train_image_size"), or None."""
    import json

    try:
        size = json.loads((Path(model_dir) / "config.json").read_text()).get("train_image_size")
    except (OSError, ValueError, AttributeError):
        return None
    return (int(size[0]), int(size[1])) if size else None


def bundled_path(name: str) -> Path:
    """The folder of a `BUNDLED` name; FileNotFoundError when the install lacks it."""
    path = BUNDLED[name]
    # rvggt-small is an Orbax folder (params/), tiny-random an upstream model.safetensors
    if not (path / "config.json").is_file() or not ((path / "params").is_dir() or (path / "model.safetensors").is_file()):
        raise FileNotFoundError(f"the bundled model {name!r} is missing from this install ({path}: no config.json "
                                "with params/ or model.safetensors); reinstall rvggt-jax")
    return path


def load_pretrained(path: str | Path, *, skip_track: bool = False, device_put: bool = True, progress: bool = False,
                    param_dtype: Any = "float32", verify: bool = False) -> tuple[dict, VGGTConfig]:
    """Load VGGT parameters -> `(params, config)`.

    `path` is a reserved name of `BUNDLED` ("rvggt-small": the small VGGT trained here
    and shipped in the package; "tiny-random"), a Hugging Face repo id such as `"facebook/VGGT-1B"` (not an existing local
    path: downloaded into the hub cache and converted once to an Orbax copy under
    `~/.cache/rvggt-jax/weights`, `rvggt_jax.weights.hub`; offline the caches are used, and
    `HubError` says what is missing), or a local checkpoint: a folder with
    `model.safetensors`, a `.safetensors` file or an Orbax folder, as
    `rvggt_jax.weights.checkpoint.load_checkpoint` takes them. The options are
    `load_checkpoint`'s: `skip_track=True` drops the track head, `device_put=False` keeps
    numpy leaves, `param_dtype="bfloat16"` stores the aggregator's weights in bfloat16
    (for `config.with_dtype("bfloat16")`), `verify=True` checks a converted copy's arrays
    against their recorded digests on this load (otherwise once per copy).
    """
    if isinstance(path, str) and path in BUNDLED:
        path = bundled_path(path)
    elif is_repo_id(path):
        path = resolve_checkpoint(path, progress=progress)
    return load_checkpoint(path, skip_track=skip_track, device_put=device_put, progress=progress,
                           param_dtype=param_dtype, verify=verify)
