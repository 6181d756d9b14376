"""Image preprocessing: bit-exact against upstream's `load_and_preprocess_images`
(fixture tests/data/preprocess, made with upstream + torch), plus errors and the
per-image pixel maps."""

import numpy as np
import pytest
from PIL import Image

from rvggt_jax.io import ImageLoadError, find_images, load_images, load_images_with_info, preprocessed_size
from tests.helpers import PREPROCESS as DATA


def _fixture():
    order = (DATA / "ORDER.txt").read_text().split()
    with np.load(DATA / "preprocess.npz") as z:
        expected = {k: z[k].astype(np.float32) / np.float32(255.0) for k in z.files}
    return [DATA / n for n in order], expected


@pytest.mark.parametrize("mode", ["crop", "pad"])
def test_mixed_matches_upstream(mode):
    paths, expected = _fixture()
    got = load_images(paths, mode=mode)
    want = expected[f"{mode}_mixed"]
    assert got.dtype == np.float32
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)


@pytest.mark.parametrize("mode", ["crop", "pad"])
def test_single_matches_upstream(mode):
    paths, expected = _fixture()
    got = load_images(paths[:1], mode=mode)
    want = expected[f"{mode}_single"]
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)


def test_sizes_follow_upstream_rounding():
    assert preprocessed_size(640, 480, "crop") == (518, 392)
    assert preprocessed_size(250, 700, "crop") == (518, 1456)  # then cropped to 518
    assert preprocessed_size(250, 700, "pad") == (182, 518)
    assert preprocessed_size(517, 301, "pad") == (518, 308)
    with pytest.raises(ValueError, match="too thin"):
        preprocessed_size(1000, 10, "crop")  # upstream would resize to height 0
    for w, h in [(640, 480), (517, 301), (250, 700), (1000, 30)]:
        for mode in ("crop", "pad"):
            nw, nh = preprocessed_size(w, h, mode)
            assert nw % 14 == 0 and nh % 14 == 0 and max(nw, nh) >= 518


def test_infos_map_pixels(tmp_path):
    paths, _ = _fixture()
    images, infos = load_images_with_info(paths, mode="pad")
    s, _, h, w = images.shape
    for img, info in zip(images, infos):
        x0, y0, x1, y1 = info.valid
        # outside the content box: pure white padding
        mask = info.valid_mask(h, w)
        assert np.all(img[:, ~mask] == 1.0)
        # the box is where the original image's corners land
        assert abs(info.ox - x0) < 1e-9 and abs(info.oy - y0) < 1e-9
        assert abs(info.sx * info.width + info.ox - x1) < 1e-6
        assert abs(info.sy * info.height + info.oy - y1) < 1e-6
        # intrinsics: projecting with K_orig then mapping equals projecting with K_net
        k_net = np.array([[400.0, 0, w / 2], [0, 410.0, h / 2], [0, 0, 1]])
        k_org = info.intrinsic_to_original(k_net)
        X = np.array([0.3, -0.2, 2.0])
        u_org = k_org @ X
        u_org = u_org[:2] / u_org[2]
        u_net = k_net @ X
        u_net = u_net[:2] / u_net[2]
        np.testing.assert_allclose([info.sx * u_org[0] + info.ox, info.sy * u_org[1] + info.oy], u_net, atol=1e-9)
    # crop mode of a tall image: the top is cropped away (negative offset)
    _, (info,) = load_images_with_info([paths[2]], mode="crop")
    assert info.oy < 0 and info.valid == (0, 0, 518, 518)


def test_errors(tmp_path):
    with pytest.raises(ValueError, match="at least 1 image"):
        load_images([])
    paths, _ = _fixture()
    with pytest.raises(ValueError, match="mode"):
        load_images(paths[:1], mode="stretch")
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n this is not a png")
    with pytest.raises(ImageLoadError, match="broken.png"):
        load_images([paths[0], bad])
    trunc = tmp_path / "truncated.png"
    trunc.write_bytes((DATA / "img0_640x480_RGB.png").read_bytes()[:5000])
    with pytest.raises(ImageLoadError, match="truncated.png"):
        load_images([trunc])
    with pytest.raises(ImageLoadError, match="missing.jpg"):
        load_images([tmp_path / "missing.jpg"])


def test_find_images(tmp_path):
    for name in ["b.png", "a.JPG", "c.jpeg", ".hidden.png", "notes.txt"]:
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / "sub.png").mkdir()
    images, skipped = find_images(tmp_path)
    assert [p.name for p in images] == ["a.JPG", "b.png", "c.jpeg"]
    assert sorted(p.name for p in skipped) == [".hidden.png", "notes.txt", "sub.png"]
    with pytest.raises(FileNotFoundError):
        find_images(tmp_path / "nope")
    with pytest.raises(NotADirectoryError):
        find_images(tmp_path / "notes.txt")


def test_rgba_blends_on_white(tmp_path):
    rgba = np.zeros((28, 28, 4), np.uint8)
    rgba[..., 0] = 255
    rgba[:, 14:, 3] = 255  # left half transparent, right half opaque red
    p = tmp_path / "a.png"
    Image.fromarray(rgba, "RGBA").save(p)
    x = load_images([p])
    assert x.shape == (1, 3, 518, 518)
    assert np.allclose(x[0, :, :, :200], 1.0)  # white
    assert np.allclose(x[0, :, :, -200:], np.array([1.0, 0.0, 0.0])[:, None, None])


def test_network_images_are_exact_uint8_or_float32():
    """Loaded images (each value some v / 255) become uint8 that scales back bit for bit;
    anything else stays float32 (values off the 1/255 grid, out of [0, 1], NaN)."""
    from rvggt_jax.io.images import network_images
    from rvggt_jax.model.patch_embed import UNIT_OF_UINT8

    paths, _ = _fixture()
    loaded = load_images(paths, mode="pad")  # RGB, RGBA on white and L, white-padded
    u8 = network_images(loaded)
    assert u8.dtype == np.uint8 and u8.shape == loaded.shape
    np.testing.assert_array_equal(UNIT_OF_UINT8[u8], loaded)
    assert network_images(u8) is u8
    off_grid = loaded.copy()
    off_grid.flat[7] = np.float32(0.5)  # 127.5 / 255
    for bad in (off_grid, loaded * 2.0, np.where(loaded > 0.5, np.nan, loaded)):
        out = network_images(bad)
        assert out.dtype == np.float32
        np.testing.assert_array_equal(out, bad.astype(np.float32))
