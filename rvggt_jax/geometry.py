"""Camera geometry: the 9-d pose encoding, quaternions, SE(3) inverses, depth unprojection.

Conventions are upstream VGGT's:
- extrinsics are camera-from-world `[R | t]` in the OpenCV frame (x right, y down,
  z forward), `[..., 3, 4]`;
- intrinsics are pixel `[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`, `[..., 3, 3]`;
- quaternions are scalar-last `(x, y, z, w)`;
- the pose encoding "absT_quaR_FoV" is `[t (3), quaternion (4), fov_h, fov_w]`, `[..., 9]`.

Everything is jit-able JAX over arbitrary leading (batch) dimensions; the quaternion
functions also take numpy arrays (and return numpy, float64 kept), and
`unproject_depth_map_to_point_map` is numpy-in/numpy-out.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

# ---------------------------------------------------------------------------------------
# Quaternions
# ---------------------------------------------------------------------------------------


def _array_module(x):
    """numpy for numpy input (float64 stays float64: the COLMAP writer needs it), else
    jax.numpy (jit-able)."""
    return np if isinstance(x, np.ndarray) else jnp


def quat_to_mat(quat: jax.Array) -> jax.Array:
    """Rotation matrices of (not necessarily unit) quaternions.

    quat [..., 4] scalar-last (x, y, z, w) -> [..., 3, 3]. The quaternion is normalised
    implicitly through `2 / |q|^2`, so any non-zero scaling of `quat` gives the same matrix.
    numpy in, numpy out (in its dtype); anything else goes through JAX."""
    xp = _array_module(quat)
    x, y, z, w = xp.moveaxis(quat, -1, 0)
    two_s = 2.0 / xp.sum(quat * quat, axis=-1)
    rows = (
        1 - two_s * (y * y + z * z), two_s * (x * y - z * w), two_s * (x * z + y * w),
        two_s * (x * y + z * w), 1 - two_s * (x * x + z * z), two_s * (y * z - x * w),
        two_s * (x * z - y * w), two_s * (y * z + x * w), 1 - two_s * (x * x + y * y),
    )
    return xp.stack(rows, axis=-1).reshape(quat.shape[:-1] + (3, 3))


def standardize_quaternion(quat: jax.Array) -> jax.Array:
    """Flip each quaternion [..., 4] (x, y, z, w) to the hemisphere w >= 0 (w == 0 kept)."""
    return _array_module(quat).where(quat[..., 3:4] < 0, -quat, quat)


def mat_to_quat(matrix: jax.Array) -> jax.Array:
    """Quaternions of rotation matrices: [..., 3, 3] -> [..., 4] scalar-last, w >= 0.

    Shepperd's method: the formula that divides by 4|w| when the trace is positive, else
    the one dividing by 4|x|, 4|y| or 4|z| for the largest diagonal entry, so that the
    divisor is never small. For a rotation this equals upstream's (PyTorch3D's, which picks
    the largest of |w|, |x|, |y|, |z|) up to rounding; it is written this way because the
    COLMAP writer (`rvggt_jax.io.colmap`) uses it in float64 and its files must not change
    by a digit. numpy in, numpy out (in its dtype); anything else goes through JAX. Not
    normalised: a non-orthonormal matrix gives a non-unit quaternion."""
    if matrix.shape[-2:] != (3, 3):
        raise ValueError(f"expected rotation matrices [..., 3, 3], got {matrix.shape}")
    xp = _array_module(matrix)
    m00, m01, m02 = matrix[..., 0, 0], matrix[..., 0, 1], matrix[..., 0, 2]
    m10, m11, m12 = matrix[..., 1, 0], matrix[..., 1, 1], matrix[..., 1, 2]
    m20, m21, m22 = matrix[..., 2, 0], matrix[..., 2, 1], matrix[..., 2, 2]
    trace = m00 + m11 + m22

    def four_times(arg):
        # 4 |component| = 2 sqrt(arg); the floor only keeps branches that are not selected
        # finite (the selected one has arg >= 1 for a rotation).
        return 2.0 * xp.sqrt(xp.maximum(arg, 1e-30))

    s = four_times(trace + 1.0)
    by_w = (0.25 * s, (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s)
    s = four_times(1.0 + m00 - m11 - m22)
    by_x = ((m21 - m12) / s, 0.25 * s, (m01 + m10) / s, (m02 + m20) / s)
    s = four_times(1.0 + m11 - m00 - m22)
    by_y = ((m02 - m20) / s, (m01 + m10) / s, 0.25 * s, (m12 + m21) / s)
    s = four_times(1.0 + m22 - m00 - m11)
    by_z = ((m10 - m01) / s, (m02 + m20) / s, (m12 + m21) / s, 0.25 * s)
    use_w, use_x, use_y = trace > 0, (m00 > m11) & (m00 > m22), m11 > m22
    wxyz = [xp.where(use_w, a, xp.where(use_x, b, xp.where(use_y, c, d))) for a, b, c, d in zip(by_w, by_x, by_y, by_z)]
    return standardize_quaternion(xp.stack(wxyz[1:] + wxyz[:1], axis=-1))


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


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    """The rotation nearest to R [3, 3] (SVD; numpy float64), so that slightly
    non-orthogonal predictions still give a valid quaternion."""
    u, _, vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    r = u @ vt
    if np.linalg.det(r) < 0:
        u[:, -1] *= -1
        r = u @ vt
    return r


def camera_centers(extrinsics: np.ndarray) -> np.ndarray:
    """World positions of the cameras: extrinsics [S, 3, 4] world-to-camera -> [S, 3] (-R^T t)."""
    e = np.asarray(extrinsics, dtype=np.float64)
    return -np.einsum("sji,sj->si", e[:, :3, :3], e[:, :3, 3])
