"""Tracks for bundle adjustment: query points in a few query frames, tracked through all
frames, filtered by the tracker's visibility and confidence. Pure numpy; the tracker is
any callable (`TrackFn`), the model's track head in `rvggt reconstruct --ba`.

Pixel coordinates are continuous, as everywhere in rvggt_jax (the image spans
[0, W] x [0, H]) and in COLMAP, so SIFT keypoints, track positions and the intrinsics
agree without half-pixel shifts.

Query points. The track head follows points given in frame 0 of its input; a track
from query frame j is obtained by running it on the frames reordered with j first
(`track_from_query_frames`) and putting the result back in the original order. Several
query frames (`choose_query_frames`: evenly spaced, frame 0 first) give tracks that
cover the parts of the scene frame 0 does not see.

Which points: `keypoints="sift"` (the default) takes SIFT keypoints (pycolmap's `Sift`,
already installed with the `[ba]` extra), ranked by the model's depth confidence at
the keypoint: a keypoint is a corner or blob the tracker can localise to a fraction of
a pixel, which flat high-confidence pixels (a white wall) are not, and the confidence
ranking keeps it off the sky and off padding. Where SIFT finds too few (a textureless
image), the rest are grid points (`grid_keypoints`): the most confident pixel of each
cell of a coarse grid, the best cells first, spread over the image by construction.
`keypoints="grid"` uses grid points only (no pycolmap needed for this step; cheaper).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

__all__ = ["TrackFn", "Tracks", "choose_query_frames", "filter_tracks", "grid_keypoints", "query_points",
           "sift_keypoints", "track_from_query_frames"]

KEYPOINT_METHODS = ("sift", "grid")

TrackFn = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]
"""`track_fn(images [S, 3, H, W], queries [N, 2]) -> (tracks [S, N, 2], vis [S, N],
conf [S, N])`: the queries are pixel (x, y) in frame 0 of `images`; vis and conf in
[0, 1]."""


@dataclass(frozen=True, eq=False)
class Tracks:
    """N tracks through S frames (network-input pixels).

    points       [S, N, 2] float64 pixel (x, y) of each track in each frame
    vis          [S, N] float32 the tracker's visibility in [0, 1]
    conf         [S, N] float32 the tracker's confidence in [0, 1]
    query_frame  [N] int32 the frame each track was queried in
    """

    points: np.ndarray
    vis: np.ndarray
    conf: np.ndarray
    query_frame: np.ndarray

    @property
    def num_frames(self) -> int:
        return self.points.shape[0]

    def __len__(self) -> int:
        return self.points.shape[1]


def choose_query_frames(num_frames: int, count: int) -> list[int]:
    """`min(count, num_frames)` frame indices evenly spaced over [0, num_frames), frame 0
    first (the model's reference frame: its tracks are the best supported)."""
    if num_frames < 1 or count < 1:
        raise ValueError(f"need at least one frame and one query frame; got {num_frames}, {count}")
    count = min(count, num_frames)
    return sorted({int(round(i * num_frames / count)) for i in range(count)})


def grid_keypoints(score: np.ndarray, valid: np.ndarray | None, count: int, *, border: int = 4,
                   exclude: np.ndarray | None = None, min_distance: float = 2.0) -> np.ndarray:
    """`count` points (x, y) [count, 2] of a score map [H, W]: the image is cut into about
    2 x `count` cells, each cell proposes its best-scoring valid pixel (`valid` [H, W]
    bool, None: all; `border` pixels from the edge left out), and the best proposals win,
    so the points are both confident and spread out. Pixel centres are (col + 0.5,
    row + 0.5). `exclude` [M, 2]: points already chosen (no proposal within
    `min_distance` pixels of one). Fewer than `count` when the valid area is too small."""
    score = np.asarray(score, dtype=np.float64)
    h, w = score.shape
    ok = np.isfinite(score) if valid is None else (np.asarray(valid, bool) & np.isfinite(score))
    ok[:border] = ok[h - border:] = False
    ok[:, :border] = ok[:, w - border:] = False
    if count < 1 or not ok.any():
        return np.zeros((0, 2))
    cell = max(1, int(np.sqrt(h * w / (2 * count))))
    s = np.where(ok, score, -np.inf)
    ys, xs = np.mgrid[0:h, 0:w]
    if exclude is not None and len(exclude):
        # pixels near a point already chosen cannot be proposed again
        for x, y in np.asarray(exclude, dtype=np.float64):
            near = (xs + 0.5 - x) ** 2 + (ys + 0.5 - y) ** 2 < min_distance ** 2
            s[near] = -np.inf
    props = []
    for y0 in range(0, h, cell):
        for x0 in range(0, w, cell):
            block = s[y0:y0 + cell, x0:x0 + cell]
            k = int(np.argmax(block))
            r, c = divmod(k, block.shape[1])
            if np.isfinite(block[r, c]):
                props.append((block[r, c], x0 + c + 0.5, y0 + r + 0.5))
    props.sort(key=lambda p: -p[0])
    return np.array([(x, y) for _, x, y in props[:count]], dtype=np.float64).reshape(-1, 2)


def sift_keypoints(image: np.ndarray, score: np.ndarray, valid: np.ndarray | None, count: int, *,
                   border: int = 4, min_distance: float = 2.0) -> np.ndarray:
    """Up to `count` SIFT keypoints (x, y) [<= count, 2] of image [3, H, W] (float in
    [0, 1]), the ones on the highest `score` [H, W] first (the model's confidence at the
    keypoint), none on invalid pixels (`valid` [H, W], e.g. padding), within `border`
    pixels of the edge, or within `min_distance` of a better one (SIFT reports a blob
    once per orientation). Needs pycolmap."""
    from rvggt_jax.ba import quiet_pycolmap

    gray = np.ascontiguousarray(np.asarray(image, np.float32).mean(axis=0))
    h, w = gray.shape
    with quiet_pycolmap() as pycolmap:
        opts = pycolmap.FeatureExtractionOptions()
        opts.sift.max_num_features = max(4 * count, 256)
        # the upsampled octave (-1) only for small images: at the model's 518 pixels it costs
        # 4x the time for the tiniest blobs, the ones a tracker localises worst
        opts.sift.first_octave = 0 if max(h, w) >= 400 else -1
        opts.num_threads = 1  # one image at a time, small: threads would only contend with XLA's
        if hasattr(pycolmap, "FeatureExtractor"):  # pycolmap >= 4: keypoints as FeatureKeypoints
            kp, _ = pycolmap.FeatureExtractor.create(opts, pycolmap.Device.cpu).extract_from_float32_array(gray)
            kp = pycolmap.keypoints_to_matrix(kp)
        else:  # the older Sift class: keypoints as an [M, 4] array
            kp, _ = pycolmap.Sift(opts, pycolmap.Device.cpu).extract(gray)
    xy = np.asarray(kp, np.float64)[:, :2].reshape(-1, 2)
    inside = ((xy[:, 0] >= border) & (xy[:, 0] < w - border) & (xy[:, 1] >= border) & (xy[:, 1] < h - border))
    xy = xy[inside]
    col = np.clip(xy[:, 0].astype(int), 0, w - 1)
    row = np.clip(xy[:, 1].astype(int), 0, h - 1)
    if valid is not None:
        keep = np.asarray(valid, bool)[row, col]
        xy, row, col = xy[keep], row[keep], col[keep]
    order = np.argsort(-np.asarray(score, np.float64)[row, col], kind="stable")
    chosen: list[np.ndarray] = []
    for p in xy[order]:
        if len(chosen) == count:
            break
        if chosen and np.min(np.sum((np.asarray(chosen) - p) ** 2, axis=1)) < min_distance ** 2:
            continue
        chosen.append(p)
    return np.asarray(chosen, np.float64).reshape(-1, 2)


def query_points(image: np.ndarray, score: np.ndarray, valid: np.ndarray | None, count: int,
                 keypoints: str = "sift") -> np.ndarray:
    """Exactly `count` query points [count, 2] of one frame (image [3, H, W], score and
    valid [H, W]) when the frame has room for them: SIFT keypoints topped up with grid
    points (`keypoints="sift"`), or grid points only ("grid"); see the module docstring."""
    if keypoints not in KEYPOINT_METHODS:
        raise ValueError(f"keypoints must be one of {KEYPOINT_METHODS}; got {keypoints!r}")
    pts = sift_keypoints(image, score, valid, count) if keypoints == "sift" else np.zeros((0, 2))
    if len(pts) < count:
        pts = np.concatenate([pts, grid_keypoints(score, valid, count - len(pts), exclude=pts)])
    return pts


def track_from_query_frames(track_fn: TrackFn, images: np.ndarray, queries: Sequence[np.ndarray],
                            query_frames: Sequence[int]) -> Tracks:
    """Track `queries[k]` ([N_k, 2] pixels of frame `query_frames[k]`) through images
    [S, 3, H, W]: for each query frame j the tracker runs on the frames reordered as
    (j, then the others in order), since it follows points given in its first frame, and
    its outputs are put back in the original frame order. In its own query frame a track
    is the query point itself, with visibility and confidence 1 (it is observed there by
    construction). Returns the `Tracks` of all queries, query frame by query frame."""
    s = images.shape[0]
    pts, vis, conf, qf = [], [], [], []
    for j, q in zip(query_frames, queries):
        q = np.asarray(q, np.float64).reshape(-1, 2)
        if not len(q):
            continue
        order = np.array([j] + [i for i in range(s) if i != j])
        t, v, c = (np.asarray(a) for a in track_fn(images[order], q))
        if t.shape != (s, len(q), 2) or v.shape != (s, len(q)) or c.shape != (s, len(q)):
            raise ValueError(f"track_fn must return [S, N, 2], [S, N], [S, N] = {(s, len(q))}; got {t.shape}, "
                             f"{v.shape}, {c.shape}")
        back = np.empty(s, dtype=int)
        back[order] = np.arange(s)  # row i of the reordered output belongs to frame order[i]
        t, v, c = t[back].astype(np.float64), v[back].astype(np.float32), c[back].astype(np.float32)
        t[j], v[j], c[j] = q, 1.0, 1.0
        pts.append(t)
        vis.append(v)
        conf.append(c)
        qf.append(np.full(len(q), j, np.int32))
    if not pts:
        return Tracks(np.zeros((s, 0, 2)), np.zeros((s, 0), np.float32), np.zeros((s, 0), np.float32),
                      np.zeros(0, np.int32))
    return Tracks(np.concatenate(pts, axis=1), np.concatenate(vis, axis=1), np.concatenate(conf, axis=1),
                  np.concatenate(qf))


def filter_tracks(tracks: Tracks, image_hw: tuple[int, int], valid: np.ndarray | None = None, *,
                  vis_threshold: float = 0.2, conf_threshold: float = 0.2) -> np.ndarray:
    """Observations to keep [S, N] bool: visibility >= `vis_threshold`, confidence >=
    `conf_threshold`, finite, inside the image (H, W) and on image content (`valid`
    [S, H, W] bool, False on padding; None: everywhere)."""
    h, w = image_hw
    p = tracks.points
    x, y = p[..., 0], p[..., 1]
    keep = np.isfinite(p).all(axis=-1) & (tracks.vis >= vis_threshold) & (tracks.conf >= conf_threshold)
    keep &= (x >= 0) & (x < w) & (y >= 0) & (y < h)
    if valid is not None:
        valid = np.asarray(valid, bool)
        s = np.arange(p.shape[0])[:, None]
        col = np.clip(np.nan_to_num(x).astype(int), 0, w - 1)
        row = np.clip(np.nan_to_num(y).astype(int), 0, h - 1)
        keep &= valid[s, row, col]
    return keep
