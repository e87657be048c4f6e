"""Small quaternion / SO(3) helpers for the EKF, following Solà, "Quaternion kinematics for the
error-state Kalman filter" (arXiv:1711.02508): Hamilton quaternions (w, x, y, z), q maps body vectors
into the world (R_world_body = R(q)), local (right) perturbations R_true = R Exp(dtheta).

Hand-written on plain floats/arrays rather than scipy's Rotation because the IMU loop calls them
100-200 times a second and constructing a Rotation object costs ~10-20 us each.
"""

from __future__ import annotations

import math

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """3x3 matrix [v]x with [v]x @ w = v x w."""
    x, y, z = np.asarray(v, float).tolist()
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p (x) q of (4,) quaternions (w, x, y, z)."""
    # Python floats: the same IEEE arithmetic without the numpy-scalar overhead (IMU-rate code)
    pw, px, py, pz = np.asarray(p, float).tolist()
    qw, qx, qy, qz = np.asarray(q, float).tolist()
    return np.array(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ]
    )


def quat_exp(theta: np.ndarray) -> np.ndarray:
    """(4,) unit quaternion Exp(theta) of a rotation vector (3,) in radians."""
    t0, t1, t2 = np.asarray(theta, float).tolist()
    a = math.sqrt(t0**2 + t1**2 + t2**2)
    if a < 1e-10:
        return np.array([1.0, 0.5 * t0, 0.5 * t1, 0.5 * t2])
    s = math.sin(0.5 * a) / a
    return np.array([math.cos(0.5 * a), s * t0, s * t1, s * t2])


def quat_normalised(q: np.ndarray) -> np.ndarray:
    """q / |q| with w >= 0 (the same rotation)."""
    n = math.sqrt(float(q @ q))  # not np.linalg.norm: this runs at the IMU rate, where its overhead shows
    return q * (-1.0 / n) if q[0] < 0 else q * (1.0 / n)


def rot_from_quat(q: np.ndarray) -> np.ndarray:
    """3x3 rotation matrix of a unit quaternion (w, x, y, z)."""
    w, x, y, z = np.asarray(q, float).tolist()
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_from_rot(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of a 3x3 rotation matrix (Shepperd's method)."""
    t = np.trace(R)
    if t > 0:
        s = 2.0 * math.sqrt(1.0 + t)
        q = np.array([0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s])
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = np.array([(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s])
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = np.array([(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s])
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = np.array([(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s])
    return quat_normalised(q)


def rot_exp(theta: np.ndarray) -> np.ndarray:
    """3x3 rotation Exp(theta) (Rodrigues) of a rotation vector (3,)."""
    a = math.sqrt(float(theta[0] ** 2 + theta[1] ** 2 + theta[2] ** 2))
    K = skew(theta)
    if a < 1e-8:
        return np.eye(3) + K
    return np.eye(3) + (math.sin(a) / a) * K + ((1.0 - math.cos(a)) / (a * a)) * (K @ K)


def rot_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector (3,) of a 3x3 rotation matrix (inverse of rot_exp for angles < pi)."""
    c = min(1.0, max(-1.0, 0.5 * (np.trace(R) - 1.0)))
    a = math.acos(c)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if a < 1e-8:
        return 0.5 * w
    if a > math.pi - 1e-6:
        # near pi: axis from the symmetric part
        B = 0.5 * (R + np.eye(3))
        axis = np.sqrt(np.clip(np.diag(B), 0.0, None))
        i = int(np.argmax(axis))
        axis = B[i] / axis[i]
        return a * axis / np.linalg.norm(axis)
    return (a / (2.0 * math.sin(a))) * w


def euler_rate_matrix(rpy: np.ndarray) -> np.ndarray:
    """3x3 W with d(roll, pitch, yaw) = W @ dtheta_body (intrinsic ZYX Euler angles).

    Used to map the filter's local attitude covariance (body-frame dtheta) to roll/pitch/yaw.
    """
    r, p = rpy[0], rpy[1]
    cr, sr, cp = math.cos(r), math.sin(r), math.cos(p)
    cp = cp if abs(cp) > 1e-6 else math.copysign(1e-6, cp)
    tp = math.sin(p) / cp
    return np.array([[1.0, sr * tp, cr * tp], [0.0, cr, -sr], [0.0, sr / cp, cr / cp]])
