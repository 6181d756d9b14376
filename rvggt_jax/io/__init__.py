"""Input images and output files, one module per format.

- `load_images(paths, mode)`: preprocessing identical to upstream VGGT's
  `load_and_preprocess_images` -> float32 [S, 3, H, W]; `load_images_with_info` also
  returns where each image's pixels went (`ImageInfo`); `find_images(folder)`.
- `video_frames(path, every=N | fps=F, max_frames=M)`: frames of a video (PyAV),
  named by timestamp.
- Writers: `ply` (points with confidence), `glb` (scene.glb), `colmap` (COLMAP text
  model), `cameras` (cameras.json), `depth` (16-bit depth PNGs), `plots` (trajectory,
  thumbnails, depth colours), `raw` (predictions.npz, read back by `load_predictions`);
  `export.export_reconstruction` writes all of them for a
  `rvggt_jax.app.pipeline.Reconstruction`.
"""

from rvggt_jax.io.cameras import write_cameras_json
from rvggt_jax.io.colmap import write_colmap_text
from rvggt_jax.io.depth import write_depth_pngs
from rvggt_jax.io.export import export_reconstruction
from rvggt_jax.io.glb import write_glb
from rvggt_jax.io.images import (
    IMAGE_EXTENSIONS,
    ImageInfo,
    ImageLoadError,
    find_images,
    load_images,
    load_images_with_info,
    preprocessed_size,
)
from rvggt_jax.io.plots import write_trajectory_png
from rvggt_jax.io.ply import read_ply_properties, write_ply
from rvggt_jax.io.raw import RawPredictionsError, load_predictions
from rvggt_jax.io.video import VideoError, video_frames

__all__ = [
    "IMAGE_EXTENSIONS",
    "ImageInfo",
    "ImageLoadError",
    "RawPredictionsError",
    "VideoError",
    "export_reconstruction",
    "find_images",
    "load_images",
    "load_images_with_info",
    "load_predictions",
    "preprocessed_size",
    "read_ply_properties",
    "video_frames",
    "write_cameras_json",
    "write_colmap_text",
    "write_depth_pngs",
    "write_glb",
    "write_ply",
    "write_trajectory_png",
]
