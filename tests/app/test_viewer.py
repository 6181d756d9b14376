"""`rvggt view`: the viser viewer of a reconstruction, opened in a real browser
(headless Chromium): the page connects, the 3D canvas shows the points, and the scene
holds one frustum per camera (through viser's API). No model runs here: the
reconstruction folder is written directly."""

import shutil
import socket
import subprocess

import numpy as np
import pytest
from PIL import Image

from rvggt_jax.io.cameras import write_cameras_json
from rvggt_jax.io.ply import write_ply

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
                            f"http://127.0.0.1:{port}/"], capture_output=True, text=True, timeout=180)
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
