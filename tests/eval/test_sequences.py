"""Long-sequence evaluation: the KITTI odometry and TUM RGB-D readers on synthetic
sequences written in their formats (poses, intrinsics, TUM's timestamp association),
malformed files named by file and line, and `rvggt eval --chunk-frames` with the
chunked predictor replaced by the ground truth under a random Sim(3) (ATE 0) or with
noise (ATE > 0)."""

import csv
import types

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rvggt_jax.eval.datasets import DatasetError, load_scenes
from rvggt_jax.eval.datasets.files import c2w_to_w2c, save_image, w2c_to_c2w
from rvggt_jax.eval.datasets.kitti import read_kitti_poses, write_kitti_poses
from rvggt_jax.eval.datasets.tum import associate, read_tum_trajectory, sensor_camera, write_tum_trajectory
from rvggt_jax.synthetic import make_scene, write_scene

H, W = 28, 42


def random_w2c(n, seed=0):
    rng = np.random.default_rng(seed)
    c2w = np.zeros((n, 4, 4))
    c2w[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    c2w[:, :3, 3] = rng.normal(scale=5.0, size=(n, 3))
    c2w[:, 3, 3] = 1
    return c2w_to_w2c(c2w)


@pytest.fixture(scope="module")
def scene():
    return make_scene(frames=7, height=H, width=W, seed=5)


# ---------------------------------------------------------------------------------------
# trajectory files
# ---------------------------------------------------------------------------------------


def test_kitti_poses_round_trip(tmp_path):
    w2c = random_w2c(9)
    p = write_kitti_poses(tmp_path / "poses" / "00.txt", w2c)
    lines = p.read_text().splitlines()
    assert len(lines) == 9 and all(len(ln.split()) == 12 for ln in lines)
    first = np.array(lines[0].split(), float).reshape(3, 4)
    np.testing.assert_allclose(first, w2c_to_c2w(w2c[0])[:3], atol=1e-12)  # the file holds camera-to-world
    np.testing.assert_allclose(read_kitti_poses(p), w2c, atol=1e-9)
    w2c4 = np.concatenate([w2c, np.tile([[[0, 0, 0, 1.0]]], (9, 1, 1))], axis=1)
    np.testing.assert_allclose(read_kitti_poses(write_kitti_poses(tmp_path / "b.txt", w2c4)), w2c, atol=1e-9)
    with pytest.raises(ValueError, match="non-finite"):
        write_kitti_poses(tmp_path / "c.txt", np.where(np.arange(12).reshape(3, 4) == 5, np.nan, w2c))


def test_tum_trajectory_round_trip(tmp_path):
    w2c = random_w2c(8, seed=1)
    stamps = 1305031102.175304 + np.arange(8) * 0.0333
    p = write_tum_trajectory(tmp_path / "traj.txt", stamps, w2c)
    rows = [ln.split() for ln in p.read_text().splitlines() if not ln.startswith("#")]
    assert len(rows) == 8 and all(len(r) == 8 for r in rows)
    np.testing.assert_allclose(np.array(rows[2][1:4], float), w2c_to_c2w(w2c[2])[:3, 3], atol=1e-12)  # centres
    t, back = read_tum_trajectory(p)
    np.testing.assert_array_equal(t, stamps)
    np.testing.assert_allclose(back, w2c, atol=1e-9)
    with pytest.raises(ValueError, match="timestamps"):
        write_tum_trajectory(tmp_path / "x.txt", stamps[:3], w2c)


# ---------------------------------------------------------------------------------------
# dataset readers
# ---------------------------------------------------------------------------------------


def test_kitti_sequence(scene, tmp_path):
    seq = write_scene(scene, "kitti", tmp_path)
    assert seq == tmp_path / "sequences" / "00" and (tmp_path / "poses" / "00.txt").is_file()
    assert write_scene(make_scene(frames=3, height=H, width=W, seed=6), "kitti", tmp_path).name == "01"
    assert load_scenes("kitti", tmp_path, ["01"])[0].extrinsics.shape == (3, 3, 4)
    (sc,) = load_scenes("kitti", tmp_path, ["00"])
    assert sc.dataset == "kitti" and len(sc) == 7
    assert [p.name for p in sc.image_paths[:2]] == ["000000.png", "000001.png"]
    np.testing.assert_allclose(sc.extrinsics, scene.extrinsics, atol=1e-9)
    np.testing.assert_allclose(sc.intrinsics, scene.intrinsics, atol=1e-9)
    np.testing.assert_allclose(sc.meta["timestamps"], 0.1 * np.arange(7), atol=1e-9)
    # a real calib.txt puts camera 2 to the side of camera 0: P2 = K [I | t]
    calib = seq / "calib.txt"
    k = scene.intrinsics[0]
    t = np.array([0.06, -0.0003, 0.004])
    lines = [ln for ln in calib.read_text().splitlines() if not ln.startswith("P2:")]
    p2 = np.c_[k, k @ t]
    calib.write_text("\n".join(lines + ["P2: " + " ".join(f"{x:.12e}" for x in p2.ravel())]) + "\n")
    (moved,) = load_scenes("kitti", tmp_path, ["00"])
    np.testing.assert_allclose(moved.extrinsics[:, :, 3], scene.extrinsics[:, :, 3] + t, atol=1e-9)
    np.testing.assert_allclose(moved.intrinsics[0], k, atol=1e-9)


def test_tum_sequence(scene, tmp_path):
    d = write_scene(scene, "tum", tmp_path)
    gt = d / "groundtruth.txt"
    assert len(read_tum_trajectory(gt)[0]) == 2 * 7 - 1  # twice the images' rate
    (sc,) = load_scenes("tum", tmp_path)
    assert sc.name == scene.name and len(sc) == 7 and sc.meta["dropped"] == 0
    np.testing.assert_allclose(sc.extrinsics, scene.extrinsics, atol=1e-9)
    np.testing.assert_allclose(sc.intrinsics, scene.intrinsics, atol=1e-9)  # from calibration.txt
    # a sequence of a TUM sensor without calibration.txt: the published camera, scaled
    named = make_scene(frames=3, height=H, width=W, seed=5, name="rgbd_dataset_freiburg2_xyz")
    write_scene(named, "tum", tmp_path / "named")
    (tmp_path / "named" / named.name / "calibration.txt").unlink()
    (sc2,) = load_scenes("tum", tmp_path / "named")
    np.testing.assert_allclose(sc2.intrinsics[0], [[520.9 * W / 640, 0, 325.1 * W / 640],
                                                   [0, 521.0 * H / 480, 249.7 * H / 480], [0, 0, 1]])
    assert sensor_camera("fr3_long_office", 640, 480)[0, 0] == 535.4
    assert sensor_camera("frame_dump", 640, 480) is None and sensor_camera("my_fr12", 640, 480) is None
    (d / "calibration.txt").unlink()
    assert load_scenes("tum", tmp_path)[0].intrinsics is None  # no sensor named, no file: unknown


def test_tum_association(tmp_path):
    """Ground truth at 100 Hz with a 0.2 s gap, images at 30 Hz offset by 3 ms: each
    image gets the nearest pose within 0.02 s; those in the gap are dropped."""
    d = tmp_path / "rgbd_dataset_freiburg1_desk"
    (d / "rgb").mkdir(parents=True)
    gt_t = np.round(10.0 + np.arange(101) * 0.01, 6)
    gt_t = gt_t[(gt_t < 10.4) | (gt_t > 10.6)]
    c2w = np.tile(np.eye(4), (len(gt_t), 1, 1))
    c2w[:, 0, 3] = gt_t  # the pose says which ground-truth row it came from
    write_tum_trajectory(d / "groundtruth.txt", gt_t, c2w_to_w2c(c2w))
    img_t = np.round(10.003 + np.arange(30) / 30, 6)
    img = np.zeros((4, 6, 3), np.uint8)
    lines = ["# timestamp filename"]
    for t in img_t:
        save_image(d / "rgb" / f"{t:.6f}.png", img)
        lines.append(f"{t:.6f} rgb/{t:.6f}.png")
    (d / "rgb.txt").write_text("\n".join(lines) + "\n")
    (sc,) = load_scenes("tum", tmp_path)
    near = gt_t[np.abs(img_t[:, None] - gt_t[None]).argmin(1)]
    keep = np.abs(near - img_t) <= 0.02
    assert 0 < keep.sum() < len(img_t) and sc.meta["dropped"] == (~keep).sum()
    np.testing.assert_allclose(sc.meta["timestamps"], img_t[keep])
    np.testing.assert_allclose(w2c_to_c2w(sc.extrinsics)[:, 0, 3], near[keep], atol=1e-9)
    np.testing.assert_allclose(sc.intrinsics[0, 0, 0], 517.3 * 6 / 640)  # fr1, scaled to 6x4 images
    rng = np.random.default_rng(3)
    q, r = rng.uniform(0, 5, 200), rng.uniform(0, 5, 300)
    qi, ri = associate(q, r, 0.01)
    best = np.abs(q[:, None] - r[None]).argmin(1)
    ok = np.abs(q - r[best]) <= 0.01
    np.testing.assert_array_equal(qi, np.flatnonzero(ok))
    np.testing.assert_array_equal(ri, best[ok])


# ---------------------------------------------------------------------------------------
# malformed files
# ---------------------------------------------------------------------------------------

_POSE = "1 0 0 0 0 1 0 0 0 0 1 0"
_GT = "1.0 0 0 0 0 0 0 1"


@pytest.mark.parametrize("text,needles", [
    (f"{_POSE}\n{_POSE}\n1 0 0 0 0 1 0 0 0 0 1\n", (":3:", "12 fields", "11")),
    (f"{_POSE}\n1 0 0 nan 0 1 0 0 0 0 1 0\n", (":2:", "non-finite")),
    (f"{_POSE}\n1 0 0 0 0 1 0 0 0 0 1 x\n", (":2:", "not a number")),
    ("2 0 0 0 0 1 0 0 0 0 1 0\n", (":1:", "not a rotation")),
    ("\n\n", ("no pose",)),
])
def test_malformed_kitti_poses(tmp_path, text, needles):
    p = tmp_path / "07.txt"
    p.write_text(text)
    with pytest.raises(DatasetError) as e:
        read_kitti_poses(p)
    assert str(p) in str(e.value)
    for n in needles:
        assert n in str(e.value), str(e.value)


@pytest.mark.parametrize("text,needles", [
    (f"# header\n{_GT}\n# note\n2.0 0 0 0 0 0 1\n", (":4:", "8 fields", "7")),
    (f"{_GT}\n2.0 0 0 inf 0 0 0 1\n", (":2:", "non-finite")),
    (f"{_GT}\n{_GT}\n3.0 0 0 0 0 0 0 2\n", (":3:", "unit length")),
])
def test_malformed_tum_trajectory(tmp_path, text, needles):
    p = tmp_path / "groundtruth.txt"
    p.write_text(text)
    with pytest.raises(DatasetError) as e:
        read_tum_trajectory(p)
    assert str(p) in str(e.value)
    for n in needles:
        assert n in str(e.value), str(e.value)


def test_broken_sequence_folders(scene, tmp_path):
    def fails(fmt, root, *needles):
        with pytest.raises(DatasetError) as e:
            load_scenes(fmt, root)
        for n in needles:
            assert str(n) in str(e.value), str(e.value)

    seq = write_scene(scene, "kitti", tmp_path / "k")
    (seq / "image_2" / "000006.png").unlink()
    fails("kitti", tmp_path / "k", tmp_path / "k" / "poses" / "00.txt", "7 poses for 6 images")
    (seq / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    (seq / "image_2" / "000005.png").unlink()
    (tmp_path / "k" / "poses" / "00.txt").write_text(f"{_POSE}\n" * 5)
    fails("kitti", tmp_path / "k", seq / "calib.txt", "P2")
    (seq / "calib.txt").write_text("P2: 1 0 0 0 0 1 0 0 0 0 1\n")
    fails("kitti", tmp_path / "k", f"{seq / 'calib.txt'}:1", "12 numbers")
    for p in (seq / "image_2").iterdir():
        p.unlink()
    fails("kitti", tmp_path / "k", "no .png images", seq / "image_2")
    (tmp_path / "empty").mkdir()
    fails("kitti", tmp_path / "empty", "kitti", "poses/<NN>.txt")

    d = write_scene(scene, "tum", tmp_path / "t")
    rgb = d / "rgb.txt"
    lines = rgb.read_text().splitlines()
    rgb.write_text("\n".join(lines[:3] + [lines[3] + " extra"] + lines[4:]) + "\n")
    fails("tum", tmp_path / "t", f"{rgb}:4", "2 fields")
    rgb.write_text("\n".join(lines[:2] + ["99.0 rgb/none.png"]) + "\n")
    fails("tum", tmp_path / "t", "no image", "within 0.02 s")
    rgb.write_text("\n".join(lines[:2] + [lines[2].split()[0] + " rgb/none.png"]) + "\n")
    fails("tum", tmp_path / "t", "missing image", "none.png")


# ---------------------------------------------------------------------------------------
# rvggt eval --chunk-frames, with the chunked predictor replaced
# ---------------------------------------------------------------------------------------


def sim3_of(w2c, seed):
    """The same cameras in another world: x' = s R x + t (random s, R, t)."""
    rng = np.random.default_rng(seed)
    s, r, t = rng.uniform(0.2, 5.0), Rotation.random(random_state=seed).as_matrix(), rng.normal(size=3)
    rot = w2c[:, :, :3] @ r.T
    return np.concatenate([rot, (s * w2c[:, :, 3] - rot @ t)[..., None]], axis=-1)


@pytest.fixture
def fake_chunking(monkeypatch):
    """Replace `predict_sequence`: "dense" returns the ground truth under a random Sim(3),
    any other preset the ground truth with 5 cm of noise on the camera centres. The
    module is made up when it does not exist yet."""
    import rvggt_jax.app.long_sequence as mod

    truth, calls = {}, []

    def predict_sequence(image_paths, params, config, *, chunk_frames, overlap, loop_closure=False, mode="crop",
                         cache_dir=None, quiet=True, size=518):
        calls.append(dict(n=len(image_paths), chunk_frames=chunk_frames, overlap=overlap,
                          loop_closure=loop_closure, mode=mode, preset=config.compression))
        gt = np.stack([truth[p] for p in image_paths])
        ext = sim3_of(gt, seed=len(calls))
        if len(calls) % 2 == 0:  # the second preset of each scene
            c2w = w2c_to_c2w(gt)
            c2w[:, :3, 3] += np.random.default_rng(0).normal(scale=0.05, size=(len(gt), 3))
            ext = c2w_to_w2c(c2w)
        return types.SimpleNamespace(extrinsics=ext, intrinsics=np.zeros((len(gt), 3, 3)))

    monkeypatch.setattr(mod, "predict_sequence", predict_sequence, raising=False)
    return truth, calls


@pytest.mark.parametrize("fmt", ["kitti", "tum"])
def test_eval_chunked_sequences(fmt, fake_chunking, tmp_path, capsys):
    from rvggt_jax.app.cli import main

    truth, calls = fake_chunking
    for i in range(2):
        write_scene(make_scene(frames=9, height=H, width=W, seed=30 + i, name=f"seq{i}"), fmt, tmp_path / "data")
    for sc in load_scenes(fmt, tmp_path / "data"):
        truth.update(zip(sc.image_paths, sc.extrinsics))
    out = tmp_path / "out"
    code = main(["eval", "--dataset", fmt, "--root", str(tmp_path / "data"), "--presets", "dense,regime",
                 "--chunk-frames", "4", "--overlap", "2", "--loop-closure", "--out", str(out),
                 "--quiet", "--no-plots"])
    assert code in (0, None), capsys.readouterr().err
    assert len(calls) == 4 and all(c["n"] == 9 and c["chunk_frames"] == 4 and c["overlap"] == 2 and c["loop_closure"]
                                   and c["mode"] == "crop" for c in calls)
    assert calls[0]["preset"] != calls[1]["preset"]  # dense, then regime: each preset's own config
    rows = list(csv.DictReader(open(out / "results.csv")))
    assert len(rows) == 4
    for r in rows:
        assert r["frames"] == "9"
        if r["preset"] == "dense":  # the truth in another frame and scale
            for k in ("ate", "rpe_trans", "rpe_rot", "are"):
                assert float(r[k]) < 1e-6, (k, r[k])
        else:
            assert 0.01 < float(r["ate"]) < 0.2 and float(r["rpe_trans"]) > 0.01
    md = (out / "results.md").read_text()
    assert "| dense |" in md and "ate per scene" in md


def one_error(capsys, argv, *needles):
    from rvggt_jax.app.cli import main

    code = main(["eval", *map(str, argv)])
    err = capsys.readouterr().err
    assert code not in (0, None) and "Traceback" not in err, err
    errs = [ln for ln in err.splitlines() if ln.startswith("rvggt: error:")]
    assert len(errs) == 1, err
    for n in needles:
        assert n in errs[0], errs[0]


def test_eval_sequence_option_errors(capsys, tmp_path, scene, monkeypatch):
    out = ("--out", tmp_path / "o", "--quiet", "--no-plots")
    one_error(capsys, ["--dataset", "tnt", "--root", tmp_path, "--chunk-frames", "8", *out], "--chunk-frames", "kitti")
    one_error(capsys, ["--dataset", "7scenes", "--root", tmp_path, "--loop-closure", *out], "--loop-closure", "7scenes")
    one_error(capsys, ["--dataset", "kitti", "--root", tmp_path, "--overlap", "2", *out], "needs --chunk-frames")
    one_error(capsys, ["--dataset", "tum", "--root", tmp_path, "--chunk-frames", "8", "--overlap", "8", *out],
              "--overlap")
    one_error(capsys, ["--dataset", "kitti", "--root", tmp_path, "--chunk-frames", "1", *out], "at least 2")
    # without --chunk-frames, a sequence longer than one forward takes is refused with a hint
    import rvggt_jax.eval.runner as runner

    write_scene(scene, "kitti", tmp_path / "k")
    monkeypatch.setattr(runner, "MAX_ONE_FORWARD_FRAMES", 5)
    one_error(capsys, ["--dataset", "kitti", "--root", tmp_path / "k", *out], "7 frames", "--chunk-frames")
