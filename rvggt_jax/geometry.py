"""Camera geometry: the 9-d pose encoding, quaternions, SE(3) inverses, depth unprojection.

Conventions are upstream VGGT's:
- extrinsics are camera-from-world `[R | t]` in the OpenCV frame (x right, y down,
  z forward), `[..., 3, 4]`;
- intrinsics are pixel `[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`, `[..., 3, 3]`;
- quaternions are scalar-last `(x, y, z, w)`;
- the pose encoding "absT_quaR_FoV" is `[t (3), quaternion (4), fov_h, fov_w]`, `[..., 9]`.

Everything is jit-able JAX over arbitrary leading (batch) dimensions; the one
numpy-in/numpy-out helper is `unproject_depth_map_to_point_map`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

# ---------------------------------------------------------------------------------------
# Quaternions
# ---------------------------------------------------------------------------------------


def quat_to_mat(quat: jax.Array) -> jax.Array:
    """Rotation matrices of (not necessarily unit) quaternions.

    quat [..., 4] scalar-last (x, y, z, w) -> [..., 3, 3]. The quaternion is normalised
    implicitly through `2 / |q|^2`, so any non-zero scaling of `quat` gives the same matrix."""
    x, y, z, w = jnp.moveaxis(quat, -1, 0)
    two_s = 2.0 / jnp.sum(quat * quat, axis=-1)
    rows = (
        1 - two_s * (y * y + z * z), two_s * (x * y - z * w), two_s * (x * z + y * w),
        two_s * (x * y + z * w), 1 - two_s * (x * x + z * z), two_s * (y * z - x * w),
        two_s * (x * z - y * w), two_s * (y * z + x * w), 1 - two_s * (x * x + y * y),
    )
    return jnp.stack(rows, axis=-1).reshape(quat.shape[:-1] + (3, 3))


def _sqrt_positive_part(x: jax.Array) -> jax.Array:
    # The inner `where` keeps the gradient finite (zero) where x <= 0.
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


def standardize_quaternion(quat: jax.Array) -> jax.Array:
    """Flip each quaternion [..., 4] (x, y, z, w) to the hemisphere w >= 0 (w == 0 kept)."""
    return jnp.where(quat[..., 3:4] < 0, -quat, quat)


def mat_to_quat(matrix: jax.Array) -> jax.Array:
    """Quaternions of rotation matrices: [..., 3, 3] -> [..., 4] scalar-last, w >= 0.

    Of the four algebraically equivalent formulas (each divides by one of 2|w|, 2|x|,
    2|y|, 2|z|) the one with the largest divisor is used, which keeps it accurate for
    every rotation, as upstream (PyTorch3D's algorithm)."""
    if matrix.shape[-2:] != (3, 3):
        raise ValueError(f"expected rotation matrices [..., 3, 3], got {matrix.shape}")
    m = jnp.moveaxis(matrix.reshape(matrix.shape[:-2] + (9,)), -1, 0)
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = m

    # 2|w|, 2|x|, 2|y|, 2|z| for a unit quaternion, up to the factor 2.
    q_abs = _sqrt_positive_part(jnp.stack([
        1.0 + m00 + m11 + m22,
        1.0 + m00 - m11 - m22,
        1.0 - m00 + m11 - m22,
        1.0 - m00 - m11 + m22,
    ], axis=-1))

    # Row r is the (w, x, y, z) quaternion times 4 * (its r-th component).
    by_wxyz = jnp.stack([
        jnp.stack([q_abs[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], axis=-1),
        jnp.stack([m21 - m12, q_abs[..., 1] ** 2, m10 + m01, m02 + m20], axis=-1),
        jnp.stack([m02 - m20, m10 + m01, q_abs[..., 2] ** 2, m12 + m21], axis=-1),
        jnp.stack([m10 - m01, m20 + m02, m21 + m12, q_abs[..., 3] ** 2], axis=-1),
    ], axis=-2)
    # The floor only avoids division by ~0 in rows that are never selected.
    candidates = by_wxyz / (2.0 * jnp.maximum(q_abs, 0.1)[..., None])

    best = jnp.argmax(q_abs, axis=-1)
    wxyz = jnp.take_along_axis(candidates, best[..., None, None], axis=-2)[..., 0, :]
    return standardize_quaternion(jnp.concatenate([wxyz[..., 1:], wxyz[..., :1]], axis=-1))


# ---------------------------------------------------------------------------------------
# Pose encoding
# ---------------------------------------------------------------------------------------


def pose_encoding_to_extri_intri(pose_enc: jax.Array, image_size_hw: tuple[int, int] | None = None,
                                 build_intrinsics: bool = True) -> tuple[jax.Array, jax.Array | None]:
    """Decode "absT_quaR_FoV" pose encodings.

    pose_enc [B, S, 9] (any leading dims) -> extrinsic [B, S, 3, 4], intrinsic [B, S, 3, 3]
    (None when `build_intrinsics` is False). `image_size_hw` = (H, W) in pixels; the
    principal point is the image centre (W/2, H/2)."""
    t = pose_enc[..., :3]
    rot = quat_to_mat(pose_enc[..., 3:7])
    extrinsic = jnp.concatenate([rot, t[..., None]], axis=-1)
    if not build_intrinsics:
        return extrinsic, None
    if image_size_hw is None:
        raise ValueError("image_size_hw is needed to build intrinsics")
    h, w = image_size_hw
    fy = (h / 2.0) / jnp.tan(pose_enc[..., 7] / 2.0)
    fx = (w / 2.0) / jnp.tan(pose_enc[..., 8] / 2.0)
    zero = jnp.zeros_like(fx)
    one = jnp.ones_like(fx)
    intrinsic = jnp.stack([
        fx, zero, jnp.full_like(fx, w / 2),
        zero, fy, jnp.full_like(fx, h / 2),
        zero, zero, one,
    ], axis=-1).reshape(fx.shape + (3, 3))
    return extrinsic, intrinsic


def extri_intri_to_pose_encoding(extrinsic: jax.Array, intrinsic: jax.Array,
                                 image_size_hw: tuple[int, int]) -> jax.Array:
    """Encode cameras as "absT_quaR_FoV": extrinsic [B, S, 3, 4], intrinsic [B, S, 3, 3]
    (any leading dims), image_size_hw = (H, W) -> [B, S, 9] float32."""
    h, w = image_size_hw
    quat = mat_to_quat(extrinsic[..., :3, :3])
    fov_h = 2.0 * jnp.arctan((h / 2) / intrinsic[..., 1, 1])
    fov_w = 2.0 * jnp.arctan((w / 2) / intrinsic[..., 0, 0])
    enc = jnp.concatenate([extrinsic[..., :3, 3], quat, fov_h[..., None], fov_w[..., None]], axis=-1)
    return enc.astype(jnp.float32)


# ---------------------------------------------------------------------------------------
# SE(3) and depth unprojection
# ---------------------------------------------------------------------------------------


def _matvec(m: jax.Array, v: jax.Array) -> jax.Array:
    """m [..., 3, 3] @ v [..., 3] as an elementwise sum: exact float32 even where XLA
    would lower a tiny matmul to reduced-precision (TF32) units."""
    return jnp.sum(m * v[..., None, :], axis=-1)


def closed_form_inverse_se3(se3: jax.Array) -> jax.Array:
    """Inverse of rigid transforms via `[R^T | -R^T t]`: se3 [..., 3|4, 4] -> [..., 4, 4]."""
    if se3.shape[-2:] not in ((3, 4), (4, 4)):
        raise ValueError(f"expected [..., 3, 4] or [..., 4, 4], got {se3.shape}")
    r_t = jnp.swapaxes(se3[..., :3, :3], -1, -2)
    t_inv = -_matvec(r_t, se3[..., :3, 3])[..., None]
    top = jnp.concatenate([r_t, t_inv], axis=-1)
    bottom = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 0.0, 1.0], se3.dtype), top.shape[:-2] + (1, 4))
    return jnp.concatenate([top, bottom], axis=-2)


def depth_to_cam_points(depth: jax.Array, intrinsic: jax.Array) -> jax.Array:
    """Pinhole unprojection of pixel centres at integer coordinates (u, v) = (col, row).

    depth [..., H, W], intrinsic [..., 3, 3] (zero skew) -> camera points [..., H, W, 3]."""
    h, w = depth.shape[-2:]
    u = jnp.arange(w, dtype=depth.dtype)[None, :]
    v = jnp.arange(h, dtype=depth.dtype)[:, None]

    def k(i, j):
        return intrinsic[..., i, j][..., None, None]

    x = (u - k(0, 2)) * depth / k(0, 0)
    y = (v - k(1, 2)) * depth / k(1, 1)
    return jnp.stack([x, y, depth], axis=-1)


def depth_to_world_points(depth: jax.Array, extrinsic: jax.Array, intrinsic: jax.Array) -> jax.Array:
    """World points of depth maps, as upstream's `unproject_depth_map_to_point_map`.

    depth [..., H, W] or [..., H, W, 1]; extrinsic [..., 3, 4] camera-from-world;
    intrinsic [..., 3, 3]; the leading dims (e.g. S or B, S) of all three agree.
    Returns [..., H, W, 3]. Pixels with depth <= 0 are not masked (upstream returns the
    mask separately; compute `depth > 1e-8` if needed)."""
    n_lead = extrinsic.ndim - 2
    if depth.ndim == n_lead + 3 and depth.shape[-1] == 1:
        depth = depth[..., 0]
    if depth.ndim != n_lead + 2:
        raise ValueError(f"depth {depth.shape} does not match extrinsic {extrinsic.shape}")
    cam = depth_to_cam_points(depth, intrinsic)
    cam_to_world = closed_form_inverse_se3(extrinsic)
    rot = cam_to_world[..., None, None, :3, :3]
    t = cam_to_world[..., None, None, :3, 3]
    return _matvec(rot, cam) + t


def unproject_depth_map_to_point_map(depth_map, extrinsics, intrinsics) -> np.ndarray:
    """numpy-friendly `depth_to_world_points` (upstream's name): depth [S, H, W(, 1)],
    extrinsics [S, 3, 4], intrinsics [S, 3, 3] (numpy, JAX or anything array-like)
    -> np.ndarray [S, H, W, 3] float32."""
    pts = _depth_to_world_points_jit(jnp.asarray(depth_map, jnp.float32), jnp.asarray(extrinsics, jnp.float32),
                                     jnp.asarray(intrinsics, jnp.float32))
    return np.asarray(pts)


_depth_to_world_points_jit = jax.jit(depth_to_world_points)
