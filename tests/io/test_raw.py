"""predictions.npz (`rvggt reconstruct --save-raw`, `rvggt_jax.io.raw`): written by the
export of a synthetic reconstruction with upstream's keys and shapes, read back by
`load_predictions`, which refuses what is not one."""

from __future__ import annotations

import numpy as np
import pytest

from rvggt_jax.app.pipeline import build_reconstruction
from rvggt_jax.io.export import export_reconstruction
from rvggt_jax.io.raw import RAW_NAME, RawPredictionsError, load_predictions, write_predictions

S, H, W = 2, 6, 8


def _recon_and_outputs():
    rng = np.random.default_rng(0)
    ext = np.zeros((S, 3, 4))
    ext[:, :, :3] = np.eye(3)
    ext[1, 0, 3] = -0.5
    k = np.tile(np.array([[10.0, 0, W / 2], [0, 11.0, H / 2], [0, 0, 1]]), (S, 1, 1))
    depth = rng.uniform(1, 3, (S, H, W, 1)).astype(np.float32)
    outputs = dict(pose_enc=rng.normal(size=(S, 9)).astype(np.float32), depth=depth,
                   depth_conf=rng.uniform(1, 5, (S, H, W)).astype(np.float32),
                   world_points=rng.normal(size=(S, H, W, 3)).astype(np.float32),
                   world_points_conf=rng.uniform(1, 5, (S, H, W)).astype(np.float32))
    recon = build_reconstruction(rng.uniform(size=(S, 3, H, W)).astype(np.float32), ext, k, depth,
                                 outputs["depth_conf"], names=["a.jpg", "b.jpg"])
    return recon, outputs


def test_export_saves_raw_predictions(tmp_path):
    recon, outputs = _recon_and_outputs()
    summary = export_reconstruction(tmp_path, recon, write_scene=False, save_raw=True, model_outputs=outputs)
    assert summary["raw"] == RAW_NAME
    got = load_predictions(tmp_path / RAW_NAME)
    shapes = {k: v.shape for k, v in got.items()}
    assert shapes == {"extrinsic": (S, 3, 4), "intrinsic": (S, 3, 3), "depth": (S, H, W, 1),
                      "depth_conf": (S, H, W), "world_points_from_depth": (S, H, W, 3), "images": (S, 3, H, W),
                      "pose_enc": (S, 9), "image_names": (S,), "world_points": (S, H, W, 3),
                      "world_points_conf": (S, H, W)}
    assert got["image_names"].tolist() == ["a.jpg", "b.jpg"]
    for key in ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf"):
        np.testing.assert_array_equal(got[key], outputs[key])
    np.testing.assert_allclose(got["intrinsic"], recon.network_intrinsic)
    np.testing.assert_allclose(got["extrinsic"], recon.extrinsic)
    np.testing.assert_array_equal(got["images"], recon.images)
    # frame 1's centre is at x = 0.5: its pixel (col, row) sits at depth * K^-1 [col, row, 1] from there
    d = outputs["depth"][1, 2, 3, 0]
    np.testing.assert_allclose(got["world_points_from_depth"][1, 2, 3],
                               [0.5 + d * (3 - W / 2) / 10.0, d * (2 - H / 2) / 11.0, d], rtol=1e-5)
    assert not (tmp_path / "other").exists()
    # off by default
    assert export_reconstruction(tmp_path / "other", recon, write_scene=False)["raw"] is None
    assert not (tmp_path / "other" / RAW_NAME).exists()


def test_without_point_head_or_outputs(tmp_path):
    """No model outputs: pose_enc encoded from the cameras, no world_points."""
    recon, _ = _recon_and_outputs()
    got = load_predictions(write_predictions(tmp_path / RAW_NAME, recon))
    assert "world_points" not in got and got["pose_enc"].shape == (S, 9)
    np.testing.assert_allclose(got["pose_enc"][1, :3], recon.extrinsic[1, :, 3], atol=1e-6)


def test_load_predictions_refuses_other_files(tmp_path):
    recon, outputs = _recon_and_outputs()
    good = load_predictions(write_predictions(tmp_path / RAW_NAME, recon, outputs))
    with pytest.raises(FileNotFoundError, match="no predictions file"):
        load_predictions(tmp_path / "missing.npz")
    (tmp_path / "text.npz").write_text("not an archive")
    with pytest.raises(RawPredictionsError, match="cannot read it as .npz"):
        load_predictions(tmp_path / "text.npz")
    np.save(tmp_path / "one.npy", np.zeros(3))
    with pytest.raises(RawPredictionsError, match=r"\.npy"):
        load_predictions(tmp_path / "one.npy")
    np.savez(tmp_path / "partial.npz", **{k: v for k, v in good.items() if k != "depth_conf"})
    with pytest.raises(RawPredictionsError, match="missing depth_conf"):
        load_predictions(tmp_path / "partial.npz")
    np.savez(tmp_path / "bad_shape.npz", **{**good, "depth": good["depth"][:, :-1]})
    with pytest.raises(RawPredictionsError, match=r"depth has shape \[2, 5, 8, 1\], expected \[S=2, H=6, W=8, 1\]"):
        load_predictions(tmp_path / "bad_shape.npz")
