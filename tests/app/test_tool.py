"""`rvggt reconstruct` as a new user runs it: a video, phone photos (EXIF-rotated), a
16-bit PNG, a corrupt file among good ones, a hub repo id, a reused output folder; and
its outputs (scene.glb, PLY confidence). Every run here has 3 frames of 518 x 392, so the
model compiles once for the whole module (in-process runs)."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from rvggt_jax.io.ply import read_ply_properties
from tests.helpers import SAMPLE_IMAGES, REPO, TINY


def make_video(path: Path, seconds: float = 4.0, fps: int = 10, w: int = 160, h: int = 120) -> Path:
    """A small MPEG-4 clip (4:3, so its frames preprocess to 518 x 392): a ramp with a
    moving white square."""
    import av

    with av.open(str(path), "w") as c:
        s = c.add_stream("mpeg4", rate=fps)
        s.width, s.height, s.pix_fmt = w, h, "yuv420p"
        for i in range(int(seconds * fps)):
            a = np.zeros((h, w, 3), np.uint8)
            a[..., 0] = (np.arange(w) * 255 // w)[None]
            a[..., 1] = (i * 7) % 255
            x0 = (i * 5) % (w - 20)
            a[h // 3:h // 3 + 20, x0:x0 + 20] = 255
            for p in s.encode(av.VideoFrame.from_ndarray(a, format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    return path


@pytest.fixture(autouse=True)
def _no_disk_cache(monkeypatch):
    monkeypatch.setenv("RVGGT_CACHE_DIR", "off")


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    """The tiny checkpoint converted to Orbax, as a hub repo id resolves to: every run of
    the module then loads alike (committed device arrays) and shares one compilation."""
    from rvggt_jax import load_pretrained
    from rvggt_jax.weights.checkpoint import save_orbax

    params, config = load_pretrained(TINY, device_put=False)
    return save_orbax(params, config, tmp_path_factory.mktemp("ckpt") / "tiny")


def reconstruct(*args, **kw):
    from rvggt_jax.app.commands import ReconstructOptions, reconstruct_folder as r

    kw.setdefault("quiet", True)
    return r(*args, ReconstructOptions(**kw))


# ---- video ---------------------------------------------------------------------------


def test_video_frames_selection(tmp_path):
    from rvggt_jax.io.video import VideoError, video_frames

    v = make_video(tmp_path / "clip.mp4")  # 40 frames at 10 fps
    names = [f.name for f in video_frames(v, fps=1)]
    assert names == [f"clip_0000{i}.000s" for i in range(4)]
    fr = video_frames(v, every=7, max_frames=3)  # frames 0, 7, ..., 35 -> 3 evenly spaced
    assert [f.name for f in fr] == ["clip_00000.000s", "clip_00001.400s", "clip_00003.500s"]
    assert fr[0].image.size == (160, 120) and fr[0].image.mode == "RGB"
    assert len(video_frames(v, every=1)) == 40
    assert len(video_frames(v, every=1, max_frames=5)) == 5
    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"\x00\x00\x00\x18ftypmp42 this is not a video")
    with pytest.raises(VideoError, match="broken.mp4"):
        video_frames(bad)


def test_video_reconstruct_glb_and_ply_confidence(tmp_path, ckpt):
    import trimesh

    v = make_video(tmp_path / "clip.mp4")
    out = tmp_path / "out"
    summary = reconstruct(v, ckpt, out, fps=1, max_frames=3, conf_threshold="0%")
    names = ["clip_00000.000s.jpg", "clip_00002.000s.jpg", "clip_00003.000s.jpg"]  # 4 s at 1 fps: 3 of 4
    assert sorted(p.name for p in (out / "frames").iterdir()) == names
    doc = json.loads((out / "cameras.json").read_text())
    assert [f["image"] for f in doc["frames"]] == names
    assert (doc["frames"][0]["width"], doc["frames"][0]["height"]) == (160, 120)
    # PLY: confidence and source frame per point; '0%' keeps every finite point
    props = read_ply_properties(out / "points.ply")
    assert set(props) == {"x", "y", "z", "red", "green", "blue", "confidence", "frame"}
    assert props["confidence"].dtype == np.float32 and (props["confidence"] >= 1).all()
    assert sorted(np.unique(props["frame"]).tolist()) == [0, 1, 2]
    assert summary["points"] == len(props["x"])
    # scene.glb: the points (coloured) and one frustum per frame
    scene = trimesh.load(out / "scene.glb", file_type="glb")
    geoms = scene.geometry
    assert sorted(k for k in geoms if k.startswith("camera_")) == ["camera_000", "camera_001", "camera_002"]
    pts = geoms["points"]
    assert isinstance(pts, trimesh.PointCloud) and len(pts.vertices) == summary["points"]
    assert pts.colors.shape == (len(pts.vertices), 4)
    np.testing.assert_allclose(pts.vertices[:, 1], -props["y"], rtol=1e-5, atol=1e-5)  # OpenCV -> glTF (y up)
    # the manifest lists the frames too: --overwrite removes them
    files = json.loads((out / ".rvggt-manifest.json").read_text())["files"]
    assert f"frames/{names[0]}" in files and "scene.glb" in files and "points.ply" in files


# ---- images ------------------------------------------------------------------------------


def test_phone_photos_16bit_and_skip_bad(tmp_path, capsys, ckpt):
    from tests.helpers.image_files import gradient16 as _gradient16, rotated_jpeg as _rotated_jpeg

    src = tmp_path / "imgs"
    src.mkdir()
    _rotated_jpeg(src / "a_phone.jpg")
    Image.fromarray(_gradient16()).save(src / "b_depthcam.png")
    shutil.copy(sorted(SAMPLE_IMAGES.glob("*.jpg"))[0], src / "c_plain.jpg")
    (src / "d_corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\ngarbage")
    # default: stop at the corrupt file, before any model work, naming it
    from rvggt_jax.app.messages import CLIError

    with pytest.raises(CLIError, match="d_corrupt.png.*--skip-bad"):
        reconstruct(src, ckpt, tmp_path / "o1")
    out = tmp_path / "o2"
    reconstruct(src, ckpt, out, skip_bad=True)
    err = capsys.readouterr().err
    assert "rvggt: warning: --skip-bad: skipped unreadable image" in err and "d_corrupt.png" in err
    doc = json.loads((out / "cameras.json").read_text())
    frames = {f["image"]: f for f in doc["frames"]}
    assert list(frames) == ["a_phone.jpg", "b_depthcam.png", "c_plain.jpg"]
    assert (frames["a_phone.jpg"]["width"], frames["a_phone.jpg"]["height"]) == (160, 120)  # upright
    # cameras follow the upright image: principal point inside it, near its centre
    k = np.array(frames["a_phone.jpg"]["intrinsic"])
    assert abs(k[0, 2] - 80) < 1 and abs(k[1, 2] - 60) < 1
    # the 16-bit image reached the model as a ramp, not as white
    with Image.open(out / "thumbnails" / "b_depthcam.jpg") as im:
        a = np.asarray(im.convert("L"), np.float64)
    assert a[:, :5].mean() < 30 and a[:, -5:].mean() > 225


def test_reused_out_dir_needs_overwrite_and_keeps_user_files(tmp_path, ckpt):
    from rvggt_jax.app.messages import CLIError

    src = tmp_path / "imgs"
    src.mkdir()
    for i, p in enumerate(sorted(SAMPLE_IMAGES.glob("*.jpg"))):
        shutil.copy(p, src / f"f{i}.jpg")
    out = tmp_path / "out"
    reconstruct(src, ckpt, out)
    (out / "my_notes.txt").write_text("mine")
    stale = out / "depth" / "old_frame.png"  # as if a bigger earlier run left it: listed, so removed
    stale.write_bytes(b"x")
    mf = out / ".rvggt-manifest.json"
    doc = json.loads(mf.read_text())
    mf.write_text(json.dumps(dict(doc, files=doc["files"] + ["depth/old_frame.png"])))
    with pytest.raises(CLIError, match="not empty.*--overwrite"):
        reconstruct(src, ckpt, out)
    os.rename(src / "f2.jpg", src / "g2.jpg")
    reconstruct(src, ckpt, out, overwrite=True)
    assert (out / "my_notes.txt").read_text() == "mine" and not stale.exists()
    depth = sorted(p.name for p in (out / "depth").iterdir())
    assert depth == ["depth_scale.json", "f0.png", "f1.png", "g2.png"]
    assert json.loads((out / "depth" / "depth_scale.json").read_text())["frames"] == ["f0", "f1", "g2"]


def test_hub_repo_id_weights(tmp_path, monkeypatch):
    import huggingface_hub.constants as c

    from tests.helpers.hub_cache import populate_hub_cache

    hf_home = tmp_path / "hf"
    monkeypatch.setenv("RVGGT_WEIGHTS_DIR", str(tmp_path / "converted"))
    monkeypatch.setattr(c, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(c, "HF_HUB_CACHE", str(hf_home / "hub"))
    populate_hub_cache(hf_home, "test/tiny-vggt")
    out = tmp_path / "out"
    reconstruct(SAMPLE_IMAGES, "test/tiny-vggt", out)
    assert json.loads((out / "cameras.json").read_text())["weights"] == "test/tiny-vggt"
    assert (tmp_path / "converted" / "test--tiny-vggt").is_dir()


# ---- command line: failures before any slow step -----------------------------------------


def rvggt(*args, env=None):
    e = dict(os.environ, RVGGT_CACHE_DIR="off", JAX_PLATFORMS="cpu", **(env or {}))
    e["PYTHONPATH"] = str(REPO) + os.pathsep + e.get("PYTHONPATH", "")
    e.pop("RVGGT_DEBUG", None)
    return subprocess.run([sys.executable, "-m", "rvggt_jax.app.cli", *map(str, args)], capture_output=True,
                          text=True, timeout=300, env=e, cwd=REPO)


def one_error(r, *needles):
    assert r.returncode != 0 and "Traceback" not in r.stderr, r.stderr
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("rvggt: error:")]
    assert len(errors) == 1, r.stderr
    for n in needles:
        assert n in errors[0], errors[0]
    # nothing slow happened: no image was loaded, no weights either
    assert "loaded" not in r.stdout and "converting" not in r.stderr, r.stdout
    return errors[0]


def test_cli_early_failures(tmp_path):
    f = tmp_path / "file.txt"
    f.write_text("x")
    one_error(rvggt("reconstruct", SAMPLE_IMAGES, "--weights", TINY, "--out", f / "out"), "file.txt", "is a file")
    one_error(rvggt("reconstruct", SAMPLE_IMAGES, "--weights", TINY, "--out", tmp_path / "o",
                    "--conf-threshold", "nan"), "nan")
    one_error(rvggt("reconstruct", SAMPLE_IMAGES, "--weights", TINY, "--out", tmp_path / "o", "--every", "2"),
              "--every")
    one_error(rvggt("reconstruct", SAMPLE_IMAGES, "--weights", TINY, "--out", tmp_path / "o", "--fps", "0"), "--fps")
    full = tmp_path / "full"
    full.mkdir()
    (full / "x.txt").write_text("x")
    one_error(rvggt("reconstruct", SAMPLE_IMAGES, "--weights", TINY, "--out", full), "not empty", "--overwrite")
    line = one_error(rvggt("reconstruct", SAMPLE_IMAGES, "--weights", "facebook/VGGT-1B", "--out", tmp_path / "o2",
                           env=dict(HF_HUB_OFFLINE="1", HF_HOME=str(tmp_path / "hf"),
                                    RVGGT_WEIGHTS_DIR=str(tmp_path / "w"))),
                     "model.safetensors", "facebook/VGGT-1B", "HF_HUB_OFFLINE")
    assert "loaded" not in line
    pt = tmp_path / "model.pt"
    pt.write_bytes(b"PK not really")
    one_error(rvggt("reconstruct", SAMPLE_IMAGES, "--weights", pt, "--out", tmp_path / "o3"), "model.pt", "safetensors")
    cut = tmp_path / "cut.safetensors"
    cut.write_bytes((TINY / "model.safetensors").read_bytes()[:3_000_000])
    one_error(rvggt("reconstruct", SAMPLE_IMAGES, "--weights", cut, "--out", tmp_path / "o4"), "cut.safetensors",
              "truncated or corrupt")
    # failed runs leave no empty output folder behind
    assert not any((tmp_path / d).exists() for d in ("o", "o2", "o3", "o4"))
