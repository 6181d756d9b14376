"""Dataset readers for the evaluation: one module per on-disk format, each with
`NAME`, `list_scenes(root) -> [name]`, `read_scene(root, name, **options) -> Scene` and
`write(synthetic_scene, root) -> folder` (used by `rvggt_jax.synthetic.write_scene`).

    from rvggt_jax.eval.datasets import load_scenes
    scenes = load_scenes("7scenes", "/data/7scenes")     # [Scene], see base.Scene
"""

from __future__ import annotations

import importlib
from pathlib import Path
from types import ModuleType
from typing import Sequence

from rvggt_jax.eval.datasets.base import SAMPLING, DatasetError, Scene, sample_indices

__all__ = ["FORMATS", "SAMPLING", "DatasetError", "Scene", "get_format", "load_scenes", "sample_indices"]

FORMATS = {"7scenes": "sevenscenes", "nrgbd": "nrgbd", "scannet": "scannet", "tnt": "tnt", "dtu": "dtu",
           "folder": "folder", "images": "images", "co3d": "co3d", "kitti": "kitti", "tum": "tum"}
"""Dataset name -> module of this package. kitti and tum are long sequences (cameras
only); their modules also read and write bare trajectory files (`read_kitti_poses`,
`write_kitti_poses`, `read_tum_trajectory`, `write_tum_trajectory`)."""


def get_format(name: str) -> ModuleType:
    key = name.lower()
    if key not in FORMATS:
        raise DatasetError(f"unknown dataset {name!r}; known: {', '.join(FORMATS)}")
    return importlib.import_module(f"rvggt_jax.eval.datasets.{FORMATS[key]}")


def load_scenes(dataset: str, root: str | Path, scenes: Sequence[str] | None = None, **options) -> list[Scene]:
    """The scenes of `dataset` under `root` (all of them, or those named), unsampled."""
    fmt = get_format(dataset)
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"dataset folder not found: {root}")
    names = list(scenes) if scenes else fmt.list_scenes(root)
    return [fmt.read_scene(root, n, **options) for n in names]
