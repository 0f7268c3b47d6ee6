"""Small rigid-body helpers (rotation vectors, quaternions, 4x4 poses) in plain NumPy.

Kept dependency-free and vectorised so the runtime can evaluate link poses every loop tick without
SciPy's per-call overhead. Quaternions are ``(w, x, y, z)``; rotation vectors are axis times angle (rad).
"""

from __future__ import annotations

import math

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """The cross-product matrix of a 3-vector."""
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def rotvec_to_matrix(r: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues); works on ``(3,)`` or ``(n, 3)``."""
    r = np.asarray(r, dtype=float)
    if r.ndim == 1:  # fast path for one vector
        theta = math.sqrt(float(r @ r))
        if theta < 1e-8:
            a, b = 1.0 - theta**2 / 6.0, 0.5 - theta**2 / 24.0
        else:
            a, b = math.sin(theta) / theta, (1.0 - math.cos(theta)) / theta**2
        K = skew(r)
        return np.eye(3) + a * K + b * (K @ K)
    single = False
    rv = r.reshape(-1, 3)
    theta = np.linalg.norm(rv, axis=1)
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    # sin(t)/t and (1-cos t)/t^2 with series fallbacks near zero
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    x, y, z = rv[:, 0], rv[:, 1], rv[:, 2]
    zero = np.zeros_like(x)
    K = np.stack([np.stack([zero, -z, y], -1), np.stack([z, zero, -x], -1), np.stack([-y, x, zero], -1)], -2)
    R = np.eye(3)[None] + a[:, None, None] * K + b[:, None, None] * (K @ K)
    return R[0] if single else R


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix (angle below pi); works on ``(3, 3)`` or ``(n, 3, 3)``."""
    return quat_to_rotvec(matrix_to_quat(R))


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a (not necessarily unit) quaternion ``(w, x, y, z)``; ``(4,)`` or ``(n, 4)``."""
    q = np.asarray(q, dtype=float)
    if q.ndim == 1:  # fast path for one quaternion
        w, x, y, z = q / math.sqrt(float(q @ q))
        return np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ])
    single = False
    qq = q.reshape(-1, 4)
    qq = qq / np.linalg.norm(qq, axis=1, keepdims=True)
    w, x, y, z = qq.T
    R = np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )
    return R[0] if single else R


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` with ``w >= 0`` of a rotation matrix; ``(3, 3)`` or ``(n, 3, 3)``."""
    R = np.asarray(R, dtype=float)
    single = R.ndim == 2
    M = R.reshape(-1, 3, 3)
    n = M.shape[0]
    q = np.empty((n, 4))
    tr = np.trace(M, axis1=1, axis2=2)
    for i in range(n):
        m = M[i]
        if tr[i] > 0:
            s = 2.0 * np.sqrt(tr[i] + 1.0)
            q[i] = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
        elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
            q[i] = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
        elif m[1, 1] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
            q[i] = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
            q[i] = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1.0
    return q[0] if single else q


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    """Rotation vector of a quaternion ``(w, x, y, z)``; ``(4,)`` or ``(n, 4)``."""
    q = np.asarray(q, dtype=float)
    single = q.ndim == 1
    qq = q.reshape(-1, 4) / np.linalg.norm(q.reshape(-1, 4), axis=1, keepdims=True)
    qq = np.where(qq[:, :1] < 0, -qq, qq)
    w = np.clip(qq[:, 0], -1.0, 1.0)
    v = qq[:, 1:]
    s = np.linalg.norm(v, axis=1)
    angle = 2.0 * np.arctan2(s, w)
    small = s < 1e-12
    factor = np.where(small, 2.0, angle / np.where(small, 1.0, s))
    r = v * factor[:, None]
    return r[0] if single else r


def rotvec_to_quat(r: np.ndarray) -> np.ndarray:
    """Quaternion ``(w, x, y, z)`` of a rotation vector; ``(3,)`` or ``(n, 3)``."""
    r = np.asarray(r, dtype=float)
    single = r.ndim == 1
    rv = r.reshape(-1, 3)
    theta = np.linalg.norm(rv, axis=1)
    half = 0.5 * theta
    small = theta < 1e-12
    k = np.where(small, 0.5, np.sin(half) / np.where(small, 1.0, theta))
    q = np.concatenate([np.cos(half)[:, None], rv * k[:, None]], axis=1)
    return q[0] if single else q


def pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """A 4x4 homogeneous transform from a rotation matrix and a translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    R = T[:3, :3]
    return pose(R.T, -R.T @ T[:3, 3])


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Angle (rad) of a rotation matrix or a stack of them."""
    tr = np.trace(np.asarray(R), axis1=-2, axis2=-1)
    return np.arccos(np.clip(0.5 * (tr - 1.0), -1.0, 1.0))
