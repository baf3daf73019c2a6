"""Scalar building blocks of the AHRS (estimators/ahrs.py), written once in plain floats for the
per-sample path; estimators/ahrs_batch.py has the vectorised twins with the same formulas in the
same order, so both forms agree to round-off."""
from __future__ import annotations

import math

REJECT, ACCEPT = 0, 1      # block variants: the stage uses its measurement or holds on the gyro
TWO_PI = 2.0 * math.pi
SERIES_MAX_RAD = 0.05     # below this the Rodrigues coefficients come from their Taylor series


def rodrigues(tx: float, ty: float, tz: float) -> tuple[float, float, float]:
    """(cos a, sin a / a, (1 − cos a)/a²) for a = |θ|: R(−θ) v = cos·v − sinc·(θ×v) + vers·(θ·v)θ.
    Below ``SERIES_MAX_RAD`` the Taylor series to a⁶ (truncation < 2e-16), so the common small
    steps need no sqrt/sin/cos."""
    a2 = tx * tx + ty * ty + tz * tz
    if a2 < SERIES_MAX_RAD * SERIES_MAX_RAD:
        return (1.0 - a2 * (0.5 - a2 * (1.0 / 24.0 - a2 * (1.0 / 720.0 - a2 / 40320.0))),
                1.0 - a2 * (1.0 / 6.0 - a2 * (1.0 / 120.0 - a2 / 5040.0)),
                0.5 - a2 * (1.0 / 24.0 - a2 * (1.0 / 720.0 - a2 / 40320.0)))
    a = math.sqrt(a2)
    c = math.cos(a)
    return c, math.sin(a) / a, (1.0 - c) / a2


def rotate(v: list, tx, ty, tz, c, s, w) -> None:
    """v ← R(−θ) v in place (v a 3-list); coefficients from ``rodrigues``."""
    vx, vy, vz = v
    d = w * (tx * vx + ty * vy + tz * vz)
    v[0] = c * vx - s * (ty * vz - tz * vy) + d * tx
    v[1] = c * vy - s * (tz * vx - tx * vz) + d * ty
    v[2] = c * vz - s * (tx * vy - ty * vx) + d * tz


def measurement_gain(gain_per_s: float, interval_s: float, since_init_s: float) -> float:
    """g = max(1 − exp(−k Δt), Δt/(t − t_init + Δt)): the filter gain, or the running mean just after
    (re)initialisation when that is larger (Fusion's start-up ramp, by time); 0 for Δt ≤ 0."""
    if interval_s <= 0.0:
        return 0.0
    g = -math.expm1(-gain_per_s * interval_s)
    if since_init_s > 0.0:
        g = max(g, interval_s / (since_init_s + interval_s))
    return g


def attitude_from_vectors(g, m, latest) -> tuple[float, float, float, float]:
    """(roll, pitch, magnetic heading of m, heading of ``latest``) [rad, headings in [0, 2π)] from a
    body-frame specific force g and fields (seed 000 sec. 2.2 and eqs. 11–13, the formulas of
    roll_pitch_from_specific_force and tilt_compensated_heading_rad)."""
    gx, gy, gz = g
    roll = math.atan2(-gy, -gz)
    pitch = math.atan2(gx, math.hypot(gy, gz))
    sr, cr, sp, cp = math.sin(roll), math.cos(roll), math.sin(pitch), math.cos(pitch)
    spsr, spcr = sp * sr, sp * cr
    h1 = math.atan2(-(m[1] * cr - m[2] * sr), m[0] * cp + m[1] * spsr + m[2] * spcr) % TWO_PI
    h2 = math.atan2(-(latest[1] * cr - latest[2] * sr), latest[0] * cp + latest[1] * spsr + latest[2] * spcr) % TWO_PI
    return roll, pitch, (0.0 if h1 >= TWO_PI else h1 + 0.0), (0.0 if h2 >= TWO_PI else h2 + 0.0)
