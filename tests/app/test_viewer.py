"""`rvggt view`: the viser viewer of a reconstruction, opened in a real browser
(headless Chromium): the page connects, the 3D canvas shows the points, and the scene
holds one frustum per camera (through viser's API). The reconstruction folders are
written directly, but for the upload form's test, which runs the bundled tiny
random-weight model on the sample images from the page."""

import shutil
import socket
import subprocess
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from rvggt_jax.io.cameras import write_cameras_json
from rvggt_jax.io.ply import write_ply
from tests.helpers.allocator import without_preload

S = 4


def _browser():
    return shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def make_reconstruction(out):
    """S cameras on a line looking down +z at a magenta slab of points (confidence
    rising with x; each point tagged with a frame)."""
    out.mkdir()
    rng = np.random.default_rng(0)
    n = 20000
    pts = np.stack([rng.uniform(-1, 1, n), rng.uniform(-0.7, 0.7, n), rng.uniform(3.8, 4.2, n)], 1)
    cols = np.tile(np.array([[255, 0, 255]], np.uint8), (n, 1))
    write_ply(out / "points.ply", pts, cols,
              extra=dict(confidence=(1 + pts[:, 0] + 1).astype(np.float32), frame=np.arange(n, dtype=np.int32) % S))
    ext = np.zeros((S, 3, 4))
    ext[:, :, :3] = np.eye(3)
    ext[:, 0, 3] = -np.linspace(-0.5, 0.5, S)  # centres at x = -0.5 .. 0.5
    k = np.tile(np.array([[150.0, 0, 80], [0, 150.0, 60], [0, 0, 1]]), (S, 1, 1))
    names = [f"img_{i}.jpg" for i in range(S)]
    write_cameras_json(out / "cameras.json", names, ext, k, [(160, 120)] * S)
    (out / "thumbnails").mkdir()
    for i in range(S):
        Image.new("RGB", (160, 120), (0, 120 + 30 * i, 0)).save(out / "thumbnails" / f"img_{i}.jpg")
    return names


def test_viewer_scene_and_controls(tmp_path):
    from rvggt_jax.app.viewer import ALL_FRAMES, start

    names = make_reconstruction(tmp_path / "rec")
    server, viewer = start(tmp_path / "rec", port=_free_port())
    try:
        handles = [server.scene.get_handle_by_name(f"/cameras/frame_{i:03d}") for i in range(S + 1)]
        assert all(type(h).__name__ == "CameraFrustumHandle" for h in handles[:S]) and handles[S] is None
        assert viewer.visible_mask().sum() == 20000
        viewer.conf_slider.value = 50
        assert abs(viewer.visible_mask().mean() - 0.5) < 0.01  # the confidence slider keeps the top half
        viewer.conf_slider.value = 0
        viewer.frame_select.value = names[2]
        m = viewer.visible_mask()
        assert m.sum() == 5000 and (viewer.rec.frame[m] == 2).all()
        assert tuple(handles[2].color) == (255, 140, 0)  # the selected frame's frustum is highlighted
        viewer.frame_select.value = ALL_FRAMES
    finally:
        server.stop()


def test_view_errors(tmp_path):
    from rvggt_jax.app.messages import CLIError
    from rvggt_jax.app.viewer import serve

    with pytest.raises(CLIError, match="not an rvggt reconstruction"):
        serve(tmp_path, port=_free_port())


@pytest.mark.skipif(_browser() is None, reason="no Chromium (Debian: apt-get install chromium); .ci/run installs it")
def test_viewer_in_headless_chromium(tmp_path):
    from rvggt_jax.app.viewer import start

    make_reconstruction(tmp_path / "rec")
    port = _free_port()
    server, viewer = start(tmp_path / "rec", port=port)
    connected = []
    server.on_client_connect(lambda client: connected.append(client.client_id))
    shot = tmp_path / "shot.png"
    try:
        r = subprocess.run([_browser(), "--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader",
                            "--enable-unsafe-swiftshader", "--window-size=1000,700", "--virtual-time-budget=15000",
                            f"--user-data-dir={tmp_path / 'profile'}", f"--screenshot={shot}",
                            f"http://127.0.0.1:{port}/"], capture_output=True, text=True, timeout=180,
                           env=without_preload())
        assert shot.is_file(), r.stderr[-2000:]
        assert connected, "the page never opened a websocket to the viewer"
        frustums = [server.scene.get_handle_by_name(f"/cameras/frame_{i:03d}") for i in range(S)]
        assert all(type(h).__name__ == "CameraFrustumHandle" for h in frustums)
    finally:
        server.stop()
    img = np.asarray(Image.open(shot).convert("RGB")).astype(int)
    canvas = img[:, :600]  # left of the control panel
    # magenta hue, at any lightness: software WebGL blends the small points with the white
    # background by a varying amount between runs (green from ~10 to ~180 in the same
    # scene); nothing else on the canvas has R and B far above G
    r, g, b = canvas[..., 0], canvas[..., 1], canvas[..., 2]
    magenta = (r > 180) & (b > 180) & (g < np.minimum(r, b) - 50)
    assert magenta.sum() > 2000, f"the 3D canvas shows no points ({magenta.sum()} magenta pixels)"
    assert canvas.std() > 10  # not a blank page


def test_a_port_that_cannot_be_had_is_one_error(tmp_path):
    """viser used to take the next port when one was in use, and to hang on 70000."""
    from rvggt_jax.app import cli
    from rvggt_jax.app.messages import CLIError
    from rvggt_jax.app.viewer import ViewerError, start

    make_reconstruction(tmp_path / "rec")
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(ViewerError, match=f"cannot serve on 127.0.0.1:{port}: .*in use"):
            server, _ = start(tmp_path / "rec", port=port)
            server.stop()  # (before the fix: a server on another port)
    with pytest.raises(CLIError, match="a port is 1-65535, got 70000"):
        cli.build_parser().parse_args(["view", str(tmp_path / "rec"), "--port", "70000"])
    with pytest.raises(ViewerError, match="1-65535"):
        start(tmp_path / "rec", port=70000)


def test_reconstruct_view_serves_the_result_after_the_run(tmp_path, monkeypatch):
    """`--view` serves the viewer on OUT once the reconstruction is written (the run and
    the server replaced by recorders here); a port that cannot be had is refused before
    anything runs, and --port without --view is a usage error."""
    from rvggt_jax.app import cli, commands, viewer

    calls = []
    monkeypatch.setattr(commands, "reconstruct_folder", lambda src, w, out, opts: calls.append(("run", str(out))))
    monkeypatch.setattr(viewer, "serve", lambda out, port=8080, host="127.0.0.1": calls.append(("serve", str(out),
                                                                                                 port)))
    port = _free_port()
    out = str(tmp_path / "o")
    assert cli.main(["reconstruct", str(tmp_path), "--weights", "w", "--out", out, "--view", "--port", str(port)]) == 0
    assert calls == [("run", out), ("serve", out, port)]
    calls.clear()
    assert cli.main(["reconstruct", str(tmp_path), "--weights", "w", "--out", out]) == 0
    assert calls == [("run", out)]
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        taken = busy.getsockname()[1]
        calls.clear()
        assert cli.main(["reconstruct", str(tmp_path), "--weights", "w", "--out", out, "--view", "--port",
                         str(taken)]) != 0
        assert calls == []  # refused before the run
    assert cli.main(["reconstruct", str(tmp_path), "--weights", "w", "--out", out, "--port", "9000"]) != 0
    assert calls == []


# ---------------------------------------------------------------------------------------
# The background filter, the "points from" switch and the upload form
# ---------------------------------------------------------------------------------------


def _rewrite_points(out, colors):
    """points.ply of `make_reconstruction` again, with `colors` [20000, 3] uint8."""
    from rvggt_jax.io.ply import read_ply_properties

    p = read_ply_properties(out / "points.ply")
    pts = np.stack([p["x"], p["y"], p["z"]], 1)
    write_ply(out / "points.ply", pts, colors, extra=dict(confidence=p["confidence"], frame=p["frame"]))


def test_background_filter_hides_exactly_near_black_and_white_points(tmp_path):
    """Near black is R + G + B < 16, near white every channel > 240 (upstream
    demo_viser's thresholds): colours on either side of both edges, cycled over the
    cloud; the filter composes with the confidence slider and the frame selection, and
    the cloud sent to the browser is the mask's."""
    from rvggt_jax.app.viewer import ALL_FRAMES, start

    hidden_black = [(0, 0, 0), (5, 5, 5), (15, 0, 0), (0, 7, 8)]
    kept_dark = [(5, 5, 6), (16, 0, 0), (0, 8, 8), (40, 40, 40)]
    hidden_white = [(255, 255, 255), (241, 241, 241), (250, 245, 241)]
    kept_bright = [(240, 255, 255), (255, 240, 255), (255, 255, 240), (255, 255, 0), (200, 200, 200)]
    palette = np.array(hidden_black + kept_dark + hidden_white + kept_bright + [(255, 0, 255)], np.uint8)
    kind = np.array(["b"] * 4 + ["k"] * 4 + ["w"] * 3 + ["k"] * 5 + ["k"])
    n = 20000
    which = np.arange(n) % len(palette)
    names = make_reconstruction(tmp_path / "rec")
    _rewrite_points(tmp_path / "rec", palette[which])
    server, viewer = start(tmp_path / "rec", port=_free_port())
    try:
        is_black, is_white = kind[which] == "b", kind[which] == "w"
        assert viewer.visible_mask().all()  # off by default
        viewer.hide_black.value = True
        np.testing.assert_array_equal(viewer.visible_mask(), ~is_black)
        assert len(viewer.cloud.points) == n - is_black.sum()
        assert (viewer.cloud.colors.astype(int).sum(1) >= 16).all()
        viewer.hide_white.value = True
        np.testing.assert_array_equal(viewer.visible_mask(), ~is_black & ~is_white)
        viewer.hide_black.value = False
        np.testing.assert_array_equal(viewer.visible_mask(), ~is_white)
        viewer.hide_black.value = True
        viewer.conf_slider.value = 50
        viewer.frame_select.value = names[1]
        rec = viewer.rec
        want = ~is_black & ~is_white & (rec.confidence >= np.percentile(rec.confidence, 50)) & (rec.frame == 1)
        assert 0 < want.sum() < n
        np.testing.assert_array_equal(viewer.visible_mask(), want)
        # (viser sends float16 positions)
        np.testing.assert_allclose(viewer.cloud.points, rec.points[want], rtol=2e-3, atol=1e-3)
        viewer.hide_black.value = viewer.hide_white.value = False
        viewer.conf_slider.value = 0
        viewer.frame_select.value = ALL_FRAMES
        assert viewer.visible_mask().all() and len(viewer.cloud.points) == n
    finally:
        server.stop()


H, W = 6, 8  # network input of the hand-written predictions.npz
K_NET = np.array([[7.5, 0, 4.0], [0, 7.5, 3.0], [0, 0, 1]])


def _write_predictions(out):
    """predictions.npz for `make_reconstruction`'s S cameras (R = I, centres at x = -0.5 ..
    0.5) through rvggt_jax.io.raw's writer: depth 2 + i in frame i except one pixel of
    depth 0 (and the highest confidence), a point map of its own, random confidences; colours: frame i is (40 + 50 i,
    100, 200) with a black pixel. Returns the arrays."""
    from types import SimpleNamespace

    from rvggt_jax.io.raw import write_predictions

    rng = np.random.default_rng(1)
    ext = np.zeros((S, 3, 4))
    ext[:, :, :3] = np.eye(3)
    ext[:, 0, 3] = -np.linspace(-0.5, 0.5, S)
    depth = np.stack([np.full((H, W), 2.0 + i) for i in range(S)]).astype(np.float32)
    depth[1, 2, 3] = 0.0
    images = np.zeros((S, 3, H, W), np.float32)
    for i in range(S):
        images[i] = (np.array([40 + 50 * i, 100, 200], np.float32) / 255)[:, None, None]
    images[2, :, 0, 0] = 0.0
    world_points = rng.normal(size=(S, H, W, 3)).astype(np.float32) + np.array([0, 0, 4], np.float32)
    depth_conf = rng.uniform(1, 5, (S, H, W)).astype(np.float32)
    depth_conf[1, 2, 3] = 10.0  # kept by any threshold but for its depth
    recon = SimpleNamespace(images=images, extrinsic=ext, network_intrinsic=np.tile(K_NET, (S, 1, 1)), depth=depth,
                            depth_conf=depth_conf, names=[f"img_{i}.jpg" for i in range(S)])
    world_points_conf = rng.uniform(1, 5, (S, H, W)).astype(np.float32)
    write_predictions(out / "predictions.npz", recon, dict(world_points=world_points,
                                                          world_points_conf=world_points_conf))
    return dict(depth=depth, depth_conf=depth_conf, world_points=world_points, world_points_conf=world_points_conf,
                images=images, ext=ext)


def test_points_from_switch_rebuilds_the_cloud_from_predictions(tmp_path):
    """Without predictions.npz the switch is disabled and says --save-raw. With it: the
    run's own source (cameras.json's points_from) is points.ply as written; the other is
    rebuilt from the npz (the point head's map with its confidences, or the depth maps
    unprojected with the predicted cameras: checked here against the pinhole model by
    hand, the pixel of depth 0 dropped), kept by the run's --conf-threshold; the
    background filter applies to the rebuilt cloud."""
    from rvggt_jax.app.viewer import load_reconstruction, start
    from rvggt_jax.io.cameras import write_cameras_json

    out = tmp_path / "rec"
    names = make_reconstruction(out)
    server, viewer = start(out, port=_free_port())
    try:
        assert viewer.source_select.disabled and "--save-raw" in viewer.source_note.content
        ply_points = viewer.rec.points.copy()

        a = _write_predictions(out)
        viewer.show(load_reconstruction(out), out)  # (cameras.json says no points_from: depth, keep all)
        assert not viewer.source_select.disabled and viewer.source_select.value == "depth"
        viewer.source_select.value = "point map"
        want = a["world_points"].reshape(-1, 3)
        np.testing.assert_allclose(viewer.rec.points, want, rtol=1e-6)
        np.testing.assert_array_equal(viewer.rec.confidence, a["world_points_conf"].reshape(-1))
        np.testing.assert_array_equal(viewer.rec.frame, np.repeat(np.arange(S), H * W))
        colors = (np.round(a["images"].transpose(0, 2, 3, 1) * 255)).astype(np.uint8).reshape(-1, 3)
        np.testing.assert_array_equal(viewer.rec.colors, colors)
        assert len(viewer.cloud.points) == S * H * W
        viewer.hide_black.value = True  # the black pixel of frame 2
        assert len(viewer.cloud.points) == S * H * W - 1
        viewer.hide_black.value = False
        viewer.source_select.value = "depth"  # the run's own: points.ply again
        np.testing.assert_array_equal(viewer.rec.points, ply_points)

        # a run whose points came from the point map, kept at the 50th percentile
        cams = load_reconstruction(out)
        write_cameras_json(out / "cameras.json", names, cams.extrinsic, cams.intrinsic, cams.sizes,
                           meta=dict(points_from="pointmap", conf_threshold="50%"))
        viewer.show(load_reconstruction(out), out)
        assert viewer.source_select.value == "point map"
        np.testing.assert_array_equal(viewer.rec.points, ply_points)
        viewer.source_select.value = "depth"
        d = a["depth"]
        v, u = np.mgrid[0:H, 0:W]
        cam = np.stack([(u - 4.0) * d / 7.5, (v - 3.0) * d / 7.5, d], -1)  # [S, H, W, 3]
        world = cam + (-a["ext"][:, :, 3])[:, None, None, :]  # R = I: centre = -t
        valid = d > 0
        conf = a["depth_conf"]
        keep = valid & (conf >= np.percentile(conf[valid], 50))
        np.testing.assert_allclose(viewer.rec.points, world[keep], rtol=1e-5, atol=1e-6)
        np.testing.assert_array_equal(viewer.rec.confidence, conf[keep])
        np.testing.assert_array_equal(viewer.rec.frame, np.nonzero(keep)[0])
        assert not keep[1, 2, 3] and len(viewer.cloud.points) == keep.sum() < S * H * W // 2 + 1
        assert "rebuilt from predictions.npz" in viewer.source_note.content
    finally:
        server.stop()


def test_view_weights_and_work_dir_errors(tmp_path, capsys):
    """--weights that is not there is said at once; --work-dir without --weights is a usage error."""
    from rvggt_jax.app import cli

    make_reconstruction(tmp_path / "rec")
    port = str(_free_port())
    assert cli.main(["view", str(tmp_path / "rec"), "--port", port, "--weights", str(tmp_path / "nope")]) == 1
    assert "--weights: checkpoint not found" in capsys.readouterr().err
    assert cli.main(["view", str(tmp_path / "rec"), "--port", port, "--work-dir", str(tmp_path / "w")]) == 1
    assert "--work-dir applies with --weights" in capsys.readouterr().err


def _tiny_weights():
    import rvggt_jax

    return Path(rvggt_jax.__file__).parent / "examples_data" / "tiny"


def test_upload_errors_are_shown_in_the_page(tmp_path):
    """A file the form cannot take (not an image, a .zip with two images of one name or
    none, a damaged .zip), and a run that fails (reconstruct_folder's CLIError: an image
    that cannot be read), are one line in the page's status, and the files stay for
    another try."""
    import io
    import zipfile

    from rvggt_jax.app.viewer import start

    make_reconstruction(tmp_path / "rec")
    server, viewer = start(tmp_path / "rec", port=_free_port(), weights=_tiny_weights(), work_dir=tmp_path / "work")
    form = viewer.uploads
    try:
        assert form.run_button.disabled
        form.add("notes.txt", b"hello")
        assert form.status.content.startswith("**failed**") and "notes.txt is not an image" in form.status.content
        assert form.pending == {} and form.run_button.disabled
        for files, says in (({"a/x.jpg": b"1", "b/x.jpg": b"2"}, "holds two images named x.jpg"),
                            ({"readme.md": b"", "__MACOSX/._y.jpg": b""}, "no images in")):
            buf = io.BytesIO()
            with zipfile.ZipFile(buf, "w") as z:
                for n, c in files.items():
                    z.writestr(n, c)
            form.add("set.zip", buf.getvalue())
            assert form.status.content.startswith("**failed**") and says in form.status.content, form.status.content
        form.add("junk.zip", b"PK not really")
        assert "cannot unpack junk.zip" in form.status.content and form.pending == {}
        form.add("bad.jpg", b"not a jpeg")
        assert list(form.pending) == ["bad.jpg"] and not form.run_button.disabled
        thread = form.run()
        thread.join(120)
        assert not thread.is_alive()
        assert form.status.content.startswith("**failed**"), form.status.content
        assert "bad.jpg" in form.status.content and "Traceback" not in form.status.content
        assert form.progress.value == 100 and list(form.pending) == ["bad.jpg"] and not form.busy
        assert len(viewer.rec.names) == S  # the shown reconstruction is kept
        assert (tmp_path / "work" / "upload_001" / "input" / "bad.jpg").is_file()
    finally:
        server.stop()


class _DevTools:
    """A page of a headless Chromium, driven over the DevTools protocol (websocket)."""

    def __init__(self, profile, deadline):
        import json
        import time
        import urllib.request

        from websockets.sync.client import connect

        active = profile / "DevToolsActivePort"  # Chromium writes its debugging port here
        while not active.is_file() or not active.read_text().strip():
            assert time.monotonic() < deadline, "headless Chromium opened no debugging port"
            time.sleep(0.2)
        port = active.read_text().split()[0]
        while True:
            pages = [t for t in json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list").read())
                     if t["type"] == "page"]
            if pages:
                break
            assert time.monotonic() < deadline, "headless Chromium shows no page"
            time.sleep(0.2)
        self.ws = connect(pages[0]["webSocketDebuggerUrl"], max_size=None)
        self.n = 0

    def call(self, method, **params):
        import json

        self.n += 1
        self.ws.send(json.dumps(dict(id=self.n, method=method, params=params)))
        while True:
            msg = json.loads(self.ws.recv(timeout=60))
            if msg.get("id") == self.n:
                assert "error" not in msg, msg
                return msg["result"]

    def eval(self, js):
        return self.call("Runtime.evaluate", expression=js, returnByValue=True)["result"].get("value")

    def close(self):
        self.ws.close()


def _wait(what, ok, deadline, step=0.25):
    import time

    while not ok():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(step)


@pytest.mark.skipif(_browser() is None, reason="no Chromium (Debian: apt-get install chromium); .ci/run installs it")
def test_upload_form_reconstructs_in_headless_chromium(tmp_path):
    """`rvggt view --weights tiny`: the page, open in headless Chromium and connected,
    uploads a .zip of the 3 sample images through its upload button (a real file input,
    set over the DevTools protocol), the reconstruct button is clicked in the page, the
    run goes through reconstruct_folder in the background, the progress element ends at
    "done" (on the server and in the page), and the viewer shows the new result: its 3
    cameras in place of the 4 shown before, with predictions.npz for the switch."""
    import time
    import zipfile

    import rvggt_jax
    from rvggt_jax.app.viewer import start

    sample = Path(rvggt_jax.__file__).parent / "examples_data" / "images"
    photos = tmp_path / "photos.zip"
    with zipfile.ZipFile(photos, "w") as z:
        for p in sorted(sample.glob("*.jpg")):
            z.write(p, f"photos/{p.name}")
    make_reconstruction(tmp_path / "rec")
    port = _free_port()
    server, viewer = start(tmp_path / "rec", port=port, weights=_tiny_weights(), work_dir=tmp_path / "work")
    form = viewer.uploads
    connected = []
    server.on_client_connect(lambda client: connected.append(client.client_id))
    profile = tmp_path / "profile"
    browser = subprocess.Popen([_browser(), "--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader",
                                "--enable-unsafe-swiftshader", "--window-size=1000,700", "--remote-debugging-port=0",
                                f"--user-data-dir={profile}", f"http://127.0.0.1:{port}/"],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=without_preload())
    page = None
    try:
        deadline = time.monotonic() + 120
        page = _DevTools(profile, deadline)
        _wait("the page's websocket to the viewer", lambda: connected, deadline)
        _wait("the upload button in the page", lambda: page.eval("!!document.querySelector('input[type=file]')"),
              deadline)
        node = page.call("Runtime.evaluate", expression="document.querySelector('input[type=file]')")["result"]
        page.call("DOM.setFileInputFiles", files=[str(photos)], objectId=node["objectId"])
        _wait("the upload to reach the server", lambda: len(form.pending) == 3, deadline)
        assert sorted(form.pending) == ["view_00.jpg", "view_01.jpg", "view_02.jpg"]
        find_button = "[...document.querySelectorAll('button')].find(b => b.textContent.trim() === 'reconstruct')"
        _wait("the reconstruct button to be enabled in the page", lambda: page.eval(f"!{find_button}.disabled"),
              deadline)
        page.eval(f"{find_button}.click()")

        deadline = time.monotonic() + 300  # the first run compiles the model
        _wait("the click to start a run", lambda: form.thread is not None, deadline)
        _wait("the reconstruction to end", lambda: not form.thread.is_alive(), deadline, step=0.5)
        assert form.status.content.startswith("**done**"), form.status.content
        assert form.progress.value == 100
        _wait("the page to show the progress at done",
              lambda: "done: 3 cameras" in (page.eval("document.body.innerText") or ""), time.monotonic() + 30)
        form.thread.join(30)
        assert not form.thread.is_alive() and not form.busy and form.pending == {}

        out = tmp_path / "work" / "upload_001" / "reconstruction"
        assert form.last_out == out and (out / "points.ply").is_file() and (out / "predictions.npz").is_file()
        assert viewer.rec.names == ["view_00.jpg", "view_01.jpg", "view_02.jpg"]
        frustums = [server.scene.get_handle_by_name(f"/cameras/frame_{i:03d}") for i in range(4)]
        assert all(type(h).__name__ == "CameraFrustumHandle" for h in frustums[:3]) and frustums[3] is None
        assert len(viewer.cloud.points) == len(viewer.rec.points) > 0
        assert viewer.frame_select.options == ("all frames", "view_00.jpg", "view_01.jpg", "view_02.jpg")
        assert not viewer.source_select.disabled  # the upload runs save predictions.npz
        # the page looks at the new scene (its own camera reports may cross the move on the way)
        view = next(iter(server.get_clients().values())).camera
        np.testing.assert_allclose(server.initial_camera.look_at, np.median(viewer.rec.points, 0), atol=1e-6)
        _wait("the page's view to move to the new scene",
              lambda: np.allclose(view.look_at, server.initial_camera.look_at, atol=1e-4), time.monotonic() + 30)
    finally:
        if page is not None:
            page.close()
        browser.terminate()
        browser.wait(30)
        if form.thread is not None:
            form.thread.join(120)
        server.stop()
