"""`rvggt reconstruct --chunk-frames C --overlap O`: a chunk as large as the sequence equals
the one-forward run; 12 frames in 3 chunks write every output for all 12 frames (pycolmap
reads the model), and a run stopped after its first chunk resumes to the same result;
the options' and the folder's bad values are one-line errors. Every forward here has 6
frames of 112 x 84 (`--size 112`: what is checked here is the chunking, not the network
size): one compilation for the module (in-process runs)."""

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tests.helpers import TINY

FRAMES = 12
SIZE = 112  # the network width: 112 x 84 from the frames' 80 x 60


@pytest.fixture(autouse=True)
def _no_disk_cache(monkeypatch):
    monkeypatch.setenv("RVGGT_CACHE_DIR", "off")


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    """The tiny checkpoint as Orbax, loaded alike by every run (one compilation)."""
    from rvggt_jax import load_pretrained
    from rvggt_jax.weights.checkpoint import save_orbax

    params, config = load_pretrained(TINY, device_put=False)
    return save_orbax(params, config, tmp_path_factory.mktemp("ckpt") / "tiny")


@pytest.fixture(scope="module")
def frames_dir(tmp_path_factory):
    """12 frames of a procedural room along an arc, named in capture order."""
    from rvggt_jax.synthetic import make_scene

    folder = tmp_path_factory.mktemp("frames")
    for i, im in enumerate(make_scene(frames=FRAMES, height=60, width=80, seed=3).images):
        Image.fromarray(im).save(folder / f"frame_{i:03d}.png")
    return folder


def reconstruct(*args, **kw):
    from rvggt_jax.app.commands import ReconstructOptions, reconstruct_folder

    kw.setdefault("quiet", True)
    kw.setdefault("size", SIZE)
    kw.setdefault("max_points", 20_000)
    return reconstruct_folder(*args, ReconstructOptions(**kw))


def cameras(out: Path) -> tuple[list[str], np.ndarray]:
    doc = json.loads((out / "cameras.json").read_text())
    return [f["image"] for f in doc["frames"]], np.array([f["extrinsic"] for f in doc["frames"]])


def test_one_chunk_equals_the_unchunked_run(tmp_path, frames_dir, ckpt):
    six = tmp_path / "six"
    six.mkdir()
    for p in sorted(frames_dir.iterdir())[:6]:
        (six / p.name).write_bytes(p.read_bytes())
    reconstruct(six, ckpt, tmp_path / "plain")
    summary = reconstruct(six, ckpt, tmp_path / "chunked", chunk_frames=100, overlap=2)
    assert summary["chunks"] == 1
    names_a, ext_a = cameras(tmp_path / "plain")
    names_b, ext_b = cameras(tmp_path / "chunked")
    assert names_a == names_b and len(names_a) == 6
    np.testing.assert_allclose(ext_b, ext_a, rtol=0, atol=1e-5)
    doc_a = json.loads((tmp_path / "plain" / "cameras.json").read_text())
    doc_b = json.loads((tmp_path / "chunked" / "cameras.json").read_text())
    np.testing.assert_allclose([f["intrinsic"] for f in doc_b["frames"]], [f["intrinsic"] for f in doc_a["frames"]],
                               rtol=1e-5)


@pytest.fixture(scope="module")
def chunked_run(tmp_path_factory, frames_dir, ckpt):
    """12 frames in 3 chunks, with loop closure on (the frames' descriptors are predicted
    and cached; 12 frames hold no revisit), one shared SIMPLE_PINHOLE COLMAP camera."""
    out = tmp_path_factory.mktemp("run") / "out"
    summary = reconstruct(frames_dir, ckpt, out, chunk_frames=6, overlap=2, loop_closure=True,
                          camera_type="SIMPLE_PINHOLE", shared_camera=True)
    return out, summary


def test_three_chunks_write_every_frame(chunked_run, frames_dir):
    import pycolmap

    out, summary = chunked_run
    names = sorted(p.name for p in frames_dir.iterdir())
    assert summary["chunks"] == 3 and summary["frames"] == FRAMES
    got, ext = cameras(out)
    assert got == names and np.isfinite(ext).all()
    stems = sorted(Path(n).stem for n in names)
    for folder, suffix in (("depth", ".png"), ("depth_preview", ".png"), ("thumbnails", ".jpg")):
        assert sorted(p.stem for p in (out / folder).glob(f"*{suffix}")) == stems, folder
    assert json.loads((out / "depth" / "depth_scale.json").read_text())["frames"] == stems
    from rvggt_jax.eval.datasets.kitti import read_kitti_poses

    np.testing.assert_allclose(read_kitti_poses(out / "poses_kitti.txt"), ext, atol=1e-9)
    transforms = json.loads((out / "transforms.json").read_text())
    assert len(transforms["frames"]) == FRAMES
    assert sorted(p.name for p in (out / "images").iterdir()) == names
    model = pycolmap.Reconstruction(str(out / "sparse"))
    assert sorted(im.name for im in model.images.values()) == names
    assert [c.model.name for c in model.cameras.values()] == ["SIMPLE_PINHOLE"]  # --shared-camera
    assert 0 < len(model.points3D) <= 20_000
    # the cache is listed by the manifest (--overwrite removes it), one folder per chunk
    files = json.loads((out / ".rvggt-manifest.json").read_text())["files"]
    assert {f"chunks/chunk_0000{k}/depth.npy" for k in range(3)} <= set(files)
    # the chunks' Sim(3)s are recorded; chunk 0 is the world
    doc = json.loads((out / "cameras.json").read_text())
    assert len(doc["chunk_sim3"]) == 3 and doc["chunk_sim3"][0]["scale"] == 1.0
    assert [f["chunk"] for f in doc["frames"]] == [0] * 5 + [1] * 3 + [2] * 4
    assert doc["loop_closure"] is True and doc["loops"] == summary["loops"] == 0
    desc = np.load(out / "chunks" / "chunk_00001" / "descriptors.npy")
    assert desc.shape[0] == 6 and np.allclose(np.linalg.norm(desc, axis=1), 1.0, atol=1e-5)


def test_stopped_run_resumes_to_the_same_result(tmp_path, chunked_run, frames_dir, ckpt, monkeypatch):
    from rvggt_jax.app.long_sequence import ChunkedRun

    reference, _ = chunked_run
    out = tmp_path / "out"
    calls = []
    predict = ChunkedRun.predict

    def stop_after_first(self, frames):
        calls.append(list(frames))
        if len(calls) == 2:
            raise KeyboardInterrupt  # what Ctrl-C raises between two chunks
        return predict(self, frames)

    monkeypatch.setattr(ChunkedRun, "predict", stop_after_first)
    with pytest.raises(KeyboardInterrupt):
        reconstruct(frames_dir, ckpt, out, chunk_frames=6, overlap=2, loop_closure=True)
    assert (out / "chunks" / "chunk_00000" / "meta.json").is_file()
    assert not (out / "chunks" / "chunk_00001").exists() and not (out / "cameras.json").exists()
    listed = json.loads((out / ".rvggt-manifest.json").read_text())["files"]
    assert "chunks/chunk_00000/depth.npy" in listed

    calls.clear()
    monkeypatch.setattr(ChunkedRun, "predict", lambda self, frames: calls.append(list(frames)) or predict(self, frames))
    summary = reconstruct(frames_dir, ckpt, out, chunk_frames=6, overlap=2, loop_closure=True)
    assert calls == [list(range(4, 10)), list(range(6, 12))]  # chunk 0 came from the cache
    assert summary["frames"] == FRAMES
    np.testing.assert_allclose(cameras(out)[1], cameras(reference)[1], rtol=0, atol=1e-6)
    assert (out / "points.ply").read_bytes() == (reference / "points.ply").read_bytes()
    # the resumed run's manifest still lists what the stopped run wrote
    files = json.loads((out / ".rvggt-manifest.json").read_text())["files"]
    assert "chunks/chunk_00000/depth.npy" in files and "cameras.json" in files


def test_a_cache_of_other_settings_is_refused(chunked_run, frames_dir, ckpt):
    from rvggt_jax.app.messages import CLIError

    out, _ = chunked_run
    with pytest.raises(CLIError, match=r"other settings \(overlap 2 -> 3\).*--overwrite"):
        reconstruct(frames_dir, ckpt, out, chunk_frames=6, overlap=3, loop_closure=True)


@pytest.mark.parametrize("args, needles", [
    (["--chunk-frames", "6", "--overlap", "6"], ["--overlap", "smaller than --chunk-frames 6", "--overlap 1"]),
    (["--chunk-frames", "1"], ["--chunk-frames", "at least 2", "--chunk-frames 60"]),
    (["--chunk-frames", "6", "--overlap", "0"], ["--overlap", "at least 1", "--overlap 1"]),
    (["--overlap", "2"], ["--overlap", "only applies with --chunk-frames"]),
    (["--chunk-frames", "six"], ["--chunk-frames", "'six'"]),
])
def test_bad_chunk_options_are_one_line_errors(tmp_path, frames_dir, capsys, args, needles):
    from rvggt_jax.app.cli import main

    code = main(["reconstruct", str(frames_dir), "--weights", str(TINY), "--out", str(tmp_path / "o"), *args])
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("rvggt: error:")]
    assert code != 0 and len(lines) == 1 and "Traceback" not in err, err
    for n in needles:
        assert n in lines[0], lines[0]
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("names, needle", [
    (["b.png", "a.png", "c.png"], "has no frame number"),
    (["frame_1.png", "frame_10.png", "frame_2.png"], "'frame_10.png' sorts before 'frame_2.png'"),
])
def test_a_folder_without_order_is_refused(tmp_path, capsys, names, needle):
    from rvggt_jax.app.cli import main

    folder = tmp_path / "imgs"
    folder.mkdir()
    for i, n in enumerate(names):  # mixed sizes are fine; the order is what matters
        Image.fromarray(np.full((40 + 8 * i, 60, 3), 40 * i, np.uint8)).save(folder / n)
    code = main(["reconstruct", str(folder), "--weights", str(TINY), "--out", str(tmp_path / "o"),
                 "--chunk-frames", "2", "--overlap", "1"])
    err = capsys.readouterr().err
    assert code != 0 and needle in err and "order matters" in err and "Traceback" not in err, err


def test_auto_chunk_is_the_largest_the_memory_plan_fits(monkeypatch):
    """--chunk-frames auto: a line through two small plans, 90% of the device's memory."""
    import types

    import rvggt_jax.planning.memory as memory
    from rvggt_jax.app.long_sequence import resolve_chunk_frames
    from rvggt_jax.app.messages import CLIError
    from rvggt_jax.app.options import ReconstructOptions

    planned = []

    def plan(config, frames, *a, **kw):  # 1 GB fixed + 50 MB a frame
        planned.append(frames)
        return types.SimpleNamespace(total_bytes=1e9 + 5e7 * frames)

    monkeypatch.setattr(memory, "memory_report", plan)
    monkeypatch.setattr(memory, "device_memory_bytes", lambda: (10e9, "a test device"))
    chunk = resolve_chunk_frames("auto", None, (392, 518), ReconstructOptions(), frames=10_000)
    assert chunk == int((0.9 * 10e9 - 1e9) / 5e7) and len(planned) == 2  # 160
    assert resolve_chunk_frames("auto", None, (392, 518), ReconstructOptions(), frames=40) == 40
    assert resolve_chunk_frames(12, None, (392, 518), ReconstructOptions(), frames=40) == 12
    monkeypatch.setattr(memory, "device_memory_bytes", lambda: (1e9, "a test device"))
    with pytest.raises(CLIError, match="not even 2 frames"):
        resolve_chunk_frames("auto", None, (392, 518), ReconstructOptions(), frames=40)


def test_a_loop_verification_is_topped_up_to_the_compiled_chunk():
    """verify(frames) with fewer frames than a chunk runs the compiled chunk size: the
    frames asked for first (the first is the reference), then their nearest neighbours."""
    from rvggt_jax.app.long_sequence import _top_up

    asked = [10, 11, 50, 51]
    run = _top_up(asked, 8, 60)
    assert run[:4] == asked and len(run) == len(set(run)) == 8
    assert sorted(run[4:]) == [9, 12, 49, 52]
    assert _top_up([0, 1], 5, 3) == [0, 1, 2]  # never past the sequence
    assert _top_up(list(range(6)), 4, 10) == list(range(6))  # a full list stays as it is


def test_loop_closure_without_gtsam_is_said_before_anything_runs(tmp_path, frames_dir, monkeypatch, capsys):
    import importlib.util

    from rvggt_jax.app.cli import main

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "gtsam" else find_spec(name, *a))
    code = main(["reconstruct", str(frames_dir), "--weights", str(TINY), "--out", str(tmp_path / "o"),
                 "--chunk-frames", "6", "--loop-closure"])
    err = capsys.readouterr().err
    assert code != 0 and 'pip install "rvggt-jax[sequence]"' in err and "Traceback" not in err, err
    assert not (tmp_path / "o").exists()
