"""Images that used to load silently wrong: 16-bit and other high-bit-depth modes,
EXIF orientation, transparency outside RGBA; and `on_error="skip"`."""

import numpy as np
import pytest
from PIL import Image

from rvggt_jax.io import ImageLoadError, load_images, load_images_with_info
from tests.helpers.image_files import gradient16 as _gradient16, rotated_jpeg as _rotated_jpeg


def test_16bit_png_is_read_by_range(tmp_path):
    p = tmp_path / "depthcam.png"
    Image.fromarray(_gradient16()).save(p)  # uint16 -> mode I;16
    with Image.open(p) as im:
        assert im.mode in ("I;16", "I")  # what Pillow opens: the mode the fix must handle
    x = load_images([p])
    assert x.shape == (1, 3, 392, 518)
    # not a solid white image: dark on the left, bright on the right, grey (R = G = B)
    assert x[0, :, :, :20].mean() < 0.05 and x[0, :, :, -20:].mean() > 0.95
    assert 0.4 < x[0, :, :, 259].mean() < 0.6
    np.testing.assert_array_equal(x[0, 0], x[0, 1])


@pytest.mark.parametrize("mode", ["I", "F"])
def test_32bit_modes_are_read_by_range(tmp_path, mode):
    a = _gradient16().astype(np.int32 if mode == "I" else np.float32)
    p = tmp_path / "img.tif"
    Image.fromarray(a).save(p)  # int32 -> I, float32 -> F
    x = load_images([p])
    assert x[0, :, :, :20].mean() < 0.05 and x[0, :, :, -20:].mean() > 0.95


def test_float_image_in_unit_range_kept(tmp_path):
    a = np.full((120, 160), 0.5, np.float32)
    p = tmp_path / "unit.tif"
    Image.fromarray(a).save(p)
    x = load_images([p])
    assert abs(float(x.mean()) - 128 / 255) < 2 / 255


def test_exif_orientation_applied(tmp_path):
    p = tmp_path / "phone.jpg"
    _rotated_jpeg(p)
    x, (info,) = load_images_with_info([p])
    assert (info.width, info.height) == (160, 120)
    assert x.shape == (1, 3, 392, 518)
    top, bottom = x[0, :, :40].mean(axis=(1, 2)), x[0, :, -40:].mean(axis=(1, 2))
    assert top[0] > 0.8 and top[1] < 0.2 and bottom.max() < 0.2  # red on top: upright
    # upstream's behaviour on request: the stored (sideways) pixels
    x_raw, (info_raw,) = load_images_with_info([p], exif_orientation=False)
    assert (info_raw.width, info_raw.height) == (120, 160)
    assert x_raw.shape[2:] == (518, 518)  # tall: cropped to 518 x 518


def test_transparency_outside_rgba_blends_on_white(tmp_path):
    la = np.zeros((28, 28, 2), np.uint8)
    la[:, 14:, 1] = 255  # left half transparent, right half opaque black
    p = tmp_path / "la.png"
    Image.fromarray(la, mode="LA").save(p)
    x = load_images([p])
    assert np.allclose(x[0, :, :, :200], 1.0) and np.allclose(x[0, :, :, -200:], 0.0)


def test_skip_bad(tmp_path):
    good = tmp_path / "a.png"
    Image.fromarray(np.zeros((120, 160, 3), np.uint8)).save(good)
    bad = tmp_path / "b.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\nbroken")
    with pytest.raises(ImageLoadError, match="b.png"):
        load_images_with_info([good, bad])
    x, infos = load_images_with_info([good, bad, good], on_error="skip")
    assert x.shape[0] == 2 and [i.name for i in infos] == ["a.png", "a.png"]
    with pytest.raises(ImageLoadError, match="none of the 1"):
        load_images_with_info([bad], on_error="skip")
