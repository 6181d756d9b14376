"""Stand-in for the converter (convert/) in the head tests: turns a subtree of an upstream
state dict into our parameter pytree by the rules of docs/conventions.md.

Only what the camera and DPT heads contain is handled (Linear, fused qkv, LayerNorm,
Conv2d, ConvTranspose2d, raw parameters). Replace with the real converter once it exists.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np
from safetensors.numpy import load_file

DATA = Path(__file__).parent / "data" / "vggt_tiny"

# Leaf names that upstream stores as nn.Parameter and we keep as they are.
_RAW = {"gamma", "empty_pose_tokens", "pos_embed", "cls_token", "camera_token", "register_token"}


def load_io() -> dict[str, np.ndarray]:
    return load_file(str(DATA / "io.safetensors"))


def load_head_params(prefix: str, conv_transpose: Iterable[str] = ()) -> dict[str, Any]:
    """Convert every `prefix.*` tensor of the tiny fixture; `conv_transpose` lists module
    paths (relative to prefix) that are nn.ConvTranspose2d."""
    state = load_file(str(DATA / "model.safetensors"))
    sub = {k[len(prefix) + 1:]: v for k, v in state.items() if k.startswith(prefix + ".")}
    if not sub:
        raise KeyError(f"no tensors under {prefix!r}")
    return convert_subtree(sub, set(conv_transpose))


def convert_subtree(state: Mapping[str, np.ndarray], conv_transpose: set[str]) -> dict[str, Any]:
    """Upstream keys relative to one module -> nested dict of our leaves."""
    tree: dict[str, Any] = {}
    for key, value in _split_qkv(state).items():
        *path, leaf = key.split(".")
        name, array = _convert_leaf(".".join(path), leaf, np.asarray(value, np.float32), conv_transpose)
        node = tree
        for part in path:
            node = node.setdefault(part, {})
        node[name] = array
    return tree


def _convert_leaf(module: str, leaf: str, v: np.ndarray, conv_transpose: set[str]):
    """(our leaf name, array) for one upstream leaf of `module`."""
    if leaf in _RAW:
        return leaf, v
    if leaf == "bias":
        return "bias", v
    if leaf == "weight" and v.ndim == 1:  # LayerNorm / GroupNorm
        return "scale", v
    if leaf == "weight" and v.ndim == 2:  # Linear [out, in]
        return "kernel", np.ascontiguousarray(v.T)
    if leaf == "weight" and v.ndim == 4:  # Conv2d [O, I, kh, kw] / ConvTranspose2d [I, O, kh, kw]
        perm = (2, 3, 0, 1) if module in conv_transpose else (2, 3, 1, 0)
        return "kernel", np.ascontiguousarray(v.transpose(perm))
    raise ValueError(f"no conversion rule for {module}.{leaf} {v.shape}")


def _split_qkv(state: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Rewrite `*.attn.qkv.{weight,bias}` into `*.attn.{q,k,v}.{weight,bias}` rows."""
    out = {}
    for key, v in state.items():
        *path, leaf = key.split(".")
        if path[-2:] == ["attn", "qkv"]:
            base = ".".join(path[:-1])
            c = v.shape[0] // 3
            for i, name in enumerate("qkv"):
                out[f"{base}.{name}.{leaf}"] = v[i * c:(i + 1) * c]
        else:
            out[key] = v
    return out
