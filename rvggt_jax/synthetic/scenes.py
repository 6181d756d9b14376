"""The evaluation's procedural scenes: `SyntheticScene` (rendered frames and their exact
geometry), cameras on an arc (`orbit_cameras`, `look_at`), the room of `make_scene`, and
`write_scene` into the evaluation datasets' formats."""

from __future__ import annotations

import dataclasses
from pathlib import Path
import numpy as np

from rvggt_jax.synthetic.render import Box, Rect, render


@dataclasses.dataclass
class SyntheticScene:
    """Rendered frames and their exact geometry; shapes in `rvggt_jax.synthetic`'s docstring."""

    name: str
    images: np.ndarray
    depth: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    extrinsics: np.ndarray
    intrinsics: np.ndarray
    primitives: tuple = ()

    @property
    def valid(self) -> np.ndarray:
        """[S, H, W] bool: pixels whose ray hits a surface."""
        return self.depth > 0

    def cloud(self) -> tuple[np.ndarray, np.ndarray]:
        """All hit pixels' world points [N, 3] and normals [N, 3] (float64)."""
        m = self.valid
        return self.points[m].astype(np.float64), self.normals[m].astype(np.float64)


def camera_centers(extrinsics: np.ndarray) -> np.ndarray:
    """Camera centres [S, 3] = -R^T t of world-to-camera extrinsics [S, 3, 4]."""
    e = np.asarray(extrinsics, dtype=np.float64)
    return -np.einsum("sji,sj->si", e[:, :, :3], e[:, :, 3])


def look_at(center: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, -1.0, 0.0)) -> np.ndarray:
    """World-to-camera [3, 4] (OpenCV) of a camera at `center` [3] looking at `target`
    [3]; `up` is the world direction that appears upwards in the image (y down)."""
    center, target, up = (np.asarray(x, np.float64) for x in (center, target, up))
    z = target - center
    z /= np.linalg.norm(z)
    x = np.cross(-up, z)  # image x = right; with y down, -up points down
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    r = np.stack([x, y, z])  # rows: camera axes in world coordinates
    return np.concatenate([r, (-r @ center)[:, None]], axis=1)


def orbit_cameras(frames: int, radius: float = 3.0, height: float = -1.0, arc_deg: float = 60.0,
                  target=(0.0, 0.2, 0.0), phase_deg: float = 0.0, jitter: float = 0.0,
                  rng: np.random.Generator | None = None) -> np.ndarray:
    """`frames` world-to-camera [S, 3, 4] on a horizontal arc of `arc_deg` degrees at
    `radius` from the y axis, `height` along y (y points down: negative is above the
    floor), all looking at `target`; `jitter` moves each centre by up to that much."""
    angles = np.deg2rad(phase_deg + np.linspace(-arc_deg / 2, arc_deg / 2, frames))
    out = []
    for a in angles:
        c = np.array([radius * np.sin(a), height, -radius * np.cos(a)])
        if jitter and rng is not None:
            c = c + rng.uniform(-jitter, jitter, 3)
        out.append(look_at(c, np.asarray(target, np.float64) + 0.05 * np.array([np.sin(3 * a), 0.0, 0.0])))
    return np.stack(out)


def _rot_y(deg: float) -> tuple:
    a = np.deg2rad(deg)
    m = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    return tuple(map(tuple, m))


def room(rng: np.random.Generator, boxes: int = 3) -> tuple:
    """A floor, three walls and `boxes` randomly placed, rotated boxes (world y down,
    the floor at y = 1)."""
    hue = lambda: tuple(rng.uniform(0.3, 1.0, 3))  # noqa: E731
    prims: list = [
        Rect((0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (3.0, 3.0), hue(), 2.0),   # floor
        Rect((0.0, -0.5, 2.5), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (3.0, 1.5), hue(), 3.0),  # back wall
        Rect((-2.5, -0.5, 0.0), (0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (3.0, 1.5), hue(), 3.0),  # left wall
        Rect((2.5, -0.5, 0.0), (0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (3.0, 1.5), hue(), 3.0),  # right wall
    ]
    for _ in range(boxes):
        half = tuple(rng.uniform(0.2, 0.45, 3))
        c = (rng.uniform(-1.2, 1.2), 1.0 - half[1], rng.uniform(-0.6, 1.4))
        prims.append(Box(c, _rot_y(rng.uniform(0, 90)), half, hue(), 5.0))
    return tuple(prims)


def make_scene(frames: int = 6, height: int = 60, width: int = 80, seed: int = 0, *,
               focal: float | tuple[float, float] | None = None,
               name: str | None = None, arc_deg: float = 50.0, radius: float = 3.2, boxes: int = 3,
               jitter: float = 0.05) -> SyntheticScene:
    """A procedural room (`room`) seen by `frames` cameras on an arc (`orbit_cameras`)
    with focal length `focal` pixels (default 0.9 x width; a pair = (fx, fy)) and the
    principal point at the image centre (width/2, height/2). Deterministic in `seed`."""
    if frames < 1 or height < 2 or width < 2:
        raise ValueError(f"need frames >= 1 and an image of at least 2x2 pixels; got {frames}, {width}x{height}")
    rng = np.random.default_rng(seed)
    prims = room(rng, boxes)
    fx, fy = np.broadcast_to(np.asarray(0.9 * width if focal is None else focal, np.float64), (2,))
    k = np.array([[fx, 0.0, width / 2.0], [0.0, fy, height / 2.0], [0.0, 0.0, 1.0]])
    ext = orbit_cameras(frames, radius=radius, height=rng.uniform(-0.6, -0.2), arc_deg=arc_deg,
                        phase_deg=rng.uniform(-20, 20), jitter=jitter, rng=rng)
    outs = [render(e, k, height, width, prims) for e in ext]
    imgs, depth, pts, nrm = (np.stack(x) for x in zip(*outs))
    return SyntheticScene(name=name or f"synthetic_{seed:03d}", images=imgs, depth=depth, points=pts, normals=nrm,
                          extrinsics=ext, intrinsics=np.repeat(k[None], frames, axis=0), primitives=prims)


def write_scene(scene: SyntheticScene, fmt: str, root: str | Path) -> Path:
    """Store `scene` under `root` in the on-disk format `fmt` (a name of
    `rvggt_jax.eval.datasets.FORMATS`: 7scenes, nrgbd, scannet, tnt, dtu, folder, co3d);
    returns the scene's folder."""
    from rvggt_jax.eval.datasets import get_format

    return get_format(fmt).write(scene, Path(root))
