"""The `rvggt` command line, run as a subprocess (`python -m rvggt_jax.app.cli`): the demo
end to end (every output parses, one camera per image) and the one-line errors."""

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tests.helpers import SAMPLE_IMAGES, REPO, TINY
from tests.helpers.readers import read_colmap_text, read_depth_png, read_ply


_CACHE = {}


@pytest.fixture(scope="module", autouse=True)
def _compile_cache(tmp_path_factory):
    """The runs of this module share a compilation cache (the reconstructs of the tiny
    model compile the same programs) in pytest's temporary folder."""
    _CACHE["dir"] = str(tmp_path_factory.mktemp("xla_cache"))
    yield
    _CACHE.pop("dir", None)


def rvggt(*args, timeout=600):
    """Run `python -m rvggt_jax.app.cli ARGS` (timeout in seconds) -> CompletedProcess."""
    env = dict(os.environ)
    env["RVGGT_CACHE_DIR"] = _CACHE.get("dir", "off")
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.pop("RVGGT_DEBUG", None)
    env.setdefault("JAX_PLATFORMS", "cpu")
    return subprocess.run([sys.executable, "-m", "rvggt_jax.app.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, env=env, cwd=REPO)


# absl's native log lines (`I0000 00:00:...  cudart_stub.cc:31] ...`) and its one-time
# notice before them: what the CUDA plugin of the [plan] extra writes when JAX loads it on
# a machine without a CUDA driver (fd 2, before any Python code of ours could filter it);
# `rvggt` leaves that plugin unloaded on the CPU, so none may appear
_NATIVE_LOG = re.compile(r"^(WARNING: All log messages before absl::InitializeLog\(\)|[IWEF]\d{4} [\d:.]+ +\d+ \S+:\d+\])")


def native_startup_log(line: str) -> bool:
    return bool(_NATIVE_LOG.match(line))


def assert_one_line_error(r, *needles):
    assert r.returncode != 0, r.stdout + r.stderr
    assert "Traceback" not in r.stderr, r.stderr
    errors = [ln for ln in r.stderr.replace("\r", "\n").splitlines() if ln.startswith("rvggt: error:")]
    assert len(errors) == 1, r.stderr
    for n in needles:
        assert n in errors[0], errors[0]
    return errors[0]


def check_outputs(out: Path, names: list[str]):
    """Every file of a reconstruction parses; one camera per image, in order."""
    pts, cols = read_ply(out / "points.ply")
    assert pts.ndim == 2 and pts.shape[1] == 3 and cols.dtype == np.uint8 and len(pts) > 0
    assert np.isfinite(pts).all()
    doc = json.loads((out / "cameras.json").read_text())
    assert [f["image"] for f in doc["frames"]] == names
    for f in doc["frames"]:
        e, k = np.array(f["extrinsic"]), np.array(f["intrinsic"])
        assert e.shape == (3, 4) and k.shape == (3, 3) and np.isfinite(e).all() and np.isfinite(k).all()
        np.testing.assert_allclose(e[:, :3] @ e[:, :3].T, np.eye(3), atol=1e-4)
        assert f["width"] > 0 and f["height"] > 0
    m = read_colmap_text(out / "sparse")
    assert len(m["cameras"]) == len(m["images"]) == len(names)
    assert [m["images"][i]["name"] for i in sorted(m["images"])] == names
    assert all(c["model"] == "PINHOLE" and len(c["params"]) == 4 for c in m["cameras"].values())
    assert 0 < len(m["points"]) <= len(pts)
    scale = json.loads((out / "depth" / "depth_scale.json").read_text())["scale"]
    assert scale > 0
    for n in names:
        stem = Path(n).stem
        d = read_depth_png(out / "depth" / f"{stem}.png")
        assert d.ndim == 2 and (d > 0).any()
        with Image.open(out / "depth_preview" / f"{stem}.png") as im:
            assert im.mode == "RGB"
    with Image.open(out / "trajectory.png") as im:
        im.load()
    return doc


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "out"
    return out, rvggt("demo", "--out", out)


def test_demo_end_to_end(demo_run):
    """The demo reconstructs the bundled held-out scene with the trained rvggt-small, at
    its training size, says which model it ran, and compares its cameras with the scene's
    true ones: the median relative rotation error is below that of predicting every
    camera as the first (0.8x: what the shipped model reaches, tests/train/test_small_model.py)."""
    from rvggt_jax.app.demo import DEMO_SCENE

    out, r = demo_run
    assert r.returncode == 0, r.stderr[-3000:]
    assert not [ln for ln in r.stderr.splitlines() if native_startup_log(ln)], r.stderr[-3000:]
    assert "rvggt-small" in r.stdout and "held-out" in r.stdout and "RANDOM" not in r.stdout
    names = sorted(p.name for p in (DEMO_SCENE / "images").iterdir())
    doc = check_outputs(out, names)
    assert doc["frames"][0]["width"] == 112 and doc["frames"][0]["height"] == 84  # original pixels
    assert "network input 112x84" in r.stdout
    m = re.search(r"rotation error median ([\d.]+) deg \(every camera predicted as the first: ([\d.]+) deg\)",
                  r.stdout)
    assert m, r.stdout[-2000:]
    assert float(m[1]) <= 0.8 * float(m[2]), m[0]


def test_reconstruct_options(tmp_path, converted):
    """A converted (Orbax) checkpoint, --max-frames, non-image files skipped, --quiet."""
    src = tmp_path / "imgs"
    src.mkdir()
    demo = sorted(SAMPLE_IMAGES.glob("*.jpg"))
    for i, p in enumerate(demo + demo[:1]):
        shutil.copy(p, src / f"frame_{i}.jpg")
    (src / "notes.txt").write_text("not an image")
    out = tmp_path / "out"
    r = rvggt("reconstruct", src, "--weights", converted, "--out", out, "--max-frames", "3",
              "--conf-threshold", "0%", "--points", "pointmap", "--quiet")
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout == ""
    # no progress bars: only our warnings (none of the CUDA plugin's native log lines either)
    assert all(ln.startswith("rvggt: warning:") for ln in r.stderr.splitlines()), r.stderr
    doc = check_outputs(out, ["frame_0.jpg", "frame_2.jpg", "frame_3.jpg"])
    assert doc["preset"] == "dense" and doc["mode"] == "crop" and doc["points_from"] == "pointmap"
    n_pts = len(read_ply(out / "points.ply")[0])
    assert n_pts == 3 * 392 * 518  # '0%' keeps every finite point


def test_empty_folder(tmp_path):
    assert_one_line_error(rvggt("reconstruct", tmp_path, "--weights", TINY, "--out", tmp_path / "o"), "empty")


def test_no_images(tmp_path):
    (tmp_path / "a.txt").write_text("x")
    assert_one_line_error(rvggt("reconstruct", tmp_path, "--weights", TINY, "--out", tmp_path / "o"), "no images")


def test_missing_folder(tmp_path):
    assert_one_line_error(rvggt("reconstruct", tmp_path / "nope", "--weights", TINY, "--out", tmp_path / "o"), "nope")


def test_corrupt_image(tmp_path):
    shutil.copy(sorted(SAMPLE_IMAGES.glob("*.jpg"))[0], tmp_path / "a.jpg")
    (tmp_path / "b.png").write_bytes(b"\x89PNG\r\n\x1a\ngarbage")
    assert_one_line_error(rvggt("reconstruct", tmp_path, "--weights", TINY, "--out", tmp_path / "o"), "b.png")


def test_unknown_preset(tmp_path):
    shutil.copy(sorted(SAMPLE_IMAGES.glob("*.jpg"))[0], tmp_path / "a.jpg")
    line = assert_one_line_error(
        rvggt("reconstruct", tmp_path, "--weights", TINY, "--out", tmp_path / "o", "--preset", "nosuch"), "nosuch")
    assert "dense" in line  # lists the known presets


def test_missing_checkpoint(tmp_path):
    shutil.copy(sorted(SAMPLE_IMAGES.glob("*.jpg"))[0], tmp_path / "a.jpg")
    assert_one_line_error(rvggt("reconstruct", tmp_path, "--weights", tmp_path / "nockpt", "--out", tmp_path / "o"),
                          "checkpoint", "nockpt")


def test_checkpoint_that_does_not_fit(tmp_path):
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    shutil.copy(sorted(SAMPLE_IMAGES.glob("*.jpg"))[0], imgs / "a.jpg")
    ck = tmp_path / "ck"
    ck.mkdir()
    shutil.copy(TINY / "model.safetensors", ck / "model.safetensors")
    cfg = json.loads((TINY / "config.json").read_text())
    cfg["embed_dim"] = 64  # not the tensors' width
    (ck / "config.json").write_text(json.dumps(cfg))
    assert_one_line_error(rvggt("reconstruct", imgs, "--weights", ck, "--out", tmp_path / "o", "--quiet"), str(ck))


def test_no_accelerator_noise_on_a_cpu_host():
    """On a host without a GPU or TPU (JAX_PLATFORMS unset: `rvggt` picks the CPU), with the
    [plan] extra's CUDA and TPU plugins installed (as in the test environment), `rvggt
    --version` (which imports JAX) prints the version and nothing on stderr: no absl
    "Could not find cuda drivers" lines, no plugin traceback."""
    from rvggt_jax.app.xla_cpu import ACCELERATOR_NODES

    if any(os.path.exists(n) for n in ACCELERATOR_NODES):
        pytest.skip("this host has an accelerator: JAX loads its plugins")
    env = {k: v for k, v in os.environ.items() if k != "JAX_PLATFORMS"}
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    r = subprocess.run([sys.executable, "-m", "rvggt_jax.app.cli", "--version"], capture_output=True, text=True,
                       timeout=300, env=env, cwd=REPO)
    assert r.returncode == 0 and r.stdout.startswith("rvggt (rvggt-jax)"), r.stdout + r.stderr
    assert r.stderr == ""


def test_bad_arguments(tmp_path):
    assert_one_line_error(rvggt("reconstruct", tmp_path, "--out", tmp_path / "o"), "--weights")
    assert_one_line_error(rvggt("reconstruct", tmp_path, "--weights", TINY, "--out", tmp_path / "o",
                                "--conf-threshold", "lots"), "lots")
    assert_one_line_error(rvggt("frobnicate"), "frobnicate")


def test_help():
    r = rvggt("--help")
    assert r.returncode == 0 and "reconstruct" in r.stdout and "demo" in r.stdout
    r = rvggt("reconstruct", "--help")
    assert r.returncode == 0 and "--conf-threshold" in r.stdout and "percentile" in r.stdout


@pytest.fixture(scope="module")
def converted(tmp_path_factory):
    dst = tmp_path_factory.mktemp("conv") / "tiny_orbax"
    r = rvggt("convert", TINY, dst, "--quiet")
    assert r.returncode == 0, r.stderr[-3000:]
    return dst


def test_convert_then_load(converted):
    from rvggt_jax import load_pretrained

    assert (converted / "config.json").is_file()
    params, config = load_pretrained(converted, device_put=False)
    assert config.embed_dim == 32 and "aggregator" in params


def test_bundled_demo_data_found():
    from rvggt_jax.app.commands import SAMPLE_IMAGES as images, TINY_WEIGHTS as weights
    from rvggt_jax.app.demo import DEMO_SCENE
    from rvggt_jax.weights.pretrained import bundled_path

    assert images == SAMPLE_IMAGES and any(images.glob("*.jpg"))
    assert (weights / "config.json").is_file()
    assert len(list((DEMO_SCENE / "images").glob("*.png"))) == 8 and (DEMO_SCENE / "cameras.json").is_file()
    assert (bundled_path("rvggt-small") / "config.json").is_file()


def test_select_frames():
    from rvggt_jax.app.options import select_frames

    paths = [Path(f"{i:02d}.png") for i in range(10)]
    assert select_frames(paths, None) == paths and select_frames(paths, 20) == paths
    assert [p.stem for p in select_frames(paths, 3)] == ["00", "04", "09"] or \
        [p.stem for p in select_frames(paths, 3)] == ["00", "05", "09"]
    assert len(select_frames(paths, 4)) == 4 and select_frames(paths, 1) == paths[:1]


def test_memory_check_refuses_with_what_to_change(monkeypatch):
    # XLA's plan of the real VGGT-1B forward (compiled, not run): 300 frames at float32
    # dense need more than 16 GB (19.7 GB; 200 frames, 14.8 GB, fit since layers 4 and 11
    # are kept as their heads' projections); the message names the need, the limit, and
    # the ways out; 2 frames fit.
    import dataclasses

    from rvggt_jax.config import VGGTConfig
    from rvggt_jax.planning.memory import MEMORY_LIMIT_ENV, InsufficientMemoryError, check_fits

    cfg = dataclasses.replace(VGGTConfig(), enable_track=False)
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "16")
    rep = check_fits(cfg, 2, 392, 518)
    assert 5e9 < rep.total_bytes < 16e9  # 4.7 GB of float32 weights + activations
    with pytest.raises(InsufficientMemoryError) as e:
        check_fits(cfg, 300, 392, 518)
    msg = str(e.value)
    assert "need" in msg and "16.0 GB" in msg and "--preset regime" in msg and "--dtype bfloat16" in msg
    n = int(msg.rsplit("--max-frames ", 1)[1])
    assert 2 <= n < 300


def test_reconstruct_refuses_what_does_not_fit(tmp_path, monkeypatch, capsys):
    from rvggt_jax.app.cli import main
    from rvggt_jax.planning.memory import MEMORY_LIMIT_ENV

    monkeypatch.setenv(MEMORY_LIMIT_ENV, "0.001")  # 1 MB
    code = main(["reconstruct", str(SAMPLE_IMAGES), "--weights", str(TINY),
                 "--out", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert code != 0 and err.startswith("rvggt: error:") and "GB" in err and "--max-frames" in err
    assert not (tmp_path / "out" / "points.ply").exists()


def test_reconstruct_devices_must_exist(tmp_path, capsys):
    from rvggt_jax.app.cli import main

    code = main(["reconstruct", str(SAMPLE_IMAGES), "--weights", str(TINY), "--out", str(tmp_path / "out"),
                 "--quiet", "--devices", "64"])
    err = capsys.readouterr().err
    assert code != 0 and err.startswith("rvggt: error:") and "--devices 64" in err and "device(s)" in err
