"""The COLMAP model's camera models and the shared camera (`rvggt reconstruct --camera-type
... --shared-camera`), at the export level on a synthetic reconstruction, read back by
pycolmap from the text and the binary files; and the options' checks."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from rvggt_jax.app.messages import CLIError
from rvggt_jax.app.options import ReconstructOptions
from rvggt_jax.app.pipeline import build_reconstruction
from rvggt_jax.io.colmap import colmap_cameras
from rvggt_jax.io.export import export_reconstruction
from rvggt_jax.io.images import ImageInfo

S, H, W = 3, 14, 20


def _recon(widths=(40, 40, 40)):
    """3 frames (network 20x14, originals widths[i] x 28) whose focal lengths differ."""
    ext = np.zeros((S, 3, 4))
    ext[:, :, :3] = np.eye(3)
    ext[:, 0, 3] = -0.2 * np.arange(S)
    f = np.array([[20.0, 22.0], [21.0, 23.0], [26.0, 24.0]])  # (fx, fy) per frame
    k = np.zeros((S, 3, 3))
    k[:, 0, 0], k[:, 1, 1], k[:, 0, 2], k[:, 1, 2], k[:, 2, 2] = f[:, 0], f[:, 1], W / 2, H / 2, 1
    rng = np.random.default_rng(0)
    infos = [ImageInfo(path=f"/x/f{i}.png", name=f"f{i}.png", width=wd, height=2 * H, sx=W / wd, sy=0.5, ox=0.0,
                       oy=0.0, valid=(0, 0, W, H)) for i, wd in enumerate(widths)]
    return build_reconstruction(rng.uniform(size=(S, 3, H, W)).astype(np.float32), ext, k,
                                np.full((S, H, W), 2.0, np.float32), rng.uniform(1, 5, (S, H, W)).astype(np.float32),
                                names=[i.name for i in infos], infos=infos, conf_threshold="0%")


@pytest.mark.parametrize("model, shared", [("SIMPLE_PINHOLE", True), ("SIMPLE_RADIAL", False), ("PINHOLE", True)])
def test_export_camera_models_read_back_by_pycolmap(tmp_path, model, shared):
    recon = _recon()
    export_reconstruction(tmp_path, recon, write_scene=False, camera_model=model, shared_camera=shared)
    k = recon.intrinsic  # original pixels
    f = (k[:, 0, 0] + k[:, 1, 1]) / 2
    expected = {"PINHOLE": np.stack([k[:, 0, 0], k[:, 1, 1], k[:, 0, 2], k[:, 1, 2]], 1),
                "SIMPLE_PINHOLE": np.stack([f, k[:, 0, 2], k[:, 1, 2]], 1),
                "SIMPLE_RADIAL": np.stack([f, k[:, 0, 2], k[:, 1, 2], np.zeros(S)], 1)}[model]
    if shared:
        expected = np.median(expected, axis=0, keepdims=True)
    for read in ("read_text", "read_binary"):
        rec = pycolmap.Reconstruction()
        getattr(rec, read)(str(tmp_path / "sparse"))
        assert rec.num_cameras() == len(expected) and rec.num_images() == S
        for i in range(S):
            image = rec.image(i + 1)
            assert image.camera_id == (1 if shared else i + 1)
            cam = rec.camera(image.camera_id)
            assert cam.model.name == model and (cam.width, cam.height) == recon.sizes[i]
            np.testing.assert_allclose(cam.params, expected[image.camera_id - 1], rtol=1e-12)


def test_shared_camera_needs_one_image_size(tmp_path):
    recon = _recon(widths=(40, 40, 60))
    with pytest.raises(ValueError, match="40x28 and 60x28"):
        export_reconstruction(tmp_path / "out", recon, write_scene=False, shared_camera=True)
    assert not (tmp_path / "out").exists()  # refused before writing anything
    with pytest.raises(ValueError, match="unknown COLMAP camera model 'FISHEYE'"):
        colmap_cameras(recon.intrinsic, recon.sizes, "FISHEYE")


def test_camera_options_checked():
    ReconstructOptions(camera_type="SIMPLE_RADIAL", shared_camera=True, save_raw=True).check()
    with pytest.raises(CLIError, match="--camera-type"):
        ReconstructOptions(camera_type="OPENCV").check()
    with pytest.raises(CLIError, match="--save-raw does not run with --chunk-frames.*OUT/chunks"):
        ReconstructOptions(shared_camera=True, save_raw=True, chunk_frames=8).check()
    ReconstructOptions(camera_type="SIMPLE_PINHOLE", shared_camera=True, chunk_frames=8).check()


def test_cli_camera_flags():
    from rvggt_jax.app.cli import build_parser, reconstruct_options

    args = build_parser().parse_args(["reconstruct", "in", "--weights", "w", "--out", "o", "--camera-type",
                                      "simple_pinhole", "--shared-camera", "--save-raw"])
    o = reconstruct_options(args)
    assert (o.camera_type, o.shared_camera, o.save_raw) == ("SIMPLE_PINHOLE", True, True)
    o = reconstruct_options(build_parser().parse_args(["reconstruct", "in", "--weights", "w", "--out", "o"]))
    assert (o.camera_type, o.shared_camera, o.save_raw) == ("PINHOLE", False, False)
