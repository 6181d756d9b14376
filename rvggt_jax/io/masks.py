"""Per-image masks (`rvggt reconstruct --masks DIR`): one mask image per input image, found
by the image's file stem (`view_00.jpg` <- `DIR/view_00.png`, any image extension), white
(bright) = keep, black = drop. A mask goes through its image's preprocessing (the same
resize, crop and padding of `rvggt_jax.io.images.load_images_with_info`), then is read as
keep where its grey value is >= 0.5, so a mask of another resolution but the same aspect
works and a rough box works.

What the pipeline does with them: masked pixels are set to 0 in the network input before
the forward (as upstream's README suggests) and their points are dropped from every
output (`rvggt_jax.app.pipeline.build_reconstruction`'s `masks`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from rvggt_jax.io.images import ImageInfo, ImageLoadError, find_images, load_images_with_info

__all__ = ["MaskError", "find_masks", "load_masks"]

KEEP_THRESHOLD = 0.5


class MaskError(ValueError):
    """A mask that is missing, ambiguous, unreadable or of the wrong size; the message
    names the file."""


def find_masks(image_paths: Sequence[str | os.PathLike], folder: str | os.PathLike) -> list[Path]:
    """The mask of each image in `folder`, matched by file stem -> [S] paths.
    `MaskError` naming the first image without a mask (or with two), or two images that
    share a stem (their masks could not be told apart)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise MaskError(f"mask folder {'is not a folder' if folder.exists() else 'not found'}: {folder}")
    files, _ = find_images(folder)
    by_stem: dict[str, list[Path]] = {}
    for f in files:
        by_stem.setdefault(f.stem, []).append(f)
    seen: dict[str, Path] = {}
    out = []
    for p in map(Path, image_paths):
        if p.stem in seen:
            raise MaskError(f"images {seen[p.stem].name} and {p.name} share the stem {p.stem!r}: masks are "
                            f"matched by stem, rename one")
        seen[p.stem] = p
        found = by_stem.get(p.stem, [])
        if not found:
            raise MaskError(f"no mask for image {p.name} in {folder} (expected {p.stem}.png or another image "
                            f"file named {p.stem}.*)")
        if len(found) > 1:
            raise MaskError(f"two masks for image {p.name}: {', '.join(f.name for f in found)}")
        out.append(found[0])
    return out


def _content_size(info: ImageInfo) -> tuple[int, int]:
    x0, y0, x1, y1 = info.valid
    return x1 - x0, y1 - y0


def load_masks(mask_paths: Sequence[str | os.PathLike], infos: Sequence[ImageInfo], image_hw: tuple[int, int],
               mode: str = "crop", *, exif_orientation: bool = True, target: int = 518) -> np.ndarray:
    """Masks [S, H, W] bool (True = keep) on the network input of the images `infos`
    describe (as `load_images_with_info` returned them, batch H x W = `image_hw`).
    Each mask is preprocessed as its image; a mask that does not come out at its image's
    size is a `MaskError` naming both. Padding is False (it holds no image content)."""
    if len(mask_paths) != len(infos):
        raise ValueError(f"{len(infos)} images need {len(infos)} masks; got {len(mask_paths)}")
    try:
        # padded to the images' batch size: a chunk of a long run pads to its sequence's
        masks, mask_infos = load_images_with_info(mask_paths, mode, exif_orientation=exif_orientation,
                                                  pad_to=tuple(image_hw), target=target)
    except ImageLoadError as e:
        raise MaskError(f"mask: {e}") from None
    for path, m, info in zip(mask_paths, mask_infos, infos):
        if _content_size(m) != _content_size(info):
            mw, mh = _content_size(m)
            iw, ih = _content_size(info)
            raise MaskError(f"mask {path} is {m.width}x{m.height} ({mw}x{mh} after preprocessing); its image "
                            f"{info.name} is {info.width}x{info.height} ({iw}x{ih}): a mask needs its image's "
                            f"size or aspect ratio")
    h, w = image_hw
    if masks.shape[2:] != (h, w):  # (cannot happen when every content size matched)
        raise MaskError(f"masks come out at {masks.shape[3]}x{masks.shape[2]}, the images at {w}x{h}")
    keep = masks.mean(axis=1) >= KEEP_THRESHOLD
    return keep & np.stack([info.valid_mask(h, w) for info in infos])
