"""Training examples: your own folder of scenes, or procedural synthetic scenes.

**Folder layout** (read by `rvggt_jax.eval.datasets.folder`, the evaluation's "folder"
format, also what `rvggt reconstruct` writes):

    DATA_DIR/<scene>/images/<name>.png|jpg ...
    DATA_DIR/<scene>/cameras.json    {"frames": [{"image": "<name>.png",
                                       "extrinsic": 3x4 world-to-camera (OpenCV: x right, y down, z forward),
                                       "intrinsic": 3x3 in pixels of that image}, ...]}
    DATA_DIR/<scene>/depth/<stem>.npy   optional depth [H, W] float (z, 0 = unknown), or
    DATA_DIR/<scene>/depth/<stem>.png   16-bit PNG with depth/depth_scale.json {"scale": s}
                                        (depth = value x s)

DATA_DIR may itself be one scene (DATA_DIR/cameras.json). Pixel (col, row) integer
coordinates are pixel centres (upstream's unprojection convention).

An *example* is a dict of numpy arrays for S frames at the network size H x W (see
`rvggt_jax.train.losses` for the keys and shapes): images are resized to H x W (the
intrinsics follow), depth by nearest neighbour, and the scene is normalised as upstream
trains: cameras relative to frame 0 (its extrinsic becomes [I | 0]) and every length
divided by the mean distance of the valid points from frame 0's camera.

**Other formats**: `open_scenes(DATA_DIR, fmt)` reads every format of
`rvggt_jax.eval.datasets` as training data (folder, co3d, scannet, 7scenes, nrgbd, dtu, and
colmap = the T&T reader), "auto" detecting it (`TRAIN_FORMATS`, in order). **Batches**:
`step_batch(scenes, step, seed, ...)` is step `step`'s batch, a function of (seed, step)
only (exact resume): a random frame count in a range rounded down to a compiled bucket
(`draw_batch_plan`), read from the files then (`BatchStream` reads ahead in a thread).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np

from rvggt_jax.errors import InputError

Example = dict[str, np.ndarray]


def _check_size(size: tuple[int, int], patch: int = 14) -> tuple[int, int]:
    h, w = (int(v) for v in size)
    if h <= 0 or w <= 0 or h % patch or w % patch:
        raise InputError(f"the network size must be positive multiples of {patch}; got {h} x {w}")
    return h, w


def _resize_image(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """[h0, w0, 3] uint8 or float in [0, 1] -> [H, W, 3] float32 in [0, 1] (bilinear)."""
    from PIL import Image

    if img.dtype != np.uint8:
        img = (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
    h, w = size
    if img.shape[:2] != (h, w):
        img = np.asarray(Image.fromarray(img).resize((w, h), Image.BILINEAR))
    return img.astype(np.float32) / 255.0


def _resize_depth(depth: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Nearest neighbour (no depth is invented between surfaces)."""
    from PIL import Image

    h, w = size
    if depth.shape == (h, w):
        return depth.astype(np.float32)
    return np.asarray(Image.fromarray(depth.astype(np.float32), mode="F").resize((w, h), Image.NEAREST))


def _scale_intrinsics(k: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics after resizing by (sx, sy), integer pixels being pixel centres:
    x' + 0.5 = (x + 0.5) sx."""
    k = np.array(k, np.float64)
    k[0, 0], k[0, 1], k[1, 1] = k[0, 0] * sx, k[0, 1] * sx, k[1, 1] * sy
    k[0, 2] = (k[0, 2] + 0.5) * sx - 0.5
    k[1, 2] = (k[1, 2] + 0.5) * sy - 0.5
    return k


def _inverse(ext: np.ndarray) -> np.ndarray:
    """[S, 3, 4] world-to-camera -> [S, 4, 4] camera-to-world."""
    out = np.tile(np.eye(4), (len(ext), 1, 1))
    r, t = ext[:, :3, :3], ext[:, :3, 3:]
    out[:, :3, :3] = np.transpose(r, (0, 2, 1))
    out[:, :3, 3:] = -np.transpose(r, (0, 2, 1)) @ t
    return out


def world_points(depth: np.ndarray, extrinsics: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """depth [S, H, W], world-to-camera [S, 3, 4], intrinsics [S, 3, 3] -> world points
    [S, H, W, 3] (float64)."""
    s, h, w = depth.shape
    cols, rows = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pix = np.stack([cols, rows, np.ones_like(cols)], -1)  # [H, W, 3]
    rays = np.einsum("sij,hwj->shwi", np.linalg.inv(intrinsics), pix)
    cam = rays * depth[..., None]
    c2w = _inverse(extrinsics)
    return np.einsum("sij,shwj->shwi", c2w[:, :3, :3], cam) + c2w[:, None, None, :3, 3]


def make_example(images: np.ndarray, extrinsics: np.ndarray, intrinsics: np.ndarray,
                 depth: np.ndarray | None, size: tuple[int, int] | None = None, normalize: bool = True) -> Example:
    """One training example from S frames: images [S, h0, w0, 3] (uint8, or float in
    [0, 1]), extrinsics [S, 3, 4] (or [S, 4, 4]) world-to-camera, intrinsics [S, 3, 3] in
    pixels of the images, depth [S, h0, w0] (0 = unknown) or None; resized to `size`
    (H, W; default: the images' size, which must then be multiples of 14)."""
    images = np.asarray(images)
    if images.ndim != 4 or images.shape[-1] != 3:
        raise InputError(f"images must be [S, H, W, 3]; got shape {images.shape}")
    s, h0, w0 = images.shape[:3]
    extrinsics = np.asarray(extrinsics, np.float64)[:, :3, :4]
    intrinsics = np.asarray(intrinsics, np.float64)
    if extrinsics.shape != (s, 3, 4) or intrinsics.shape != (s, 3, 3):
        raise InputError(f"need one 3x4 extrinsic and one 3x3 intrinsic per frame ({s}); got "
                         f"{extrinsics.shape} and {intrinsics.shape}")
    h, w = _check_size(size if size is not None else (h0, w0))
    sx, sy = w / w0, h / h0
    imgs = np.stack([_resize_image(im, (h, w)) for im in images]).transpose(0, 3, 1, 2)
    ks = np.stack([_scale_intrinsics(k, sx, sy) for k in intrinsics])
    if depth is None:
        d = np.zeros((s, h, w), np.float32)
    else:
        depth = np.asarray(depth, np.float32)
        if depth.shape[0] != s or depth.ndim != 3:
            raise InputError(f"depth must be [S, H, W] with S = {s}; got shape {depth.shape}")
        d = np.stack([_resize_depth(x, (h, w)) for x in depth])
    d = np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)
    ex = {"images": imgs.astype(np.float32), "extrinsics": extrinsics, "intrinsics": ks, "depth": d}
    return normalize_example(ex) if normalize else _finish(ex)


def normalize_example(ex: Example) -> Example:
    """Cameras relative to frame 0, lengths divided by the mean distance of the valid
    world points from camera 0 (upstream's normalisation); adds world_points and
    point_mask."""
    ext = np.asarray(ex["extrinsics"], np.float64)
    c2w0 = _inverse(ext[:1])[0]
    rel = np.einsum("sij,jk->sik", np.concatenate([ext, np.tile([[[0, 0, 0, 1.0]]], (len(ext), 1, 1))], 1), c2w0)
    ex = dict(ex, extrinsics=rel[:, :3])
    ex = _finish(ex)
    mask = ex["point_mask"]
    scale = float(np.linalg.norm(ex["world_points"][mask], axis=-1).mean()) if mask.any() else 1.0
    scale = scale if np.isfinite(scale) and scale > 0 else 1.0
    ext = ex["extrinsics"].copy()
    ext[:, :, 3] /= scale
    return dict(ex, extrinsics=ext.astype(np.float32), depth=(ex["depth"] / scale).astype(np.float32),
                world_points=(ex["world_points"] / scale).astype(np.float32))


def _finish(ex: Example) -> Example:
    mask = ex["depth"] > 0
    pts = np.where(mask[..., None], world_points(ex["depth"], ex["extrinsics"], ex["intrinsics"]), 0.0)
    return dict(ex, extrinsics=np.asarray(ex["extrinsics"], np.float32),
                intrinsics=np.asarray(ex["intrinsics"], np.float32),
                world_points=pts.astype(np.float32), point_mask=mask)


def synthetic_example(frames: int, size: tuple[int, int], seed: int = 0, **scene_kwargs) -> Example:
    """An example from `rvggt_jax.synthetic.make_scene` (rendered at the network size)."""
    from rvggt_jax.synthetic import make_scene

    h, w = _check_size(size)
    sc = make_scene(frames=frames, height=h, width=w, seed=seed, **scene_kwargs)
    return make_example(sc.images, sc.extrinsics, sc.intrinsics, sc.depth)


def folder_scenes(root: str | Path) -> list:
    """The scenes of a folder in the layout above (`rvggt_jax.eval.datasets.Scene`)."""
    from rvggt_jax.eval.datasets import folder

    root = Path(root)
    if not root.is_dir():
        raise InputError(f"no such data folder: {root}")
    return [folder.read_scene(root, name) for name in folder.list_scenes(root)]


def scene_example(scene, frames: int, size: tuple[int, int], rng: np.random.Generator | None = None,
                  frame_indices: Sequence[int] | None = None) -> Example:
    """`frames` frames of a `Scene` (`frame_indices`, else a random sorted subset with
    `rng`, else evenly spaced) as an example at `size`. Only those frames' files are read."""
    from PIL import Image, ImageOps

    from rvggt_jax.eval.datasets import DatasetError

    n = len(scene)
    if n < frames:
        raise InputError(f"scene {scene.name} has {n} frames; {frames} are needed")
    if frame_indices is not None:
        idx = np.asarray(frame_indices, int)
    elif rng is not None:
        idx = np.sort(rng.choice(n, frames, replace=False))
    else:
        idx = np.round(np.linspace(0, n - 1, frames)).astype(int)
    imgs = []
    for i in idx:
        with Image.open(scene.image_paths[i]) as im:
            imgs.append(np.asarray(ImageOps.exif_transpose(im).convert("RGB")))
    shapes = {im.shape for im in imgs}
    if len(shapes) > 1:
        raise InputError(f"scene {scene.name}: frames of different sizes {sorted(shapes)}")
    try:
        depth = np.stack([scene.depth(int(i)) for i in idx]) if scene.has_depth else None
    except DatasetError as e:
        raise InputError(f"scene {scene.name}: {e}") from None
    if depth is not None and depth.shape[1:] != imgs[0].shape[:2]:
        depth = np.stack([_resize_depth(d, imgs[0].shape[:2]) for d in depth])
    return make_example(np.stack(imgs), scene.extrinsics[idx], scene.intrinsics[idx], depth, size)


def stack(examples: Sequence[Example]) -> Example:
    """Examples with the same keys and shapes -> a batch (leading axis B)."""
    return {k: np.stack([e[k] for e in examples]) for k in examples[0]}


def batches(examples_fn, batch_size: int, seed: int = 0) -> Iterator[Example]:
    """Endless batches: `examples_fn(rng)` returns one example per call."""
    rng = np.random.default_rng(seed)
    while True:
        yield stack([examples_fn(rng) for _ in range(batch_size)])


# ---------------------------------------------------------------------------------------
# datasets for training: the evaluation's readers, random frame counts in a few buckets
# ---------------------------------------------------------------------------------------

TRAIN_FORMATS = ("folder", "co3d", "scannet", "7scenes", "nrgbd", "dtu", "colmap")
"""The formats `open_scenes` reads, in the order auto-detection tries them ("colmap" is
`rvggt_jax.eval.datasets.tnt`: <scene>/images + <scene>/sparse/0/{cameras,images}.bin|txt)."""

_MODULES = {"colmap": "tnt", "tnt": "tnt"}
_EXPECTED = {"folder": "<scene>/cameras.json", "co3d": "<category>/frame_annotations.jgz",
             "scannet": "<scene>/pose/<i>.txt", "7scenes": "<scene>/TestSplit.txt", "nrgbd": "<scene>/poses.txt",
             "dtu": "scan<N>/cams/<id>_cam.txt", "colmap": "<scene>/sparse/0/images.bin"}
_DEPTH = {"folder": "depth/<stem>.npy or depth/<stem>.png", "co3d": "depths/<frame>.jpg.geometric.png",
          "scannet": "depth/<i>.png", "7scenes": "<frame>.depth.proj.png", "nrgbd": "depth/depth<i>.png"}


def _format_module(fmt: str):
    from rvggt_jax.eval.datasets import get_format

    return get_format(_MODULES.get(fmt, fmt))


def detect_format(root: str | Path) -> str:
    """The first of `TRAIN_FORMATS` whose scene listing finds scenes in `root`; an
    InputError naming the file each format expected when none does."""
    from rvggt_jax.eval.datasets import DatasetError

    root = Path(root)
    if not root.is_dir():
        raise InputError(f"no such data folder: {root}")
    for fmt in TRAIN_FORMATS:
        try:
            if _format_module(fmt).list_scenes(root):
                return fmt
        except (DatasetError, OSError):
            continue
    expected = ", ".join(f"{root / e} ({f})" for f, e in _EXPECTED.items())
    raise InputError(f"no scene with cameras in {root}: expected one of {expected}")


def open_scenes(root: str | Path, fmt: str = "auto", *, require_depth: bool = False,
                log=None) -> tuple[str, list]:
    """(format, scenes) of a training data folder: every scene's frame list, cameras and
    where its depth maps are (`rvggt_jax.eval.datasets.Scene`); no image or depth is
    read (batches read theirs, `scene_example`). `fmt`: a name of `TRAIN_FORMATS` or
    "auto" (`detect_format`). Every listed depth file must exist (an InputError names
    the first missing one); a scene without depth is a camera-only scene (`log` says so
    and names the file it looked for), or an InputError with `require_depth`."""
    from rvggt_jax.eval.datasets import DatasetError

    root = Path(root)
    if not root.is_dir():
        raise InputError(f"no such data folder: {root}")
    fmt = detect_format(root) if fmt == "auto" else fmt.lower()
    if fmt not in TRAIN_FORMATS and fmt != "tnt":
        raise InputError(f"unknown data format {fmt!r}; known: auto, {', '.join(TRAIN_FORMATS)}")
    mod = _format_module(fmt)
    try:
        names = mod.list_scenes(root)
        scenes = [mod.read_scene(root, n) for n in names]
    except DatasetError as e:
        raise InputError(f"{fmt} data in {root}: {e} (expected {root / _EXPECTED.get(fmt, '<scene>')})") from None
    for sc in scenes:
        if sc.extrinsics is None or sc.intrinsics is None:
            raise InputError(f"scene {sc.name} has no cameras: {root / _EXPECTED.get(fmt, '<scene>/cameras.json')} "
                             "not found")
        if sc.depth_paths is not None:
            missing = next((p for p in sc.depth_paths if not Path(p).is_file()), None)
            if missing is not None:
                raise InputError(f"scene {sc.name}: depth map {missing} not found")
        else:
            where = _DEPTH.get(fmt)
            what = (f"{root / sc.name / where} not found" if where else f"the {fmt} format has no depth maps")
            if require_depth:
                raise InputError(f"scene {sc.name} has no depth: {what}")
            if log is not None:
                log(f"scene {sc.name} has no depth ({what}): camera loss only")
    return fmt, scenes


def default_buckets(lo: int, hi: int) -> tuple[int, ...]:
    """The frame counts compiled for a range lo..hi: lo, the powers of two between, hi
    (2..24: 2, 4, 8, 16, 24)."""
    if lo < 1 or hi < lo:
        raise InputError(f"the frame range must be 1 <= min <= max; got {lo}..{hi}")
    out = {lo, hi}
    p = 1
    while p < hi:
        if p > lo:
            out.add(p)
        p *= 2
    return tuple(sorted(out))


def frame_plan(frames: int | tuple[int, int], buckets: Sequence[int] | None = None
               ) -> tuple[int, int, tuple[int, ...]]:
    """(min, max, buckets) of `FinetuneOptions.frames` (a count, or a (min, max) range)
    and its buckets (the frame counts a step is compiled for; default `default_buckets`).
    Every bucket must lie in the range and the smallest must be the minimum (a drawn
    count is rounded down to a bucket)."""
    lo, hi = (int(frames), int(frames)) if np.ndim(frames) == 0 else (int(frames[0]), int(frames[1]))
    bs = tuple(sorted({int(b) for b in buckets})) if buckets else default_buckets(lo, hi)
    if lo < 1 or hi < lo:
        raise InputError(f"the frame range must be 1 <= min <= max; got {lo}..{hi}")
    if bs[0] != lo or bs[-1] > hi:
        raise InputError(f"frame buckets {list(bs)} must lie in {lo}..{hi} and include the minimum {lo}")
    return lo, hi, bs


def step_rng(seed: int, step: int) -> np.random.Generator:
    """The generator of step `step`'s batch: a function of (seed, step) only, so a run
    resumed at step k draws exactly the batches the uninterrupted run drew."""
    return np.random.default_rng([int(seed), int(step)])


def draw_batch_plan(scene_frames: Sequence[int], step: int, seed: int, batch: int, frames: int | tuple[int, int],
                    buckets: Sequence[int] | None = None) -> tuple[list[int], list[np.ndarray]]:
    """Step `step`'s choice, from (seed, step) only: `batch` scenes (indices into
    `scene_frames`, each scene's frame count) and each one's sorted frame indices. A frame
    count is drawn uniformly in the range, clamped to the smallest chosen scene and
    rounded down to a bucket; every scene of the batch gets that many frames (one shape
    per step)."""
    lo, hi, bs = frame_plan(frames, buckets)
    usable = [i for i, n in enumerate(scene_frames) if n >= lo]
    if not usable:
        raise InputError(f"no scene has {lo} frames (the minimum); they have {sorted(scene_frames)}")
    rng = step_rng(seed, step)
    n = int(rng.integers(lo, hi + 1))
    picks = [usable[int(j)] for j in rng.integers(len(usable), size=batch)]
    n = min(n, min(scene_frames[i] for i in picks))
    s = max(b for b in bs if b <= n)
    return picks, [np.sort(rng.choice(scene_frames[i], s, replace=False)) for i in picks]


def step_batch(scenes: Sequence, step: int, seed: int, batch: int, frames: int | tuple[int, int],
               size: tuple[int, int], buckets: Sequence[int] | None = None) -> Example:
    """The batch of step `step` (`draw_batch_plan`), read from the scenes' files."""
    picks, idx = draw_batch_plan([len(s) for s in scenes], step, seed, batch, frames, buckets)
    return stack([scene_example(scenes[p], len(i), size, frame_indices=i) for p, i in zip(picks, idx)])


class BatchStream:
    """Batches of steps start, start + 1, ... < stop (`step_batch`), read ahead by a
    background thread (`prefetch` batches; 0: read in the caller's thread). Iterate for
    (step, batch); a reader error is raised in the caller. `close()` stops the thread."""

    def __init__(self, make: "Callable[[int], Example]", start: int, stop: int, prefetch: int = 2):
        import queue
        import threading

        self.make, self.start, self.stop, self.prefetch = make, start, stop, prefetch
        self._done = threading.Event()
        if prefetch > 0:
            self._q: "queue.Queue" = queue.Queue(maxsize=prefetch)
            self._thread = threading.Thread(target=self._run, daemon=True, name="rvggt-train-data")
            self._thread.start()

    def _run(self) -> None:
        import queue

        for i in range(self.start, self.stop):
            try:
                item = (i, self.make(i), None)
            except BaseException as e:  # handed to the consumer
                item = (i, None, e)
            while not self._done.is_set():
                try:
                    self._q.put(item, timeout=0.1)
                    break
                except queue.Full:
                    continue
            if self._done.is_set() or item[2] is not None:
                return

    def __iter__(self):
        for i in range(self.start, self.stop):
            if self.prefetch <= 0:
                yield i, self.make(i)
                continue
            j, b, err = self._q.get()
            if err is not None:
                raise err
            yield j, b

    def close(self) -> None:
        self._done.set()
