"""Image loading and preprocessing, numerically identical to upstream VGGT.

`load_images(paths, mode)` reproduces `vggt.utils.load_fn.load_and_preprocess_images`
to the last bit (the same Pillow BICUBIC resize, the same `uint8 / 255` float32
conversion, the same rounding of sizes to multiples of the 14-pixel patch, the same
white padding), without torch.

`load_images_with_info` also returns, per image, where its pixels went
(`ImageInfo`): the original size and the affine map from original pixel coordinates
to network-input pixel coordinates, used to express the predicted intrinsics in the
original image's pixels and to tell padding from image content.

Where this departs from upstream (which calls `Image.open(p).convert("RGB")`):
- the EXIF orientation is applied first (`ImageOps.exif_transpose`), so a phone photo
  taken upright is read upright and `ImageInfo.width/height` are the upright size
  (`exif_orientation=False` reads the stored pixels as upstream does);
- 16-bit and 32-bit images (Pillow modes `I;16*`, `I`, `F`) are read by their range,
  value / 65535 (`F` images already in [0, 1] as they are), then quantised to 8 bits
  like every other image; `convert("RGB")` would clip them to a solid white image;
- images with transparency in modes other than RGBA (`LA`, `PA`, `P` with a
  transparent colour) are blended on white as upstream blends RGBA.
Images without EXIF orientation, high bit depth or such transparency are read exactly as
upstream reads them.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

__all__ = [
    "IMAGE_EXTENSIONS",
    "ImageInfo",
    "ImageLoadError",
    "TARGET_SIZE",
    "find_images",
    "load_images",
    "load_images_with_info",
    "network_images",
    "network_shape",
    "upright_size",
    "preprocessed_size",
]

TARGET_SIZE = 518
"""Upstream's fixed network resolution: the width (crop) or the longest side (pad)."""

PATCH = 14

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".gif", ".ppm", ".pgm")
"""File name endings (case-insensitive) `find_images` treats as images."""

_MODES = ("crop", "pad")


class ImageLoadError(ValueError):
    """An image could not be read or decoded; the message names the file."""


@dataclasses.dataclass(frozen=True)
class ImageInfo:
    """Where one image's pixels ended up in the preprocessed batch.

    Pixel coordinates are continuous (the image spans `[0, width] x [0, height]`):
    a point `(u, v)` of the original image lands at `(sx*u + ox, sy*v + oy)` of the
    network input. `valid` is the box `(x0, y0, x1, y1)` (integers, end exclusive) of
    the network input covered by image content; outside it is white padding.
    """

    path: str
    name: str
    width: int
    height: int
    sx: float
    sy: float
    ox: float
    oy: float
    valid: tuple[int, int, int, int]

    def intrinsic_to_original(self, intrinsic: np.ndarray) -> np.ndarray:
        """A pinhole matrix `[3, 3]` in network-input pixels -> the same camera in
        original-image pixels (inverse of the affine pixel map)."""
        k = np.array(intrinsic, dtype=np.float64, copy=True)
        k[0, :] = (k[0, :] - self.ox * k[2, :]) / self.sx
        k[1, :] = (k[1, :] - self.oy * k[2, :]) / self.sy
        return k

    def valid_mask(self, height: int, width: int) -> np.ndarray:
        """Boolean `[height, width]` mask of network-input pixels that hold image content."""
        m = np.zeros((height, width), dtype=bool)
        x0, y0, x1, y1 = self.valid
        m[y0:y1, x0:x1] = True
        return m


def preprocessed_size(width: int, height: int, mode: str = "crop", target: int = TARGET_SIZE) -> tuple[int, int]:
    """`(new_width, new_height)` upstream resizes a `width x height` image to (before
    cropping / padding) for a network size `target` (upstream's 518). Python's `round`
    (half to even) as upstream."""
    _check_mode(mode)
    _check_target(target)
    if mode == "pad" and height > width:
        new_height = target
        new_width = round(width * (new_height / height) / PATCH) * PATCH
    else:
        new_width = target
        new_height = round(height * (new_width / width) / PATCH) * PATCH
    if new_width <= 0 or new_height <= 0:
        raise ValueError(f"image of {width}x{height} pixels is too thin to resize to {target} pixels")
    return new_width, new_height


def _check_target(target: int) -> None:
    if isinstance(target, bool) or not isinstance(target, int) or target < PATCH or target % PATCH:
        raise ValueError(f"the network size must be a positive multiple of {PATCH}; got {target!r}")


def _check_mode(mode: str) -> None:
    if mode not in _MODES:
        raise ValueError(f"mode must be 'crop' or 'pad', got {mode!r}")


_HIGH_BIT_MODES = ("I;16", "I;16L", "I;16B", "I;16N", "I", "F")


def _to_8bit(img: Image.Image) -> Image.Image:
    """A single-channel 16/32-bit image -> mode "L", value / 65535 in [0, 1] -> 0..255.

    Why: Pillow's convert("RGB") clips these modes at 255, so a 16-bit photo becomes a
    solid white image and the run silently "succeeds" on garbage. Float ("F") images
    whose values already lie in [0, 1] are taken as they are."""
    a = np.asarray(img, dtype=np.float64)
    finite = a[np.isfinite(a)]
    if img.mode == "F" and finite.size and finite.min() >= 0.0 and finite.max() <= 1.0:
        unit = a
    else:
        unit = a / 65535.0
    unit = np.nan_to_num(unit, nan=0.0, posinf=1.0, neginf=0.0)
    return Image.fromarray((np.clip(unit, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8), "L")


def _has_alpha(img: Image.Image) -> bool:
    return img.mode in ("RGBA", "LA", "PA", "RGBa", "La") or (img.mode == "P" and "transparency" in img.info)


def _open_rgb(path: str, exif_orientation: bool = True) -> Image.Image:
    """Open, decode fully, apply the EXIF orientation (optional), blend transparency on
    white and convert to RGB (upstream's steps, plus the ones named in the module doc)."""
    try:
        with Image.open(path) as img:
            img.load()
            if exif_orientation:
                img = ImageOps.exif_transpose(img)
            if img.mode in _HIGH_BIT_MODES:
                img = _to_8bit(img)
            if _has_alpha(img):
                if img.mode != "RGBA":
                    img = img.convert("RGBA")
                background = Image.new("RGBA", img.size, (255, 255, 255, 255))
                img = Image.alpha_composite(background, img)
            return img.convert("RGB")
    except FileNotFoundError:
        raise ImageLoadError(f"image not found: {path}") from None
    except IsADirectoryError:
        raise ImageLoadError(f"not an image file (a directory): {path}") from None
    except UnidentifiedImageError:
        raise ImageLoadError(f"cannot read image {path}: not a recognised image format (corrupt or not an image)") from None
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as e:
        raise ImageLoadError(f"cannot read image {path}: {e}") from None


def _pad_white(img: np.ndarray, top: int, bottom: int, left: int, right: int) -> np.ndarray:
    """`[3, H, W]` -> `[3, H+top+bottom, W+left+right]`, new pixels = 1.0."""
    return np.pad(img, ((0, 0), (top, bottom), (left, right)), mode="constant", constant_values=1.0)


def load_images_with_info(
    paths: Sequence[str | os.PathLike],
    mode: str = "crop",
    progress: Callable[[Iterable], Iterable] | None = None,
    *,
    exif_orientation: bool = True,
    on_error: str = "raise",
    pad_to: tuple[int, int] | None = None,
    target: int = TARGET_SIZE,
) -> tuple[np.ndarray, list[ImageInfo]]:
    """Load and preprocess images as upstream's `load_and_preprocess_images`.

    Args:
      paths: image files, in the order of the frames.
      mode: "crop" (width 518, height rounded to a multiple of 14 and centre-cropped to
        at most 518) or "pad" (longest side 518, the other rounded to a multiple of 14,
        white-padded to 518 x 518).
      progress: optional wrapper of the path iterable (e.g. `tqdm`).
      exif_orientation: apply the EXIF orientation tag (default); False reads the
        stored pixels as upstream does.
      on_error: "raise" (default) stops at the first unreadable image; "skip" leaves
        it out (the returned infos then list only the images loaded: compare their
        `path` with `paths` to see which were skipped).
      pad_to: (H, W): centre-pad with white to at least this size (a long run's
        chunks all take their sequence's `network_shape`).
      target: the network size in place of upstream's 518 (a model trained at another
        size: `ReconstructOptions.size`).

    Returns:
      images `[S, 3, H, W]` float32 in [0, 1]; images of different sizes are
      centre-padded with white (1.0) to the largest height and width, and
      per-image `ImageInfo`.

    Raises:
      ValueError: empty `paths` or a bad `mode`.
      ImageLoadError: a file that cannot be read (the message names it).
    """
    paths = [os.fspath(p) for p in paths]
    if len(paths) == 0:
        raise ValueError("at least 1 image is required")
    _check_mode(mode)
    _check_target(target)
    if on_error not in ("raise", "skip"):
        raise ValueError(f"on_error must be 'raise' or 'skip', got {on_error!r}")

    arrays: list[np.ndarray] = []
    infos: list[dict] = []
    it = progress(paths) if progress is not None else paths
    for path in it:
        try:
            img = _open_rgb(path, exif_orientation)
            width, height = img.size
            try:
                new_width, new_height = preprocessed_size(width, height, mode, target)
            except ValueError as e:
                raise ImageLoadError(f"cannot use image {path}: {e}") from None
        except ImageLoadError:
            if on_error == "skip":
                continue
            raise
        img = img.resize((new_width, new_height), Image.Resampling.BICUBIC)
        # Upstream's ToTensor: uint8 -> float32, divided by 255 in float32.
        arr = np.asarray(img, dtype=np.uint8).transpose(2, 0, 1).astype(np.float32) / np.float32(255.0)
        sx, sy = new_width / width, new_height / height
        ox = oy = 0.0
        if mode == "crop" and new_height > target:
            start_y = (new_height - target) // 2
            arr = arr[:, start_y : start_y + target, :]
            oy -= start_y
        content = (arr.shape[2], arr.shape[1])
        if mode == "pad":
            h_pad = target - arr.shape[1]
            w_pad = target - arr.shape[2]
            if h_pad > 0 or w_pad > 0:
                top, left = h_pad // 2, w_pad // 2
                arr = _pad_white(arr, top, h_pad - top, left, w_pad - left)
                ox += left
                oy += top
        arrays.append(arr)
        infos.append(dict(path=path, name=os.path.basename(path), width=width, height=height, sx=sx, sy=sy, ox=ox, oy=oy,
                          content=content))

    _pad_to_common(arrays, infos, pad_to)
    if not arrays:
        raise ImageLoadError(f"none of the {len(paths)} images could be read")
    images = np.stack(arrays).astype(np.float32, copy=False)
    H, W = images.shape[2:]

    out_infos = []
    for d in infos:
        cw, ch = d.pop("content")
        # the content's top-left corner moved only by padding (the crop offset is < 0 only
        # in crop mode, where no per-image padding happens)
        x0, y0 = int(round(max(d["ox"], 0.0))), int(round(max(d["oy"], 0.0)))
        out_infos.append(ImageInfo(valid=(x0, y0, min(W, x0 + cw), min(H, y0 + ch)), **d))
    return images, out_infos


def _pad_to_common(arrays: list[np.ndarray], infos: list[dict], pad_to: tuple[int, int] | None) -> None:
    """Centre-pad (white) each [3, h, w] of `arrays` in place to the largest height and
    width among them and `pad_to`, moving its info's offsets with it."""
    shapes = {a.shape[1:] for a in arrays} | ({tuple(pad_to)} if pad_to is not None and arrays else set())
    if len(shapes) <= 1:
        return
    max_h = max(s[0] for s in shapes)
    max_w = max(s[1] for s in shapes)
    for i, arr in enumerate(arrays):
        h_pad = max_h - arr.shape[1]
        w_pad = max_w - arr.shape[2]
        if h_pad > 0 or w_pad > 0:
            top, left = h_pad // 2, w_pad // 2
            arrays[i] = _pad_white(arr, top, h_pad - top, left, w_pad - left)
            infos[i]["ox"] += left
            infos[i]["oy"] += top


def load_images(paths: Sequence[str | os.PathLike], mode: str = "crop", *, exif_orientation: bool = True) -> np.ndarray:
    """Images `[S, 3, H, W]` float32 in [0, 1], equal to upstream's
    `load_and_preprocess_images(paths, mode)` (up to the departures in the module doc);
    see `load_images_with_info`."""
    return load_images_with_info(paths, mode, exif_orientation=exif_orientation)[0]


def upright_size(path: str | os.PathLike, exif_orientation: bool = True) -> tuple[int, int]:
    """(width, height) of the image file as it is viewed, from its header alone."""
    with Image.open(path) as img:
        w, h = img.size
        # orientations 5-8 turn the picture a quarter turn
        if exif_orientation and img.getexif().get(0x0112, 1) in (5, 6, 7, 8):
            w, h = h, w
    return w, h


def network_shape(paths: Sequence[str | os.PathLike], mode: str = "crop", *, exif_orientation: bool = True,
                  on_error: str = "raise", target: int = TARGET_SIZE) -> tuple[tuple[int, int], list[str]]:
    """`((H, W), unreadable)`: the network input size `load_images_with_info` gives all of
    `paths` together, from the files' headers alone (no decoding: fast for thousands of
    frames), and the paths whose header cannot be read (skipped with on_error="skip";
    "raise": `ImageLoadError` naming the first)."""
    _check_mode(mode)
    height = width = 0
    bad = []
    for path in map(os.fspath, paths):
        try:
            w, h = upright_size(path, exif_orientation)
            nw, nh = preprocessed_size(w, h, mode, target)
        except (OSError, SyntaxError, ValueError, UnidentifiedImageError, Image.DecompressionBombError) as e:
            if on_error == "skip":
                bad.append(path)
                continue
            raise ImageLoadError(f"cannot read image {path}: {e}") from None
        if mode == "pad":
            nw, nh = target, target
        else:
            nh = min(nh, target)
        height, width = max(height, nh), max(width, nw)
    return (height, width), bad


def network_images(images: np.ndarray) -> np.ndarray:
    """The smallest exact form of images [..., 3, H, W] for the forward: uint8 when every
    value is some v / 255 in float32 (as `load_images` makes them; the forward scales
    uint8 back bit for bit), else float32. A quarter of the bytes in and on the device:
    0.57 instead of 2.27 GiB for 1000 frames of 392 x 518."""
    images = np.asarray(images)
    if images.dtype == np.uint8:
        return images
    images = images.astype(np.float32, copy=False)
    if images.size and np.all(np.isfinite(images)) and images.min() >= 0.0 and images.max() <= 1.0:
        u8 = np.rint(images * np.float32(255.0)).astype(np.uint8)
        if np.array_equal(u8.astype(np.float32) / np.float32(255.0), images):
            return u8
    return images


def find_images(folder: str | os.PathLike) -> tuple[list[Path], list[Path]]:
    """Image files directly inside `folder` sorted by name, and the other entries skipped.

    Image files are recognised by their extension (`IMAGE_EXTENSIONS`,
    case-insensitive); hidden files and sub-folders are skipped.

    Raises:
      FileNotFoundError / NotADirectoryError: `folder` is missing or not a folder.
    """
    folder = Path(folder)
    if not folder.exists():
        raise FileNotFoundError(f"image folder not found: {folder}")
    if not folder.is_dir():
        raise NotADirectoryError(f"not a folder: {folder}")
    images, skipped = [], []
    for p in sorted(folder.iterdir(), key=lambda q: q.name):
        if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in IMAGE_EXTENSIONS:
            images.append(p)
        else:
            skipped.append(p)
    return images, skipped
