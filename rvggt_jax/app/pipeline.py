"""From images to a reconstruction in memory: `reconstruct(images, params, config)` runs
the model and returns a `Reconstruction` (cameras in the original images' pixels, depth,
a confidence-filtered coloured point cloud), with the predicted cameras repaired where
they are unusable (`sanitize_cameras`) and the points chosen by confidence
(`select_points`). Nothing here touches files: `rvggt_jax.io.export` writes a
`Reconstruction`, `rvggt_jax.app.commands` is what `rvggt reconstruct` does around both.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from rvggt_jax.geometry import nearest_rotation

__all__ = ["Reconstruction", "apply_masks", "build_reconstruction", "parse_threshold", "reconstruct", "reconstruction_from_outputs", "run_model",
           "sanitize_cameras", "select_points"]

POINT_SOURCES = ("depth", "pointmap")
_OUTPUT_KEYS = ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf", "descriptors")


@dataclass(frozen=True, eq=False)
class Reconstruction:
    """One reconstructed sequence of S images (network input H x W), numpy arrays.

    names        S image names
    images       [S, 3, H, W] float32 in [0, 1], the network input
    valid        [S, H, W] bool, image content the outputs keep (False on padding and on
                 masked pixels)
    extrinsic    [S, 3, 4] float64 world-to-camera, OpenCV axes (x right, y down, z forward)
    intrinsic    [S, 3, 3] float64 pinhole in the ORIGINAL image's pixels
    sizes        S (width, height) of the original images
    network_intrinsic  [S, 3, 3] float64 in the network input's pixels
    depth        [S, H, W] float32, depth_conf [S, H, W] float32
    points       [N, 3] float32 world points kept by confidence, colors [N, 3] uint8,
                 confidences [N] float32, frames [N] int32 (the source image)
    conf_threshold  the absolute confidence threshold used
    repairs      one message per kind of camera repair (`sanitize_cameras`)
    """

    names: tuple[str, ...]
    images: np.ndarray
    valid: np.ndarray
    extrinsic: np.ndarray
    intrinsic: np.ndarray
    sizes: tuple[tuple[int, int], ...]
    network_intrinsic: np.ndarray
    depth: np.ndarray
    depth_conf: np.ndarray
    points: np.ndarray
    colors: np.ndarray
    confidences: np.ndarray
    frames: np.ndarray
    conf_threshold: float
    repairs: tuple[str, ...] = ()


def run_model(params, images, config, compiled=None, mesh=None) -> dict[str, np.ndarray]:
    """The forward pass on images [S, 3, H, W] -> numpy outputs of batch element 0
    (`pose_enc`, `depth`, `depth_conf`, and `world_points(_conf)` with the point head).
    Images that are exactly some v / 255 (as `load_images` makes them) go in as uint8
    (`network_images`): `compiled`, the forward already compiled for these shapes
    (`MemoryReport.compiled`, of the sharded forward when `mesh` is given), must then
    be compiled for uint8 images; `mesh`: split the frames over its
    "frames" axis (`rvggt_jax.sharded_forward`)."""
    import functools

    import jax

    from rvggt_jax.model.forward import rvggt_forward
    from rvggt_jax.planning.memory import unused_donation_allowed

    missing = [k for k, on in (("camera", config.enable_camera), ("depth", config.enable_depth)) if not on]
    if missing:
        raise ValueError(f"the model has no {' / '.join(missing)} head; a reconstruction needs the camera and "
                         f"depth heads")
    from rvggt_jax.io.images import network_images

    batch = jax.numpy.asarray(network_images(images))[None]
    from rvggt_jax.model.low_memory import low_memory_forward, runs_in_parts

    if mesh is None and compiled is None and runs_in_parts(config):
        # the low-memory mode runs in parts (`model.low_memory`), as `rvggt plan` plans it
        out = low_memory_forward(params, batch, config)
    else:
        forward = rvggt_forward
        if mesh is not None:
            from rvggt_jax.parallel.sharded import input_shardings, sharded_forward

            replicated, split = input_shardings(mesh, batch.shape[1])
            params, batch = jax.device_put(params, replicated), jax.device_put(batch, split)
            forward = functools.partial(sharded_forward, mesh=mesh)
        # the batch is this call's own array: donated, XLA may reuse its buffer once the
        # patch embed has read it (as `memory_report` plans the program)
        with unused_donation_allowed():
            out = (compiled if compiled is not None else jax.jit(forward, donate_argnums=1))(params, batch, config)
    # (float32 for what follows: the low-memory mode returns 16-bit depth and points)
    return {k: np.asarray(out[k])[0].astype(np.float32, copy=False) for k in _OUTPUT_KEYS if k in out}


def reconstruct(images, params, config, *, names: Sequence[str] | None = None, infos: Sequence[Any] | None = None,
                points_from: str = "depth", conf_threshold: str | float = "50%",
                max_points: int | None = 2_000_000, compiled=None, masks=None) -> Reconstruction:
    """Run the model on images [S, 3, H, W] (as `rvggt_jax.load_images` returns them) and
    build the `Reconstruction` (the keyword arguments: see `build_reconstruction`);
    `compiled`: the forward already compiled for these shapes (`MemoryReport.compiled`);
    masks [S, H, W] bool (True = keep): masked pixels are 0 in the network input
    (`apply_masks`) and have no point."""
    images = np.asarray(images, dtype=np.float32)
    _check_images(images)
    if masks is not None:
        images = apply_masks(images, masks)
    _check_options(points_from, conf_threshold, max_points)
    if points_from == "pointmap" and not config.enable_point:
        raise ValueError("points_from='pointmap' needs the point head; the model has none")
    outputs = run_model(params, images, config, compiled)
    return reconstruction_from_outputs(outputs, images, names=names, infos=infos, points_from=points_from,
                                       conf_threshold=conf_threshold, max_points=max_points, masks=masks)


def apply_masks(images: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """images [S, 3, H, W] with the pixels where masks [S, H, W] (True = keep) is False set
    to 0: what the model sees of a masked pixel (upstream's README: masked pixels 0)."""
    images = np.asarray(images, dtype=np.float32)
    masks = np.asarray(masks, dtype=bool)
    if masks.shape != (images.shape[0],) + images.shape[2:]:
        raise ValueError(f"masks must be [S, H, W] = {(images.shape[0],) + images.shape[2:]}; got {masks.shape}")
    return images * masks[:, None]


def reconstruction_from_outputs(outputs: Mapping[str, np.ndarray], images, **kw) -> Reconstruction:
    """The `Reconstruction` of one batch element's model outputs: `pose_enc` [S, 9] decoded
    into cameras, then `build_reconstruction` (its keyword arguments) with `depth`,
    `depth_conf` (and `world_points`, `world_points_conf` when present)."""
    from rvggt_jax.geometry import pose_encoding_to_extri_intri

    images = np.asarray(images, dtype=np.float32)
    _check_images(images)
    s, _, h, w = images.shape
    pose_enc = np.asarray(outputs["pose_enc"])
    if pose_enc.shape != (s, 9):
        raise ValueError(f"pose_enc must be [S, 9] with S = {s}; got {pose_enc.shape}")
    extrinsic, intrinsic = (np.asarray(a)[0] for a in pose_encoding_to_extri_intri(pose_enc[None], (h, w)))
    return build_reconstruction(images, extrinsic, intrinsic, outputs["depth"], outputs["depth_conf"],
                                world_points=outputs.get("world_points"),
                                world_points_conf=outputs.get("world_points_conf"), **kw)


def build_reconstruction(images, extrinsic, intrinsic, depth, depth_conf, *, world_points=None,
                         world_points_conf=None, names: Sequence[str] | None = None,
                         infos: Sequence[Any] | None = None, points_from: str = "depth",
                         conf_threshold: str | float = "50%", max_points: int | None = 2_000_000,
                         masks=None) -> Reconstruction:
    """A `Reconstruction` from predicted cameras and maps at network resolution.

    images [S, 3, H, W] in [0, 1]; extrinsic [S, 3, 4] world-to-camera; intrinsic
    [S, 3, 3] in network pixels; depth [S, H, W(, 1)], depth_conf [S, H, W];
    world_points [S, H, W, 3] and world_points_conf [S, H, W] for
    `points_from="pointmap"` (`"depth"` unprojects the depth maps with the cameras,
    upstream's default). names [S] (default `frame_000`, ...); infos [S] `ImageInfo` of
    `load_images_with_info` (None: network pixels are the original pixels). Unusable
    cameras are repaired (`sanitize_cameras`, messages in `repairs`); conf_threshold /
    max_points choose the points (`select_points`). masks [S, H, W] bool (True = keep):
    masked pixels are left out of `valid`, so they have no point (PLY, GLB, COLMAP) and
    no depth in the depth PNGs."""
    images = np.asarray(images, dtype=np.float32)
    _check_images(images)
    _check_options(points_from, conf_threshold, max_points)
    s, _, h, w = images.shape
    names = tuple(f"frame_{i:03d}" for i in range(s)) if names is None else tuple(names)
    infos = [None] * s if infos is None else list(infos)
    if len(names) != s or len(infos) != s:
        raise ValueError(f"{s} images need {s} names and infos; got {len(names)} and {len(infos)}")
    extrinsic, intrinsic, repairs = sanitize_cameras(extrinsic, intrinsic, (h, w))
    depth = np.asarray(depth, dtype=np.float32)
    depth = depth[..., 0] if depth.ndim == 4 else depth
    depth_conf = np.asarray(depth_conf, dtype=np.float32)
    if depth.shape != (s, h, w) or depth_conf.shape != (s, h, w):
        raise ValueError(f"depth and depth_conf must be [S, H, W] = {(s, h, w)}; got {depth.shape}, "
                         f"{depth_conf.shape}")
    valid = np.stack([np.ones((h, w), bool) if info is None else info.valid_mask(h, w) for info in infos])
    if masks is not None:
        masks = np.asarray(masks, dtype=bool)
        if masks.shape != (s, h, w):
            raise ValueError(f"masks must be [S, H, W] = {(s, h, w)}; got {masks.shape}")
        valid = valid & masks
    colors = (np.clip(images.transpose(0, 2, 3, 1), 0, 1) * 255 + 0.5).astype(np.uint8)

    if points_from == "depth":
        pts, conf, pvalid = _unproject(depth, extrinsic, intrinsic), depth_conf, valid & (depth > 1e-8)
    else:
        if world_points is None or world_points_conf is None:
            raise ValueError("points_from='pointmap' needs world_points and world_points_conf")
        pts = np.asarray(world_points, dtype=np.float32)
        conf, pvalid = np.asarray(world_points_conf, dtype=np.float32), valid
    points, point_colors, threshold, idx = select_points(pts, conf, colors, pvalid, conf_threshold, max_points,
                                                         return_index=True)
    original_k = np.stack([intrinsic[i] if info is None else info.intrinsic_to_original(intrinsic[i])
                           for i, info in enumerate(infos)])
    sizes = tuple((w, h) if info is None else (info.width, info.height) for info in infos)
    return Reconstruction(
        names=names, images=images, valid=valid, extrinsic=extrinsic, intrinsic=original_k, sizes=sizes,
        network_intrinsic=intrinsic, depth=depth, depth_conf=depth_conf, points=points, colors=point_colors,
        confidences=conf.reshape(-1)[idx].astype(np.float32), frames=(idx // (h * w)).astype(np.int32),
        conf_threshold=threshold, repairs=tuple(repairs))


def _check_images(images: np.ndarray) -> None:
    if images.ndim != 4 or images.shape[1] != 3 or images.shape[0] < 1:
        raise ValueError(f"images must be [S, 3, H, W] with S >= 1; got {images.shape}")


def _check_options(points_from: str, conf_threshold, max_points) -> None:
    if points_from not in POINT_SOURCES:
        raise ValueError(f"points_from must be 'depth' or 'pointmap'; got {points_from!r}")
    parse_threshold(conf_threshold)
    if max_points is not None and max_points < 1:
        raise ValueError(f"max_points must be at least 1; got {max_points}")


def sanitize_cameras(extrinsic: np.ndarray, intrinsic: np.ndarray, image_hw: tuple[int, int],
                     default_fov_deg: float = 60.0) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Make predicted cameras writable: extrinsic [S, 3, 4], intrinsic [S, 3, 3] ->
    copies with unusable values replaced, and a message per kind of replacement.

    A focal length that is not finite and positive (e.g. a predicted field of view of
    0, as random weights give) takes the other axis' focal when that one is usable,
    else the focal of a `default_fov_deg` horizontal field of view; non-finite
    rotations become the identity (re-orthonormalised otherwise) and non-finite
    translations 0. The principal point is the image centre `(W/2, H/2)` if not finite.
    """
    e = np.array(extrinsic, dtype=np.float64, copy=True)
    k = np.array(intrinsic, dtype=np.float64, copy=True)
    h, w = image_hw
    msgs: dict[str, list[int]] = {}

    def note(msg, i):
        msgs.setdefault(msg, []).append(i)

    def usable(f):
        return bool(np.isfinite(f) and f > 0 and f < 1e6 * max(h, w))

    for i in range(len(e)):
        fx, fy = k[i, 0, 0], k[i, 1, 1]
        if not usable(fx) or not usable(fy):
            default = (w / 2) / np.tan(np.radians(default_fov_deg) / 2)
            good = fx if usable(fx) else fy if usable(fy) else default
            note("unusable predicted focal length replaced" + ("" if usable(fx) or usable(fy) else
                 f" by a {default_fov_deg:g} degree field of view"), i)
            k[i, 0, 0] = fx if usable(fx) else good
            k[i, 1, 1] = fy if usable(fy) else good
        if not np.isfinite(k[i, :2, 2]).all():
            k[i, 0, 2], k[i, 1, 2] = w / 2, h / 2
            note("non-finite principal point replaced by the image centre", i)
        if not np.isfinite(e[i, :, :3]).all():
            e[i, :, :3] = np.eye(3)
            note("non-finite rotation replaced by the identity", i)
        else:
            e[i, :, :3] = nearest_rotation(e[i, :, :3])
        if not np.isfinite(e[i, :, 3]).all():
            e[i, :, 3] = 0.0
            note("non-finite translation replaced by 0", i)
    return e, k, [f"{m} (frame{'s' if len(ix) > 1 else ''} {', '.join(map(str, ix))})" for m, ix in msgs.items()]


def select_points(points: np.ndarray, conf: np.ndarray, colors: np.ndarray, valid: np.ndarray | None,
                  threshold: str | float = "50%", max_points: int | None = None,
                  seed: int = 0, return_index: bool = False) -> tuple:
    """Filter a point map by confidence.

    points [S, H, W, 3], conf [S, H, W], colors [S, H, W, 3] uint8, valid [S, H, W]
    (image content, not padding). `threshold`: a number X keeps points with
    conf >= X (VGGT's confidences are 1 + exp(.) >= 1); a string "P%" keeps points at
    or above the P-th percentile of the confidences of valid pixels ("0%" keeps all).
    Non-finite points are dropped. At most `max_points` are kept (uniform random
    subset, fixed seed). Returns points [N, 3] float32, colors [N, 3] uint8 and the
    absolute confidence threshold used; with `return_index`, also the kept points'
    flat indices [N] into [S * H * W] (frame = index // (H * W)).
    """
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    cf = np.asarray(conf, dtype=np.float32).reshape(-1)
    col = np.asarray(colors).reshape(-1, 3)
    ok = np.all(np.isfinite(pts), axis=1) & np.isfinite(cf)
    if valid is not None:
        ok &= np.asarray(valid, dtype=bool).reshape(-1)
    thr = parse_threshold(threshold)
    if isinstance(thr, tuple):
        abs_thr = float(np.percentile(cf[ok], thr[0])) if ok.any() else 0.0
    else:
        abs_thr = float(thr)
    ok &= cf >= abs_thr
    idx = np.flatnonzero(ok)
    if max_points is not None and len(idx) > max_points:
        idx = np.sort(np.random.default_rng(seed).choice(idx, size=max_points, replace=False))
    if return_index:
        return pts[idx], col[idx].astype(np.uint8), abs_thr, idx
    return pts[idx], col[idx].astype(np.uint8), abs_thr


def parse_threshold(threshold: str | float) -> float | tuple[float]:
    """`"P%"` -> (P,) (a percentile in [0, 100]); a number or numeric string -> float.
    NaN and infinities are refused (a NaN threshold would keep no point, silently)."""
    value = _parse_threshold(threshold)
    if not np.all(np.isfinite(value)):
        raise ValueError(f"bad confidence threshold {threshold!r}: must be a finite number or a percentage like '50%'")
    return value


def _parse_threshold(threshold: str | float) -> float | tuple[float]:
    if isinstance(threshold, str):
        s = threshold.strip()
        if s.endswith("%"):
            try:
                p = float(s[:-1])
            except ValueError:
                raise ValueError(f"bad confidence threshold {threshold!r}: expected a number or a percentage like '50%'") from None
            if not 0.0 <= p <= 100.0:
                raise ValueError(f"confidence percentile must be in [0, 100]; got {threshold!r}")
            return (p,)
        try:
            return float(s)
        except ValueError:
            raise ValueError(f"bad confidence threshold {threshold!r}: expected a number or a percentage like '50%'") from None
    return float(threshold)


def _unproject(depth: np.ndarray, extrinsic: np.ndarray, intrinsic: np.ndarray) -> np.ndarray:
    """World points [S, H, W, 3] of depth [S, H, W]: upstream's unprojection (pixel
    (col, row) at integer coordinates), via `rvggt_jax.geometry`."""
    from rvggt_jax.geometry import unproject_depth_map_to_point_map

    return np.asarray(unproject_depth_map_to_point_map(depth, extrinsic, intrinsic), dtype=np.float32)
