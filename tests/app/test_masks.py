"""`rvggt reconstruct --masks DIR`: the bundled demo images with synthetic masks.

A masked pixel is 0 in the network input and has no point in points.ply, scene.glb or the
COLMAP points, and depth/ value 0; a missing mask or one of the wrong size is refused,
naming the file."""

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from rvggt_jax.app import commands
from rvggt_jax.app.messages import CLIError
from rvggt_jax.app.options import ReconstructOptions
from rvggt_jax.io.images import find_images, load_images_with_info
from rvggt_jax.io.masks import MaskError, find_masks, load_masks
from tests.helpers import SAMPLE_IMAGES
from tests.helpers.readers import read_colmap_text, read_depth_png, read_ply

FRAMES = 2  # the first and last demo image (--max-frames 2): a small forward


def _write_masks(folder: Path, images, scale=1.0, ext=".png"):
    """Per image: black (drop) on the left 40% and a black box in the middle; `scale`
    shrinks the mask file (same aspect ratio, another resolution)."""
    folder.mkdir(parents=True, exist_ok=True)
    for p in images:
        w, h = Image.open(p).size
        w, h = round(w * scale), round(h * scale)
        m = np.full((h, w), 255, np.uint8)
        m[:, : int(0.4 * w)] = 0
        m[h // 3: h // 2, w // 2: 3 * w // 4] = 0
        Image.fromarray(m).save(folder / (Path(p).stem + ext))
    return folder


def test_masks_found_by_stem_and_preprocessed_like_their_images(tmp_path):
    paths, _ = find_images(SAMPLE_IMAGES)
    images, infos = load_images_with_info(paths, "crop")
    full = load_masks(find_masks(paths, _write_masks(tmp_path / "full", paths)), infos, images.shape[2:])
    half = load_masks(find_masks(paths, _write_masks(tmp_path / "half", paths, 0.5, ".jpg")), infos,
                      images.shape[2:])
    assert full.shape == (len(paths),) + images.shape[2:] and full.dtype == bool
    w = images.shape[3]
    # the left 40% is dropped, the right edge kept, whatever the mask file's resolution
    assert not full[:, :, : int(0.4 * w) - 2].any() and full[:, :, -5:].all()
    assert (full != half).mean() < 0.01  # only resampled edges differ


def test_missing_ambiguous_and_wrong_size_masks_are_named(tmp_path):
    paths, _ = find_images(SAMPLE_IMAGES)
    masks = _write_masks(tmp_path / "m", paths)
    (masks / f"{paths[1].stem}.png").unlink()
    with pytest.raises(MaskError, match=f"no mask for image {paths[1].name}"):
        find_masks(paths, masks)
    _write_masks(masks, paths[:1], ext=".jpg")
    with pytest.raises(MaskError, match=f"two masks for image {paths[0].name}"):
        find_masks(paths, masks)
    with pytest.raises(MaskError, match="mask folder"):
        find_masks(paths, tmp_path / "nowhere")

    wrong = tmp_path / "wrong"
    wrong.mkdir()
    for p in paths:
        Image.new("L", (64, 64), 255).save(wrong / f"{p.stem}.png")  # square: not the images' aspect
    images, infos = load_images_with_info(paths, "crop")
    with pytest.raises(MaskError, match=rf"mask {wrong / paths[0].stem}\.png is 64x64 .*its image {paths[0].name}"):
        load_masks(find_masks(paths, wrong), infos, images.shape[2:])


def test_cli_refuses_a_missing_mask_before_loading_weights(tmp_path):
    paths, _ = find_images(SAMPLE_IMAGES)
    masks = _write_masks(tmp_path / "m", paths[:1])
    with pytest.raises(CLIError, match=f"--masks: no mask for image {paths[1].name}"):
        commands.reconstruct_folder(SAMPLE_IMAGES, commands.TINY_WEIGHTS, tmp_path / "out",
                                    ReconstructOptions(masks=masks, quiet=True))


def test_masks_option_on_the_command_line(tmp_path):
    """`rvggt reconstruct --masks DIR` reaches the options: a missing folder is one line
    naming it, before the weights load."""
    import os
    import subprocess
    import sys

    from tests.helpers import REPO

    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""),
           "RVGGT_CACHE_DIR": "off", "JAX_PLATFORMS": "cpu"}
    r = subprocess.run([sys.executable, "-m", "rvggt_jax.app.cli", "reconstruct", str(SAMPLE_IMAGES), "--weights",
                        str(commands.TINY_WEIGHTS), "--out", str(tmp_path / "out"), "--masks",
                        str(tmp_path / "nowhere")], capture_output=True, text=True, timeout=300, env=env, cwd=REPO)
    assert r.returncode != 0 and "Traceback" not in r.stderr, r.stderr
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("rvggt: error:")]
    assert len(errors) == 1 and "--masks: mask folder" in errors[0] and "nowhere" in errors[0], r.stderr


@pytest.fixture(scope="module")
def masked_run(tmp_path_factory):
    """The demo (tiny random weights) on 2 demo images with masks, every point kept;
    the network input the model saw is recorded."""
    tmp = tmp_path_factory.mktemp("masked")
    paths, _ = find_images(SAMPLE_IMAGES)
    masks_dir = _write_masks(tmp / "masks", paths)
    seen = {}
    run = commands.run_model

    def recording_run(params, images, *a, **k):
        seen["images"] = np.asarray(images)
        return run(params, images, *a, **k)

    mp = pytest.MonkeyPatch()
    mp.setattr(commands, "run_model", recording_run)
    mp.setenv("RVGGT_CACHE_DIR", "off")  # in-process: leave this session's JAX cache settings alone
    try:
        out = tmp / "out"
        options = ReconstructOptions(masks=masks_dir, max_frames=FRAMES, conf_threshold="0%", max_points=None,
                                     all_colmap_points=True, quiet=True)
        commands.reconstruct_folder(SAMPLE_IMAGES, commands.TINY_WEIGHTS, out, options)
    finally:
        mp.undo()
    chosen = [paths[0], paths[-1]]
    images, infos = load_images_with_info(chosen, "crop")
    keep = load_masks(find_masks(chosen, masks_dir), infos, images.shape[2:])
    return out, seen["images"], keep, chosen


def test_masked_pixels_are_zero_in_the_network_input(masked_run):
    _, seen, keep, _ = masked_run
    assert seen.shape[0] == FRAMES and (~keep).any() and keep.any()
    assert (seen.transpose(1, 0, 2, 3)[:, ~keep] == 0).all()
    assert (seen.transpose(1, 0, 2, 3)[:, keep] > 0).any()


def test_masked_pixels_have_no_depth_and_no_point(masked_run):
    out, _, keep, chosen = masked_run
    depth = np.stack([read_depth_png(out / "depth" / f"{p.stem}.png") for p in chosen])
    assert (depth[~keep] == 0).all()
    assert (depth[keep] > 0).mean() > 0.99

    # every point of points.ply comes from a kept pixel: project each into its own frame
    # (network-input camera, integer pixel it was unprojected from), and they are all
    # the kept pixels with depth (threshold 0%, no cap)
    from rvggt_jax.io.ply import read_ply_properties

    props = read_ply_properties(out / "points.ply")
    pts = np.stack([props["x"], props["y"], props["z"]], 1).astype(np.float64)
    frame = props["frame"].astype(int)
    cams = json.loads((out / "cameras.json").read_text())["frames"]
    h, w = keep.shape[1:]
    for i, cam in enumerate(cams):
        e, k = np.array(cam["extrinsic"]), np.array(cam["network"]["intrinsic"])
        cam_pts = pts[frame == i] @ e[:, :3].T + e[:, 3]
        uv = cam_pts @ k.T
        col, row = np.rint(uv[:, 0] / uv[:, 2]).astype(int), np.rint(uv[:, 1] / uv[:, 2]).astype(int)
        assert ((col >= 0) & (col < w) & (row >= 0) & (row < h)).all()
        assert keep[i, row, col].all(), f"frame {i}: {(~keep[i, row, col]).sum()} points from masked pixels"
        assert len(np.unique(row * w + col)) == (depth[i] > 0).sum()

    # the same cloud in scene.glb and (all points asked for) the COLMAP model
    import trimesh

    scene = trimesh.load(out / "scene.glb")
    assert len(scene.geometry["points"].vertices) == len(pts)
    colmap = read_colmap_text(out / "sparse")["points"]
    xyz = np.stack([colmap[j]["xyz"] for j in sorted(colmap)])
    np.testing.assert_allclose(xyz, read_ply(out / "points.ply")[0], rtol=1e-6, atol=1e-6)


def test_all_black_masks_are_named_as_the_cause(tmp_path, monkeypatch):
    """Masks that keep nothing stop the run before the model, saying so (the run used to
    end with "no point passed the confidence threshold ... lower --conf-threshold")."""
    from PIL import Image

    from rvggt_jax.app.messages import CLIError

    monkeypatch.setenv("RVGGT_CACHE_DIR", "off")
    monkeypatch.setattr(commands, "run_model", lambda *a, **k: pytest.fail("the model ran"))
    paths, _ = find_images(SAMPLE_IMAGES)
    (tmp_path / "masks").mkdir()
    for p in paths:
        w, h = Image.open(p).size
        Image.new("L", (w, h), 0).save(tmp_path / "masks" / f"{p.stem}.png")
    options = ReconstructOptions(masks=tmp_path / "masks", quiet=True)
    with pytest.raises(CLIError, match="keep no pixel of any image"):
        commands.reconstruct_folder(SAMPLE_IMAGES, commands.TINY_WEIGHTS, tmp_path / "out", options)
