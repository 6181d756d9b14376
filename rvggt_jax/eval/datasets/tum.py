"""TUM RGB-D sequences, as distributed (one folder per sequence):

    ROOT/<scene>/rgb.txt            "timestamp filename" lines (# comments), e.g.
                                    "1305031102.175304 rgb/1305031102.175304.png"
    ROOT/<scene>/rgb/<stamp>.png    640x480 colour frames (~30 Hz)
    ROOT/<scene>/groundtruth.txt    "timestamp tx ty tz qx qy qz qw": camera-to-world pose
                                    of the colour camera (OpenCV axes, metres, unit
                                    quaternion with the scalar last), motion capture at a
                                    higher rate (~100 Hz) than the images
    ROOT/<scene>/depth.txt          (depth frames: not read; the protocol scores cameras)
    ROOT/<scene>/calibration.txt    optional, ours: "fx fy cx cy" in the images' pixels
                                    (further numbers, distortion, are not applied)

Each image is paired with the ground-truth pose nearest in time, if within 0.02 s (the
TUM tools' default `max_difference`); images without one are dropped. Intrinsics:
calibration.txt, else TUM's published camera of the sequence's sensor, found in the
folder's name (`freiburg1` / `fr1`, 2, 3) and scaled to the images' size, else unknown
(None: the trajectory protocol does not need them).

`read_tum_trajectory` / `write_tum_trajectory` read and write a trajectory file on its
own (timestamps [S] and world-to-camera [S, 3, 4]), e.g. for a predicted trajectory.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from rvggt_jax.eval.datasets.base import DatasetError, Scene, need_file
from rvggt_jax.eval.datasets.files import c2w_to_w2c, save_image, w2c_to_c2w
from rvggt_jax.eval.datasets.text_table import as_extrinsics, format_floats, numbers, read_rows

__all__ = ["CAMERAS", "MAX_DIFFERENCE", "NAME", "associate", "list_scenes", "read_scene", "read_tum_trajectory",
           "sensor_camera", "write", "write_tum_trajectory"]

NAME = "tum"
MAX_DIFFERENCE = 0.02
CAMERAS = {1: (517.3, 516.5, 318.6, 255.3), 2: (520.9, 521.0, 325.1, 249.7), 3: (535.4, 539.2, 320.1, 247.6)}
"""fx, fy, cx, cy of the freiburg1/2/3 colour cameras at 640x480 (TUM's published values)."""
W0, H0 = 640, 480
_SENSOR = re.compile(r"(?:freiburg|(?<![a-z])fr)([123])(?!\d)")
_UNIT_TOL = 1e-2  # TUM files print 4 decimals of each quaternion component


def read_tum_trajectory(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A TUM trajectory file ("timestamp tx ty tz qx qy qz qw" lines, camera-to-world)
    -> (timestamps [S] float64 in file order, world-to-camera extrinsics [S, 3, 4]).
    DatasetError naming `path:line` for a line without 8 numbers, a non-finite value or
    a quaternion far from unit length."""
    from scipy.spatial.transform import Rotation

    path = Path(path)
    rows = read_rows(path, "TUM trajectory", 8)
    if not rows:
        raise DatasetError(f"no pose in {path}")
    vals = np.stack([numbers(t, path, line, "TUM trajectory") for line, t in rows])
    norms = np.linalg.norm(vals[:, 4:], axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > _UNIT_TOL)
    if len(bad):
        raise DatasetError(f"{path}:{rows[bad[0]][0]}: the quaternion qx qy qz qw is not of unit length "
                           f"(norm {norms[bad[0]]:.4g})")
    c2w = np.zeros((len(vals), 4, 4))
    c2w[:, :3, :3] = Rotation.from_quat(vals[:, 4:]).as_matrix()  # scipy normalises; scalar last, as TUM
    c2w[:, :3, 3] = vals[:, 1:4]
    c2w[:, 3, 3] = 1.0
    return vals[:, 0], c2w_to_w2c(c2w)


def write_tum_trajectory(path: str | Path, timestamps, w2c) -> Path:
    """Write timestamps [S] (seconds) and world-to-camera extrinsics [S, 3, 4] (or
    [S, 4, 4]) as a TUM trajectory file (camera-to-world, exact decimals); returns the
    path."""
    from scipy.spatial.transform import Rotation

    path = Path(path)
    a = as_extrinsics(w2c)
    t = np.asarray(timestamps, np.float64)
    if t.shape != (len(a),) or not np.isfinite(t).all():
        raise ValueError(f"timestamps must be [S] = [{len(a)}] finite seconds; got shape {list(t.shape)}")
    c2w = w2c_to_c2w(a)
    q = Rotation.from_matrix(c2w[:, :3, :3]).as_quat()
    lines = [format_floats([t[i], *c2w[i, :3, 3], *q[i]]) for i in range(len(a))]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("# timestamp tx ty tz qx qy qz qw\n" + "".join(ln + "\n" for ln in lines))
    return path


def associate(query, reference, max_difference: float = MAX_DIFFERENCE) -> tuple[np.ndarray, np.ndarray]:
    """Pair each query time [N] with the nearest reference time [M] (any order) at most
    `max_difference` away. Returns (query indices [K], reference indices [K]), in query
    order; queries without a partner are left out."""
    q, ref = np.asarray(query, np.float64), np.asarray(reference, np.float64)
    if len(q) == 0 or len(ref) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    order = np.argsort(ref, kind="stable")
    r = ref[order]
    hi = np.clip(np.searchsorted(r, q), 1, len(r) - 1) if len(r) > 1 else np.zeros(len(q), np.int64)
    lo = np.maximum(hi - 1, 0)
    pick = np.where(np.abs(q - r[lo]) <= np.abs(r[hi] - q), lo, hi)
    ok = np.abs(r[pick] - q) <= max_difference
    return np.flatnonzero(ok), order[pick[ok]]


def sensor_camera(name: str, width: int, height: int) -> np.ndarray | None:
    """TUM's published intrinsics [3, 3] of the sensor named in a sequence folder's name
    (freiburg1/2/3 or fr1/2/3), scaled to width x height; None when no sensor is named."""
    m = _SENSOR.search(name.lower())
    if m is None:
        return None
    fx, fy, cx, cy = CAMERAS[int(m.group(1))]
    sx, sy = width / W0, height / H0
    return np.array([[fx * sx, 0.0, cx * sx], [0.0, fy * sy, cy * sy], [0.0, 0.0, 1.0]])


def _read_calibration(path: Path) -> np.ndarray:
    rows = read_rows(path, "TUM calibration")
    if len(rows) != 1 or len(rows[0][1]) < 4:
        raise DatasetError(f"{path}: a calibration file holds one line 'fx fy cx cy' (then optional distortion)")
    line, tokens = rows[0]
    fx, fy, cx, cy = numbers(tokens, path, line, "TUM calibration")[:4]
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _is_sequence(d: Path) -> bool:
    return (d / "rgb.txt").is_file() and (d / "groundtruth.txt").is_file()


def list_scenes(root: Path) -> list[str]:
    if _is_sequence(root):
        return ["."]
    names = sorted(p.name for p in root.iterdir() if p.is_dir() and _is_sequence(p))
    if not names:
        raise DatasetError(f"no TUM RGB-D sequence (a folder with rgb.txt and groundtruth.txt) in {root}")
    return names


def read_scene(root: Path, name: str, *, max_difference: float = MAX_DIFFERENCE, **_) -> Scene:
    d = root / name
    if not d.is_dir():
        raise DatasetError(f"missing TUM sequence folder: {d}")
    rgb_txt = need_file(d / "rgb.txt", "TUM image list")
    rows = read_rows(rgb_txt, "TUM image list", 2)
    if not rows:
        raise DatasetError(f"no image in {rgb_txt}")
    stamps = np.array([numbers(t[:1], rgb_txt, line, "TUM image list")[0] for line, t in rows])
    files = [d / t[1] for _, t in rows]
    gt_stamps, gt_w2c = read_tum_trajectory(need_file(d / "groundtruth.txt", "TUM ground truth"))
    qi, gi = associate(stamps, gt_stamps, max_difference)
    if not len(qi):
        raise DatasetError(f"no image of {rgb_txt} has a ground-truth pose within {max_difference} s "
                           f"(images {stamps.min():.3f}..{stamps.max():.3f} s, ground truth "
                           f"{gt_stamps.min():.3f}..{gt_stamps.max():.3f} s)")
    order = np.argsort(stamps[qi], kind="stable")  # frames in time order, whatever the list's
    qi, gi = qi[order], gi[order]
    paths = [files[i] for i in qi]
    missing = next((p for p in paths if not p.is_file()), None)
    if missing is not None:
        raise DatasetError(f"missing image listed in {rgb_txt}: {missing}")
    calib = d / "calibration.txt"
    if calib.is_file():
        k = _read_calibration(calib)
    else:
        from PIL import Image

        with Image.open(paths[0]) as im:
            k = sensor_camera(d.resolve().name if name == "." else name, *im.size)
    label = root.resolve().name if name == "." else name
    return Scene(NAME, label, paths, gt_w2c[gi], None if k is None else np.repeat(k[None], len(paths), axis=0),
                 [p.stem for p in paths],
                 meta=dict(timestamps=stamps[qi], gt_timestamps=gt_stamps[gi], dropped=len(stamps) - len(qi)))


def write(scene, root: Path, rate: float = 30.0) -> Path:
    """Write a `rvggt_jax.synthetic.SyntheticScene` as ROOT/<name>: frames at `rate` Hz,
    ground truth at twice that rate (the frames' poses and, between them, interpolated
    ones), calibration.txt unless the scene's camera is the one its name implies."""
    from scipy.spatial.transform import Rotation, Slerp

    k = np.asarray(scene.intrinsics[0], np.float64)
    if not np.allclose(scene.intrinsics, k[None], rtol=0, atol=1e-12):
        raise ValueError("a TUM sequence has one camera: the scene's intrinsics differ between frames")
    d = root / scene.name
    (d / "rgb").mkdir(parents=True, exist_ok=True)
    s = len(scene.images)
    stamps = np.round(1305031102.0 + np.arange(s) / rate, 6)  # TUM's microsecond stamps
    names = [f"rgb/{t:.6f}.png" for t in stamps]
    for n, img in zip(names, scene.images):
        save_image(d / n, img)
    (d / "rgb.txt").write_text("# color images\n# timestamp filename\n"
                               + "".join(f"{t:.6f} {n}\n" for t, n in zip(stamps, names)))
    c2w = w2c_to_c2w(scene.extrinsics)
    mid = np.round((stamps[:-1] + stamps[1:]) / 2, 6)
    if s > 1:
        between = np.zeros((s - 1, 4, 4))
        between[:, :3, :3] = Slerp(stamps, Rotation.from_matrix(c2w[:, :3, :3]))(mid).as_matrix()
        between[:, :3, 3] = (c2w[:-1, :3, 3] + c2w[1:, :3, 3]) / 2
        between[:, 3, 3] = 1.0
        c2w = np.concatenate([c2w, between])
    times = np.concatenate([stamps, mid])
    order = np.argsort(times, kind="stable")
    write_tum_trajectory(d / "groundtruth.txt", times[order], c2w_to_w2c(c2w[order]))
    h, w = scene.images.shape[1:3]
    default = sensor_camera(scene.name, w, h)
    if default is None or not np.allclose(default, k, rtol=0, atol=1e-9):
        (d / "calibration.txt").write_text(format_floats([k[0, 0], k[1, 1], k[0, 2], k[1, 2]]) + "\n")
    return d
