"""Head tests start from the fixture's aggregator outputs, so they need only a head's
parameter subtree: taken from the tiny checkpoint through the real converter."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Any, Iterable

import numpy as np
from safetensors.numpy import load_file

from rvggt_jax.weights.converter import load_safetensors
from rvggt_jax.config import VGGTConfig
from tests.helpers.paths import TINY


def load_io() -> dict[str, np.ndarray]:
    return load_file(str(TINY / "io.safetensors"))


@lru_cache(maxsize=4)
def _converted(path: Path) -> dict[str, Any]:
    return load_safetensors(path, VGGTConfig.from_json(path.parent / "config.json"))


def load_head_params(prefix: str, conv_transpose: Iterable[str] = (), path: Path = TINY / "model.safetensors"
                     ) -> dict[str, Any]:
    """The converted subtree at dotted `prefix` (e.g. "track_head.feature_extractor").
    `conv_transpose` is accepted for old call sites; the converter's rules know them."""
    tree = _converted(Path(path))
    for part in prefix.split("."):
        tree = tree[part]
    return tree


def load_track_params(path: Path = TINY / "model.safetensors", prefix: str = "track_head") -> dict[str, Any]:
    return load_head_params(prefix, path=path)
