"""Splatting-ready export: the COLMAP model in binary (read back by the project's own
COLMAP reader, `rvggt_jax.eval.datasets.colmap_binary`), and nerfstudio's transforms.json
(its documented schema; its matrices are our cameras after the OpenCV -> OpenGL change)."""

import json
import struct

import numpy as np
import pytest

from rvggt_jax.app.pipeline import build_reconstruction
from rvggt_jax.eval.datasets.colmap_binary import read_model
from rvggt_jax.geometry import quat_to_mat
from rvggt_jax.io.colmap import write_colmap_binary, write_colmap_text
from rvggt_jax.io.export import export_reconstruction
from rvggt_jax.io.images import ImageInfo
from rvggt_jax.io.transforms import opengl_camera_to_world, write_transforms_json
from tests.helpers.readers import read_colmap_text

S = 3


def _cameras(seed=0):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(S, 4))
    e = np.concatenate([np.stack([np.asarray(quat_to_mat(x / np.linalg.norm(x))) for x in q]),
                        rng.normal(size=(S, 3, 1))], axis=2)
    sizes = [(640, 480), (480, 640), (800, 600)]
    k = np.stack([[[500.0 + 10 * i, 0, w / 2 + i], [0, 505.0 + 10 * i, h / 2 - i], [0, 0, 1]]
                  for i, (w, h) in enumerate(sizes)])
    return e, k, sizes


def _read_points3d_bin(path):
    """points3D.bin as COLMAP's documentation lays it out -> (ids, xyz, rgb, errors, tracks)."""
    data = path.read_bytes()
    (n,), off = struct.unpack_from("<Q", data), 8
    ids, xyz, rgb, err, tracks = [], [], [], [], []
    for _ in range(n):
        pid, x, y, z, r, g, b, e, tl = struct.unpack_from("<Q3d3BdQ", data, off)
        off += struct.calcsize("<Q3d3BdQ") + 8 * tl
        ids.append(pid), xyz.append((x, y, z)), rgb.append((r, g, b)), err.append(e), tracks.append(tl)
    assert off == len(data)
    return np.array(ids), np.array(xyz), np.array(rgb), np.array(err), np.array(tracks)


def test_colmap_binary_reads_back_as_written_and_as_the_text_model(tmp_path):
    e, k, sizes = _cameras()
    names = ["a.jpg", "b.png", "c_d.jpg"]
    pts = np.random.default_rng(2).normal(size=(50, 3)).astype(np.float32)
    cols = np.random.default_rng(3).integers(0, 256, size=(50, 3)).astype(np.uint8)
    write_colmap_binary(tmp_path / "bin", names, e, k, sizes, pts, cols)
    model = read_model(tmp_path / "bin")  # the project's reader (the binary pair)
    assert [m["name"] for m in model] == names
    for i, m in enumerate(model):
        np.testing.assert_allclose(m["extrinsic"], e[i], atol=1e-12)
        np.testing.assert_allclose(m["intrinsic"], k[i], atol=0)
        assert (m["width"], m["height"]) == sizes[i]
    ids, xyz, rgb, err, tracks = _read_points3d_bin(tmp_path / "bin" / "points3D.bin")
    assert ids.tolist() == list(range(1, 51)) and (err == 0).all() and (tracks == 0).all()
    np.testing.assert_array_equal(xyz, pts.astype(np.float64))
    np.testing.assert_array_equal(rgb, cols)

    # the text model of the same cameras reads back the same
    write_colmap_text(tmp_path / "txt", names, e, k, sizes, pts, cols)
    for a, b in zip(read_model(tmp_path / "txt"), model):
        np.testing.assert_allclose(a["extrinsic"], b["extrinsic"], atol=1e-12)
    with pytest.raises(ValueError, match="spaces"):
        write_colmap_binary(tmp_path / "x", ["a b.jpg", "b", "c"], e, k, sizes)


def _project_nerfstudio(c2w_gl, k, x):
    """Pixel of world point x seen by a nerfstudio camera (camera-to-world, OpenGL axes: the
    camera looks down -z, y up; image rows go down)."""
    p = np.linalg.inv(c2w_gl) @ np.append(x, 1.0)
    depth = -p[2]
    return np.array([k[0, 0] * p[0] / depth + k[0, 2], k[1, 1] * -p[1] / depth + k[1, 2]]), depth


def test_transforms_json_schema_and_matrices(tmp_path):
    e, k, sizes = _cameras()
    doc = write_transforms_json(tmp_path / "transforms.json", ["images/a.jpg", "images/b.png", "images/c.jpg"],
                                e, k, sizes, ply_file_path="points.ply")
    assert json.loads((tmp_path / "transforms.json").read_text()) == doc
    # nerfstudio's documented keys: camera_model; intrinsics at the top or per frame
    # (they differ per frame here); frames with file_path and a 4x4 transform_matrix
    assert doc["camera_model"] in ("OPENCV", "OPENCV_FISHEYE") and doc["ply_file_path"] == "points.ply"
    assert not {"fl_x", "fl_y", "cx", "cy", "w", "h"} & doc.keys()
    assert len(doc["frames"]) == S
    for i, f in enumerate(doc["frames"]):
        assert set(f) == {"file_path", "transform_matrix", "fl_x", "fl_y", "cx", "cy", "w", "h"}
        t = np.array(f["transform_matrix"])
        assert t.shape == (4, 4)
        np.testing.assert_allclose(t[3], [0, 0, 0, 1])
        assert (f["fl_x"], f["fl_y"], f["cx"], f["cy"]) == (k[i, 0, 0], k[i, 1, 1], k[i, 0, 2], k[i, 1, 2])
        assert (f["w"], f["h"]) == sizes[i]
        # the camera centre is the same point; the OpenGL axes are OpenCV's x, -y, -z
        r, tr = e[i, :, :3], e[i, :, 3]
        np.testing.assert_allclose(t[:3, 3], -r.T @ tr, atol=1e-12)
        np.testing.assert_allclose(t[:3, :3], r.T @ np.diag([1, -1, -1]), atol=1e-12)
        # and a point in front of our camera lands on the same pixel in nerfstudio's
        x = r.T @ (np.array([0.3, -0.2, 4.0]) - tr)
        uv_cv = k[i] @ (r @ x + tr)
        uv, depth = _project_nerfstudio(t, k[i], x)
        assert depth > 0
        np.testing.assert_allclose(uv, uv_cv[:2] / uv_cv[2], atol=1e-9)


def test_transforms_json_shared_intrinsics_at_the_top_level(tmp_path):
    e, k, _ = _cameras()
    k[:] = k[0]
    doc = write_transforms_json(tmp_path / "t.json", ["a", "b", "c"], e, k, [(640, 480)] * S)
    assert (doc["fl_x"], doc["fl_y"], doc["cx"], doc["cy"], doc["w"], doc["h"]) == (
        k[0, 0, 0], k[0, 1, 1], k[0, 0, 2], k[0, 1, 2], 640, 480)
    assert all(set(f) == {"file_path", "transform_matrix"} for f in doc["frames"])
    np.testing.assert_allclose(opengl_camera_to_world(e)[1], doc["frames"][1]["transform_matrix"])


def test_export_writes_a_folder_nerfstudio_and_gsplat_read(tmp_path):
    """export_reconstruction with the image files: images/ beside sparse/ (text and
    binary) and transforms.json, whose paths resolve inside the folder."""
    s, h, w = 2, 28, 42
    e, _, _ = _cameras(1)
    e = e[:s]
    k = np.tile(np.array([[40.0, 0, w / 2], [0, 40.0, h / 2], [0, 0, 1]]), (s, 1, 1))
    src = tmp_path / "photos"
    src.mkdir()
    paths = []
    for i, name in enumerate(["p 0.png", "p1.png"]):
        (src / name).write_bytes(bytes([i]) * 10)  # (the export copies files, it does not decode them)
        paths.append(src / name)
    infos = [ImageInfo(path=str(p), name=p.name, width=84, height=56, sx=0.5, sy=0.5, ox=0.0, oy=0.0,
                       valid=(0, 0, w, h)) for p in paths]
    recon = build_reconstruction(np.full((s, 3, h, w), 0.5, np.float32), e, k, np.full((s, h, w), 2.0),
                                 np.full((s, h, w), 2.0), names=[p.name for p in paths], infos=infos,
                                 conf_threshold="0%")
    out = tmp_path / "recon"
    export_reconstruction(out, recon, image_paths=paths, max_colmap_points=None)
    for f in ("cameras", "images", "points3D"):
        assert (out / "sparse" / f"{f}.bin").is_file() and (out / "sparse" / f"{f}.txt").is_file()
    doc = json.loads((out / "transforms.json").read_text())
    assert [f["file_path"] for f in doc["frames"]] == ["images/p_0.png", "images/p1.png"]
    for f, p in zip(doc["frames"], paths):
        assert (out / f["file_path"]).read_bytes() == p.read_bytes()
    assert (out / doc["ply_file_path"]).is_file()
    names = [m["name"] for m in read_model(out / "sparse")]
    assert names == sorted(n for n in ("p_0.png", "p1.png")) and all((out / "images" / n).is_file() for n in names)
    assert len(_read_points3d_bin(out / "sparse" / "points3D.bin")[0]) == len(read_colmap_text(out / "sparse")["points"])
    # a second export into the same folder replaces the links
    export_reconstruction(out, recon, image_paths=paths)
    assert (out / "images" / "p1.png").read_bytes() == paths[1].read_bytes()
