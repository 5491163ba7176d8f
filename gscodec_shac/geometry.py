"""Quaternion and covariance helpers shared by the generator, codec, renderer and camera files.

Quaternions are (w, x, y, z), as in the Inria PLY. The 3D covariance of a Gaussian
is ``Sigma = R S S^T R^T`` with ``S = diag(exp(log_scales))`` (paper eq. 2).
"""

from __future__ import annotations

import numpy as np


def quat_to_rotmat(quats: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions, w first, any norm -> (..., 3, 3) rotation matrices (zero -> identity)."""
    q = np.asarray(quats, dtype=np.float64)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(norm > 0, q / np.where(norm > 0, norm, 1.0), np.array([1.0, 0.0, 0.0, 0.0]))
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rot = np.empty(q.shape[:-1] + (3, 3))
    rot[..., 0, 0] = 1 - 2 * (y * y + z * z)
    rot[..., 0, 1] = 2 * (x * y - w * z)
    rot[..., 0, 2] = 2 * (x * z + w * y)
    rot[..., 1, 0] = 2 * (x * y + w * z)
    rot[..., 1, 1] = 1 - 2 * (x * x + z * z)
    rot[..., 1, 2] = 2 * (y * z - w * x)
    rot[..., 2, 0] = 2 * (x * z - w * y)
    rot[..., 2, 1] = 2 * (y * z + w * x)
    rot[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return rot


def rotmat_to_quat(rot: np.ndarray) -> np.ndarray:
    """(..., 3, 3) proper rotations -> (..., 4) unit quaternions (w first, w >= 0).

    For a nearly orthonormal matrix the quaternion's rotation is within about
    1.5 x max |R R^T - I| of the nearest rotation.
    """
    m = np.asarray(rot, dtype=np.float64)
    trace = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    # Shepperd's method: pick the largest of 4 candidates for numerical stability.
    cand = np.stack(
        [trace, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], axis=-1
    )
    choice = np.argmax(cand, axis=-1)
    q = np.empty(m.shape[:-2] + (4,))
    for c in range(4):
        sel = choice == c
        if not np.any(sel):
            continue
        r = m[sel]
        if c == 0:
            s = np.sqrt(1.0 + r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2]) * 2
            q[sel] = np.stack([0.25 * s, (r[:, 2, 1] - r[:, 1, 2]) / s, (r[:, 0, 2] - r[:, 2, 0]) / s, (r[:, 1, 0] - r[:, 0, 1]) / s], -1)
        elif c == 1:
            s = np.sqrt(1.0 + r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2]) * 2
            q[sel] = np.stack([(r[:, 2, 1] - r[:, 1, 2]) / s, 0.25 * s, (r[:, 0, 1] + r[:, 1, 0]) / s, (r[:, 0, 2] + r[:, 2, 0]) / s], -1)
        elif c == 2:
            s = np.sqrt(1.0 + r[:, 1, 1] - r[:, 0, 0] - r[:, 2, 2]) * 2
            q[sel] = np.stack([(r[:, 0, 2] - r[:, 2, 0]) / s, (r[:, 0, 1] + r[:, 1, 0]) / s, 0.25 * s, (r[:, 1, 2] + r[:, 2, 1]) / s], -1)
        else:
            s = np.sqrt(1.0 + r[:, 2, 2] - r[:, 0, 0] - r[:, 1, 1]) * 2
            q[sel] = np.stack([(r[:, 1, 0] - r[:, 0, 1]) / s, (r[:, 0, 2] + r[:, 2, 0]) / s, (r[:, 1, 2] + r[:, 2, 1]) / s, 0.25 * s], -1)
    q *= np.where(q[..., :1] < 0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def covariances(log_scales: np.ndarray, quats: np.ndarray) -> np.ndarray:
    """(N, 3, 3) world-space covariances R S S^T R^T (paper eq. 2)."""
    rot = quat_to_rotmat(quats)
    scaled = rot * np.exp(np.asarray(log_scales, dtype=np.float64))[:, None, :]
    return scaled @ np.swapaxes(scaled, -1, -2)


def fibonacci_sphere(n: int) -> np.ndarray:
    """(n, 3) nearly uniform unit directions (deterministic)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
