"""CO3D v2 (Common Objects in 3D, Reizenstein et al. 2021) as distributed:

    ROOT/<category>/frame_annotations.jgz              gzipped JSON: a list of frames, one
                                                       dict each (below), every sequence of
                                                       the category
    ROOT/<category>/<sequence>/images/frame000001.jpg   RGB
    ROOT/<category>/<sequence>/depths/frame000001.jpg.geometric.png
                                                       depth: 16-bit PNG whose values are the
                                                       bits of float16 numbers
    ROOT/<category>/<sequence>/depth_masks/frame000001.png
                                                       depth validity (non-zero = valid)

A frame annotation (the fields read here; paths are relative to ROOT, i.e. they start
with the category; ROOT may also be one category folder):

    {"sequence_name": "110_13051_23361", "frame_number": 1,
     "image": {"path": "<category>/<sequence>/images/frame000001.jpg", "size": [H, W]},
     "depth": {"path": ".../depths/frame000001.jpg.geometric.png", "scale_adjustment": s,
               "mask_path": ".../depth_masks/frame000001.png"},      (or null: no depth)
     "viewpoint": {"R": 3x3, "T": 3, "focal_length": [fx, fy], "principal_point": [px, py],
                   "intrinsics_format": "ndc_isotropic"}}

Conventions (PyTorch3D's cameras, which CO3D stores):

- A world point X (a row vector) is in camera coordinates at X R + T, camera axes +X
  left, +Y up, +Z forward. OpenCV world-to-camera (x right, y down, z forward) is
  therefore R_cv = F R^T, t_cv = F T with F = diag(-1, -1, 1).
- focal_length and principal_point are in NDC. "ndc_isotropic" (CO3D v2): both axes
  scaled by s = min(W, H) / 2; "ndc_norm_image_bounds" (v1): x by W / 2 and y by H / 2.
  NDC +x points left and +y up, so in pixels f = f_ndc s and c = size / 2 - p_ndc s,
  where size / 2 is the image centre with pixel edges at integers. This package's
  integer coordinates are pixel centres, so c - 0.5 is stored.
- depth = float16 value x scale_adjustment (z along the optical axis), 0 where the
  depth mask is 0.

Scenes are named `<category>/<sequence>` (or `<sequence>` when ROOT is one category
folder), frames ordered by frame_number. A sequence none of whose frames has a depth
annotation has no depth; one where only some lack it is an error naming the frame.
"""

from __future__ import annotations

import gzip
import json
from functools import lru_cache
from pathlib import Path

import numpy as np

from rvggt_jax.eval.datasets.base import DatasetError, Scene, need_file
from rvggt_jax.eval.datasets.files import save_image

NAME = "co3d"
ANNOTATIONS = "frame_annotations.jgz"
CV_FROM_P3D = np.diag([-1.0, -1.0, 1.0])


@lru_cache(maxsize=8)
def _annotations(path: Path, mtime: float) -> dict[str, list[dict]]:
    """{sequence: [frame annotation, ...] by frame_number} of one category's file."""
    try:
        with gzip.open(path, "rt") as f:
            frames = json.load(f)
        out: dict[str, list[dict]] = {}
        for fr in frames:
            out.setdefault(str(fr["sequence_name"]), []).append(fr)
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise DatasetError(f"malformed CO3D frame annotations {path}: {e}") from None
    return {k: sorted(v, key=lambda fr: int(fr.get("frame_number", 0))) for k, v in out.items()}


def _category_annotations(cat: Path) -> dict[str, list[dict]]:
    p = need_file(cat / ANNOTATIONS, "CO3D frame annotations")
    return _annotations(p, p.stat().st_mtime)


def _categories(root: Path) -> list[tuple[str, Path]]:
    """(name prefix, category folder): ROOT itself, or its sub-folders with annotations."""
    if (root / ANNOTATIONS).is_file():
        return [("", root)]
    return sorted((p.name + "/", p) for p in root.iterdir() if p.is_dir() and (p / ANNOTATIONS).is_file())


def list_scenes(root: Path) -> list[str]:
    names = [prefix + seq for prefix, cat in _categories(root) for seq in _category_annotations(cat)]
    if not names:
        raise DatasetError(f"no CO3D category folder (with {ANNOTATIONS}) in {root}")
    return sorted(names)


def ndc_to_pixels(focal: np.ndarray, principal: np.ndarray, size_hw, fmt: str = "ndc_isotropic") -> np.ndarray:
    """[3, 3] intrinsics in pixels (integer coordinates = pixel centres) of a CO3D
    viewpoint's NDC focal length and principal point for an image of size (H, W)."""
    h, w = (float(v) for v in size_hw)
    if fmt == "ndc_isotropic":
        sx = sy = min(w, h) / 2.0
    elif fmt == "ndc_norm_image_bounds":
        sx, sy = w / 2.0, h / 2.0
    else:
        raise DatasetError(f"unknown CO3D intrinsics_format {fmt!r} (ndc_isotropic or ndc_norm_image_bounds)")
    fx, fy = np.asarray(focal, np.float64).reshape(2)
    px, py = np.asarray(principal, np.float64).reshape(2)
    return np.array([[fx * sx, 0, w / 2.0 - px * sx - 0.5], [0, fy * sy, h / 2.0 - py * sy - 0.5], [0, 0, 1.0]])


def pixels_to_ndc(k: np.ndarray, size_hw) -> tuple[list[float], list[float]]:
    """The inverse of `ndc_to_pixels` ("ndc_isotropic"): (focal_length, principal_point)."""
    h, w = (float(v) for v in size_hw)
    s = min(w, h) / 2.0
    return [k[0, 0] / s, k[1, 1] / s], [(w / 2.0 - 0.5 - k[0, 2]) / s, (h / 2.0 - 0.5 - k[1, 2]) / s]


def viewpoint_to_opencv(r, t) -> np.ndarray:
    """PyTorch3D R [3, 3], T [3] (X_cam = X_world R + T, +X left, +Y up) -> [3, 4]
    OpenCV world-to-camera."""
    r = np.asarray(r, np.float64).reshape(3, 3)
    t = np.asarray(t, np.float64).reshape(3)
    return np.concatenate([CV_FROM_P3D @ r.T, (CV_FROM_P3D @ t)[:, None]], axis=1)


def opencv_to_viewpoint(ext: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of `viewpoint_to_opencv`: (R, T)."""
    return (CV_FROM_P3D @ ext[:3, :3]).T, CV_FROM_P3D @ ext[:3, 3]


def read_depth_f16(path: Path, scale: float, mask_path: Path | None) -> np.ndarray:
    """A CO3D depth PNG (float16 bits in 16-bit values) -> [H, W] float32, x scale, 0
    where the mask (if given) is 0 or the value is not finite and positive."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            v = np.asarray(im, dtype=np.uint16)
    except OSError as e:
        raise DatasetError(f"cannot read depth map {path}: {e}") from None
    d = v.view(np.float16).astype(np.float32) * np.float32(scale)
    if mask_path is not None:
        with Image.open(need_file(mask_path, "depth mask")) as im:
            m = np.asarray(im)
        d = np.where(m.reshape(d.shape[:2] + (-1,))[..., 0] > 0, d, 0.0)
    return np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)


def read_scene(root: Path, name: str, **_) -> Scene:
    cat_name, _, seq = name.rpartition("/")
    cat = root / cat_name if cat_name else root
    frames = _category_annotations(cat).get(seq)
    if not frames:
        raise DatasetError(f"no frames of sequence {seq!r} in {cat / ANNOTATIONS}")
    base = cat.parent  # the annotations' paths start with the category folder
    paths, ext, ks, ids, depth_paths, depth_info = [], [], [], [], [], {}
    for fr in frames:
        try:
            img = base / fr["image"]["path"]
            vp = fr["viewpoint"]
            ext.append(viewpoint_to_opencv(vp["R"], vp["T"]))
            ks.append(ndc_to_pixels(vp["focal_length"], vp["principal_point"], fr["image"]["size"],
                                    vp.get("intrinsics_format", "ndc_isotropic")))
            dep = fr.get("depth") or None
            if dep is not None and dep.get("path"):
                dp = base / dep["path"]
                mp = base / dep["mask_path"] if dep.get("mask_path") else None
                depth_info[dp] = (float(dep.get("scale_adjustment", 1.0)), mp)
                depth_paths.append(dp)
            else:
                depth_paths.append(None)
        except (KeyError, TypeError, ValueError) as e:
            raise DatasetError(f"malformed frame annotation (frame {fr.get('frame_number')} of {seq}) in "
                               f"{cat / ANNOTATIONS}: {e!r}") from None
        paths.append(need_file(img, "image listed in " + ANNOTATIONS))
        ids.append(str(fr.get("frame_number", len(ids))))
    has_depth = any(p is not None for p in depth_paths)
    if has_depth:
        missing = [paths[i] for i, p in enumerate(depth_paths) if p is None]
        if missing:
            raise DatasetError(f"{name}: no depth annotation for {missing[0]} (other frames have depth)")

    def reader(p: Path) -> np.ndarray:
        scale, mask = depth_info[p]
        return read_depth_f16(p, scale, mask)

    return Scene(NAME, name, paths, np.stack(ext), np.stack(ks), ids, depth_paths if has_depth else None,
                 reader if has_depth else None, None, None)


def write(scene, root: Path, category: str = "synthetic") -> Path:
    """Write a `rvggt_jax.synthetic.SyntheticScene` as ROOT/<category>/<name> (JPEG
    frames, float16 depth with a scale adjustment of 0.5, all-valid depth masks) and its
    frames into ROOT/<category>/frame_annotations.jgz (added to the sequences there)."""
    from PIL import Image

    cat = root / category
    d = cat / scene.name
    for sub in ("images", "depths", "depth_masks"):
        (d / sub).mkdir(parents=True, exist_ok=True)
    s, h, w = scene.depth.shape
    scale = 0.5
    frames = []
    for i in range(s):
        stem = f"frame{i + 1:06d}"
        rel = f"{category}/{scene.name}"
        save_image(d / "images" / f"{stem}.jpg", scene.images[i])
        bits = (np.asarray(scene.depth[i], np.float32) / scale).astype(np.float16).view(np.uint16)
        Image.fromarray(bits).save(d / "depths" / f"{stem}.jpg.geometric.png")
        Image.fromarray(((scene.depth[i] > 0) * 255).astype(np.uint8)).save(d / "depth_masks" / f"{stem}.png")
        r, t = opencv_to_viewpoint(np.asarray(scene.extrinsics[i], np.float64))
        f, p = pixels_to_ndc(np.asarray(scene.intrinsics[i], np.float64), (h, w))
        frames.append({"sequence_name": scene.name, "frame_number": i + 1, "frame_timestamp": float(i),
                       "image": {"path": f"{rel}/images/{stem}.jpg", "size": [h, w]},
                       "depth": {"path": f"{rel}/depths/{stem}.jpg.geometric.png", "scale_adjustment": scale,
                                 "mask_path": f"{rel}/depth_masks/{stem}.png"},
                       "mask": None,
                       "viewpoint": {"R": r.tolist(), "T": t.tolist(), "focal_length": f, "principal_point": p,
                                     "intrinsics_format": "ndc_isotropic"}})
    ann = cat / ANNOTATIONS
    if ann.is_file():
        with gzip.open(ann, "rt") as fh:
            frames = [fr for fr in json.load(fh) if fr["sequence_name"] != scene.name] + frames
    with gzip.open(ann, "wt") as fh:
        json.dump(frames, fh)
    return d
