"""A FlightLog turned into estimator inputs on one time base (shared by analyze, navigation and live).

``detection_inputs(log, calibration, mission, settings)`` runs the heading chain on the IMU time
base and lines up everything the interference detector needs (heading difference, field
strength and inclination, cross-track against the mission); the small helpers below are the one
definition of each step (held values, calibration arrays, mission legs, steep-attitude gate).
"""
from __future__ import annotations

import time

import numpy as np

from estimators.detection import DetectionSettings, cross_track_m, field_inclination_deg, ned_from_lla
from estimators.geomag import decimal_year_from_unix, earth_field
from estimators.heading import run_heading_chain
from estimators.rotations import wrap_angle_rad

from groundstation.io.params import ardupilot_never_calibrated
from groundstation.jobs.compass_raw import compass_field
from groundstation.samples import CompassTable, FlightLog, finite_or_none

__all__ = ["detection_inputs", "calibration_arrays", "check_calibration", "primary_raw", "mission_legs",
           "cross_track_legs", "hold_last",
           "field_reference", "uncalibrated", "too_steep", "rotation_rate", "rounded", "GPS_TIMEOUT_S"]

GPS_TIMEOUT_S = 1.0


MAX_OFFSET_MG = 1e5          # 100 G: far beyond any magnetometer's range
MAX_MATRIX_CONDITION = 1e3   # a fitted soft-iron matrix is near a rotation times ~1 (ratio <= 2.5)
MATRIX_SCALE_RANGE = (1e-2, 1e2)


def check_calibration(calibration: dict) -> tuple[np.ndarray, np.ndarray]:
    """(offsets_mG (3,), matrix (3, 3)) of a calibration object (``m_cal = matrix (m_raw - offsets)``).

    Raises:
        ValueError: saying what is wrong: offsets or matrix missing, not three / 3x3 numbers, not
            finite, offsets beyond MAX_OFFSET_MG, matrix singular or of absurd scale.
    """
    off, mat = calibration.get("offsets_mG"), calibration.get("matrix")
    if off is None:
        raise ValueError("the calibration has no offsets_mG")
    if mat is None:
        raise ValueError("the calibration has no matrix")
    try:
        off = np.asarray(off, dtype=float)
    except (TypeError, ValueError):
        raise ValueError("offsets_mG must be three numbers") from None
    try:
        mat = np.asarray(mat, dtype=float)
    except (TypeError, ValueError):
        raise ValueError("matrix must be 3x3 numbers") from None
    if off.shape != (3,):
        raise ValueError("offsets_mG must be three numbers")
    if mat.shape != (3, 3):
        raise ValueError("matrix must be 3x3 numbers")
    if not (np.all(np.isfinite(off)) and np.all(np.isfinite(mat))):
        raise ValueError("offsets_mG and matrix must be finite numbers")
    if np.max(np.abs(off)) > MAX_OFFSET_MG:
        raise ValueError(f"offsets_mG beyond +-{MAX_OFFSET_MG:g} mG are not a magnetometer's")
    sv = np.linalg.svd(mat, compute_uv=False)
    if sv[-1] <= sv[0] / MAX_MATRIX_CONDITION or sv[0] == 0:
        raise ValueError(f"matrix is singular (singular values {', '.join(f'{v:.3g}' for v in sv)}): "
                         "it would map every field onto a plane or a point")
    if not MATRIX_SCALE_RANGE[0] <= sv[-1] <= sv[0] <= MATRIX_SCALE_RANGE[1]:
        raise ValueError(f"matrix scale {sv[-1]:.3g}..{sv[0]:.3g} is outside "
                         f"{MATRIX_SCALE_RANGE[0]:g}..{MATRIX_SCALE_RANGE[1]:g}")
    return off, mat


def primary_raw(log: FlightLog) -> np.ndarray:
    """The primary compass's raw field (N,3), the autopilot's corrections un-applied with the values
    in force at each sample (jobs.compass_raw), on the rows of ``log.mag``."""
    mag = np.asarray(log.mag, dtype=float).reshape(-1, 4)
    same = [c for c in log.compasses if c.compass == log.primary_compass and c.field is log.mag]
    table = CompassTable(log.primary_compass, mag, "mag", None, log.mag_calibration_applied,
                         same[0].motor_offset_mG if same else None)
    return compass_field(log, table).raw_mG


def calibration_arrays(calibration: dict | None) -> tuple[np.ndarray, np.ndarray] | None:
    """``check_calibration``'s arrays, or None when there is no usable calibration."""
    if not calibration:
        return None
    try:
        return check_calibration(calibration)
    except ValueError:
        return None


def mission_legs(points: list | None) -> list[tuple[tuple[float, float], tuple[float, float]]]:
    """Consecutive waypoint pairs [(A, B), ...] as (lat, lon) tuples; empty if fewer than two."""
    pts = [(float(p[0]), float(p[1])) for p in (points or []) if len(p) >= 2
           and np.isfinite(p[0]) and np.isfinite(p[1])]
    return [(pts[k], pts[k + 1]) for k in range(len(pts) - 1) if pts[k] != pts[k + 1]]


def cross_track_legs(lat, lon, legs, origin) -> np.ndarray:
    """Horizontal seed 002 eq. (6) distance to the nearest leg (chosen by distance to the segment)."""
    n, e = ned_from_lla(lat, lon, origin[0], origin[1])
    x = np.stack([n, e, np.zeros_like(n)], axis=1)
    best_seg = np.full(len(x), np.inf)
    best_d = np.full(len(x), np.nan)
    for (a, b) in legs:
        an, ae = ned_from_lla(a[0], a[1], origin[0], origin[1])
        bn, be = ned_from_lla(b[0], b[1], origin[0], origin[1])
        A, B = np.array([an, ae, 0.0]), np.array([bn, be, 0.0])
        ab = B - A
        u = np.clip(((x - A) @ ab) / max(ab @ ab, 1e-12), 0.0, 1.0)
        seg = np.linalg.norm(x - (A + u[:, None] * ab), axis=1)
        d = cross_track_m(x, A, B)
        better = seg < best_seg
        best_seg = np.where(better, seg, best_seg)
        best_d = np.where(better, d, best_d)
    return best_d


def hold_last(t_src: np.ndarray, v_src: np.ndarray, t: np.ndarray, timeout_s: float) -> np.ndarray:
    """Latest source value at or before each t (NaN when none within timeout)."""
    v_src = np.asarray(v_src, dtype=float)
    out_shape = (len(t),) + v_src.shape[1:]
    if len(t_src) == 0:
        return np.full(out_shape, np.nan)
    idx = np.searchsorted(t_src, t, side="right") - 1
    ok = (idx >= 0) & (t - t_src[np.maximum(idx, 0)] <= timeout_s)
    out = v_src[np.maximum(idx, 0)].astype(float)
    out[~ok] = np.nan
    return out


def field_reference(log: FlightLog):
    """WMM at the log's median GPS position and date (None when the position is unknown)."""
    g = log.gps
    if not len(g):
        return None, None
    lat, lon, alt = float(np.median(g[:, 1])), float(np.median(g[:, 2])), float(np.median(g[:, 3]))
    start = log.start_unix_s if log.start_unix_s else time.time()
    try:
        return earth_field(lat, lon, alt, decimal_year_from_unix(start)), (lat, lon, alt)
    except ValueError:
        return None, None


def uncalibrated(log: FlightLog) -> bool:
    """The log's field is the raw sensor output: raw samples (PX4 sensor_mag), or ArduPilot with
    COMPASS_OFS_* all zero (never calibrated; a calibrated compass has non-zero offsets)."""
    return getattr(log, "mag_calibration_applied", None) is False or ardupilot_never_calibrated(log.params)


def too_steep(roll_rad, pitch_rad, settings: DetectionSettings):
    """Not a flight attitude (calibration dance, vehicle carried): detection does not look there."""
    cos_tilt = np.cos(roll_rad) * np.cos(pitch_rad)
    return ~(cos_tilt >= np.cos(np.radians(settings.max_tilt_deg)))


def rotation_rate(gyro_rad_s: np.ndarray) -> np.ndarray:
    """|ω| [rad/s]: turns and other fast rotations gate the heading-difference evidence."""
    return np.linalg.norm(np.nan_to_num(np.asarray(gyro_rad_s, dtype=float)), axis=-1)


def rounded(x, nd=3):
    v = finite_or_none(x)
    return None if v is None else round(v, nd)


def detection_inputs(log: FlightLog, calibration: dict | None = None, mission: list | None = None,
                     settings: DetectionSettings | None = None) -> dict:
    """Everything the detector needs, on the IMU time base (heading chain, field, cross-track).

    Keys: t, e (heading difference rad), d (cross-track m), trusted, strength, incl, heading,
    yaw_rate, ef (EarthField or None), pos, chain, valid, g (GPS table), d_gps, legs, rtk,
    path_test, cal.
    """
    settings = settings or DetectionSettings()
    cal = calibration_arrays(calibration)
    mag = np.asarray(log.mag, dtype=float).reshape(-1, 4)
    imu = np.asarray(log.imu, dtype=float).reshape(-1, 7)
    mag_cal = mag.copy()
    field_test = "on"
    if cal is not None and len(mag):
        # the calibration is relative to the raw sensor: un-apply the autopilot's own first, as in
        # force at each sample (parameter history)
        mag_cal[:, 1:4] = (primary_raw(log) - cal[0]) @ cal[1].T
    elif uncalibrated(log):
        field_test = "off: magnetometer not calibrated (give a calibration; the log has no onboard offsets)"
    ef, pos = field_reference(log)
    decl = ef.declination_deg if ef else 0.0

    chain = run_heading_chain(imu, mag_cal, decl)
    t = chain.t_s
    n = len(t)
    valid = chain.valid
    e = np.where(valid, wrap_angle_rad(chain.mag_heading_rad - chain.yaw_rad), np.nan)

    # field strength / inclination of the latest magnetometer sample at each IMU step
    m_held = hold_last(mag_cal[:, 0], mag_cal[:, 1:4], t, GPS_TIMEOUT_S) if n else np.zeros((0, 3))
    att = np.asarray(log.attitude, dtype=float).reshape(-1, 4)
    rp = hold_last(att[:, 0], att[:, 1:3], t, 0.5) if len(att) else np.full((n, 2), np.nan)
    roll_f = np.where(np.isfinite(rp[:, 0]), rp[:, 0], chain.roll_rad)
    pitch_f = np.where(np.isfinite(rp[:, 1]), rp[:, 1], chain.pitch_rad)
    strength = np.linalg.norm(m_held, axis=1)
    incl = field_inclination_deg(m_held, roll_f, pitch_f)
    steep = too_steep(roll_f, pitch_f, settings)
    if n:   # ... and for turn_settle_s after it
        last = np.maximum.accumulate(np.where(steep, t, -np.inf))
        steep = t - last <= settings.turn_settle_s
    e = np.where(steep, np.nan, e)
    imu_rate = 1.0 / float(np.median(np.diff(t))) if n > 10 and np.median(np.diff(t)) > 0 else 0.0
    heading_test = "on"
    if imu_rate < settings.min_imu_rate_hz:
        # the gyro cannot follow the rotation between samples: the filter heading is not a reference
        e = np.full(n, np.nan)
        heading_test = (f"off: IMU rate {imu_rate:.1f} Hz < {settings.min_imu_rate_hz:g} Hz"
                        if n else "off: no IMU data")
    if not len(mag):
        heading_test = field_test = "off: no magnetometer data in the log"
    strength = np.where(steep, np.nan, strength)
    incl = np.where(steep, np.nan, incl)
    if field_test != "on" or not n:
        strength = np.full(n, np.nan)
        incl = np.full(n, np.nan)

    # path: cross-track from GPS, nearest mission leg
    points = mission if mission else log.mission
    legs = mission_legs(points)
    g = np.asarray(log.gps, dtype=float).reshape(-1, 8)
    rtk = bool(len(g) and np.mean(g[:, 7] >= settings.rtk_min_fix) > 0.5)
    if legs and len(g):
        d_gps = cross_track_legs(g[:, 1], g[:, 2], legs, legs[0][0])
        d = hold_last(g[:, 0], d_gps, t, GPS_TIMEOUT_S)
        trusted = hold_last(g[:, 0], (g[:, 7] >= settings.rtk_min_fix).astype(float), t, GPS_TIMEOUT_S) == 1.0
        path_test = "on" if rtk else "untrusted: no RTK fix (fix_type < 5), path deviation never alarms"
    else:
        d_gps = np.zeros(0)
        d = np.full(n, np.nan)
        trusted = np.zeros(n, bool)
        path_test = ("off: no mission" if not legs else "off: no GPS position in the log")

    yaw_rate = rotation_rate(imu[:, 1:4]) if n else np.zeros(0)
    heading = np.where(valid, chain.yaw_rad, np.nan)
    return dict(t=t, e=e, d=d, trusted=trusted, strength=strength, incl=incl, heading=heading, mag_cal=mag_cal,
                yaw_rate=yaw_rate, ef=ef, pos=pos, chain=chain, valid=valid, g=g, d_gps=d_gps, legs=legs,
                rtk=rtk, path_test=path_test, heading_test=heading_test, field_test=field_test, imu_rate_hz=imu_rate, cal=cal)
