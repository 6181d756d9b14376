"""Every dataset reader round-trips the synthetic generator's scenes (cameras, depth,
ground-truth points), frame sampling follows the protocols, a broken folder names the
missing file, and each protocol scores ground truth given as a prediction as perfect."""

import numpy as np
import pytest

from rvggt_jax.eval.datasets import DatasetError, FORMATS, load_scenes, sample_indices
from rvggt_jax.eval.datasets.files import w2c_to_c2w
from rvggt_jax.eval.datasets.ply import read_ply_points
from rvggt_jax.eval.network_inputs import network_images
from rvggt_jax.eval.protocols import PROTOCOLS, against_reference
from rvggt_jax.synthetic import make_scene, write_scene

W, H = 56, 42
K7 = 525 * W / 640  # the 7 Scenes calibration at 56x42 (fx = fy), which every format stores


@pytest.fixture(scope="module")
def scene():
    return make_scene(frames=5, height=H, width=W, seed=11, focal=K7)


@pytest.fixture(scope="module")
def written(scene, tmp_path_factory):
    root = tmp_path_factory.mktemp("datasets")
    for fmt in FORMATS:
        write_scene(scene, fmt, root / fmt)
    return root


@pytest.mark.parametrize("fmt", sorted(FORMATS))
def test_reader_round_trip(fmt, scene, written):
    (sc,) = load_scenes(fmt, written / fmt)
    assert len(sc) == 5 and sc.dataset == fmt
    assert all(p.is_file() for p in sc.image_paths)
    imgs, _ = network_images(sc.image_paths, W)
    assert imgs.shape == (5, 3, H, W)
    lossless = fmt not in ("scannet", "tnt", "dtu", "co3d")  # those store JPEG frames
    err = np.abs(imgs.transpose(0, 2, 3, 1) * 255 - scene.images).mean()
    assert err < (0.5 if lossless else 8.0)  # JPEG on a 56x42 checkerboard: a few levels
    if fmt == "images":
        assert sc.extrinsics is None
        return
    np.testing.assert_allclose(sc.extrinsics, scene.extrinsics, atol=1e-8)
    np.testing.assert_allclose(sc.intrinsics, scene.intrinsics, atol=1e-8)
    if fmt in ("7scenes", "nrgbd", "scannet", "folder"):
        assert sc.has_depth
        tol = 0 if fmt == "folder" else 0.5e-3 + 1e-6  # 16-bit millimetres
        for i in range(5):
            np.testing.assert_allclose(sc.depth(i), scene.depth[i], atol=tol)
    if fmt == "co3d":  # float16 depth (11 significant bits) x its scale adjustment
        assert sc.has_depth
        for i in range(5):
            np.testing.assert_allclose(sc.depth(i), scene.depth[i], rtol=1e-3)
    if fmt in ("scannet", "dtu", "folder"):
        np.testing.assert_allclose(sc.gt_points(), scene.cloud()[0], atol=1e-6)  # float32 PLY


def test_sampling():
    assert sample_indices(10, stride=3) == [0, 3, 6, 9]
    assert sample_indices(10, frames=4) == [0, 1, 2, 3]
    assert sample_indices(10, frames=4, how="even") == [0, 3, 6, 9]
    r = sample_indices(100, frames=7, how="random", seed=3)
    assert r == sorted(r) and len(set(r)) == 7 and r == sample_indices(100, frames=7, how="random", seed=3)
    assert r != sample_indices(100, frames=7, how="random", seed=4)
    # FastVGGT's ScanNet rule: the first frame, then every (99 // 4)-th of the other 99
    assert sample_indices(100, frames=5, how="scannet") == [0, 1, 25, 49, 73]
    assert sample_indices(3, frames=5) == [0, 1, 2]
    with pytest.raises(ValueError, match="sampling"):
        sample_indices(10, frames=2, how="sideways")


def test_broken_folders_name_the_missing_file(scene, tmp_path):
    root = tmp_path / "s7"
    seq = write_scene(scene, "7scenes", root)
    (seq / "frame-000002.pose.txt").unlink()
    with pytest.raises(DatasetError, match="frame-000002.pose.txt"):
        load_scenes("7scenes", root)
    d = write_scene(scene, "nrgbd", tmp_path / "nr")
    (d / "poses.txt").unlink()
    (d / "images").rename(d / "pictures")
    with pytest.raises(DatasetError, match="no NRGBD scene"):
        load_scenes("nrgbd", tmp_path / "nr")
    with pytest.raises(DatasetError, match="poses.txt"):
        load_scenes("nrgbd", tmp_path / "nr", scenes=[d.name])
    (d / "poses.txt").write_text("1 0 0 0\n")
    with pytest.raises(DatasetError, match="16 numbers"):
        load_scenes("nrgbd", tmp_path / "nr")
    d = write_scene(scene, "scannet", tmp_path / "sn")
    (d / "intrinsic" / "intrinsic_color.txt").unlink()
    with pytest.raises(DatasetError, match="intrinsic_color.txt"):
        load_scenes("scannet", tmp_path / "sn")
    d = write_scene(scene, "dtu", tmp_path / "dtu")
    (d / "cams" / "00000001_cam.txt").unlink()
    with pytest.raises(DatasetError, match="00000001_cam.txt"):
        load_scenes("dtu", tmp_path / "dtu")
    d = write_scene(scene, "tnt", tmp_path / "tnt")
    (d / "sparse" / "0" / "images.bin").unlink()
    with pytest.raises(DatasetError, match="no Tanks and Temples scene"):
        load_scenes("tnt", tmp_path / "tnt")
    with pytest.raises(DatasetError, match="images.bin"):
        load_scenes("tnt", tmp_path / "tnt", scenes=[d.name])
    with pytest.raises(DatasetError, match="not found"):
        load_scenes("folder", tmp_path / "nowhere")
    with pytest.raises(DatasetError, match="unknown dataset"):
        load_scenes("kittee", tmp_path)


def test_7scenes_every_test_sequence_and_raw_depth(scene, tmp_path):
    from rvggt_jax.eval.datasets.sevenscenes import intrinsics_for

    seq = write_scene(scene, "7scenes", tmp_path)
    (seq.parent / "TestSplit.txt").write_text("sequence1\nsequence3\n")
    (seq.parent / "seq-03").symlink_to(seq)
    assert [s.name for s in load_scenes("7scenes", tmp_path)] == [f"{scene.name}/seq-01", f"{scene.name}/seq-03"]
    for p in seq.glob("*.depth.proj.png"):  # only the raw Kinect depth: the depth camera's f = 585
        p.rename(p.with_name(p.name.replace(".depth.proj.png", ".depth.png")))
    (sc, _) = load_scenes("7scenes", tmp_path)
    np.testing.assert_allclose(sc.intrinsics[0], intrinsics_for(W, H, 585.0))
    assert sc.depth_paths[0].name.endswith(".depth.png") and sc.depth(0).shape == (H, W)


def test_nrgbd_keyframe_stride_is_capped_at_half_the_frames(tmp_path):
    from rvggt_jax.eval.runner import EvalSettings, scene_indices

    def run(dataset, **kw):
        return EvalSettings(dataset, str(tmp_path), ("dense",), str(tmp_path), "w", **kw)

    assert scene_indices(run("nrgbd"), 100) == list(range(0, 100, 10))
    assert scene_indices(run("nrgbd"), 8) == [0, 4]  # min(10, 8 // 2)
    assert scene_indices(run("7scenes"), 8) == [0]
    assert scene_indices(run("nrgbd", stride=3), 5) == [0, 2, 4]
    assert scene_indices(run("scannet"), 2000)[:3] == [0, 1, 3] and len(scene_indices(run("scannet"), 2000)) == 1000
    assert scene_indices(run("dtu"), 49) == list(range(48))
    assert scene_indices(run("tnt", frames=3, sampling="even"), 9) == [0, 4, 8]


def test_colmap_text_model_and_ascii_ply(scene, tmp_path):
    from rvggt_jax.io.colmap import write_colmap_text

    d = write_scene(scene, "tnt", tmp_path)
    model = d / "sparse" / "0"
    for f in model.iterdir():
        f.unlink()
    names = [p.name for p in sorted((d / "images").iterdir())]
    write_colmap_text(model, names, scene.extrinsics, scene.intrinsics, [(W, H)] * 5)
    (sc,) = load_scenes("tnt", tmp_path)
    np.testing.assert_allclose(sc.extrinsics, scene.extrinsics, atol=1e-5)  # text: 7 significant digits
    ply = tmp_path / "a.ply"
    ply.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
                   "property uchar red\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n"
                   "1 2 3 9\n4 5 6 9\n")
    np.testing.assert_allclose(read_ply_points(ply), [[1, 2, 3], [4, 5, 6]])


def ideal_prediction(scene, scale=0.5):
    """What a perfect model outputs: cameras and points in the first camera's frame, at
    another scale."""
    c2w0 = w2c_to_c2w(scene.extrinsics[0])
    ext = np.stack([(np.vstack([e, [0, 0, 0, 1]]) @ c2w0)[:3] for e in scene.extrinsics])
    ext[:, :, 3] *= scale
    wp = (scene.points.astype(np.float64) @ scene.extrinsics[0][:, :3].T + scene.extrinsics[0][:, 3]) * scale
    return dict(extrinsics=ext, intrinsics=scene.intrinsics, depth=scene.depth * scale,
                depth_conf=np.full(scene.depth.shape, 2.0), world_points=wp, world_points_conf=np.ones(scene.depth.shape))


@pytest.mark.parametrize("fmt", ["7scenes", "nrgbd", "scannet", "tnt", "dtu", "folder"])
def test_protocol_scores_truth_as_perfect(fmt, scene, written):
    (sc,) = load_scenes(fmt, written / fmt)
    _, infos = network_images(sc.image_paths, W)
    r = PROTOCOLS[fmt].score(sc, ideal_prediction(scene), infos)
    assert set(PROTOCOLS[fmt].metrics) <= set(r)
    for k, v in r.items():
        if k.startswith(("auc", "rra", "rta", "nc")):
            assert v == pytest.approx(1.0, abs=1e-4), (k, v)
        elif k == "scale":
            continue
        else:  # distances / angles / AbsRel; 7 Scenes etc. store 1 mm depth steps
            assert v == pytest.approx(0.0, abs=1e-3), (k, v)


def test_protocol_sees_a_perturbation(scene, written):
    (sc,) = load_scenes("7scenes", written / "7scenes")
    _, infos = network_images(sc.image_paths, W)
    pred = ideal_prediction(scene)
    rng = np.random.default_rng(0)
    pred["world_points"] = pred["world_points"] + rng.normal(scale=0.02, size=pred["world_points"].shape)
    r = PROTOCOLS["7scenes"].score(sc, pred, infos)
    assert r["acc"] > 0.005 and r["nc"] < 0.99
    ref = ideal_prediction(scene)
    assert against_reference(ref, ref)["chamfer"] == pytest.approx(0.0, abs=1e-9)
    other = dict(ref, depth=ref["depth"] * 1.1)
    assert against_reference(other, ref)["abs_rel"] == pytest.approx(0.1, rel=1e-5)


def test_co3d_cameras_project_as_pytorch3d(tmp_path):
    """CO3D's PyTorch3D cameras, projected by PyTorch3D's formulas (row-vector R, T; NDC
    +x left, +y up, isotropic scale min(W, H) / 2, pixel edges at integers), land where
    the reader's OpenCV extrinsic and pixel-centre intrinsics put them; depth is the
    float16 bits x scale_adjustment, masked."""
    import gzip
    import json

    from PIL import Image

    from rvggt_jax.eval.datasets import co3d

    h, w = 30, 50
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    r = q * np.sign(np.linalg.det(q))
    t = np.array([0.1, -0.2, 3.0])
    f, p = np.array([1.7, 1.6]), np.array([0.05, -0.1])
    x = rng.normal(size=(5, 3)) * 0.3
    cam = x @ r + t  # PyTorch3D: +X left, +Y up
    ndc = f * cam[:, :2] / cam[:, 2:] + p
    s = min(w, h) / 2
    px_edges = np.stack([w / 2 - ndc[:, 0] * s, h / 2 - ndc[:, 1] * s], 1)
    ext = co3d.viewpoint_to_opencv(r, t)
    k = co3d.ndc_to_pixels(f, p, (h, w))
    uvz = (x @ ext[:, :3].T + ext[:, 3]) @ k.T
    np.testing.assert_allclose(uvz[:, :2] / uvz[:, 2:], px_edges - 0.5, atol=1e-9)
    np.testing.assert_allclose(uvz[:, 2], cam[:, 2], atol=1e-12)  # the same depth
    # the files: one category, one sequence of 2 frames, the second without a depth file
    seq = tmp_path / "cat" / "seq1"
    for sub in ("images", "depths", "depth_masks"):
        (seq / sub).mkdir(parents=True)
    depth = np.full((h, w), 2.5, np.float16)
    frames = []
    for i in (1, 2):
        Image.fromarray(np.zeros((h, w, 3), np.uint8)).save(seq / "images" / f"frame{i:06d}.jpg")
        frames.append({"sequence_name": "seq1", "frame_number": i, "image": {"path": f"cat/seq1/images/frame{i:06d}.jpg",
                                                                           "size": [h, w]},
                       "depth": {"path": f"cat/seq1/depths/frame{i:06d}.jpg.geometric.png", "scale_adjustment": 2.0,
                                 "mask_path": f"cat/seq1/depth_masks/frame{i:06d}.png"},
                       "viewpoint": {"R": r.tolist(), "T": t.tolist(), "focal_length": f.tolist(),
                                     "principal_point": p.tolist(), "intrinsics_format": "ndc_isotropic"}})
    Image.fromarray(depth.view(np.uint16)).save(seq / "depths" / "frame000001.jpg.geometric.png")
    mask = np.full((h, w), 255, np.uint8)
    mask[:, :10] = 0
    Image.fromarray(mask).save(seq / "depth_masks" / "frame000001.png")
    with gzip.open(tmp_path / "cat" / "frame_annotations.jgz", "wt") as fh:
        json.dump(frames[::-1], fh)  # any order: frames sorted by number
    (sc,) = load_scenes("co3d", tmp_path)
    assert sc.name == "cat/seq1" and sc.frame_ids == ["1", "2"]
    np.testing.assert_allclose(sc.extrinsics[0], ext)
    np.testing.assert_allclose(sc.intrinsics[1], k)
    d = sc.depth(0)
    assert (d[:, :10] == 0).all() and (d[:, 10:] == 5.0).all()
    with pytest.raises(DatasetError, match="frame000002.jpg.geometric.png"):
        sc.depth(1)
    (sc,) = load_scenes("co3d", tmp_path / "cat")  # a category folder as the root
    assert sc.name == "seq1"
