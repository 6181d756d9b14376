"""Bundle adjustment of a feed-forward reconstruction (`rvggt reconstruct --ba`).

The model's cameras are good but not pixel-exact; this refines them the classical way,
with the model's own track head supplying the correspondences:

1. `tracks`: query points (SIFT keypoints, or high-confidence grid points) in a few
   query frames, tracked through every frame by the track head, the observations kept
   by the head's visibility and confidence;
2. `triangulate`: linear (DLT) triangulation of each track with the predicted cameras,
   observations that reproject badly dropped (pure numpy);
3. `adjust`: pycolmap's bundle adjustment of poses and points (optionally the focal
   lengths) on a `pycolmap.Reconstruction` built from the cameras, points and tracks,
   and the refined arrays read back;
4. `refine`: the three steps on a `rvggt_jax.app.pipeline.Reconstruction`, the outputs
   (COLMAP model with tracks, refined cameras, a report of the reprojection errors
   before and after) written by `write_outputs`.

pycolmap is an optional dependency (`pip install "rvggt-jax[ba]"`), imported only by
`adjust` (and by SIFT keypoints) when they run: `require_pycolmap` says which extra to
install when it is missing.
"""

from __future__ import annotations

import contextlib

__all__ = ["BA_EXTRA_HINT", "BAError", "PycolmapMissing", "quiet_pycolmap", "require_pycolmap"]

BA_EXTRA_HINT = 'pip install "rvggt-jax[ba]"'


class BAError(ValueError):
    """Bundle adjustment cannot run on this input (too few frames, too few tracks); the
    message says what is missing and which option helps."""


class PycolmapMissing(ImportError):
    """pycolmap is not installed; the message names the extra that installs it."""


def require_pycolmap():
    """The pycolmap module, or `PycolmapMissing` saying `pip install "rvggt-jax[ba]"`."""
    try:
        import pycolmap
    except ImportError as e:
        raise PycolmapMissing(f"bundle adjustment (--ba) needs pycolmap, which is not installed ({e}); "
                              f"install it with: {BA_EXTRA_HINT}") from None
    return pycolmap


@contextlib.contextmanager
def quiet_pycolmap():
    """pycolmap (COLMAP's glog) without its INFO lines ("Creating SIFT CPU feature
    extractor", ...) on stderr, which would interleave with the command's own messages;
    warnings and errors still show."""
    pycolmap = require_pycolmap()
    log = getattr(pycolmap, "logging", None)
    before = getattr(log, "minloglevel", None)
    if before is None:
        yield pycolmap
        return
    try:
        log.minloglevel = max(int(before), 1)  # glog levels: 0 INFO, 1 WARNING
        yield pycolmap
    finally:
        log.minloglevel = before
