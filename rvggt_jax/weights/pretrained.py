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

__all__ = ["load_pretrained"]


def load_pretrained(
    path: str | Path,
    *,
    skip_track: bool = False,
    device_put: bool = True,
    progress: bool = False,
    param_dtype: Any = "float32",
) -> tuple[dict, VGGTConfig]:
    """Load VGGT parameters -> `(params, config)`.

    `path` is one of:
      - a Hugging Face repo id such as `"facebook/VGGT-1B"` (not an existing local
        path): downloaded into the hub cache and converted once to an Orbax copy under
        `~/.cache/rvggt-jax/weights` (`rvggt_jax.weights.hub`; offline the caches are
        used; `HubError` says what is missing);
      - a folder with `model.safetensors` (+ optional `config.json`, else the layout
        is inferred from the shapes, `config_for_safetensors`);
      - a `.safetensors` file (a `config.json` beside it is used if present);
      - an Orbax folder written by `save_orbax` (`params/` + `config.json`), or its
        `params/` subfolder.
    The options are `rvggt_jax.weights.checkpoint.load_checkpoint`'s: upstream checkpoints
    are converted on the fly (checked first, one `CheckpointError` for every problem).
    `skip_track=True` drops the track head (and returns a config with
    `enable_track=False`). Leaves are float32 `jax.Array`s on the default device, or numpy
    arrays with `device_put=False`; `param_dtype="bfloat16"` stores the aggregator's
    weights in bfloat16 (half their memory; `cast_params`), for
    `config.with_dtype("bfloat16")`.
    """
    if is_repo_id(path):
        path = resolve_checkpoint(path, progress=progress)
    return load_checkpoint(path, skip_track=skip_track, device_put=device_put, progress=progress,
                           param_dtype=param_dtype)
