"""Procedural scenes with exact ground truth: textured planes, boxes, spheres and cylinders seen by known
pinhole cameras along a path, rendered by ray casting in numpy.

    scene = make_scene(frames=6, height=60, width=80, seed=0)
    scene.images      [S, H, W, 3] uint8      rendered colours
    scene.depth       [S, H, W] float32       z in the camera frame (0 where a ray hits nothing)
    scene.points      [S, H, W, 3] float32    world points of the pixels (NaN where no hit)
    scene.normals     [S, H, W, 3] float32    world unit normals of the hit surfaces
    scene.extrinsics  [S, 3, 4] float64       world-to-camera [R | t], OpenCV (x right, y down, z forward)
    scene.intrinsics  [S, 3, 3] float64       pixels; pixel (col, row) is the ray K^-1 [col, row, 1]

The pixel convention is `rvggt_jax.geometry.depth_to_cam_points`'s (integer pixel
coordinates are pixel centres), so unprojecting `depth` with the cameras gives back
`points` to float precision. Used by the evaluation tests (every metric and reader is
checked on these scenes) and meant for fine-tuning data as well.

`write_scene(scene, fmt, root)` stores a scene in one of the evaluation datasets'
on-disk formats (`rvggt_jax.eval.datasets.FORMATS`).

`random_scene(seed, frames, ...)` is the training data's family (`rvggt_jax.train.procedural`):
boxes, spheres and cylinders with checker, noise or stripe textures, a random light and
focal length, seen along an orbit, a forward walk or from scattered look-at cameras.

`loop_walkthrough(frames, ...)` is a long walk around a closed corridor that returns to
its start (for the long-sequence pipeline, `rvggt_jax.sequence`): it holds only the
cameras and the primitives, and renders any subset of frames on demand.
"""

from rvggt_jax.synthetic.render import (DEFAULT_LIGHT, TEXTURES, Box, Cylinder, Rect, Sphere, ray_cast,
                                        render)
from rvggt_jax.synthetic.scenes import (SyntheticScene, camera_centers, look_at, make_scene, orbit_cameras, room,
                                        write_scene)
from rvggt_jax.synthetic.training import (HELD_OUT_SEEDS, PATHS, forward_cameras, lookat_cameras, random_room,
                                          random_scene)
from rvggt_jax.synthetic.walk import LoopWalk, loop_walkthrough

__all__ = ["Box", "Cylinder", "DEFAULT_LIGHT", "HELD_OUT_SEEDS", "LoopWalk", "PATHS", "Rect", "Sphere",
           "SyntheticScene", "TEXTURES", "camera_centers", "forward_cameras", "look_at", "lookat_cameras",
           "loop_walkthrough", "make_scene", "orbit_cameras", "random_room", "random_scene", "ray_cast", "render",
           "room", "write_scene"]
