"""`rvggt_jax.ba.refine` end to end on a synthetic scene: a `Reconstruction` with the true
depth and perturbed cameras, an exact tracker (tests/ba/synthetic_ba.py) standing in for
the track head, then the written model read back by pycolmap and by our COLMAP reader."""

from __future__ import annotations

import dataclasses
import json
import sys

import numpy as np
import pytest

# pycolmap is in the [test] extra: without it these tests fail at import (never skipped)
import pycolmap  # noqa: E402

from rvggt_jax.app.pipeline import build_reconstruction  # noqa: E402
from rvggt_jax.ba import BA_EXTRA_HINT, BAError, PycolmapMissing, require_pycolmap  # noqa: E402
from rvggt_jax.ba.refine import REPORT_NAME, SPARSE_DIR, BAOptions, refine, write_outputs  # noqa: E402
from rvggt_jax.ba.tracks import (Tracks, choose_query_frames, filter_tracks, grid_keypoints,  # noqa: E402
                                 query_points, track_from_query_frames)
from rvggt_jax.eval.datasets.colmap_binary import read_model  # noqa: E402
from rvggt_jax.io.colmap import colmap_rotation  # noqa: E402
from rvggt_jax.io.ply import read_ply_properties  # noqa: E402
from tests.ba.synthetic_ba import ExactTracker, center_error, perturb, relative_rotation_error_deg, scene  # noqa: E402

OPTIONS = BAOptions(query_frames=3, query_points=300, keypoints="grid", max_error=30.0)


@pytest.fixture(scope="module")
def sc():
    return scene()


def _recon(sc, extrinsic):
    images = sc.images.transpose(0, 3, 1, 2).astype(np.float32) / 255.0
    conf = np.where(sc.depth > 0, 2.0, 1.0).astype(np.float32)  # confident where the scene is hit
    return build_reconstruction(images, extrinsic, sc.intrinsics, sc.depth, conf,
                                names=[f"view {i}.png" for i in range(len(images))])


@pytest.fixture(scope="module")
def refined(sc, tmp_path_factory):
    start = perturb(sc.extrinsics, np.random.default_rng(2), rot_deg=1.5, trans_frac=0.03)
    recon = _recon(sc, start)
    # little noise: this test is about the plumbing (what BA recovers from noisier tracks is
    # tests/ba/test_adjust.py's); without any the solution would be exact
    tracker = ExactTracker(sc, noise_px=0.02)
    outcome = refine(recon, tracker, OPTIONS)
    out = tmp_path_factory.mktemp("ba")
    report = write_outputs(out, outcome, recon.names, recon.sizes, OPTIONS)
    return start, recon, tracker, outcome, out, report


def test_refine_reduces_errors(sc, refined):
    start, _, _, outcome, _, report = refined
    truth = sc.extrinsics
    rot0, rot1 = relative_rotation_error_deg(start, truth), relative_rotation_error_deg(outcome.extrinsic, truth)
    c0, c1 = center_error(start, truth), center_error(outcome.extrinsic, truth)
    print(f"refine: reprojection {outcome.error_before:.3f} -> {outcome.error_after:.4f} px; rotation {rot0:.3f} -> "
          f"{rot1:.4f} deg; centres {c0:.4f} -> {c1:.5f}; {outcome.counts}")
    assert outcome.error_before / outcome.error_after >= 5.0
    assert rot0 / rot1 >= 10.0 and c0 / c1 >= 10.0
    assert report["mean_reprojection_error_before_px"] == outcome.error_before
    assert report["mean_reprojection_error_after_px"] == outcome.error_after
    assert outcome.counts["points"] >= 100


def test_refine_with_sift_keypoints(sc):
    start = perturb(sc.extrinsics, np.random.default_rng(3), rot_deg=1.0, trans_frac=0.02)
    opts = dataclasses.replace(OPTIONS, keypoints="sift", query_points=120)
    outcome = refine(_recon(sc, start), ExactTracker(sc, noise_px=0.02), opts)
    assert outcome.counts["points"] >= 60
    assert outcome.error_before / outcome.error_after >= 5.0
    assert relative_rotation_error_deg(start, sc.extrinsics) / relative_rotation_error_deg(
        outcome.extrinsic, sc.extrinsics) >= 5.0


def test_refine_tracks_from_every_query_frame(sc, refined):
    _, _, tracker, outcome, _, _ = refined
    qf = choose_query_frames(len(sc.images), OPTIONS.query_frames)
    assert outcome.query_frames == tuple(qf) and qf[0] == 0 and len(qf) == 3
    # the tracker saw each query frame first, the others after it in their order
    assert [o[0] for o in tracker.orders] == qf
    for o in tracker.orders:
        assert sorted(o) == list(range(len(sc.images))) and o[1:] == sorted(o[1:])


def test_written_model_read_back(sc, refined):
    _, recon, _, outcome, out, report = refined
    s, m = outcome.mask.shape
    for folder in (out / SPARSE_DIR, out / SPARSE_DIR / "bin"):  # our text writer, pycolmap's binary
        rec = pycolmap.Reconstruction(str(folder))
        assert rec.num_images() == s and rec.num_points3D() == m
        assert rec.compute_num_observations() == int(outcome.mask.sum())
        for i in range(s):
            img = rec.image(i + 1)
            assert img.name == recon.names[i].replace(" ", "_")
            np.testing.assert_allclose(img.cam_from_world().matrix(), outcome.extrinsic[i], atol=1e-9)
            np.testing.assert_allclose(rec.camera(i + 1).calibration_matrix(), outcome.intrinsic[i], atol=1e-9)
        for j in (0, m // 2, m - 1):
            p = rec.point3D(j + 1)
            np.testing.assert_allclose(p.xyz, outcome.points[j], rtol=1e-12, atol=1e-12)
            seen = sorted(el.image_id - 1 for el in p.track.elements)
            assert seen == np.flatnonzero(outcome.mask[:, j]).tolist()
            for el in p.track.elements:
                xy = rec.image(el.image_id).points2D[el.point2D_idx].xy
                np.testing.assert_allclose(xy, outcome.tracks[el.image_id - 1, j], atol=1e-9)
        # the model is in the original images' pixels: errors there are scaled by the resize (1 here)
        rec.update_point_3d_errors()
        assert rec.compute_mean_reprojection_error() == pytest.approx(report["pycolmap_mean_reprojection_error_px"],
                                                                      rel=1e-6)
    # our binary reader (rvggt eval's) reads pycolmap's cameras.bin / images.bin
    ours = {r["name"]: r for r in read_model(out / SPARSE_DIR / "bin")}
    for i, name in enumerate(recon.names):
        r = ours[name.replace(" ", "_")]
        np.testing.assert_allclose(r["extrinsic"], outcome.extrinsic[i], atol=1e-9)
        np.testing.assert_allclose(r["intrinsic"], outcome.intrinsic[i], atol=1e-9)
    doc = json.loads((out / REPORT_NAME).read_text())
    assert doc["points"] == m and doc["observations"] == int(outcome.mask.sum())
    props = read_ply_properties(out / "points_ba.ply")
    np.testing.assert_allclose(np.stack([props["x"], props["y"], props["z"]], 1), outcome.points, rtol=1e-6)
    assert props["track_length"].tolist() == outcome.mask.sum(0).tolist()
    cams = json.loads((out / "cameras_ba.json").read_text())["frames"]
    np.testing.assert_allclose(np.array(cams[1]["extrinsic"]), outcome.extrinsic[1], atol=1e-12)


def test_text_model_tracks_format(refined):
    _, _, _, outcome, out, _ = refined
    lines = [ln for ln in (out / SPARSE_DIR / "points3D.txt").read_text().splitlines() if not ln.startswith("#")]
    first = lines[0].split()
    assert first[0] == "1" and len(first) == 8 + 2 * int(outcome.mask[:, 0].sum())
    q = np.array(first[1:4], float)
    np.testing.assert_allclose(q, outcome.points[0])
    imgs = [ln for ln in (out / SPARSE_DIR / "images.txt").read_text().splitlines() if not ln.startswith("#")]
    np.testing.assert_allclose(colmap_rotation(np.array(imgs[0].split()[1:5], float)), outcome.extrinsic[0, :, :3],
                               atol=1e-9)
    assert len(imgs[1].split()) == 3 * int(outcome.mask[0].sum())


# ---------------------------------------------------------------------------------------
# pieces and failures
# ---------------------------------------------------------------------------------------


def test_choose_query_frames():
    assert choose_query_frames(10, 4) == [0, 2, 5, 8]
    assert choose_query_frames(3, 4) == [0, 1, 2]
    assert choose_query_frames(1, 4) == [0]


def test_grid_keypoints_spread_and_valid():
    rng = np.random.default_rng(0)
    score = rng.uniform(size=(60, 80))
    valid = np.ones((60, 80), bool)
    valid[:, 40:] = False
    pts = grid_keypoints(score, valid, 30)
    assert pts.shape == (30, 2)
    assert (pts[:, 0] < 40).all() and (pts[:, 0] >= 4).all() and (pts[:, 1] >= 4).all() and (pts[:, 1] < 56).all()
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1) + np.eye(30) * 1e9
    assert d.min() >= 1.0  # one per cell: no two on the same pixel


def test_sift_query_points(sc):
    image = sc.images[0].transpose(2, 0, 1).astype(np.float32) / 255.0
    valid = sc.depth[0] > 0
    valid[:, :20] = False
    pts = query_points(image, np.ones(valid.shape), valid, 40, "sift")
    assert pts.shape == (40, 2)
    h, w = valid.shape
    assert valid[pts[:, 1].astype(int), pts[:, 0].astype(int)].all()
    # SIFT's sub-pixel keypoints, not grid points (pixel centres), make up most of them
    assert (np.abs(pts % 1.0 - 0.5) > 1e-6).any(axis=1).mean() > 0.5


def test_filter_tracks():
    pts = np.array([[[5.0, 5.0], [5.0, 5.0], [5.0, 5.0], [50.0, 5.0], [np.nan, 1.0]]])
    t = Tracks(pts, np.array([[0.9, 0.1, 0.9, 0.9, 0.9]], np.float32), np.array([[0.9, 0.9, 0.1, 0.9, 0.9]],
               np.float32), np.zeros(5, np.int32))
    keep = filter_tracks(t, (20, 20), vis_threshold=0.5, conf_threshold=0.5)
    assert keep.tolist() == [[True, False, False, False, False]]
    valid = np.zeros((1, 20, 20), bool)
    assert not filter_tracks(t, (20, 20), valid, vis_threshold=0.5, conf_threshold=0.5).any()


def test_track_from_query_frames_puts_frames_back():
    # a tracker whose output in row r says which input frame row r was (image value)
    images = np.arange(4, dtype=np.float32)[:, None, None, None] * np.ones((4, 3, 2, 2), np.float32)

    def tracker(ims, q):
        ids = ims[:, 0, 0, 0]
        t = np.broadcast_to(ids[:, None, None], (4, len(q), 2)).astype(np.float64)
        return t, np.full((4, len(q)), 0.5), np.full((4, len(q)), 0.5)

    tr = track_from_query_frames(tracker, images, [np.array([[0.5, 0.5]]), np.array([[1.0, 1.0], [1.5, 1.5]])],
                                 [0, 2])
    assert tr.points.shape == (4, 3, 2) and tr.query_frame.tolist() == [0, 2, 2]
    for s in (1, 3):
        assert (tr.points[s, :, 0] == s).all()
    np.testing.assert_array_equal(tr.points[2, 1:], [[1.0, 1.0], [1.5, 1.5]])  # the query frame holds its queries
    assert tr.vis[2, 1:].tolist() == [1.0, 1.0] and tr.vis[1].tolist() == [0.5] * 3


def test_refine_needs_two_frames(sc):
    recon = _recon(sc, sc.extrinsics)
    one = build_reconstruction(recon.images[:1], sc.extrinsics[:1], sc.intrinsics[:1], sc.depth[:1],
                               recon.depth_conf[:1])
    with pytest.raises(BAError, match="at least 2 frames"):
        refine(one, ExactTracker(sc), OPTIONS)


def test_refine_too_few_tracks(sc):
    recon = _recon(sc, sc.extrinsics)

    def blind(ims, q):  # sees nothing anywhere but its query frame
        t, v, c = ExactTracker(sc)(ims, q)
        return t, np.zeros_like(v), c

    with pytest.raises(BAError, match="too few tracks.*--ba-vis-threshold"):
        refine(recon, blind, OPTIONS)


def test_require_pycolmap_names_the_extra(monkeypatch):
    assert require_pycolmap() is pycolmap
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # what `import pycolmap` meets when it is not installed
    with pytest.raises(PycolmapMissing) as e:
        require_pycolmap()
    assert BA_EXTRA_HINT in str(e.value) and BA_EXTRA_HINT == 'pip install "rvggt-jax[ba]"'
