"""Image files that used to load silently wrong (tests/io/test_inputs.py, and through
`rvggt reconstruct` in tests/app/test_tool.py)."""

import numpy as np
from PIL import Image


def gradient16(h=120, w=160):
    """A 16-bit horizontal ramp 0 .. 65535 (left to right)."""
    return np.tile(np.linspace(0, 65535, w).round().astype(np.uint16), (h, 1))


def rotated_jpeg(path):
    """An image stored 120 wide x 160 high with EXIF orientation 6 (rotate 90 degrees
    clockwise to view): upright it is 160 x 120 with a red band at the top."""
    up = np.zeros((120, 160, 3), np.uint8)
    up[:30] = (255, 0, 0)  # red band at the top of the upright picture
    stored = np.rot90(up, k=1).copy()  # what a camera held sideways stores (120 wide)
    im = Image.fromarray(stored)
    exif = Image.Exif()
    exif[0x0112] = 6
    im.save(path, exif=exif, quality=95)
    return up
