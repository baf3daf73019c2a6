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


def wrap_heading_rad(angle_rad):
    """Heading in [0, 2π) radians (vectorised).  ``np.mod(-1e-18, 2π)`` rounds to 2π itself and
    ``np.mod(-0.0, …)`` keeps the sign; both are folded to +0.0 here."""
    a = np.mod(np.asarray(angle_rad, dtype=float), TWO_PI)
    return np.where(a >= TWO_PI, 0.0, a) + 0.0


def wrap_heading_deg(angle_deg):
    """Heading in [0, 360) degrees (vectorised); see ``wrap_heading_rad``."""
    a = np.mod(np.asarray(angle_deg, dtype=float), 360.0)
    return np.where(a >= 360.0, 0.0, a) + 0.0


def wrap_heading_rad_float(angle_rad: float) -> float:
    """``wrap_heading_rad`` for one plain float (the per-sample paths)."""
    a = angle_rad % TWO_PI
    return 0.0 if a >= TWO_PI else a + 0.0


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


def quaternion_from_dcm(c) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w ≥ 0, of a rotation matrix C (…, 3, 3) with v' = C v
    (Hamilton convention: C = R(q), q ⊗ v ⊗ q* = C v).  Shepperd's method: the largest of
    4w², 4x², 4y², 4z² (from the trace and the diagonal) picks the numerically safe formula."""
    c = np.asarray(c, dtype=float)
    tr = c[..., 0, 0] + c[..., 1, 1] + c[..., 2, 2]
    cand = np.stack([1.0 + tr, 1.0 + 2.0 * c[..., 0, 0] - tr, 1.0 + 2.0 * c[..., 1, 1] - tr,
                     1.0 + 2.0 * c[..., 2, 2] - tr], -1)           # 4w², 4x², 4y², 4z²
    k = np.argmax(cand, axis=-1)
    r = np.sqrt(np.maximum(np.take_along_axis(cand, k[..., None], -1)[..., 0], 1e-300))
    d21, d02, d10 = c[..., 2, 1] - c[..., 1, 2], c[..., 0, 2] - c[..., 2, 0], c[..., 1, 0] - c[..., 0, 1]
    s21, s02, s10 = c[..., 2, 1] + c[..., 1, 2], c[..., 0, 2] + c[..., 2, 0], c[..., 1, 0] + c[..., 0, 1]
    q = np.select([k[..., None] == i for i in range(4)], [
        np.stack([r, d21 / r, d02 / r, d10 / r], -1), np.stack([d21 / r, r, s10 / r, s02 / r], -1),
        np.stack([d02 / r, s10 / r, r, s21 / r], -1), np.stack([d10 / r, s02 / r, s21 / r, r], -1)]) / 2.0
    q = np.where(q[..., :1] < 0.0, -q, q)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def dcm_from_quaternion(q) -> np.ndarray:
    """Rotation matrix (…, 3, 3) of a quaternion (w, x, y, z) (normalised first); inverse of
    ``quaternion_from_dcm``."""
    q = np.asarray(q, dtype=float)
    w, x, y, z = np.moveaxis(q / np.linalg.norm(q, axis=-1, keepdims=True), -1, 0)
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def quaternion_multiply(q1, q2) -> np.ndarray:
    """Hamilton product q1 ⊗ q2 of (…, 4) arrays (w, x, y, z); R(q1 ⊗ q2) = R(q1) R(q2)."""
    a = np.asarray(q1, dtype=float)
    b = np.asarray(q2, dtype=float)
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], -1)


def earth_frame_errors_rad(q_est, q_ref) -> tuple[np.ndarray, np.ndarray]:
    """Heading and inclination error [rad] of estimated vs reference orientations (…, 4), both
    body → the same earth frame with a vertical third axis (ENU or NED).

    The error quaternion in the earth frame q_e = q_est ⊗ q_ref* is split into a rotation about
    the vertical (heading, 2·atan(|z/w|)) and the rest (inclination, 2·acos(√(w² + z²))): the
    metric of the BROAD benchmark (Laidig et al., Data 6(7):72, 2021, sec. 4; its broad_utils.py).
    Rows with non-finite input give NaN."""
    e = quaternion_multiply(q_est, np.asarray(q_ref, dtype=float) * np.array([1.0, -1.0, -1.0, -1.0]))
    with np.errstate(invalid="ignore", divide="ignore"):
        e = e / np.linalg.norm(e, axis=-1, keepdims=True)
        heading = 2.0 * np.arctan(np.abs(e[..., 3] / e[..., 0]))
        incl = 2.0 * np.arccos(np.clip(np.sqrt(e[..., 0] ** 2 + e[..., 3] ** 2), 0.0, 1.0))
    return heading, incl


def dcm_body_to_ned_float(roll_rad: float, pitch_rad: float, yaw_rad: float) -> tuple[float, ...]:
    """``dcm_body_to_ned`` for one attitude in plain floats (the per-sample paths): the nine
    elements of C_b^n row by row (c11, c12, c13, c21, ..., c33)."""
    cr, sr, cp, sp = math.cos(roll_rad), math.sin(roll_rad), math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return (cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy,
            cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy,
            -sp, sr * cp, cr * cp)
