"""Input images and output files.

- `load_images(paths, mode)`: preprocessing identical to upstream VGGT's
  `load_and_preprocess_images` -> float32 [S, 3, H, W]; `load_images_with_info` also
  returns where each image's pixels went (`ImageInfo`); `find_images(folder)`.
- `video_frames(path, every=N | fps=F, max_frames=M)`: frames of a video (PyAV),
  named by timestamp.
- `export_reconstruction(...)` and the single writers (PLY with confidence, scene.glb,
  COLMAP text model, cameras.json, 16-bit depth PNGs, trajectory plot) with readers for
  checking.
"""

from rvggt_jax.io.export import (
    export_reconstruction,
    read_colmap_text,
    read_depth_png,
    read_ply,
    write_cameras_json,
    write_colmap_text,
    write_depth_pngs,
    write_ply,
    write_trajectory_png,
)
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
from rvggt_jax.io.ply import read_ply_properties
from rvggt_jax.io.video import VideoError, video_frames

__all__ = [
    "IMAGE_EXTENSIONS",
    "ImageInfo",
    "ImageLoadError",
    "VideoError",
    "export_reconstruction",
    "find_images",
    "load_images",
    "load_images_with_info",
    "preprocessed_size",
    "read_colmap_text",
    "read_depth_png",
    "read_ply",
    "read_ply_properties",
    "write_cameras_json",
    "video_frames",
    "write_colmap_text",
    "write_depth_pngs",
    "write_glb",
    "write_ply",
    "write_trajectory_png",
]
