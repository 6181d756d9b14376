"""`rvggt view OUT_DIR`: an interactive viewer of a reconstruction in the browser, served
on localhost with viser (what upstream's own demo uses).

It reads what `rvggt reconstruct` wrote: points.ply (with its per-point `confidence`
and `frame`), cameras.json and thumbnails/. The scene: the point cloud under `/points`,
one camera frustum per image under `/cameras/frame_000`, `/cameras/frame_001`, ...
(showing the image), in the first camera's OpenCV frame with -y up. The panel: a
confidence slider (keep points at or above a percentile of the stored points'
confidences), a frame selector (all frames, or one frame's points with its frustum
highlighted) and the point size. At most `MAX_SHOWN` points are sent to the browser.
When the folder (or its diagnostics/ subfolder) holds what `rvggt analyze` wrote, its
images (rank profile, saliency, K/V coverage, merged groups) are shown in a panel folder.
"""

from __future__ import annotations

import dataclasses
import json
import os
import threading
from pathlib import Path

import numpy as np

__all__ = ["MAX_SHOWN", "Reconstruction", "Viewer", "diagnostics_images", "load_reconstruction", "serve"]

MAX_SHOWN = 1_000_000  # points sent to the browser (a random subset beyond that)
ALL_FRAMES = "all frames"


@dataclasses.dataclass
class Reconstruction:
    """What the viewer shows. points [N, 3], colors [N, 3] uint8, confidence [N],
    frame [N] (index into `names`; -1 unknown), extrinsic [S, 3, 4] world-to-camera,
    intrinsic [S, 3, 3], sizes [S] (W, H), thumbnails [S] (uint8 [h, w, 3] or None)."""

    names: list[str]
    points: np.ndarray
    colors: np.ndarray
    confidence: np.ndarray
    frame: np.ndarray
    extrinsic: np.ndarray
    intrinsic: np.ndarray
    sizes: list[tuple[int, int]]
    thumbnails: list[np.ndarray | None]


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
    frames = json.loads((out / "cameras.json").read_text())["frames"]
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
    return Reconstruction(
        names=names, points=pts, colors=cols, confidence=conf, frame=frame,
        extrinsic=np.array([f["extrinsic"] for f in frames], np.float64),
        intrinsic=np.array([f["intrinsic"] for f in frames], np.float64),
        sizes=[(int(f["width"]), int(f["height"])) for f in frames], thumbnails=thumbs)


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


class Viewer:
    """The scene and panel of one reconstruction on a `viser.ViserServer`."""

    def __init__(self, server, rec: Reconstruction):
        from rvggt_jax.io.colmap import colmap_qvec

        self.server, self.rec = server, rec
        self.diagnostics: list = []  # GUI images of `rvggt analyze` (`add_diagnostics_panel`)
        server.scene.set_up_direction("-y")  # OpenCV world: y points down
        self.scale = _frustum_scale(rec)
        gui = server.gui
        self.conf_slider = gui.add_slider("confidence percentile", min=0, max=99, step=1, initial_value=0,
                                          hint="show points at or above this percentile of confidence")
        self.frame_select = gui.add_dropdown("frame", [ALL_FRAMES, *rec.names], initial_value=ALL_FRAMES)
        self.point_size = gui.add_slider("point size", min=0.001, max=0.05, step=0.001,
                                         initial_value=round(max(0.001, min(0.05, self.scale * 0.02)), 3))
        self.frustums = []
        for i, name in enumerate(rec.names):
            e = rec.extrinsic[i]
            r_c2w = e[:, :3].T
            center = -r_c2w @ e[:, 3]
            w, h = rec.sizes[i]
            fy = rec.intrinsic[i][1, 1]
            fov = 2 * np.arctan2(h / 2, fy) if fy > 0 else np.deg2rad(60)
            self.frustums.append(server.scene.add_camera_frustum(
                f"/cameras/frame_{i:03d}", fov=float(fov), aspect=w / h, scale=self.scale,
                image=rec.thumbnails[i], wxyz=colmap_qvec(r_c2w), position=center, color=self._color(i, False)))
        self._place_initial_camera()
        self.cloud = None
        self._lock = threading.Lock()
        self.update()
        self.conf_slider.on_update(lambda _: self.update())
        self.frame_select.on_update(lambda _: self.update())
        self.point_size.on_update(lambda _: self.update())

    def _place_initial_camera(self) -> None:
        """Open the browser's view behind and above the first camera, looking at the
        scene's centre (viser's default looks at the origin from far off)."""
        rec = self.rec
        e = rec.extrinsic[0]
        r_c2w = e[:, :3].T
        center = -r_c2w @ e[:, 3]
        target = np.median(rec.points, axis=0) if len(rec.points) else center + r_c2w[:, 2]
        back = 2.0 * max(float(np.linalg.norm(target - center)), 10 * self.scale)
        cam = self.server.initial_camera
        cam.position = tuple(center - r_c2w[:, 2] * back * 0.5 - r_c2w[:, 1] * back * 0.3)
        cam.look_at = tuple(target)
        cam.up = tuple(-r_c2w[:, 1])

    def _color(self, i: int, selected: bool) -> tuple[int, int, int]:
        if selected:
            return (255, 140, 0)
        f = i / max(len(self.rec.names) - 1, 1)
        return (int(255 * f), int(200 * (1 - f)), 40)

    def visible_mask(self) -> np.ndarray:
        """[N] bool: the points the current panel settings show."""
        rec = self.rec
        mask = np.ones(len(rec.points), bool)
        if len(rec.points) and self.conf_slider.value > 0:
            mask &= rec.confidence >= np.percentile(rec.confidence, self.conf_slider.value)
        sel = self.frame_select.value
        if sel != ALL_FRAMES:
            mask &= rec.frame == rec.names.index(sel)
        return mask

    def update(self) -> None:
        """Re-send the point cloud and frustum colours for the panel's settings."""
        with self._lock:
            m = self.visible_mask()
            sel = self.frame_select.value
            for i, h in enumerate(self.frustums):
                h.color = self._color(i, sel == self.rec.names[i])
            self.cloud = self.server.scene.add_point_cloud(
                "/points", self.rec.points[m], self.rec.colors[m], point_size=float(self.point_size.value),
                point_shape="rounded")


def diagnostics_images(out_dir: str | os.PathLike) -> list[Path]:
    """The PNGs `rvggt analyze` wrote in `out_dir` or `out_dir`/diagnostics (those its
    diagnostics.json lists and that exist), in its order; [] when there are none."""
    found = []
    for folder in (Path(out_dir), Path(out_dir) / "diagnostics"):
        try:
            listed = json.loads((folder / "diagnostics.json").read_text())["files"]
        except (OSError, ValueError, KeyError, TypeError):
            continue
        found += [folder / name for name in listed
                  if isinstance(name, str) and name.endswith(".png") and (folder / name).is_file()]
    return found


def add_diagnostics_panel(server, out_dir: str | os.PathLike) -> list:
    """A collapsed panel folder with the analyze images of `out_dir` (`diagnostics_images`);
    returns their GUI handles ([] and no folder when there are none)."""
    from PIL import Image

    paths = diagnostics_images(out_dir)
    if not paths:
        return []
    handles = []
    with server.gui.add_folder("diagnostics (rvggt analyze)", expand_by_default=False):
        for p in paths:
            with Image.open(p) as im:
                handles.append(server.gui.add_image(np.asarray(im.convert("RGB")), label=p.stem, format="png"))
    return handles


def check_bindable(host: str, port: int) -> None:
    """`ViewerError` unless a server can listen on `host`:`port`, tried with a socket of our
    own first: viser moves on to another port when one is in use, and fails in its own
    thread (the command then hangs) on a port out of range or not ours to bind."""
    import errno
    import socket

    if not isinstance(port, int) or not 1 <= port <= 65535:
        raise ViewerError(f"cannot serve on {host}:{port}: a port is 1-65535")
    try:
        family, kind, proto, _, addr = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
        with socket.socket(family, kind, proto) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server will (TIME_WAIT is no obstacle)
            s.bind(addr)
    except OSError as e:
        hint = " (ports below 1024 need privileges)" if e.errno == errno.EACCES else ""
        raise ViewerError(f"cannot serve on {host}:{port}: {e.strerror or e}{hint}; choose another --port") from None


def start(out_dir: str | os.PathLike, port: int = 8080, host: str = "127.0.0.1", verbose: bool = False):
    """Start a viser server showing `out_dir` -> (server, Viewer); returns at once (the
    server runs in its own threads; `server.stop()` ends it)."""
    import viser

    rec = load_reconstruction(out_dir)
    check_bindable(host, port)
    try:
        server = viser.ViserServer(host=host, port=port, verbose=verbose)
    except OSError as e:
        raise ViewerError(f"cannot serve on {host}:{port}: {e.strerror or e} (choose another --port)") from None
    viewer = Viewer(server, rec)
    viewer.diagnostics = add_diagnostics_panel(server, out_dir)
    return server, viewer


def serve(out_dir: str | os.PathLike, port: int = 8080, host: str = "127.0.0.1") -> None:
    """`rvggt view`: serve until Ctrl-C."""
    import time

    from rvggt_jax.app.messages import CLIError

    try:
        server, viewer = start(out_dir, port, host)
    except ViewerError as e:
        raise CLIError(str(e)) from None
    shown = "localhost" if host in ("127.0.0.1", "localhost", "::1") else host
    print(f"rvggt view: {len(viewer.rec.names)} cameras, {len(viewer.rec.points)} points from {out_dir}\n"
          f"open http://{shown}:{server.get_port()} in a browser (Ctrl-C to stop)", flush=True)
    try:
        while True:
            time.sleep(3600)
    finally:
        server.stop()
