"""Rotation helpers shared by every estimator: one definition of each convention.

Frames: NED navigation frame, FRD body frame.  Euler angles are ZYX (yaw ψ, then pitch θ, then
roll φ), so C_b^n = Rz(ψ) · Ry(θ) · Rx(φ) maps body vectors into NED (seed 002 eq. 1; the same
convention as MAVLink ATTITUDE).  All angles in radians unless the name says ``_deg``.
"""
from __future__ import annotations

import math

import numpy as np

TWO_PI = 2.0 * np.pi


def wrap_angle_deg(angle_deg):
    """Wrap to (−180, 180] degrees (vectorised)."""
    a = np.mod(np.asarray(angle_deg, dtype=float) + 180.0, 360.0) - 180.0
    return np.where(a == -180.0, 180.0, a)


def wrap_angle_rad(angle_rad):
    """Wrap to (−π, π] radians (vectorised)."""
    a = np.mod(np.asarray(angle_rad, dtype=float) + np.pi, TWO_PI) - np.pi
    return np.where(a == -np.pi, np.pi, a)


def skew(v: np.ndarray) -> np.ndarray:
    """[v ×], the cross-product matrix: skew(a) @ b == a × b."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def dcm_body_to_ned(roll_rad, pitch_rad, yaw_rad) -> np.ndarray:
    """C_b^n = Rz(yaw) Ry(pitch) Rx(roll) from ZYX Euler angles; vectorised -> (..., 3, 3)."""
    r, p, y = (np.asarray(a, dtype=float) for a in (roll_rad, pitch_rad, yaw_rad))
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.stack([
        np.stack([cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy], -1),
        np.stack([cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy], -1),
        np.stack([-sp, sr * cp, cr * cp], -1)], -2)


def euler_from_dcm(c_body_to_ned: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(roll, pitch, yaw) [rad] from C_b^n (…, 3, 3); yaw in (−π, π]."""
    c = np.asarray(c_body_to_ned, dtype=float)
    roll = np.arctan2(c[..., 2, 1], c[..., 2, 2])
    pitch = -np.arcsin(np.clip(c[..., 2, 0], -1.0, 1.0))
    yaw = np.arctan2(c[..., 1, 0], c[..., 0, 0])
    return roll, pitch, yaw


def rotation_from_vector_rad(phi) -> np.ndarray:
    """exp([φ ×]) by Rodrigues' formula: R = I + (sin a/a)·K + ((1 − cos a)/a²)·K², a = |φ|,
    K = [φ ×]; Taylor series of both coefficients for small a.  Written out in scalars: the INS
    calls it at every IMU step."""
    x, y, z = (float(v) for v in phi)
    a2 = x * x + y * y + z * z
    if a2 < 1e-6:
        s, c = 1.0 - a2 / 6.0, 0.5 - a2 / 24.0
    else:
        a = math.sqrt(a2)
        s, c = math.sin(a) / a, (1.0 - math.cos(a)) / a2
    return np.array([[1.0 - c * (y * y + z * z), c * x * y - s * z, c * x * z + s * y],
                     [c * x * y + s * z, 1.0 - c * (x * x + z * z), c * y * z - s * x],
                     [c * x * z - s * y, c * y * z + s * x, 1.0 - c * (x * x + y * y)]])


def rotation_to_vector_deg(R: np.ndarray) -> np.ndarray:
    """Rotation vector [deg] of a rotation matrix (log map); for small angles the (φx, φy, φz)
    of R ≈ I + [φ ×]."""
    R = np.asarray(R, dtype=float)
    th = np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if th < 1e-9:
        return np.degrees(w / 2.0)
    if np.pi - th < 1e-6:  # 180°: the axis comes from the symmetric part
        b = (R + np.eye(3)) / 2.0
        axis = np.sqrt(np.maximum(np.diag(b), 0.0))
        i = int(np.argmax(axis))
        axis = b[i] / max(axis[i], 1e-12)
        return np.degrees(axis / np.linalg.norm(axis) * th)
    return np.degrees(w * th / (2.0 * np.sin(th)))
