"""Exports: round trips of PLY, COLMAP text, cameras.json, depth PNGs; trajectory plot;
point selection; the whole `export_reconstruction` on a synthetic scene."""

import json
import struct

import numpy as np
import pytest
from PIL import Image

from rvggt_jax.geometry import camera_centers
from rvggt_jax.io.cameras import write_cameras_json
from rvggt_jax.io.colmap import colmap_qvec, colmap_rotation, write_colmap_text
from rvggt_jax.io.depth import write_depth_pngs
from rvggt_jax.io.export import export_reconstruction, unique_stems
from rvggt_jax.io.images import ImageInfo
from rvggt_jax.io.plots import write_trajectory_png
from rvggt_jax.io.ply import write_ply
from rvggt_jax.app.pipeline import build_reconstruction, parse_threshold, select_points
from tests.helpers.readers import read_colmap_text, read_depth_png, read_ply


def _random_rotation(rng):
    q = rng.normal(size=4)
    return colmap_rotation(q / np.linalg.norm(q))


def _cameras(rng, s=4):
    ext = np.zeros((s, 3, 4))
    for i in range(s):
        ext[i, :, :3] = _random_rotation(rng)
        ext[i, :, 3] = rng.normal(size=3)
    ext[0, :, :3] = np.eye(3)
    ext[0, :, 3] = 0
    k = np.tile(np.array([[300.0, 0, 259], [0, 310.0, 196], [0, 0, 1]]), (s, 1, 1))
    return ext, k


def test_ply_round_trip_and_layout(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(1000, 3)).astype(np.float32)
    cols = rng.integers(0, 256, size=(1000, 3), dtype=np.uint8)
    path = tmp_path / "p.ply"
    write_ply(path, pts, cols)
    got_p, got_c = read_ply(path)
    np.testing.assert_array_equal(got_p, pts)
    np.testing.assert_array_equal(got_c, cols)
    # independent parse of the bytes: ascii header, then 15-byte little-endian records
    data = path.read_bytes()
    head, body = data.split(b"end_header\n", 1)
    lines = head.decode("ascii").splitlines()
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0"
    assert "element vertex 1000" in lines
    props = [ln.split()[1:] for ln in lines if ln.startswith("property")]
    assert props == [["float", "x"], ["float", "y"], ["float", "z"], ["uchar", "red"], ["uchar", "green"], ["uchar", "blue"]]
    assert len(body) == 1000 * 15
    x, y, z, r, g, b = struct.unpack("<fffBBB", body[15 * 7: 15 * 8])
    assert (x, y, z) == tuple(pts[7].tolist()) and (r, g, b) == tuple(cols[7].tolist())
    # float colours and empty clouds
    write_ply(path, pts[:2], np.array([[0.0, 0.5, 1.0], [1, 1, 1]]))
    np.testing.assert_array_equal(read_ply(path)[1], [[0, 128, 255], [255, 255, 255]])
    write_ply(path, np.zeros((0, 3)))
    assert read_ply(path)[0].shape == (0, 3)


def test_quaternions():
    rng = np.random.default_rng(1)
    for _ in range(200):
        R = _random_rotation(rng)
        q = colmap_qvec(R)
        assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        np.testing.assert_allclose(colmap_rotation(q), R, atol=1e-10)
    # COLMAP's order is scalar first: 90 degrees about z is (cos 45, 0, 0, sin 45)
    rz = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(colmap_qvec(rz), [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], atol=1e-15)
    # 180-degree rotations (trace -1) and identity
    for R in (np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1]), np.eye(3)):
        np.testing.assert_allclose(colmap_rotation(colmap_qvec(R)), R, atol=1e-12)


def test_colmap_round_trip(tmp_path):
    rng = np.random.default_rng(2)
    ext, k = _cameras(rng)
    names = [f"img_{i}.png" for i in range(4)]
    sizes = [(518, 392), (518, 392), (640, 480), (250, 700)]
    pts = rng.normal(size=(50, 3))
    cols = rng.integers(0, 256, size=(50, 3), dtype=np.uint8)
    write_colmap_text(tmp_path, names, ext, k, sizes, pts, cols)
    for f in ("cameras.txt", "images.txt", "points3D.txt"):
        text = (tmp_path / f).read_text()
        for line in text.splitlines():
            assert line == line.strip(), f"{f}: stray whitespace would break COLMAP's reader: {line!r}"
    m = read_colmap_text(tmp_path)
    assert sorted(m["cameras"]) == [1, 2, 3, 4] and sorted(m["images"]) == [1, 2, 3, 4]
    for i in range(4):
        cam = m["cameras"][i + 1]
        assert cam["model"] == "PINHOLE" and (cam["width"], cam["height"]) == sizes[i]
        np.testing.assert_allclose(cam["params"], [k[i, 0, 0], k[i, 1, 1], k[i, 0, 2], k[i, 1, 2]])
        im = m["images"][i + 1]
        assert im["name"] == names[i] and im["camera_id"] == i + 1 and im["points2d"] == []
        np.testing.assert_allclose(colmap_rotation(im["qvec"]), ext[i, :, :3], atol=1e-12)
        np.testing.assert_allclose(im["tvec"], ext[i, :, 3])
    assert len(m["points"]) == 50
    p = m["points"][8]
    np.testing.assert_allclose(p["xyz"], pts[7], rtol=1e-6)
    assert p["rgb"].tolist() == cols[7].tolist() and p["track"] == [] and p["error"] == 0
    with pytest.raises(ValueError, match="spaces"):
        write_colmap_text(tmp_path / "x", ["a b.png"], ext[:1], k[:1], sizes[:1])


def test_cameras_json(tmp_path):
    rng = np.random.default_rng(3)
    ext, k = _cameras(rng, 3)
    names = ["a.png", "b.png", "c.png"]
    write_cameras_json(tmp_path / "c.json", names, ext, k, [(518, 392)] * 3, meta=dict(preset="dense"))
    doc = json.loads((tmp_path / "c.json").read_text())
    assert doc["preset"] == "dense" and len(doc["frames"]) == 3
    for i, fr in enumerate(doc["frames"]):
        assert fr["image"] == names[i] and fr["width"] == 518 and fr["height"] == 392
        np.testing.assert_allclose(fr["extrinsic"], ext[i])
        np.testing.assert_allclose(fr["intrinsic"], k[i])


def test_depth_png_round_trip(tmp_path):
    rng = np.random.default_rng(4)
    depth = rng.uniform(0.5, 7.0, size=(2, 28, 42)).astype(np.float32)
    valid = np.ones_like(depth, bool)
    valid[1, :, :5] = False
    depth[0, 0, 0] = np.nan
    scale = write_depth_pngs(tmp_path / "depth", ["a", "b"], depth[..., None], valid, tmp_path / "prev")
    meta = json.loads((tmp_path / "depth" / "depth_scale.json").read_text())
    assert meta["scale"] == scale
    for i, stem in enumerate(["a", "b"]):
        with Image.open(tmp_path / "depth" / f"{stem}.png") as im:
            assert im.mode.startswith("I;16") or im.mode == "I"
            assert im.size == (42, 28)
        got = read_depth_png(tmp_path / "depth" / f"{stem}.png")
        ok = valid[i] & np.isfinite(depth[i])
        np.testing.assert_allclose(got[ok], depth[i][ok], atol=scale / 2 + 1e-6)
        assert np.all(got[~ok] == 0)
        with Image.open(tmp_path / "prev" / f"{stem}.png") as im:
            assert im.mode == "RGB" and im.size == (42, 28)


def test_trajectory_png(tmp_path):
    rng = np.random.default_rng(5)
    ext, _ = _cameras(rng, 6)
    write_trajectory_png(tmp_path / "t.png", ext, rng.normal(size=(500, 3)), rng.integers(0, 256, (500, 3)))
    with Image.open(tmp_path / "t.png") as im:
        assert im.mode == "RGB" and min(im.size) >= 400
        arr = np.asarray(im)
    assert (arr != 255).any()
    write_trajectory_png(tmp_path / "one.png", ext[:1])  # a single camera, no points
    c = camera_centers(ext)
    np.testing.assert_allclose(np.einsum("sij,sj->si", ext[:, :, :3], c) + ext[:, :, 3], 0, atol=1e-12)


def test_select_points_and_threshold():
    conf = np.arange(1, 101, dtype=np.float32).reshape(1, 10, 10)
    pts = np.random.default_rng(0).normal(size=(1, 10, 10, 3))
    cols = np.zeros((1, 10, 10, 3), np.uint8)
    p, _, thr = select_points(pts, conf, cols, None, "0%")
    assert len(p) == 100 and thr == 1
    p, _, thr = select_points(pts, conf, cols, None, "50%")
    assert 49 <= len(p) <= 51
    p, _, thr = select_points(pts, conf, cols, None, 91.0)
    assert len(p) == 10 and thr == 91
    valid = np.zeros((1, 10, 10), bool)
    valid[0, :5] = True
    p, _, _ = select_points(pts, conf, cols, valid, "0%", max_points=7)
    assert len(p) == 7
    pts[0, 0, 0] = np.nan
    p, _, _ = select_points(pts, conf, cols, None, "0%")
    assert len(p) == 99
    assert parse_threshold("25%") == (25.0,) and parse_threshold("1.5") == 1.5
    for bad in ("abc", "150%", "x%"):
        with pytest.raises(ValueError):
            parse_threshold(bad)


def test_unique_stems():
    assert unique_stems(["a.png", "b.jpg"]) == ["a", "b"]
    assert unique_stems(["a.png", "a.jpg", "c d.png"]) == ["a_png", "a_jpg", "c_d"]


def test_export_reconstruction_synthetic(tmp_path):
    """A plane seen by 3 cameras: exported points land on the plane, files agree."""
    s, h, w = 3, 28, 42
    ext = np.zeros((s, 3, 4))
    for i in range(s):
        ext[i, :, :3] = np.eye(3)
        ext[i, :, 3] = [-0.2 * i, 0, 0]  # camera centre at x = 0.2 i
    k = np.tile(np.array([[40.0, 0, w / 2], [0, 40.0, h / 2], [0, 0, 1]]), (s, 1, 1))
    depth = np.full((s, h, w, 1), 2.0, np.float32)
    conf = np.random.default_rng(0).uniform(1, 5, size=(s, h, w)).astype(np.float32)
    images = np.random.default_rng(1).uniform(size=(s, 3, h, w)).astype(np.float32)
    images[2, :, :, :10] = 1.0  # padding on the left of frame 2
    infos = [ImageInfo(path=f"/x/f{i}.png", name=f"f{i}.png", width=84, height=56, sx=0.5, sy=0.5, ox=0.0, oy=0.0,
                       valid=(0, 0, w, h)) for i in range(2)]
    infos.append(ImageInfo(path="/x/f2.png", name="f2.png", width=64, height=56, sx=0.5, sy=0.5, ox=10.0, oy=0.0,
                           valid=(10, 0, w, h)))
    names = [i.name for i in infos]
    recon = build_reconstruction(images, ext, k, depth, conf, names=names, infos=infos, conf_threshold="0%")
    summary = export_reconstruction(tmp_path, recon)
    pts, cols = read_ply(tmp_path / "points.ply")
    assert len(pts) == summary["points"] == s * h * w - h * 10
    np.testing.assert_allclose(pts[:, 2], 2.0, atol=1e-5)
    doc = json.loads((tmp_path / "cameras.json").read_text())
    assert [f["image"] for f in doc["frames"]] == names
    f2 = doc["frames"][2]
    assert (f2["width"], f2["height"]) == (64, 56)
    np.testing.assert_allclose(f2["intrinsic"], [[80, 0, (w / 2 - 10) * 2], [0, 80, h], [0, 0, 1]])
    np.testing.assert_allclose(f2["network"]["intrinsic"], k[2])
    m = read_colmap_text(tmp_path / "sparse")
    assert len(m["cameras"]) == len(m["images"]) == s
    assert [m["images"][i + 1]["name"] for i in range(s)] == names
    assert len(m["points"]) == len(pts)
    for stem in ("f0", "f1", "f2"):
        d = read_depth_png(tmp_path / "depth" / f"{stem}.png")
        assert d.shape == (h, w)
        assert (tmp_path / "depth_preview" / f"{stem}.png").is_file()
    assert np.all(read_depth_png(tmp_path / "depth" / "f2.png")[:, :10] == 0)
    np.testing.assert_allclose(read_depth_png(tmp_path / "depth" / "f2.png")[:, 10:], 2.0, rtol=1e-4)
    with Image.open(tmp_path / "trajectory.png") as im:
        im.load()
