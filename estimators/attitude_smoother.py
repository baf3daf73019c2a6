"""Offline attitude for a finished log: the default AHRS run forward and backward in time, blended.

A post-flight review may use the future; the live station and the detector may not, so they keep
the causal estimate (estimators/ahrs.py).  Idea of VQF's offline mode (Laidig & Seel, Information
Fusion 91:187, 2023, sec. "offline": its low-pass and bias estimates run forward and backward and
are combined), written on our filter:

1. Bias and field hand-over.  A forward pass learns the gyro bias b̂ over the log; a backward pass starts
   from the bias at the log's end, a second forward pass from the backward pass's bias at the
   log's start.  So neither final pass starts with an unknown bias (the start of a log before the
   first rest, the end after the last).  Without an expected field the backward pass's field
   reference is the forward pass's undisturbed field (median strength and dip), not the last.
2. Backward pass = the causal filter on the time-reversed log: times t' = t_first + t_last − t,
   gyro −ω, the rotation over [t(k), t(k+1)] taken with ω(k+1) as the forward step does; the
   accelerometer and magnetometer samples as they are.  Its bias estimate is −b̂.
3. Blend per IMU step of the two final passes' body-frame unit vectors of gravity (x2) and field
   (x_m), weights w_f = 1 − exp(−(t − t_first)/τ) and w_b = 1 − exp(−(t_last − t)/τ)
   (τ = ``blend_s``, each pass counts little just after its own start) plus ``floor``; the angles
   from the blended vectors (seed 000 eqs. 11–13).  The forward inertial-frame low-pass lags
   (its error is the past's accelerations), the backward one leads: their mean is a zero-phase
   low-pass, and independent parts of their errors average out.

Units: rad, rad/s, m/s², mG, s; body FRD, navigation NED; headings magnetic in [0, 2π) (``yaw``),
true with the declination.  The flags (rejection, rest) and bias of the result are the final
forward pass's.
"""
from __future__ import annotations

from dataclasses import dataclass, field as dc_field

import numpy as np

from estimators.ahrs import AhrsSettings, ExpectedField
from estimators.ahrs_batch import AhrsResult, angles_from_vectors, run_ahrs
from estimators.heading import HeadingChainResult
from estimators.rotations import wrap_heading_rad

__all__ = ["SmootherSettings", "smooth_ahrs", "smooth_heading_chain"]


@dataclass(frozen=True)
class SmootherSettings:
    ahrs: AhrsSettings = dc_field(default_factory=AhrsSettings)
    blend_s: float = 10.0            # τ of the blend weights [s]
    floor: float = 1e-3              # weight floor (a log shorter than τ still gets both passes)

    def __post_init__(self):
        if not (self.blend_s > 0.0 and self.floor > 0.0):
            raise ValueError("need blend_s > 0 and floor > 0")


def _reverse(imu: np.ndarray, mag: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The log reversed in time (module docstring, step 2).  IMU times are cleaned as the causal
    filter does (running maximum of the finite stamps) before reversing."""
    t = imu[:, 0].copy()
    fin = np.isfinite(t)
    t = np.where(fin, t, -np.inf)
    t[0] = imu[0, 0] if fin[0] else 0.0
    t = np.maximum.accumulate(t)
    pivot = float(t[0] + t[-1])
    gyro = imu[:, 1:4]
    g_rev = -np.r_[gyro[-1:], gyro[::-1][:-1]]
    imu_r = np.c_[pivot - t[::-1], g_rev, imu[::-1, 4:7]]
    mag_r = mag[np.isfinite(mag[:, 0])][::-1].copy()
    mag_r[:, 0] = pivot - mag_r[:, 0]
    return imu_r, mag_r, pivot


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=1, keepdims=True)
    return np.divide(v, n, out=np.zeros_like(v), where=n > 0.0)


def _clean_field(r: AhrsResult) -> ExpectedField | None:
    """The field of the forward pass where it was not disturbed: median strength [mG] and dip
    below the horizontal of x2 [deg] (the reference the backward pass starts from, so that it
    does not take a disturbed field at the log's end for the earth's)."""
    ok = r.valid & ~r.mag_disturbed
    if not ok.any():
        return None
    g, m = r.gravity_body[ok], r.field_body_mG[ok]
    norm = np.linalg.norm(m, axis=1)
    up = _unit(g)
    dip = np.degrees(np.arcsin(np.clip(-np.sum(up * m, axis=1) / np.where(norm > 0, norm, 1.0), -1.0, 1.0)))
    return ExpectedField(float(np.median(norm)), float(np.median(dip)))


def smooth_ahrs(imu: np.ndarray, mag: np.ndarray, settings: SmootherSettings | None = None, *,
                expected_field: ExpectedField | None = None,
                gyro_bias_rad_s=(0.0, 0.0, 0.0)) -> AhrsResult:
    """Offline AHRS over a whole log (module docstring); arguments as ``run_ahrs``.  Returns an
    ``AhrsResult`` whose angles and vectors are the blend, flags and bias the forward pass's."""
    s = settings or SmootherSettings()
    imu = np.asarray(imu, dtype=float).reshape(-1, 7)
    mag = np.asarray(mag, dtype=float).reshape(-1, 4)
    if len(imu) < 2:
        return run_ahrs(imu, mag, s.ahrs, expected_field=expected_field, gyro_bias_rad_s=gyro_bias_rad_s)
    # each pass's result is dropped as soon as what the next needs is taken (memory: one pass and
    # the backward vectors, not three passes)
    first = run_ahrs(imu, mag, s.ahrs, expected_field=expected_field, gyro_bias_rad_s=gyro_bias_rad_s)
    ef = expected_field or _clean_field(first)
    bias_end = -first.gyro_bias_rad_s[-1]
    del first
    imu_r, mag_r, _ = _reverse(imu, mag)
    back = run_ahrs(imu_r, mag_r, s.ahrs, expected_field=ef, gyro_bias_rad_s=bias_end)
    del imu_r, mag_r
    bias_start = -back.gyro_bias_rad_s[-1]
    vb, gb, mb = back.valid[::-1], back.gravity_body[::-1], back.field_body_mG[::-1]
    del back
    fwd = run_ahrs(imu, mag, s.ahrs, expected_field=expected_field, gyro_bias_rad_s=bias_start)
    t = fwd.t_s
    wf = -np.expm1(-(t - t[0]) / s.blend_s) + s.floor
    wb = -np.expm1(-(t[-1] - t) / s.blend_s) + s.floor
    wf = np.where(fwd.valid, wf, 0.0)
    wb = np.where(vb, wb, 0.0)
    g = wf[:, None] * _unit(fwd.gravity_body) + wb[:, None] * _unit(gb)
    m = wf[:, None] * _unit(fwd.field_body_mG) + wb[:, None] * _unit(mb)
    del wf, wb
    valid = fwd.valid | vb
    # back to the vectors' scale (gravity m/s², field mG) for the callers that read them
    fv = fwd.valid[:, None]
    g = _unit(g) * np.linalg.norm(np.where(fv, fwd.gravity_body, gb), axis=1)[:, None]
    del gb
    m = _unit(m) * np.linalg.norm(np.where(fv, fwd.field_body_mG, mb), axis=1)[:, None]
    del mb
    roll, pitch, yaw, mag_heading = (np.where(valid, a, 0.0) for a in angles_from_vectors(g, m, fwd.mag_latest_mG))
    return AhrsResult(t, roll, pitch, yaw, mag_heading, fwd.gyro_bias_rad_s, fwd.acc_rejected, fwd.mag_rejected,
                      fwd.mag_disturbed, fwd.at_rest, valid, g, m, fwd.mag_latest_mG)


def smooth_heading_chain(imu: np.ndarray, mag_cal: np.ndarray, declination_deg=0.0,
                         settings: SmootherSettings | None = None, *,
                         expected_field: ExpectedField | None = None) -> HeadingChainResult:
    """``estimators.heading.run_heading_chain``'s result from the offline AHRS (estimator
    "offline"): the best attitude of a finished log."""
    r = smooth_ahrs(imu, mag_cal, settings, expected_field=expected_field)
    decl = np.broadcast_to(np.nan_to_num(np.asarray(declination_deg, dtype=float)), r.t_s.shape)
    true = np.where(r.valid, wrap_heading_rad(r.yaw_rad + np.radians(decl)), 0.0)
    return HeadingChainResult(r.t_s, r.roll_rad, r.pitch_rad, r.yaw_rad, r.mag_heading_rad, true, r.field_body_mG,
                              r.valid, r.gyro_bias_rad_s, r.acc_rejected, r.mag_rejected, r.mag_disturbed, r.at_rest,
                              "offline")
