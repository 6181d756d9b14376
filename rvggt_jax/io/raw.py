"""predictions.npz (`rvggt reconstruct --save-raw`): the model's predictions of one run,
unfiltered, in network-input pixels, under the names upstream VGGT's demo saves them by
(`np.savez`), plus the image names. S frames, network input H x W:

    extrinsic                [S, 3, 4] float32  world-to-camera, OpenCV axes (cameras.json's)
    intrinsic                [S, 3, 3] float32  in the network input's pixels
    depth                    [S, H, W, 1] float32
    depth_conf               [S, H, W] float32
    world_points_from_depth  [S, H, W, 3] float32  depth unprojected with the cameras
    images                   [S, 3, H, W] float32  the network input, in [0, 1]
    pose_enc                 [S, 9] float32  the camera head's encoding (absT_quaR_FoV)
    image_names              [S] str  the input images' names, in frame order
    world_points             [S, H, W, 3] float32  the point head's map (absent without
    world_points_conf        [S, H, W] float32      a point head)

The cameras are those of every other output: decoded from `pose_enc`, a non-finite value
repaired as the run's warnings said. Nothing is masked or thresholded (the confidences
are there to do that). `load_predictions` reads a file back, checking it.
"""

from __future__ import annotations

import os
import zipfile
from pathlib import Path
from typing import Any, Mapping

import numpy as np

__all__ = ["OPTIONAL_KEYS", "RAW_NAME", "REQUIRED_KEYS", "RawPredictionsError", "load_predictions",
           "write_predictions"]

RAW_NAME = "predictions.npz"

# key -> shape, in the dimensions S, H, W (numbers are fixed sizes)
REQUIRED_KEYS: dict[str, tuple] = {
    "extrinsic": ("S", 3, 4), "intrinsic": ("S", 3, 3), "depth": ("S", "H", "W", 1), "depth_conf": ("S", "H", "W"),
    "world_points_from_depth": ("S", "H", "W", 3), "images": ("S", 3, "H", "W"), "pose_enc": ("S", 9),
    "image_names": ("S",),
}
OPTIONAL_KEYS: dict[str, tuple] = {"world_points": ("S", "H", "W", 3), "world_points_conf": ("S", "H", "W")}


class RawPredictionsError(ValueError):
    """A file that is not a predictions.npz of `rvggt reconstruct --save-raw` (or is damaged)."""


def write_predictions(path: str | os.PathLike, recon, outputs: Mapping[str, Any] | None = None) -> Path:
    """Write predictions.npz of `recon` (a `rvggt_jax.app.pipeline.Reconstruction`: its
    images, cameras, depth and names) to `path`. `outputs`: the model's outputs of the
    run (`pose_enc` [S, 9], and `world_points` [S, H, W, 3] / `world_points_conf`
    [S, H, W] when it has a point head); without them, or without `pose_enc`, pose_enc
    is encoded from the cameras. Returns the path."""
    from rvggt_jax.geometry import extri_intri_to_pose_encoding, unproject_depth_map_to_point_map

    outputs = outputs or {}
    images = np.asarray(recon.images, np.float32)
    s, _, h, w = images.shape
    extrinsic = np.asarray(recon.extrinsic, np.float32)
    intrinsic = np.asarray(recon.network_intrinsic, np.float32)
    depth = np.asarray(recon.depth, np.float32).reshape(s, h, w)
    arrays = dict(extrinsic=extrinsic, intrinsic=intrinsic, depth=depth[..., None],
                  depth_conf=np.asarray(recon.depth_conf, np.float32),
                  world_points_from_depth=unproject_depth_map_to_point_map(depth, extrinsic, intrinsic),
                  images=images, image_names=np.array([str(n) for n in recon.names]))
    arrays["pose_enc"] = (np.asarray(outputs["pose_enc"], np.float32) if "pose_enc" in outputs else
                          np.asarray(extri_intri_to_pose_encoding(extrinsic, intrinsic, (h, w))))
    for key in OPTIONAL_KEYS:
        if outputs.get(key) is not None:
            arrays[key] = np.asarray(outputs[key], np.float32)
    _check(arrays, f"the predictions to write to {path}")
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp.npz")  # (np.savez appends .npz to other names)
    np.savez(tmp, **arrays)
    os.replace(tmp, path)
    return path


def load_predictions(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The arrays of a predictions.npz (keys and shapes in the module docstring), checked:
    every required key there, every shape consistent with one S, H, W.
    `RawPredictionsError` naming what is wrong for a file that is not one (not an .npz,
    a key missing, a shape off); FileNotFoundError for no file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no predictions file at {path}")
    what = f"{path} is not a predictions.npz of `rvggt reconstruct --save-raw`"
    try:
        npz = np.load(path, allow_pickle=False)
        if not isinstance(npz, np.lib.npyio.NpzFile):  # a plain .npy: one array
            raise RawPredictionsError(f"{what}: it holds one array (.npy), not named arrays (.npz)")
        with npz:
            arrays = {k: npz[k] for k in npz.files}
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as e:
        if isinstance(e, RawPredictionsError):
            raise
        raise RawPredictionsError(f"{what}: cannot read it as .npz ({e})") from None
    _check(arrays, what)
    return arrays


def _check(arrays: Mapping[str, np.ndarray], what: str) -> None:
    """`RawPredictionsError` unless `arrays` has every required key and every known key's
    shape matches, with one S, H and W for all."""
    missing = [k for k in REQUIRED_KEYS if k not in arrays]
    if missing:
        raise RawPredictionsError(f"{what}: missing {', '.join(missing)} (has {', '.join(sorted(arrays)) or 'none'})")
    dims: dict[str, int] = {}
    specs = {"images": REQUIRED_KEYS["images"], **REQUIRED_KEYS, **OPTIONAL_KEYS}
    for key, spec in specs.items():
        if key not in arrays:
            continue
        shape = np.shape(arrays[key])
        # S, H and W are the images' (checked first)
        ok = len(shape) == len(spec) and all(got == want if isinstance(want, int) else
                                             dims.setdefault(want, got) == got for want, got in zip(spec, shape))
        if not ok:
            expected = ", ".join(f"{d}={dims[d]}" if d in dims else str(d) for d in spec)
            raise RawPredictionsError(f"{what}: {key} has shape {list(shape)}, expected [{expected}]")
