"""Tilt-compensated magnetic heading, true heading, velocity split and the heading chain (seed 000 sec. 2).

Chain per IMU sample (seed 000 sec. 2.1–2.2):
  1. attitude: by default the AHRS of estimators/ahrs.py (two-stage gravity and field vector
     filters with gyro-bias estimation, acceleration and magnetic rejection); with
     ``HeadingChainSettings(estimator="seed000")`` seed 000's two vector complementary filters
     (estimators/attitude.py: gravity → roll φ, pitch θ; field eq. 9/10 → Ĥ^b);
  2. eqs. (11)–(12) project the field onto the horizontal plane, eq. (13) gives the magnetic heading
     in all four quadrants (atan2(−H_Y, H_X) in [0, 2π), which is eq. (13) case by case); true
     heading ψ = ψ_m + α with α the declination (WMM, estimators.geomag);
  3. GPS NED velocity split into forward/lateral with the heading (seed 000 sec. 3.3).

``run_heading_chain`` (batch, replay) and ``HeadingChain`` (per sample, live) give the same numbers.
Units: rad internally, mG, rad/s, m/s^2; body FRD, navigation NED; headings clockwise from north.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field as dc_field

import numpy as np

from estimators.ahrs import Ahrs, AhrsSettings, ExpectedField
from estimators.ahrs_batch import run_ahrs
from estimators.attitude import (FieldVectorFilter, GravityVectorFilter, VectorFilterSettings,
                                 roll_pitch_from_specific_force, run_vector_filter)
from estimators.rotations import wrap_heading_rad, wrap_heading_rad_float

__all__ = [
    "tilt_compensated_heading_rad", "split_velocity",
    "HeadingChainSettings", "HeadingChainResult", "HeadingState", "HeadingChain", "run_heading_chain",
    "ESTIMATORS",
]
ESTIMATORS = ("ahrs", "seed000")


def tilt_compensated_heading_rad(mag_body_mG, roll_rad, pitch_rad):
    """Magnetic heading [rad, 0..2π) from a body-frame field and roll/pitch (seed 000 eqs. 11–13).

    H_X = H_x cos θ + H_y sin θ sin φ + H_z sin θ cos φ      (11)
    H_Y = H_y cos φ − H_z sin φ                              (12)
    ψ_m = atan2(−H_Y, H_X) mod 2π                            (13, all quadrants)
    Vectorised: mag (..., 3), roll/pitch (...).
    """
    m = np.asarray(mag_body_mG, dtype=float)
    r = np.asarray(roll_rad, dtype=float)
    p = np.asarray(pitch_rad, dtype=float)
    sr, cr, sp, cp = np.sin(r), np.cos(r), np.sin(p), np.cos(p)
    hx = m[..., 0] * cp + m[..., 1] * sp * sr + m[..., 2] * sp * cr
    hy = m[..., 1] * cr - m[..., 2] * sr
    return wrap_heading_rad(np.arctan2(-hy, hx))


def split_velocity(vel_north_mps, vel_east_mps, heading_rad):
    """Forward/lateral (right positive) velocity from NED velocity and heading (seed 000 sec. 3.3)."""
    vn = np.asarray(vel_north_mps, dtype=float)
    ve = np.asarray(vel_east_mps, dtype=float)
    h = np.asarray(heading_rad, dtype=float)
    c, s = np.cos(h), np.sin(h)
    return vn * c + ve * s, -vn * s + ve * c


@dataclass(frozen=True)
class HeadingChainSettings:
    """``estimator``: "ahrs" (default, estimators/ahrs.py with ``ahrs``) or "seed000" (seed 000's
    vector complementary filters with ``field`` and ``gravity``)."""
    estimator: str = "ahrs"
    ahrs: AhrsSettings = dc_field(default_factory=AhrsSettings)
    field: VectorFilterSettings = dc_field(default_factory=lambda: VectorFilterSettings(gain_per_s=0.5))
    gravity: VectorFilterSettings = dc_field(default_factory=lambda: VectorFilterSettings(gain_per_s=0.2))

    def __post_init__(self):
        if self.estimator not in ESTIMATORS:
            raise ValueError(f"estimator must be one of {ESTIMATORS}, not {self.estimator!r}")


def _zeros3() -> np.ndarray:
    return np.zeros((0, 3))


def _no_flags() -> np.ndarray:
    return np.zeros(0, bool)


@dataclass
class HeadingChainResult:
    """Arrays on the IMU time base (length N). Headings in [0, 2π).

    ``valid``: attitude and field initialised (before that the angles are 0).  The AHRS fields
    (bias, rejection, rest) are zero/False with the seed-000 estimator.
    """
    t_s: np.ndarray
    roll_rad: np.ndarray
    pitch_rad: np.ndarray
    yaw_rad: np.ndarray            # filter heading (magnetic)
    mag_heading_rad: np.ndarray    # raw tilt-compensated magnetic heading of the latest mag sample
    heading_true_rad: np.ndarray   # yaw_rad + declination
    field_body_mG: np.ndarray      # filtered field in the body frame (N, 3)
    valid: np.ndarray
    gyro_bias_rad_s: np.ndarray = dc_field(default_factory=_zeros3)   # (N, 3) in effect at each step
    acc_rejected: np.ndarray = dc_field(default_factory=_no_flags)    # tilt held on the gyro
    mag_rejected: np.ndarray = dc_field(default_factory=_no_flags)    # heading held on the gyro
    mag_disturbed: np.ndarray = dc_field(default_factory=_no_flags)   # field departs from the reference
    at_rest: np.ndarray = dc_field(default_factory=_no_flags)
    estimator: str = "ahrs"


@dataclass
class HeadingState:
    t_s: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    mag_heading_rad: float
    heading_true_rad: float
    valid: bool
    gyro_bias_rad_s: tuple = (0.0, 0.0, 0.0)
    acc_rejected: bool = False
    mag_rejected: bool = False
    mag_disturbed: bool = False
    at_rest: bool = False


def _clean_time(t: np.ndarray) -> np.ndarray:
    """Running maximum of the finite times (same rule as the per-sample filters)."""
    t = np.asarray(t, dtype=float)
    if len(t) == 0:
        return t.copy()
    tt = np.where(np.isfinite(t), t, -np.inf)
    tt[0] = t[0] if np.isfinite(t[0]) else 0.0
    return np.maximum.accumulate(tt)


def _held(meas_t: np.ndarray, meas_v: np.ndarray, t_clean: np.ndarray, timeout_s: float):
    """Latest finite measurement at or before each step (zero-order hold) and whether it is fresh."""
    ok = np.isfinite(meas_t) & np.all(np.isfinite(meas_v), axis=1)
    # a sample older than one already received is ignored (as the per-sample filters do)
    prev = np.maximum.accumulate(np.where(ok, meas_t, -np.inf))
    ok &= meas_t >= np.r_[-np.inf, prev[:-1]]
    mt, mv = meas_t[ok], meas_v[ok]
    order = np.argsort(mt, kind="stable")
    mt, mv = mt[order], mv[order]
    idx = np.searchsorted(mt, t_clean, side="right") - 1
    exists = idx >= 0
    idx_c = np.maximum(idx, 0)
    if len(mt) == 0:
        return np.zeros((len(t_clean), 3)), np.zeros(len(t_clean), bool), exists
    m = np.where(exists[:, None], mv[idx_c], 0.0)
    have = exists & ((t_clean - mt[idx_c]) <= timeout_s)
    return m, have, exists


def _reinit_flags(have: np.ndarray, gap: np.ndarray) -> np.ndarray:
    """First step with a measurement after the start and after each gap."""
    seg = np.cumsum(gap)
    reinit = np.zeros(len(have), bool)
    hi = np.flatnonzero(have)
    if len(hi):
        _, first = np.unique(seg[hi], return_index=True)
        reinit[hi[first]] = True
    return reinit


def _vector_filter_batch(t_clean, gyro, meas_t, meas_v, s: VectorFilterSettings):
    dt = np.diff(t_clean, prepend=t_clean[:1])
    gap = dt > s.max_gap_s
    dt = np.where(gap, 0.0, dt)
    m, have, _ = _held(meas_t, meas_v, t_clean, s.hold_timeout_s)
    reinit = _reinit_flags(have, gap)
    x = run_vector_filter(dt, gyro, m, have, reinit, s.gain_per_s)
    inited = np.maximum.accumulate(reinit) if len(reinit) else reinit
    return x, inited


def _outputs(grav, field_b, mag_held, mag_exists, inited, decl):
    valid = inited & mag_exists
    roll, pitch = roll_pitch_from_specific_force(grav)
    yaw = tilt_compensated_heading_rad(field_b, roll, pitch)
    mag_heading = tilt_compensated_heading_rad(mag_held, roll, pitch)
    true = wrap_heading_rad(yaw + np.radians(decl))
    return tuple(np.where(valid, a, 0.0) for a in (roll, pitch, yaw, mag_heading, true)) + (valid,)


def run_heading_chain(imu: np.ndarray, mag_cal: np.ndarray, declination_deg=0.0,
                      settings: HeadingChainSettings | None = None, *,
                      expected_field: ExpectedField | None = None) -> HeadingChainResult:
    """Batch heading/attitude chain on the IMU time base (seed 000 sec. 2).

    imu: (N, 7) [t_s, gx, gy, gz rad/s, ax, ay, az m/s^2];  mag_cal: (M, 4) [t_s, mx, my, mz mG]
    (calibrated);  declination_deg: scalar or (N,);  expected_field: the field strength and
    inclination the magnetometer should see (WMM), for the AHRS's magnetic rejection (None: learned
    from the first field).  Non-finite rows are skipped, outputs are always finite.
    """
    s = settings or HeadingChainSettings()
    imu = np.asarray(imu, dtype=float).reshape(-1, 7)
    mag_cal = np.asarray(mag_cal, dtype=float).reshape(-1, 4)
    if s.estimator == "seed000":
        return _run_seed000(imu, mag_cal, declination_deg, s)
    r = run_ahrs(imu, mag_cal, s.ahrs, expected_field=expected_field)
    decl = np.broadcast_to(np.nan_to_num(np.asarray(declination_deg, dtype=float)), r.t_s.shape)
    true = np.where(r.valid, wrap_heading_rad(r.yaw_rad + np.radians(decl)), 0.0)
    return HeadingChainResult(r.t_s, r.roll_rad, r.pitch_rad, r.yaw_rad, r.mag_heading_rad, true, r.field_body_mG,
                              r.valid, r.gyro_bias_rad_s, r.acc_rejected, r.mag_rejected, r.mag_disturbed, r.at_rest,
                              "ahrs")


def _run_seed000(imu: np.ndarray, mag_cal: np.ndarray, declination_deg, s: HeadingChainSettings) -> HeadingChainResult:
    """Seed 000's chain: gravity and field vector complementary filters (estimators/attitude.py)."""
    t = _clean_time(imu[:, 0])
    gyro = imu[:, 1:4]
    gyro = np.where(np.all(np.isfinite(gyro), axis=1)[:, None], gyro, 0.0)
    grav, g_init = _vector_filter_batch(t, gyro, imu[:, 0], imu[:, 4:7], s.gravity)
    field_b, f_init = _vector_filter_batch(t, gyro, mag_cal[:, 0], mag_cal[:, 1:4], s.field)
    mag_held, _, mag_exists = _held(mag_cal[:, 0], mag_cal[:, 1:4], t, np.inf)
    decl = np.broadcast_to(np.nan_to_num(np.asarray(declination_deg, dtype=float)), t.shape)
    roll, pitch, yaw, mh, true, valid = _outputs(grav, field_b, mag_held, mag_exists, g_init & f_init, decl)
    n = len(t)
    no = np.zeros(n, bool)
    return HeadingChainResult(t, roll, pitch, yaw, mh, true, field_b, valid, np.zeros((n, 3)), no, no.copy(),
                              no.copy(), no.copy(), "seed000")


class HeadingChain:
    """Per-sample heading chain for the live path; same numbers as ``run_heading_chain``.

    Feed samples in time order: ``update_mag`` for each calibrated magnetometer sample (before an
    IMU sample with the same time), ``update_imu`` for each IMU sample, which returns the state.
    ``declination_deg`` may be changed at any time (it only shifts the true heading).
    """

    def __init__(self, declination_deg: float = 0.0, settings: HeadingChainSettings | None = None, *,
                 expected_field: ExpectedField | None = None):
        self.settings = settings or HeadingChainSettings()
        self.declination_deg = float(declination_deg)
        ahrs = self.settings.estimator == "ahrs"
        self.ahrs = Ahrs(self.settings.ahrs, expected_field=expected_field) if ahrs else None
        self.field_filter = FieldVectorFilter(self.settings.field)
        self.gravity_filter = GravityVectorFilter(self.settings.gravity)
        self._mag = np.zeros(3)
        self._mag_seen = False

    def update_mag(self, t_s: float, mag_cal_mG) -> None:
        if self.ahrs is not None:
            self.ahrs.update_mag(t_s, mag_cal_mG)
            return
        m = np.asarray(mag_cal_mG, dtype=float)
        if m.shape == (3,) and np.all(np.isfinite(m)) and np.isfinite(t_s) and t_s >= self.field_filter._meas_t:
            self.field_filter.set_measurement(t_s, m)
            self._mag = m.copy()
            self._mag_seen = True

    def update_imu(self, t_s: float, gyro_rad_s, accel_mps2) -> HeadingState:
        decl = self.declination_deg if math.isfinite(self.declination_deg) else 0.0
        if self.ahrs is not None:
            a = self.ahrs.update_imu(t_s, gyro_rad_s, accel_mps2)
            true = wrap_heading_rad_float(a.yaw_rad + math.radians(decl)) if a.valid else 0.0
            return HeadingState(a.t_s, a.roll_rad, a.pitch_rad, a.yaw_rad, a.mag_heading_rad, true, a.valid,
                                a.gyro_bias_rad_s, a.acc_rejected, a.mag_rejected, a.mag_disturbed, a.at_rest)
        return self._update_seed000(t_s, gyro_rad_s, accel_mps2, decl)

    def _update_seed000(self, t_s: float, gyro_rad_s, accel_mps2, decl: float) -> HeadingState:
        a = np.asarray(accel_mps2, dtype=float)
        if np.isfinite(t_s):
            self.gravity_filter.set_measurement(t_s, a)
        gx, gy, gz = self.gravity_filter.update(t_s, gyro_rad_s)
        fb = self.field_filter.update(t_s, gyro_rad_s)
        roll = math.atan2(-gy, -gz)                           # = roll_pitch_from_specific_force
        pitch = math.atan2(gx, math.hypot(gy, gz))
        yaw = _heading_scalar(fb, roll, pitch)
        mh = _heading_scalar(self._mag, roll, pitch)
        true = wrap_heading_rad_float(yaw + math.radians(decl))
        valid = self.gravity_filter.initialised and self.field_filter.initialised and self._mag_seen
        if not valid:
            roll = pitch = yaw = mh = true = 0.0
        return HeadingState(float(self.gravity_filter._t), roll, pitch, yaw, mh, true, bool(valid))


def _heading_scalar(m, roll: float, pitch: float) -> float:
    """tilt_compensated_heading_rad for one sample in plain floats (live path)."""
    mx, my, mz = (float(v) for v in m)
    sr, cr, sp, cp = math.sin(roll), math.cos(roll), math.sin(pitch), math.cos(pitch)
    hx = mx * cp + my * sp * sr + mz * sp * cr
    hy = my * cr - mz * sr
    return wrap_heading_rad_float(math.atan2(-hy, hx))
