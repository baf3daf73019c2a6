"""Unit conversions of the MAVLink messages into the internal units (groundstation/samples.py).

One function each, written with numpy ufuncs: ``decode.MavlinkDecoder`` calls them with the
scalars of one message, the .tlog reader (logs/mavlink_columns.py) with whole columns, so both
give the same numbers.  Units as the MAVLink XML defines them.
"""
from __future__ import annotations

import numpy as np

__all__ = ["G_MPS2", "scaled_imu_to_si", "normalised_quaternion", "euler_from_quaternion", "gps_raw_int_to_si",
           "global_position_int_to_si", "vfr_hud_throttle", "sys_status_current_A"]

G_MPS2 = 9.80665


def scaled_imu_to_si(gyro_mrad_s, acc_mG) -> tuple[np.ndarray, np.ndarray]:
    """RAW_IMU / SCALED_IMUn: gyro mrad/s -> rad/s, acceleration milli-g -> m/s^2 (x 1e-3 x g)."""
    return np.asarray(gyro_mrad_s, dtype=float) * 1e-3, np.asarray(acc_mG, dtype=float) * 1e-3 * G_MPS2


def normalised_quaternion(q1, q2, q3, q4) -> tuple[np.ndarray, np.ndarray]:
    """(q / |q| as a (..., 4) array, valid) for ATTITUDE_QUATERNION: valid where every component
    is finite and 0.5 < |q| < 1.5 (|q| = sqrt(q1^2 + q2^2 + q3^2 + q4^2))."""
    q = np.stack([np.asarray(v, dtype=float) for v in (q1, q2, q3, q4)], axis=-1)
    with np.errstate(invalid="ignore", over="ignore"):
        norm = np.sqrt(q[..., 0] * q[..., 0] + q[..., 1] * q[..., 1] + q[..., 2] * q[..., 2] + q[..., 3] * q[..., 3])
        norm = np.where(np.isfinite(q).all(axis=-1), norm, 0.0)
        valid = (norm > 0.5) & (norm < 1.5)
        return q / np.where(valid, norm, 1.0)[..., None], valid


def euler_from_quaternion(w, x, y, z) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ZYX Euler angles (roll, pitch, yaw) in rad of a unit body-to-NED quaternion:
    roll = atan2(2(wx + yz), 1 - 2(x^2 + y^2)), pitch = asin(clip(2(wy - zx), -1, 1)),
    yaw = atan2(2(wz + xy), 1 - 2(y^2 + z^2))."""
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def gps_raw_int_to_si(lat_degE7, lon_degE7, alt_mm, vel_cm_s, cog_cdeg) -> tuple[np.ndarray, ...]:
    """GPS_RAW_INT -> lat deg, lon deg, alt m, (vn, ve, vd) m/s: ground speed vel (cm/s) along
    course cog (cdeg), each 65535 when unknown (NaN); vd is not sent (NaN)."""
    vel, cog = np.asarray(vel_cm_s), np.asarray(cog_cdeg)
    speed = np.where(vel != 65535, vel * 0.01, np.nan)
    course = np.where(cog != 65535, np.radians(cog * 0.01), np.nan)
    lat, lon, alt = (np.asarray(v) * k for v, k in ((lat_degE7, 1e-7), (lon_degE7, 1e-7), (alt_mm, 1e-3)))
    return lat, lon, alt, speed * np.cos(course), speed * np.sin(course), np.full(np.shape(speed), np.nan)


def global_position_int_to_si(lat_degE7, lon_degE7, alt_mm, vx_cm_s, vy_cm_s, vz_cm_s) -> tuple[np.ndarray, ...]:
    """GLOBAL_POSITION_INT -> lat deg, lon deg, alt m (AMSL), vn, ve, vd m/s."""
    return tuple(np.asarray(v) * k for v, k in ((lat_degE7, 1e-7), (lon_degE7, 1e-7), (alt_mm, 1e-3),
                                                (vx_cm_s, 0.01), (vy_cm_s, 0.01), (vz_cm_s, 0.01)))


def vfr_hud_throttle(throttle_pct) -> tuple[np.ndarray, np.ndarray]:
    """VFR_HUD throttle percent -> (fraction 0..1, valid where 0 <= throttle <= 100)."""
    thr = np.asarray(throttle_pct)
    return thr.astype(float) * 0.01, (thr >= 0) & (thr <= 100)


def sys_status_current_A(current_cA) -> tuple[np.ndarray, np.ndarray]:
    """SYS_STATUS current_battery cA (10 mA) -> (A, valid); -1 means not measured."""
    cur = np.asarray(current_cA)
    return cur * 0.01, cur >= 0
