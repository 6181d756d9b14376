"""Stand-in for the converter (convert/) in the track-head tests: the `track_head` subtree
of the tiny upstream checkpoint as our parameter pytree, by the rules of
docs/conventions.md. Replace with the real converter once the model loader covers it.

Handled: Linear (weight [out, in] -> kernel [in, out]), nn.MultiheadAttention
(in_proj_weight [3E, E] / in_proj_bias -> q, k, v Linears; out_proj is a Linear),
LayerNorm / GroupNorm (weight -> scale), Conv2d (OIHW -> HWIO), ConvTranspose2d
(IOHW -> HWIO, the DPT `resize_layers.0/1`), raw parameters (query_ref_token,
virual_tracks) unchanged.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np
from safetensors.numpy import load_file

DATA = Path(__file__).parent / "data" / "vggt_tiny"

_RAW_LEAVES = {"query_ref_token", "virual_tracks"}
_CONV_TRANSPOSE = {"feature_extractor.resize_layers.0", "feature_extractor.resize_layers.1"}


def load_track_params(path: Path = DATA / "model.safetensors", prefix: str = "track_head") -> dict[str, Any]:
    """Every `prefix.*` tensor of an upstream checkpoint, converted; keys relative to prefix."""
    state = load_file(str(path))
    sub = {k[len(prefix) + 1:]: v for k, v in state.items() if k.startswith(prefix + ".")}
    if not sub:
        raise KeyError(f"no tensors under {prefix!r}")
    return convert_track_subtree(sub)


def convert_track_subtree(state: Mapping[str, np.ndarray]) -> dict[str, Any]:
    """Upstream keys (relative to the track head) -> nested dict of our float32 leaves."""
    tree: dict[str, Any] = {}

    def put(path: list[str], leaf: str, value: np.ndarray) -> None:
        node = tree
        for part in path:
            node = node.setdefault(part, {})
        if leaf in node:
            raise ValueError(f"duplicate leaf {'.'.join(path + [leaf])}")
        node[leaf] = np.ascontiguousarray(value, np.float32)

    for key, v in state.items():
        *path, leaf = key.split(".")
        module = ".".join(path)
        v = np.asarray(v, np.float32)
        if leaf in _RAW_LEAVES:
            put(path, leaf, v)
        elif leaf in ("in_proj_weight", "in_proj_bias"):
            e = v.shape[0] // 3
            for i, name in enumerate("qkv"):
                rows = v[i * e:(i + 1) * e]
                if leaf == "in_proj_weight":
                    put(path + [name], "kernel", rows.T)
                else:
                    put(path + [name], "bias", rows)
        elif leaf == "bias":
            put(path, "bias", v)
        elif leaf == "weight" and v.ndim == 1:
            put(path, "scale", v)
        elif leaf == "weight" and v.ndim == 2:
            put(path, "kernel", v.T)
        elif leaf == "weight" and v.ndim == 4:
            perm = (2, 3, 0, 1) if module in _CONV_TRANSPOSE else (2, 3, 1, 0)
            put(path, "kernel", v.transpose(perm))
        else:
            raise ValueError(f"no conversion rule for {key} {v.shape}")
    return tree
