"""Regenerate tests/data/interp_bicubic_aa.npz: torch's antialiased bicubic resize of a
random 37x37 grid to other sizes. Needs torch (a development tool, not a dependency).

    python tools/make_interp_fixture.py
"""

import numpy as np
import torch
import torch.nn.functional as F

CASES = [(8, 11, 0.0), (37, 37, 0.0), (19, 5, 0.0), (40, 52, 0.0), (12, 30, 0.1), (37, 23, 0.1)]


def main() -> None:
    rng = np.random.default_rng(0)
    grid = rng.standard_normal((1, 4, 37, 37)).astype(np.float32)
    out = {"grid": grid}
    for h, w, offset in CASES:
        kw = {"scale_factor": ((h + offset) / 37, (w + offset) / 37)} if offset else {"size": (h, w)}
        y = F.interpolate(torch.from_numpy(grid), mode="bicubic", antialias=True, **kw).numpy()
        out[f"{h}x{w}@{offset}"] = y
    np.savez_compressed("tests/data/interp_bicubic_aa.npz", **out)


if __name__ == "__main__":
    main()
