"""Pose encoding, quaternion and unprojection utilities."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rvggt_jax import geometry
from tests.helpers.heads_params import load_io

RTOL = 1e-4


def rel_err(ours, ref) -> float:
    ours, ref = np.asarray(ours, np.float64), np.asarray(ref, np.float64)
    assert ours.shape == ref.shape, (ours.shape, ref.shape)
    return float(np.max(np.abs(ours - ref)) / np.max(np.abs(ref)))


def random_rotations(n: int, seed: int) -> np.ndarray:
    """[n, 3, 3] proper rotations via QR, plus the awkward ones: identity, 180-degree turns."""
    rng = np.random.default_rng(seed)
    q, r = np.linalg.qr(rng.standard_normal((n, 3, 3)))
    q = q * np.sign(np.diagonal(r, axis1=-2, axis2=-1))[:, None, :]
    q[np.linalg.det(q) < 0, :, 0] *= -1
    special = np.stack([np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])])
    return np.concatenate([q, special]).astype(np.float32)


def test_pose_encoding_to_extri_intri_matches_upstream():
    io = load_io()
    h, w = io["images"].shape[-2:]
    ext, intr = jax.jit(geometry.pose_encoding_to_extri_intri, static_argnums=1)(
        jnp.asarray(io["util_pose_enc"]), (h, w))
    e_ext, e_int = rel_err(ext, io["util_extrinsic"]), rel_err(intr, io["util_intrinsic"])
    print(f"util_extrinsic {e_ext:.3g}, util_intrinsic {e_int:.3g}")
    assert e_ext <= RTOL and e_int <= RTOL
    ext_only, none = jax.jit(geometry.pose_encoding_to_extri_intri, static_argnums=(1, 2))(
        jnp.asarray(io["util_pose_enc"]), None, False)
    assert none is None and rel_err(ext_only, io["util_extrinsic"]) <= RTOL


def test_pose_encoding_round_trip():
    io = load_io()
    hw = io["images"].shape[-2:]
    enc = io["util_pose_enc"].copy()
    # The encoder returns unit quaternions with w >= 0, so compare against that form.
    quat = enc[..., 3:7] / np.linalg.norm(enc[..., 3:7], axis=-1, keepdims=True)
    enc[..., 3:7] = np.where(quat[..., 3:4] < 0, -quat, quat)
    ext, intr = jax.jit(geometry.pose_encoding_to_extri_intri, static_argnums=1)(jnp.asarray(enc), hw)
    back = jax.jit(geometry.extri_intri_to_pose_encoding, static_argnums=2)(ext, intr, hw)
    assert back.dtype == jnp.float32 and back.shape == enc.shape
    assert rel_err(back, enc) <= RTOL


def test_quaternion_matrix_round_trip():
    rots = random_rotations(64, seed=0)
    quat = np.asarray(jax.jit(geometry.mat_to_quat)(jnp.asarray(rots)))
    np.testing.assert_allclose(np.linalg.norm(quat, axis=-1), 1.0, atol=1e-5)
    assert np.all(quat[:, 3] >= 0)
    np.testing.assert_allclose(np.asarray(jax.jit(geometry.quat_to_mat)(jnp.asarray(quat))), rots, atol=1e-5)


def test_quat_to_mat_convention_is_xyzw():
    # 90 degrees about +z, scalar last, scaled by 3 (quat_to_mat normalises implicitly).
    s = np.sqrt(0.5)
    rot = np.asarray(jax.jit(geometry.quat_to_mat)(jnp.asarray([0.0, 0.0, 3 * s, 3 * s])))
    np.testing.assert_allclose(rot, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-6)
    # A negative-w quaternion comes back with w >= 0.
    back = np.asarray(jax.jit(geometry.mat_to_quat)(jnp.asarray(rot)))
    np.testing.assert_allclose(back, [0, 0, s, s], atol=1e-6)


def test_closed_form_inverse_se3():
    rots = random_rotations(5, seed=1)
    n = len(rots)
    t = np.random.default_rng(2).standard_normal((n, 3, 1)).astype(np.float32)
    se3 = np.concatenate([rots, t], axis=-1)
    inverse = jax.jit(geometry.closed_form_inverse_se3)
    inv = np.asarray(inverse(jnp.asarray(se3)))
    full = np.concatenate([se3, np.tile([[[0, 0, 0, 1]]], (n, 1, 1))], axis=1).astype(np.float32)
    np.testing.assert_allclose(inv @ full, np.tile(np.eye(4), (n, 1, 1)), atol=1e-5)
    np.testing.assert_allclose(np.asarray(inverse(jnp.asarray(full))), inv, atol=0)


def _numpy_unproject(depth, ext, intr):
    """Independent per-pixel reference: X_world = R^T (d K^-1 [u, v, 1] - t)."""
    out = np.zeros(depth.shape + (3,))
    for f in range(depth.shape[0]):
        k_inv = np.linalg.inv(intr[f].astype(np.float64))
        rot, t = ext[f, :, :3].astype(np.float64), ext[f, :, 3].astype(np.float64)
        for v in range(depth.shape[1]):
            for u in range(depth.shape[2]):
                cam = depth[f, v, u] * (k_inv @ np.array([u, v, 1.0]))
                out[f, v, u] = rot.T @ (cam - t)
    return out


@pytest.mark.parametrize("trailing_one", [False, True])
def test_depth_to_world_points(trailing_one):
    rng = np.random.default_rng(3)
    s, h, w = 2, 5, 7
    depth = rng.uniform(0.5, 3.0, (s, h, w)).astype(np.float32)
    rots = random_rotations(s, seed=4)[:s]
    ext = np.concatenate([rots, rng.standard_normal((s, 3, 1))], axis=-1).astype(np.float32)
    intr = np.zeros((s, 3, 3), np.float32)
    intr[:, 0, 0], intr[:, 1, 1] = [6.0, 9.0], [7.0, 5.0]
    intr[:, 0, 2], intr[:, 1, 2], intr[:, 2, 2] = w / 2, h / 2, 1.0
    ref = _numpy_unproject(depth, ext, intr)

    d = depth[..., None] if trailing_one else depth
    ours = geometry.unproject_depth_map_to_point_map(d, ext, intr)
    assert isinstance(ours, np.ndarray) and ours.shape == (s, h, w, 3)
    assert rel_err(ours, ref) <= RTOL
    # The jitted JAX entry point with a batch dimension agrees with the numpy wrapper.
    batched = jax.jit(geometry.depth_to_world_points)(jnp.asarray(d[None]), jnp.asarray(ext[None]),
                                                      jnp.asarray(intr[None]))
    assert rel_err(batched[0], ref) <= RTOL
