"""`rvggt view OUT_DIR`: an interactive viewer of a reconstruction in the browser, served
on localhost with viser (what upstream's own demo uses).

It reads what `rvggt reconstruct` wrote: points.ply (with its per-point `confidence`
and `frame`), cameras.json and thumbnails/. The scene: the point cloud under `/points`,
one camera frustum per image under `/cameras/frame_000`, `/cameras/frame_001`, ...
(showing the image), in the first camera's OpenCV frame with -y up. The panel:
- a confidence slider (keep points at or above a percentile of the shown points'
  confidences), a frame selector (all frames, or one frame's points with its frustum
  highlighted) and the point size;
- a background filter: hide near-black and/or near-white points (upstream demo_viser's
  "filter black / white background"), composing with the slider and the frame;
- "points from: depth | point map": with the folder's predictions.npz (`rvggt
  reconstruct --save-raw`), the cloud of the other point source than the run's, rebuilt
  from the raw predictions (the run's own source shows points.ply as written); disabled,
  with a note naming --save-raw, without one;
- with `--weights`, an upload form (upstream demo_gradio's): images (one by one, or a
  .zip of them) or a video uploaded in the page are reconstructed on the server by
  `reconstruct_folder` into a new folder of a working folder, with the stages shown in
  the page, and the result is shown in place of the current one
  (`rvggt_jax.app.viewer_upload.UploadForm`).
At most `MAX_SHOWN` points are sent to the browser. When the folder (or its
diagnostics/ subfolder) holds what `rvggt analyze` wrote, its images (rank profile,
saliency, K/V coverage, merged groups) are shown in a panel folder.
"""

from __future__ import annotations

import dataclasses
import json
import os
import threading
import time
from pathlib import Path

import numpy as np

from rvggt_jax.app.viewer_data import (BLACK_SUM_BELOW, MAX_SHOWN, POINT_SOURCES, WHITE_ALL_ABOVE, Reconstruction,
                                       ViewerError, _frustum_scale, _md, _predictions_problem, background_mask,
                                       load_reconstruction, points_from_predictions)

__all__ = ["MAX_SHOWN", "Reconstruction", "Viewer", "background_mask", "diagnostics_images", "load_reconstruction",
           "points_from_predictions", "serve", "start"]

ALL_FRAMES = "all frames"


class Viewer:
    """The scene and panel of one reconstruction on a `viser.ViserServer`; `show` puts
    another reconstruction in its place (the upload form's results)."""

    def __init__(self, server, rec: Reconstruction, folder: str | os.PathLike | None = None):
        self.server = server
        self.diagnostics: list = []  # GUI images of `rvggt analyze` (`add_diagnostics_panel`)
        self._diagnostics_folder = None
        self.uploads = None  # the upload form (`start` with weights: viewer_upload.UploadForm)
        server.scene.set_up_direction("-y")  # OpenCV world: y points down
        gui = server.gui
        self.conf_slider = gui.add_slider("confidence percentile", min=0, max=99, step=1, initial_value=0,
                                          hint="show points at or above this percentile of confidence")
        self.frame_select = gui.add_dropdown("frame", [ALL_FRAMES, *rec.names], initial_value=ALL_FRAMES)
        self.point_size = gui.add_slider("point size", min=0.001, max=0.05, step=0.001, initial_value=0.01)
        self.hide_black = gui.add_checkbox("hide black background", False,
                                           hint=f"hide near-black points (R + G + B < {BLACK_SUM_BELOW}: masked "
                                                f"pixels, black borders)")
        self.hide_white = gui.add_checkbox("hide white background", False,
                                           hint=f"hide near-white points (R, G, B > {WHITE_ALL_ABOVE}: the padding "
                                                f"of --mode pad, white backdrops)")
        self.source_select = gui.add_dropdown(
            "points from", tuple(POINT_SOURCES), initial_value="depth",
            hint="the depth maps unprojected with the predicted cameras, or the point head's map: the run's own "
                 "source is points.ply as written, the other is rebuilt from predictions.npz")
        self.source_note = gui.add_markdown("")
        self.frustums: list = []
        self.cloud = None
        self._lock = threading.RLock()
        self._quiet = 0  # > 0 while `show` sets the controls (their callbacks wait for its one update)
        self.show(rec, folder)
        for control in (self.conf_slider, self.frame_select, self.point_size, self.hide_black, self.hide_white):
            control.on_update(lambda _: self._changed())
        self.source_select.on_update(lambda _: self._source_changed())

    # -- the reconstruction shown ---------------------------------------------------------

    def show(self, rec: Reconstruction, folder: str | os.PathLike | None = None) -> None:
        """Show `rec` (read from `folder`, None: from no folder: no source switch, no
        diagnostics) in place of what is shown: its frustums, frames, points, the
        browsers' view; the filters stay as set."""
        from rvggt_jax.io.colmap import colmap_qvec
        from rvggt_jax.io.raw import RAW_NAME

        with self._lock:
            self._quiet += 1
            try:
                self.rec = self.ply_rec = rec
                self.folder = None if folder is None else Path(folder)
                self._built: dict[str, tuple] = {}  # point source -> (points, colors, confidence, frame, note)
                self.scale = _frustum_scale(rec)
                for h in self.frustums:
                    h.remove()
                self.frustums = []
                for i in range(len(rec.names)):
                    e = rec.extrinsic[i]
                    r_c2w = e[:, :3].T
                    w, h = rec.sizes[i]
                    fy = rec.intrinsic[i][1, 1]
                    fov = 2 * np.arctan2(h / 2, fy) if fy > 0 else np.deg2rad(60)
                    self.frustums.append(self.server.scene.add_camera_frustum(
                        f"/cameras/frame_{i:03d}", fov=float(fov), aspect=w / h, scale=self.scale,
                        image=rec.thumbnails[i], wxyz=colmap_qvec(r_c2w), position=-r_c2w @ e[:, 3],
                        color=self._color(i, False)))
                self.frame_select.options = [ALL_FRAMES, *rec.names]
                self.frame_select.value = ALL_FRAMES
                self.point_size.value = round(max(0.001, min(0.05, self.scale * 0.02)), 3)
                run_label = next(k for k, v in POINT_SOURCES.items() if v == rec.points_from)
                self.source_select.value = run_label
                problem = ("needs a reconstruction folder" if self.folder is None else
                           _predictions_problem(self.folder / RAW_NAME, rec.names))
                self.source_select.disabled = problem is not None
                self.source_note.content = (f"*points from*: {_md(problem)}" if problem else
                                            f"shown: points.ply as written ({run_label})")
                self._show_diagnostics()
                self._place_initial_camera()
            finally:
                self._quiet -= 1
            self.update()

    def _show_diagnostics(self) -> None:
        if self._diagnostics_folder is not None:
            self._diagnostics_folder.remove()
        self._diagnostics_folder, self.diagnostics = (None, []) if self.folder is None else \
            _diagnostics_panel(self.server, self.folder)

    def _place_initial_camera(self) -> None:
        """Open the browser's view behind and above the first camera, looking at the
        scene's centre (viser's default looks at the origin from far off); the views of
        browsers already connected (a new result) go there too."""
        rec = self.rec
        e = rec.extrinsic[0]
        r_c2w = e[:, :3].T
        center = -r_c2w @ e[:, 3]
        target = np.median(rec.points, axis=0) if len(rec.points) else center + r_c2w[:, 2]
        back = 2.0 * max(float(np.linalg.norm(target - center)), 10 * self.scale)
        position, up = center - r_c2w[:, 2] * back * 0.5 - r_c2w[:, 1] * back * 0.3, -r_c2w[:, 1]
        cam = self.server.initial_camera
        cam.position, cam.look_at, cam.up = tuple(position), tuple(target), tuple(up)
        for client in self.server.get_clients().values():
            try:
                with client.atomic():
                    client.camera.up_direction = up
                    client.camera.position = position
                    client.camera.look_at = target
            except AssertionError:  # viser has no view from this browser yet: it opens at the initial camera
                pass

    def _color(self, i: int, selected: bool) -> tuple[int, int, int]:
        if selected:
            return (255, 140, 0)
        f = i / max(len(self.rec.names) - 1, 1)
        return (int(255 * f), int(200 * (1 - f)), 40)

    # -- the point source -----------------------------------------------------------------

    def _source_changed(self) -> None:
        if self._quiet:
            return
        with self._lock:
            label = self.source_select.value
            source = POINT_SOURCES[label]
            if source == self.ply_rec.points_from:
                pts, cols, conf, frame = (self.ply_rec.points, self.ply_rec.colors, self.ply_rec.confidence,
                                          self.ply_rec.frame)
                note = f"shown: points.ply as written ({label})"
            else:
                try:
                    pts, cols, conf, frame, note = self._build(source, label)
                except (ValueError, OSError) as e:  # a damaged or removed predictions.npz: said in the panel
                    from rvggt_jax.app.messages import one_line

                    self.source_note.content = f"*points from*: {_md(one_line(e, 300))}"
                    self._quiet += 1
                    try:
                        self.source_select.value = next(k for k, v in POINT_SOURCES.items()
                                                        if v == self.ply_rec.points_from)
                    finally:
                        self._quiet -= 1
                    self.rec = self.ply_rec
                    self.update()
                    return
            self.rec = dataclasses.replace(self.ply_rec, points=pts, colors=cols, confidence=conf, frame=frame)
            self.source_note.content = note
            self.update()

    def _build(self, source: str, label: str) -> tuple:
        """(points, colors, confidence, frame, note) of `source` from the folder's
        predictions.npz, built once per folder; ValueError (`RawPredictionsError`) for a
        damaged file, OSError for one gone."""
        from rvggt_jax.io.raw import RAW_NAME, load_predictions

        if source not in self._built:
            arrays = load_predictions(self.folder / RAW_NAME)
            threshold = self.ply_rec.conf_threshold
            pts, cols, conf, frame, abs_thr = points_from_predictions(arrays, source, threshold)
            kept = f"confidence >= {abs_thr:.4g}" + (f" (the run's {threshold})" if threshold else "")
            self._built[source] = (pts, cols, conf, frame,
                                   f"shown: {len(pts)} points rebuilt from {RAW_NAME} ({label}, {_md(kept)})")
        return self._built[source]

    # -- what is shown --------------------------------------------------------------------

    def visible_mask(self) -> np.ndarray:
        """[N] bool: the points the current panel settings show."""
        rec = self.rec
        mask = ~background_mask(rec.colors, self.hide_black.value, self.hide_white.value)
        if len(rec.points) and self.conf_slider.value > 0:
            mask &= rec.confidence >= np.percentile(rec.confidence, self.conf_slider.value)
        sel = self.frame_select.value
        if sel != ALL_FRAMES:
            mask &= rec.frame == rec.names.index(sel)
        return mask

    def _changed(self) -> None:
        if not self._quiet:
            self.update()

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
    return _diagnostics_panel(server, out_dir)[1]


def _diagnostics_panel(server, out_dir: str | os.PathLike) -> tuple:
    """`add_diagnostics_panel` -> (the folder's handle or None, the images' handles). The
    folder goes last in the panel, also when made after the others (a new result)."""
    from PIL import Image

    paths = diagnostics_images(out_dir)
    if not paths:
        return None, []
    handles = []
    with server.gui.add_folder("diagnostics (rvggt analyze)", expand_by_default=False, order=1e9) as folder:
        for p in paths:
            with Image.open(p) as im:
                handles.append(server.gui.add_image(np.asarray(im.convert("RGB")), label=p.stem, format="png"))
    return folder, handles


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


def start(out_dir: str | os.PathLike, port: int = 8080, host: str = "127.0.0.1", verbose: bool = False,
          weights: str | os.PathLike | None = None, work_dir: str | os.PathLike | None = None, options=None):
    """Start a viser server showing `out_dir` -> (server, Viewer); returns at once (the
    server runs in its own threads; `server.stop()` ends it). With `weights`, the page
    also has the upload form (`UploadForm`: runs go to new folders of `work_dir`, default
    `DEFAULT_WORK_DIR`, with `options`); a local checkpoint that is not there is said now."""
    import viser

    rec = load_reconstruction(out_dir)
    if weights is not None:
        from rvggt_jax.app.commands import _check_weights
        from rvggt_jax.app.messages import CLIError

        try:
            _check_weights(weights)  # a typo is said before the server starts, not after an upload
        except CLIError as e:
            raise ViewerError(f"--weights: {e}") from None
    elif work_dir is not None:
        raise ViewerError("--work-dir applies with --weights (the upload form)")
    check_bindable(host, port)
    try:
        server = viser.ViserServer(host=host, port=port, verbose=verbose)
    except OSError as e:
        raise ViewerError(f"cannot serve on {host}:{port}: {e.strerror or e} (choose another --port)") from None
    viewer = Viewer(server, rec, out_dir)
    if weights is not None:
        from rvggt_jax.app.viewer_upload import DEFAULT_WORK_DIR, UploadForm

        viewer.uploads = UploadForm(viewer, weights, DEFAULT_WORK_DIR if work_dir is None else work_dir, options)
    return server, viewer


def serve(out_dir: str | os.PathLike, port: int = 8080, host: str = "127.0.0.1",
          weights: str | os.PathLike | None = None, work_dir: str | os.PathLike | None = None) -> None:
    """`rvggt view`: serve until Ctrl-C (`start`'s arguments)."""
    from rvggt_jax.app.messages import CLIError

    try:
        server, viewer = start(out_dir, port, host, weights=weights, work_dir=work_dir)
    except ViewerError as e:
        raise CLIError(str(e)) from None
    shown = "localhost" if host in ("127.0.0.1", "localhost", "::1") else host
    print(f"rvggt view: {len(viewer.rec.names)} cameras, {len(viewer.rec.points)} points from {out_dir}\n"
          f"open http://{shown}:{server.get_port()} in a browser (Ctrl-C to stop)", flush=True)
    if viewer.uploads is not None:
        print(f"upload form: reconstructions with {weights} go to new folders of {viewer.uploads.work_dir}",
              flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        if viewer.uploads is not None and viewer.uploads.busy:
            from rvggt_jax.app.model_runner import ABANDONED_FORWARD

            # a forward cannot be cancelled: `rvggt`'s main leaves at once instead of waiting for it
            ABANDONED_FORWARD.set()
        raise
    finally:
        server.stop()
