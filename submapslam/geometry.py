"""SE(2)/SE(3) helpers on plain numpy arrays.

Poses are ``(4, 4)`` float64 homogeneous matrices (or stacks ``(N, 4, 4)``). A pose named
``T_a_b`` maps points from frame ``b`` into frame ``a``: ``p_a = T_a_b @ p_b``.
Planar poses are ``(x, y, theta)`` triples embedded with z = 0 and roll = pitch = 0.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]


def se2_to_matrix(x: float, y: float, theta: float) -> Array:
    """Planar pose ``(x, y, theta)`` -> ``(4, 4)`` SE(3) matrix with z = 0."""
    c, s = np.cos(theta), np.sin(theta)
    T = np.eye(4)
    T[0, 0], T[0, 1], T[1, 0], T[1, 1] = c, -s, s, c
    T[0, 3], T[1, 3] = x, y
    return T


def se2_array_to_matrices(xyt: ArrayLike) -> Array:
    """``(N, 3)`` planar poses -> ``(N, 4, 4)`` matrices."""
    xyt = np.asarray(xyt, dtype=np.float64).reshape(-1, 3)
    c, s = np.cos(xyt[:, 2]), np.sin(xyt[:, 2])
    T = np.tile(np.eye(4), (len(xyt), 1, 1))
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    T[:, 0, 3], T[:, 1, 3] = xyt[:, 0], xyt[:, 1]
    return T


def matrix_to_se2(T: ArrayLike) -> Array:
    """``(4, 4)`` or ``(N, 4, 4)`` -> ``(3,)`` or ``(N, 3)`` planar ``(x, y, yaw)``."""
    T = np.asarray(T, dtype=np.float64)
    yaw = np.arctan2(T[..., 1, 0], T[..., 0, 0])
    return np.stack([T[..., 0, 3], T[..., 1, 3], yaw], axis=-1)


def wrap_angle(a: ArrayLike) -> Array:
    """Wrap angles to ``[-pi, pi)``."""
    return (np.asarray(a, dtype=np.float64) + np.pi) % (2 * np.pi) - np.pi


def inverse(T: ArrayLike) -> Array:
    """Inverse of one ``(4, 4)`` rigid transform or a stack ``(N, 4, 4)``."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape == (4, 4):  # the common single pose, without the stack machinery
        Ti = np.eye(4)
        Rt = T[:3, :3].T
        Ti[:3, :3] = Rt
        Ti[:3, 3] = -(Rt @ T[:3, 3])
        return Ti
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    Ti[..., 3, 3] = 1.0
    return Ti


def relative(T_w_a: ArrayLike, T_w_b: ArrayLike) -> Array:
    """``T_a_b = T_w_a^-1 @ T_w_b`` (broadcasts over stacks)."""
    return inverse(T_w_a) @ np.asarray(T_w_b, dtype=np.float64)


def transform_points(T: ArrayLike, points: ArrayLike) -> Array:
    """Apply ``(4, 4)`` transform to ``(N, 3)`` points."""
    T = np.asarray(T, dtype=np.float64)
    P = np.asarray(points, dtype=np.float64)
    return P @ T[:3, :3].T + T[:3, 3]


def skew(v: ArrayLike) -> Array:
    """``(3,)`` -> ``(3, 3)`` cross-product matrix."""
    x, y, z = np.asarray(v, dtype=np.float64)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def so3_exp(w: ArrayLike) -> Array:
    """Rodrigues: rotation vector ``(3,)`` -> ``(3, 3)`` rotation matrix."""
    w = np.asarray(w, dtype=np.float64)
    th = float(np.linalg.norm(w))
    K = skew(w)
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(th) / th * K + (1 - np.cos(th)) / th**2 * (K @ K)


def so3_log(R: ArrayLike) -> Array:
    """``(3, 3)`` rotation -> rotation vector ``(3,)``."""
    R = np.asarray(R, dtype=np.float64)
    cos = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    th = np.arccos(cos)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if th < 1e-9:
        return 0.5 * v
    if np.pi - th < 1e-6:
        # near pi: take the axis from the symmetric part
        A = (R + np.eye(3)) / 2.0
        axis = np.sqrt(np.clip(np.diag(A), 0.0, None))
        i = int(np.argmax(axis))
        axis = A[i] / axis[i]
        return th * axis / np.linalg.norm(axis)
    return th / (2.0 * np.sin(th)) * v


def pose_difference(T: ArrayLike) -> Array:
    """``(4, 4)`` small relative pose -> ``(6,)`` its rotation vector and translation, GTSAM order
    ``(rx, ry, rz, tx, ty, tz)`` [rad, m]: the error of a pose against another, ``T = T_a^-1 T_b``."""
    T = np.asarray(T, dtype=np.float64)
    return np.concatenate([so3_log(T[:3, :3]), T[:3, 3]])


def rotation_between(a: ArrayLike, b: ArrayLike) -> Array:
    """``(3, 3)`` smallest rotation taking unit vector ``a`` ``(3,)`` onto unit vector ``b`` ``(3,)``."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    axis = np.cross(a, b)
    s = float(np.linalg.norm(axis))
    if s < 1e-12:
        return np.eye(3)  # parallel (opposite vectors do not occur for two ups)
    return so3_exp(axis / s * np.arctan2(s, float(a @ b)))


def rotation_angle(R: ArrayLike) -> float:
    """Angle (rad) of a ``(3, 3)`` rotation or of the rotation part of a ``(4, 4)`` pose."""
    R = np.asarray(R, dtype=np.float64)[:3, :3]
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def quat_to_matrix(q_xyzw: ArrayLike) -> Array:
    """Quaternion ``(qx, qy, qz, qw)`` -> ``(3, 3)`` rotation (normalises first)."""
    x, y, z, w = np.asarray(q_xyzw, dtype=np.float64) / np.linalg.norm(q_xyzw)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(R: ArrayLike) -> Array:
    """``(3, 3)`` rotation -> unit quaternion ``(qx, qy, qz, qw)`` with ``qw >= 0``."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = np.array([(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, s / 4])
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = np.array([s / 4, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s])
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = np.array([(R[0, 1] + R[1, 0]) / s, s / 4, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s])
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = np.array([(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, s / 4, (R[1, 0] - R[0, 1]) / s])
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def pose_from_xyz_quat(xyz: ArrayLike, q_xyzw: ArrayLike) -> Array:
    """Translation ``(3,)`` and quaternion ``(qx, qy, qz, qw)`` -> ``(4, 4)``."""
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(q_xyzw)
    T[:3, 3] = np.asarray(xyz, dtype=np.float64)
    return T


def poses_from_xyz_quats(xyz: ArrayLike, q_xyzw: ArrayLike) -> Array:
    """:func:`pose_from_xyz_quat` for many: ``(N, 3)`` translations, ``(N, 4)`` quaternions ->
    ``(N, 4, 4)`` (each quaternion normalised first)."""
    q = np.asarray(q_xyzw, dtype=np.float64).reshape(-1, 4)
    x, y, z, w = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    T = np.tile(np.eye(4), (len(q), 1, 1))
    T[:, 0, 0], T[:, 0, 1], T[:, 0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)
    T[:, 1, 0], T[:, 1, 1], T[:, 1, 2] = 2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)
    T[:, 2, 0], T[:, 2, 1], T[:, 2, 2] = 2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)
    T[:, :3, 3] = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    return T


def se3_exp(xi: ArrayLike) -> Array:
    """Twist ``(6,)`` = (rho, phi) (translation first) -> ``(4, 4)``, first-order coupled."""
    xi = np.asarray(xi, dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = so3_exp(xi[3:])
    T[:3, 3] = xi[:3]
    return T


def blend_poses(T_a: ArrayLike, T_b: ArrayLike, alpha: float) -> Array:
    """Pose ``alpha`` of the way from ``T_a`` to ``T_b`` (``(4, 4)``): rotation along the geodesic,
    translation linear. ``alpha`` 0 gives ``T_a``, 1 gives ``T_b``."""
    return blend_poses_many(T_a, T_b, [alpha])[0]


def blend_poses_many(T_a: ArrayLike, T_b: ArrayLike, alphas: ArrayLike) -> Array:
    """:func:`blend_poses` for many ``alphas`` ``(N,)`` at once: ``(N, 4, 4)``."""
    T_a, T_b = np.asarray(T_a, dtype=np.float64), np.asarray(T_b, dtype=np.float64)
    alphas = np.asarray(alphas, dtype=np.float64).reshape(-1)
    w = so3_log(T_a[:3, :3].T @ T_b[:3, :3])
    th = float(np.linalg.norm(w))
    K = skew(w)
    a = alphas[:, None, None]
    if th < 1e-12:
        R_rel = np.eye(3) + a * K
    else:  # Rodrigues of alpha * w: sin and (1 - cos) of alpha * th on the unit axis
        Ku = K / th
        R_rel = np.eye(3) + np.sin(a * th) * Ku + (1 - np.cos(a * th)) * (Ku @ Ku)
    out = np.tile(np.eye(4), (len(alphas), 1, 1))
    out[:, :3, :3] = T_a[:3, :3] @ R_rel
    out[:, :3, 3] = (1.0 - alphas)[:, None] * T_a[:3, 3] + alphas[:, None] * T_b[:3, 3]
    return out


def splice_height_and_tilt(T_level: ArrayLike, T_tilt: ArrayLike) -> Array:
    """``(4, 4)`` pose with x, y and yaw of ``T_level`` and z, roll and pitch of ``T_tilt`` (yaw-pitch-roll
    order, ``R = Rz(yaw) Ry(pitch) Rx(roll)``; both ``(4, 4)`` in the same frame, z up)."""
    from scipy.spatial.transform import Rotation

    yaw = Rotation.from_matrix(np.asarray(T_level, dtype=np.float64)[:3, :3]).as_euler("ZYX")[0]
    _, pitch, roll = Rotation.from_matrix(np.asarray(T_tilt, dtype=np.float64)[:3, :3]).as_euler("ZYX")
    out = np.eye(4)
    out[:3, :3] = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()
    out[:2, 3] = np.asarray(T_level)[:2, 3]
    out[2, 3] = np.asarray(T_tilt)[2, 3]
    return out


def is_planar(T: ArrayLike, tol: float = 1e-6) -> bool:
    """True when a pose (or stack) has z = 0 and rotates about z only."""
    T = np.asarray(T, dtype=np.float64)
    return bool(
        np.all(np.abs(T[..., 2, 3]) < tol)
        and np.all(np.abs(T[..., 2, :2]) < tol)
        and np.all(np.abs(T[..., :2, 2]) < tol)
    )


def adjoint(T: np.ndarray) -> np.ndarray:
    """``(6, 6)`` adjoint of a pose in GTSAM's tangent order ``(rx, ry, rz, tx, ty, tz)``."""
    R, t = T[:3, :3], T[:3, 3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = R
    Ad[3:, 3:] = R
    Ad[3:, :3] = skew(t) @ R
    return Ad
