"""What the viewer shows, read from a reconstruction folder, without a server: the folder's
cloud and cameras (`load_reconstruction`), the background filter (`background_mask`), and
the other point source's cloud from the raw predictions (`points_from_predictions`), plus
the Markdown escapes of the panel's texts. `rvggt_jax.app.viewer` serves them."""

from __future__ import annotations

import dataclasses
import json
import os
import zipfile
from pathlib import Path

import numpy as np

__all__ = ["BLACK_SUM_BELOW", "MAX_SHOWN", "POINT_SOURCES", "Reconstruction", "ViewerError", "WHITE_ALL_ABOVE",
           "background_mask", "load_reconstruction", "points_from_predictions"]

MAX_SHOWN = 1_000_000  # points sent to the browser (a random subset beyond that)
# "points from" labels -> `rvggt reconstruct --points` values (cameras.json's "points_from")
POINT_SOURCES = {"depth": "depth", "point map": "pointmap"}
# Background filter, upstream demo_viser's thresholds: near black is R + G + B < 16 (masked
# pixels are exactly 0 in the network input, and JPEG noise around black stays a few levels
# per channel), near white is every channel > 240 (--mode pad pads with pure white; JPEG
# ringing at the padding's edge stays above ~245). Both are tight enough to keep dark and
# bright scene surfaces, which have some colour or texture.
BLACK_SUM_BELOW = 16
WHITE_ALL_ABOVE = 240


@dataclasses.dataclass
class Reconstruction:
    """What the viewer shows. points [N, 3], colors [N, 3] uint8, confidence [N],
    frame [N] (index into `names`; -1 unknown), extrinsic [S, 3, 4] world-to-camera,
    intrinsic [S, 3, 3], sizes [S] (W, H), thumbnails [S] (uint8 [h, w, 3] or None).
    points_from: the run's point source ("depth" / "pointmap", cameras.json's; "depth"
    when it does not say); conf_threshold: the run's --conf-threshold as written there
    (None when it does not say)."""

    names: list[str]
    points: np.ndarray
    colors: np.ndarray
    confidence: np.ndarray
    frame: np.ndarray
    extrinsic: np.ndarray
    intrinsic: np.ndarray
    sizes: list[tuple[int, int]]
    thumbnails: list[np.ndarray | None]
    points_from: str = "depth"
    conf_threshold: str | None = None


class ViewerError(ValueError):
    """A folder that is not a reconstruction (the message says what is missing)."""


def load_reconstruction(out_dir: str | os.PathLike, max_points: int = MAX_SHOWN, seed: int = 0) -> Reconstruction:
    """Read a `rvggt reconstruct` output folder (at most `max_points` points, random subset)."""
    from PIL import Image

    from rvggt_jax.io.export import unique_stems
    from rvggt_jax.io.ply import read_ply_properties

    out = Path(out_dir)
    missing = [f for f in ("points.ply", "cameras.json") if not (out / f).is_file()]
    if not out.is_dir() or missing:
        raise ViewerError(f"{out} is not an rvggt reconstruction folder (no {' / '.join(missing) or 'folder'}); "
                          f"make one with `rvggt reconstruct ... --out {out}`")
    doc = json.loads((out / "cameras.json").read_text())
    frames = doc["frames"]
    p = read_ply_properties(out / "points.ply")
    pts = np.stack([p["x"], p["y"], p["z"]], 1).astype(np.float32)
    cols = np.stack([p["red"], p["green"], p["blue"]], 1).astype(np.uint8)
    conf = p.get("confidence", np.ones(len(pts), np.float32)).astype(np.float32)
    frame = p.get("frame", np.full(len(pts), -1)).astype(np.int64)
    if len(pts) > max_points:
        keep = np.sort(np.random.default_rng(seed).choice(len(pts), max_points, replace=False))
        pts, cols, conf, frame = pts[keep], cols[keep], conf[keep], frame[keep]
    names = [f["image"] for f in frames]
    thumbs = []
    for stem in unique_stems(names):
        t = out / "thumbnails" / f"{stem}.jpg"
        if t.is_file():
            with Image.open(t) as im:
                thumbs.append(np.asarray(im.convert("RGB")))
        else:
            thumbs.append(None)
    threshold = doc.get("conf_threshold")
    return Reconstruction(
        names=names, points=pts, colors=cols, confidence=conf, frame=frame,
        extrinsic=np.array([f["extrinsic"] for f in frames], np.float64),
        intrinsic=np.array([f["intrinsic"] for f in frames], np.float64),
        sizes=[(int(f["width"]), int(f["height"])) for f in frames], thumbnails=thumbs,
        points_from="pointmap" if doc.get("points_from") == "pointmap" else "depth",
        conf_threshold=None if threshold is None else str(threshold))


def background_mask(colors: np.ndarray, black: bool, white: bool) -> np.ndarray:
    """[N] bool: the points of colors [N, 3] uint8 that the background filter hides
    (near black when `black`, near white when `white`; thresholds above)."""
    c = np.asarray(colors)
    hide = np.zeros(len(c), bool)
    if black:
        hide |= c.astype(np.int32).sum(1) < BLACK_SUM_BELOW
    if white:
        hide |= (c > WHITE_ALL_ABOVE).all(1)
    return hide


def _frustum_scale(rec: Reconstruction) -> float:
    """A tenth of the scene's extent (cameras and the points' robust spread)."""
    e = rec.extrinsic
    centers = -np.einsum("sji,sj->si", e[:, :3, :3], e[:, :3, 3])
    spans = [float(np.linalg.norm(np.ptp(centers, 0)))] if len(centers) > 1 else []
    if len(rec.points):
        lo, hi = np.percentile(rec.points, [5, 95], axis=0)
        spans.append(float(np.linalg.norm(hi - lo)))
    span = max([s for s in spans if np.isfinite(s)] or [1.0])
    return 0.1 * (span if span > 1e-9 else 1.0)


def _md(text: str) -> str:
    """`text` for a markdown element, its markup characters escaped (paths and error
    messages hold `_`, `*`, `<`, ...)."""
    out = str(text)
    for ch in "\\`*_{}[]()<>#+!|~":
        out = out.replace(ch, "\\" + ch)
    return out


def _code(text) -> str:
    """`text` as a markdown code span (where escapes would show as written)."""
    return "`" + str(text).replace("`", "'") + "`"


def _predictions_problem(path: Path, names: list[str]) -> str | None:
    """Why the "points from" switch cannot use the predictions.npz at `path` for frames
    `names` (None: it can). Reads only the file's index and its image names: the arrays
    are read when the switch is used."""
    from rvggt_jax.io.raw import REQUIRED_KEYS

    if not path.is_file():
        return f"needs {path.name} in the folder: reconstruct with --save-raw"
    try:
        with np.load(path, allow_pickle=False) as npz:
            keys = set(npz.files)
            missing = [k for k in REQUIRED_KEYS if k not in keys]
            if missing:
                return f"{path.name} lacks {', '.join(missing)}"
            if not {"world_points", "world_points_conf"} <= keys:
                return f"{path.name} has no point map (the model has no point head)"
            stored = [str(n) for n in npz["image_names"]]
    except (OSError, ValueError, AttributeError, EOFError, zipfile.BadZipFile) as e:
        from rvggt_jax.app.messages import one_line

        return f"cannot read {path.name} as .npz ({one_line(e, 200)})"
    if stored != list(names):
        return f"{path.name} is of other images than cameras.json"
    return None


def points_from_predictions(arrays: dict, source: str, conf_threshold: str | None, max_points: int = MAX_SHOWN):
    """The cloud of predictions.npz `arrays` (`rvggt_jax.io.raw.load_predictions`) for
    `source` "depth" (the depth maps unprojected with the predicted cameras, their
    depth_conf; pixels with depth <= 0 dropped) or "pointmap" (the point head's
    world_points, their world_points_conf), the points chosen as the run chose its own
    (`conf_threshold`, e.g. "50%"; None keeps all; at most `max_points`) ->
    (points [N, 3] float32, colors [N, 3] uint8, confidence [N] float32, frame [N] int64,
    the absolute threshold used)."""
    from rvggt_jax.app.pipeline import parse_threshold, select_points
    from rvggt_jax.geometry import unproject_depth_map_to_point_map

    images = np.asarray(arrays["images"], np.float32)
    s, _, h, w = images.shape
    colors = (np.clip(images.transpose(0, 2, 3, 1), 0, 1) * 255 + 0.5).astype(np.uint8)
    if source == "depth":
        depth = np.asarray(arrays["depth"], np.float32)[..., 0]
        pts = unproject_depth_map_to_point_map(depth, arrays["extrinsic"], arrays["intrinsic"])
        conf, valid = np.asarray(arrays["depth_conf"], np.float32), depth > 1e-8
    elif source == "pointmap":
        pts, conf, valid = arrays["world_points"], np.asarray(arrays["world_points_conf"], np.float32), None
    else:
        raise ValueError(f"unknown point source {source!r}; use depth or pointmap")
    threshold = "0%" if conf_threshold is None else conf_threshold
    try:
        parse_threshold(threshold)
    except ValueError:  # a cameras.json written by hand: keep every point
        threshold = "0%"
    points, cols, abs_thr, idx = select_points(pts, conf, colors, valid, threshold, max_points, return_index=True)
    return points, cols, conf.reshape(-1)[idx].astype(np.float32), (idx // (h * w)).astype(np.int64), abs_thr
