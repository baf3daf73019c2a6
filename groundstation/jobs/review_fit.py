"""In-flight fit of the compass against the WMM for `magstation review` (offsets, motor field).

``fit_compass(model, ...)`` is what ``review_row`` calls; two models:

* "residual_matrix" (default, ``fit_inflight`` below): the corrections in force as a strong prior,
  a general 3×3 residual matrix (soft iron *and* small misalignment) and the motor field per ampere,
  fitted against the attitude's yaw.
* "wmm" (the real-logs work, ``estimators.motor_field.fit_motor_field`` /
  ``estimators.wmm_fit.fit_wmm``): yaw-free unless the yaw is known independent, a symmetric
  soft-iron matrix, the yaw's dependence on this compass diagnosed.  On the fleet simulator
  (2° misalignment, two-leg flights, an autopilot yaw independent of the offsets) it is ~4× less
  accurate and ~10× slower than "residual_matrix" (benchmarks/review.py prints both); on real
  logs, whose EKF yaw follows the compass, its yaw-free fit is the honest one when enough
  headings are flown.

Model of "residual_matrix", in the frame of the corrections in force (m_c = C (m_raw − b), the autopilot's own
calibration), with the autopilot's attitude C_b^n and the WMM field H (NED):

    m_c,i − C_b^n,iᵀ H  =  d + E · C_b^n,iᵀ H + k · I_i + noise

d [mG] is what the corrections in force miss (hard iron moved), E a small residual soft-iron /
misalignment matrix, k [mG/A] the motor-current field per ampere (I_i the battery current).  It is
linear in θ = (d, E, k): a ridge (Gaussian-prior) least squares with Huber re-weighting, posterior
covariance σ² (JᵀWJ + Λ)⁻¹.  In level flight the vertical column of E and d are nearly collinear:
the data reach it only through the tilt, where the autopilot's own compass-dependent yaw error
(an uncompensated motor field turns its heading) leaks in.  So the prior on E (``matrix_prior_sd``,
0.005) is tighter than the physical residual (~0.03 for 2° of misalignment): on 24 simulated
flights of random bearing it gave median / p90 offset errors of 5.1 / 10.4 mG against 5.3 / 11.4 mG
with 0.03; flights along magnetic east–west, where that yaw error looks like an x offset, are the
p90.  The fitted raw-frame offsets are b + C⁻¹ d.  The attitude's yaw is used as given (an attitude
whose yaw follows this compass hides part of a horizontal offset change; the WMM fit of the
real-logs work tests for that).
Units: mG, A, rad.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimators.rotations import dcm_body_to_ned

__all__ = ["InflightFitSettings", "InflightFit", "fit_inflight", "CompassFit", "fit_compass", "FIT_MODELS"]

FIT_MODELS = ("residual_matrix", "wmm")


@dataclass(frozen=True)
class InflightFitSettings:
    """Priors and gates of the in-flight fit (units in the names)."""
    offset_prior_sd_mG: float = 1000.0
    matrix_prior_sd: float = 0.005            # residual soft iron / misalignment after the calibration in force
    motor_prior_sd_mG_per_A: float = 5.0
    min_samples: int = 200
    min_current_sd_A: float = 0.5             # below: the motor field is not fitted (not observable)
    huber_k: float = 2.5                      # Huber threshold in robust σ
    iterations: int = 4


@dataclass(frozen=True)
class InflightFit:
    """status: ok | insufficient_data.  Vectors are (3,) in the frames named."""
    status: str
    message: str
    samples: int
    offsets_change_mG: np.ndarray        # d, corrected frame
    offsets_change_sd_mG: np.ndarray
    motor_mG_per_A: np.ndarray           # k, corrected (≈ body) frame; NaN when not fitted
    motor_sd_mG_per_A: np.ndarray
    current_max_A: float
    interference_pct: float              # |k| · I_max / |H| · 100
    residual_rms_mG: float


def _failed(message: str, n: int) -> InflightFit:
    nan3 = np.full(3, np.nan)
    return InflightFit("insufficient_data", message, n, nan3, nan3, nan3, nan3, np.nan, np.nan, np.nan)


def _design(h_body: np.ndarray, current_A: np.ndarray | None) -> np.ndarray:
    """Rows of J for r = J θ, stacked per axis: θ = (d 3, E 9 row-major, k 3)."""
    n = len(h_body)
    ncol = 12 + (3 if current_A is not None else 0)
    J = np.zeros((n, 3, ncol))
    for a in range(3):
        J[:, a, a] = 1.0
        J[:, a, 3 + 3 * a:6 + 3 * a] = h_body
        if current_A is not None:
            J[:, a, 12 + a] = current_A
    return J.reshape(3 * n, ncol)


def fit_inflight(corrected_mG: np.ndarray, roll_rad: np.ndarray, pitch_rad: np.ndarray, yaw_rad: np.ndarray,
                 field_ned_mG: np.ndarray, current_A: np.ndarray | None = None,
                 settings: InflightFitSettings = InflightFitSettings()) -> InflightFit:
    """Fit d, E (and k when the current varies) from samples already gated by the caller."""
    s = settings
    ok = np.all(np.isfinite(corrected_mG), axis=1) & np.isfinite(roll_rad) & np.isfinite(pitch_rad) & np.isfinite(yaw_rad)
    if current_A is not None:
        ok &= np.isfinite(current_A)
    n = int(ok.sum())
    if n < s.min_samples:
        return _failed(f"{n} usable field samples with attitude (need {s.min_samples})", n)
    c_bn = dcm_body_to_ned(roll_rad[ok], pitch_rad[ok], yaw_rad[ok])
    h_body = np.einsum("nji,j->ni", c_bn, np.asarray(field_ned_mG, float))
    cur = current_A[ok] if current_A is not None else None
    with_motor = cur is not None and float(np.std(cur)) >= s.min_current_sd_A
    J = _design(h_body, cur if with_motor else None)
    r = (corrected_mG[ok] - h_body).reshape(-1)
    prior_sd = np.r_[np.full(3, s.offset_prior_sd_mG), np.full(9, s.matrix_prior_sd),
                     np.full(3 if with_motor else 0, s.motor_prior_sd_mG_per_A)]
    w = np.ones(len(r))
    sigma = 1.0
    for _ in range(s.iterations):
        Lam = np.diag(sigma ** 2 / prior_sd ** 2)
        A = (J * w[:, None]).T @ J + Lam
        theta = np.linalg.solve(A, (J * w[:, None]).T @ r)
        e = r - J @ theta
        sigma = max(1.4826 * float(np.median(np.abs(e))), 1e-3)
        z = np.abs(e) / sigma
        w = np.where(z <= s.huber_k, 1.0, s.huber_k / np.maximum(z, 1e-12))
    cov = sigma ** 2 * np.linalg.inv((J * w[:, None]).T @ J + np.diag(sigma ** 2 / prior_sd ** 2))
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    strength = float(np.linalg.norm(field_ned_mG))
    nan3 = np.full(3, np.nan)
    k, k_sd = (theta[12:15], sd[12:15]) if with_motor else (nan3, nan3)
    i_max = float(np.nanpercentile(cur, 99)) if cur is not None else np.nan
    pct = float(np.linalg.norm(k) * i_max / strength * 100.0) if with_motor else np.nan
    msg = "offsets, residual matrix" + (" and motor field per ampere" if with_motor else
                                        "; motor field not fitted (no current or it hardly varies)")
    return InflightFit("ok", msg, n, theta[:3].copy(), sd[:3].copy(), np.asarray(k, float), np.asarray(k_sd, float),
                       i_max, pct, float(np.sqrt(np.mean(e[w >= 1.0] ** 2))))


@dataclass(frozen=True)
class CompassFit:
    """What the review row keeps of either model.  Offsets in the body-aligned raw frame
    (m_cal = C (m_raw − b)); motor field per ampere in the corrected (≈ body) frame."""
    model: str
    status: str
    message: str
    samples: int
    offsets_mG: np.ndarray
    offsets_sd_mG: np.ndarray
    motor_mG_per_A: np.ndarray
    motor_sd_mG_per_A: np.ndarray
    current_max_A: float
    interference_pct: float
    residual_rms_mG: float
    yaw_dependence: float = float("nan")      # "wmm" only: ≈ 1 when the attitude yaw follows this compass


def _from_residual_matrix(fit: InflightFit, b: np.ndarray, C: np.ndarray) -> CompassFit:
    Ci = np.linalg.inv(C)
    b_fit = b + Ci @ fit.offsets_change_mG
    sd = np.sqrt(np.diag(Ci @ np.diag(fit.offsets_change_sd_mG ** 2) @ Ci.T))
    return CompassFit("residual_matrix", fit.status, fit.message, fit.samples, b_fit, sd, fit.motor_mG_per_A,
                      fit.motor_sd_mG_per_A, fit.current_max_A, fit.interference_pct, fit.residual_rms_mG)


def _from_wmm(t_s, raw, att, field_ned_mG, current_A, C, corrected) -> CompassFit:
    from estimators.motor_field import fit_motor_field
    from estimators.wmm_fit import fit_wmm

    args = (t_s, raw, att[:, 0], att[:, 1], att[:, 2], field_ned_mG)
    kw = dict(attitude_rate_deg_s=att[:, 3], corrected_in_force_mG=corrected, nominal_matrix=C)
    nan3 = np.full(3, np.nan)
    if current_A is not None and np.isfinite(current_A).any():
        mf = fit_motor_field(*args, current_A, **kw)
        w = mf.wmm
        if w is None:
            return CompassFit("wmm", mf.status, mf.message, 0, nan3, nan3, nan3, nan3, np.nan, np.nan, np.nan)
        motor, motor_sd = (mf.motor_mG_per_unit, mf.motor_sd_mG_per_unit) if mf.status == "ok" else (nan3, nan3)
        pct = mf.interference_pct if mf.status == "ok" else np.nan
        i_max = mf.signal_max
    else:
        w = fit_wmm(*args, **kw)
        motor, motor_sd, pct, i_max = nan3, nan3, np.nan, np.nan
    return CompassFit("wmm", w.status, w.message, w.n_used, w.offsets_mG, w.offsets_sd_mG, motor, motor_sd, i_max, pct,
                      w.residual_rms_mG, w.yaw_dependence)


def fit_compass(model: str, t_s: np.ndarray, raw_mG: np.ndarray, b_mG: np.ndarray, C: np.ndarray,
                attitude: np.ndarray, field_ned_mG: np.ndarray, current_A: np.ndarray | None,
                corrected_mG: np.ndarray, settings: InflightFitSettings = InflightFitSettings()) -> CompassFit:
    """One compass's in-flight fit with ``model`` (``FIT_MODELS``) on samples already gated.

    Args: t_s (N,); raw_mG (N,3) body-aligned raw field; b_mG, C the corrections in force;
    attitude (N,4) roll, pitch, yaw [rad] and attitude rotation rate [deg/s]; field_ned_mG (3,) WMM;
    current_A (N,) or None; corrected_mG (N,3) the field with the corrections in force.
    Raises ValueError for an unknown model."""
    if model == "residual_matrix":
        fit = fit_inflight(corrected_mG, attitude[:, 0], attitude[:, 1], attitude[:, 2], field_ned_mG, current_A, settings)
        return _from_residual_matrix(fit, b_mG, C)
    if model == "wmm":
        return _from_wmm(t_s, raw_mG, attitude, field_ned_mG, current_A, C, corrected_mG)
    raise ValueError(f"unknown in-flight fit {model!r} (choose from {', '.join(FIT_MODELS)})")
