"""A folder of images without any ground truth (for `rvggt eval --against dense`):
ROOT holds the images (one scene), or sub-folders of images (one scene each)."""

from __future__ import annotations

from pathlib import Path

from rvggt_jax.eval.datasets.base import DatasetError, Scene

NAME = "images"


def _images(d: Path) -> list[Path]:
    from rvggt_jax.io.images import find_images

    return find_images(d)[0]


def list_scenes(root: Path) -> list[str]:
    if _images(root):
        return ["."]
    names = sorted(p.name for p in root.iterdir() if p.is_dir() and _images(p))
    if not names:
        raise DatasetError(f"no images in {root} or its sub-folders")
    return names


def read_scene(root: Path, name: str, **_) -> Scene:
    d = root / name
    if not d.is_dir():
        raise DatasetError(f"missing image folder: {d}")
    paths = _images(d)
    if not paths:
        raise DatasetError(f"no images in {d}")
    return Scene(NAME, name if name != "." else root.resolve().name, paths, None, None, [p.stem for p in paths])


def write(scene, root: Path) -> Path:
    """Write only the images of a `rvggt_jax.synthetic.SyntheticScene` as ROOT/<name>/*.png."""
    from rvggt_jax.eval.datasets.files import save_image

    d = root / scene.name
    d.mkdir(parents=True, exist_ok=True)
    for i, img in enumerate(scene.images):
        save_image(d / f"frame_{i:04d}.png", img)
    return d
