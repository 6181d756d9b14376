"""Training data without compiling anything: every evaluation format opens for training
(auto-detected), batches are a function of (seed, step) alone with frame counts in the
buckets, bad folders name the file they lacked, a batch of an unplanned shape is an
error, an unknown train prefix names the nearest parameter paths, the loss plot."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import rvggt_jax
from rvggt_jax import train
from rvggt_jax.synthetic import make_scene, write_scene
from rvggt_jax.train import data
from tests.helpers.micro import micro_config

H, W = 42, 56
K7 = 525 * W / 640  # 7 Scenes' fixed calibration at 56x42 (NRGBD: fx = fy, centred), which every format takes


@pytest.fixture(scope="module")
def scene():
    return make_scene(frames=6, height=H, width=W, seed=5, focal=K7)


@pytest.mark.parametrize("fmt", ["folder", "co3d", "scannet", "7scenes", "nrgbd", "dtu", "colmap"])
def test_every_format_opens_for_training(fmt, scene, tmp_path):
    write_scene(scene, "tnt" if fmt == "colmap" else fmt, tmp_path)
    assert data.detect_format(tmp_path) == fmt
    logs = []
    got, (sc,) = data.open_scenes(tmp_path, log=logs.append)
    assert got == fmt and len(sc) == 6
    assert bool(logs) == (fmt in ("dtu", "colmap"))  # no depth: said, camera loss only
    ex = data.step_batch([sc], 3, 0, 1, (2, 6), (28, 42), (2, 4, 6))
    s = ex["images"].shape[1]
    assert ex["images"].shape == (1, s, 3, 28, 42) and s in (2, 4, 6)
    assert ex["point_mask"].any() == (fmt not in ("dtu", "colmap"))
    np.testing.assert_allclose(ex["extrinsics"][0, 0], np.eye(3, 4), atol=1e-5)


def test_batches_depend_on_seed_and_step_only():
    frames = [30, 5, 12]
    plans = [data.draw_batch_plan(frames, i, 7, 2, (2, 24)) for i in range(40)]
    # a resumed run (steps 20..39 only) draws the same
    for i in range(20, 40):
        p, idx = data.draw_batch_plan(frames, i, 7, 2, (2, 24))
        assert p == plans[i][0] and all(np.array_equal(a, b) for a, b in zip(idx, plans[i][1]))
    counts = {len(idx[0]) for _, idx in plans}
    assert counts <= set(data.default_buckets(2, 24)) and len(counts) > 1
    for picks, idx in plans:
        assert len({len(i) for i in idx}) == 1  # one frame count per batch
        for p, i in zip(picks, idx):
            assert len(i) <= frames[p] and np.all(np.diff(i) > 0) and i.max() < frames[p]
    other = [data.draw_batch_plan(frames, i, 8, 2, (2, 24)) for i in range(40)]
    assert [p for p, _ in other] != [p for p, _ in plans]  # another seed, other scenes
    assert data.default_buckets(2, 24) == (2, 4, 8, 16, 24) and data.frame_plan(8) == (8, 8, (8,))
    with pytest.raises(rvggt_jax.InputError, match="include the minimum"):
        data.frame_plan((2, 8), (4, 8))
    with pytest.raises(rvggt_jax.InputError, match="no scene has 4 frames"):
        data.draw_batch_plan([3, 2], 0, 0, 1, (4, 8))


def test_stream_prefetches_in_order_and_raises_reader_errors():
    got = [i for i, _ in data.BatchStream(lambda i: {"i": i}, 3, 9, prefetch=2)]
    assert got == list(range(3, 9))

    def bad(i):
        if i == 2:
            raise FileNotFoundError("scene/images/000002.png")
        return i

    stream = data.BatchStream(bad, 0, 5, prefetch=2)
    with pytest.raises(FileNotFoundError, match="000002.png"):
        list(stream)
    stream.close()


def test_missing_cameras_or_depth_name_the_file(scene, tmp_path):
    d = write_scene(scene, "images", tmp_path / "imgs")
    with pytest.raises(rvggt_jax.InputError, match="cameras.json"):
        data.open_scenes(d.parent)
    with pytest.raises(rvggt_jax.InputError, match=r"cameras.json"):
        data.open_scenes(d.parent, "folder")
    d = write_scene(scene, "folder", tmp_path / "f")
    (d / "depth" / "frame_0002.npy").unlink()
    with pytest.raises(rvggt_jax.InputError, match=r"depth/frame_0002.npy not found"):
        data.open_scenes(d.parent)
    for f in (d / "depth").iterdir():
        f.unlink()
    (d / "depth").rmdir()
    logs = []
    data.open_scenes(d.parent, log=logs.append)
    assert "depth/<stem>.npy" in logs[0] and "camera loss only" in logs[0]
    with pytest.raises(rvggt_jax.InputError, match=r"depth/<stem>.npy or depth/<stem>.png not found"):
        data.open_scenes(d.parent, require_depth=True)
    c = write_scene(scene, "co3d", tmp_path / "c")
    (c / "depths" / "frame000003.jpg.geometric.png").unlink()
    with pytest.raises(rvggt_jax.InputError, match="frame000003.jpg.geometric.png not found"):
        data.open_scenes(tmp_path / "c")
    (c.parent / "frame_annotations.jgz").unlink()
    with pytest.raises(rvggt_jax.InputError, match="frame_annotations.jgz"):
        data.open_scenes(tmp_path / "c", "co3d")
    with pytest.raises(rvggt_jax.InputError, match="unknown data format"):
        data.open_scenes(tmp_path, "kitti")


def test_a_batch_of_another_shape_is_an_error():
    from rvggt_jax.train.loop import BucketedStep

    logs = []
    step = BucketedStep(lambda s, b: (s, {}), 1, (2, 4), (28, 42), logs.append)
    step(None, {"images": np.zeros((1, 2, 3, 28, 42))})
    with pytest.raises(rvggt_jax.InputError, match=r"1 x 3 frames of 28x42 differs from the compiled train step "
                                                    r"\(1 x \[2, 4\] frames of 28x42\)"):
        step(None, {"images": np.zeros((1, 3, 3, 28, 42))})
    with pytest.raises(rvggt_jax.InputError, match="of 28x56 differs"):
        step(None, {"images": np.zeros((1, 2, 3, 28, 56))})


def test_unknown_train_prefix_names_the_nearest_paths():
    config = micro_config(enable_point=False, enable_track=False)
    params = jax.eval_shape(lambda: rvggt_jax.init_params(config, 0))
    with pytest.raises(ValueError, match=r"'aggregator/frame_blokcs' matches no parameter; nearest parameter "
                                         r"paths: aggregator/frame_blocks, "):
        train.param_labels(params, ("aggregator/frame_blokcs",))
    with pytest.raises(ValueError, match=r"nearest parameter paths: camera_head/trunk, "):
        train.param_labels(params, ("camera_head/trnk",))
    with pytest.raises(ValueError, match=r"nearest parameter paths: depth_head, "):
        train.param_labels(params, ("depht_head",))


def test_loss_plot(tmp_path):
    from PIL import Image

    from rvggt_jax.train.loop import plot_loss

    hist = [{"step": i + 1, "loss_objective": 3.0 / (i + 1)} for i in range(20)]
    p = plot_loss(hist, tmp_path / "loss.png")
    with Image.open(p) as im:
        a = np.asarray(im.convert("RGB"))
    assert a.shape == (360, 640, 3)
    assert ((a[..., 2] > 150) & (a[..., 0] < 80)).sum() > 200  # the blue curve is drawn
    assert plot_loss([], tmp_path / "none.png") is None


def test_finetune_cli_takes_frame_ranges_buckets_and_formats(tmp_path, capsys):
    from rvggt_jax.app.cli import build_parser, main

    a = build_parser().parse_args(["finetune", "d", "--out", "o", "--frames", "2-8", "--buckets", "2,4,8",
                                   "--format", "co3d", "--require-depth", "--stop-at", "5"])
    assert (a.frames, a.buckets, a.data_format, a.require_depth, a.stop_at) == ("2-8", "2,4,8", "co3d", True, 5)
    d = build_parser().parse_args(["finetune", "d", "--out", "o"])
    assert (d.frames, d.buckets, d.data_format) == ("2-24", None, "auto")
    assert main(["finetune", str(tmp_path), "--out", str(tmp_path / "o"), "--frames", "2-x"]) == 1
    assert "--frames must be N or MIN-MAX" in capsys.readouterr().err
