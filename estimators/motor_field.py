"""Motor / current interference from a flight log (compassmot without a ground run).

The motor and battery wires add a body-fixed field proportional to the current (or to the
throttle): m_raw = M⁻¹(h + f·x) + b.  ``fit_motor_field`` fits f jointly with the offsets (and the
supported soft-iron terms) against the WMM-predicted field, with the machinery of
estimators.wmm_fit (yaw-free when the attitude's yaw comes from this compass), so an ordinary
flight with current changes (climbs, accelerations) gives f with its covariance.

Reported, as ArduPilot's compassmot and PX4's mag_compensation.py do:
* f [mG/A] (or mG per full throttle) and its sd; interference = |f|·x_max / |H| in % of the Earth
  field at the highest current (or throttle) of the log (ArduPilot's compassmot reports the same
  percentage, advising < 30 %);
* export numbers: ArduPilot COMPASS_MOT_X/Y/Z = −f in the corrected (body) frame [mG/A], COMPASS_MOTCT
  = 2 (current) or 1 (throttle; AP_Compass_Backend::correct_field adds COMPASS_MOT·x after the
  DIA/ODI matrix); PX4 CAL_MAGn_X/Y/ZCOMP = −Rᵀf in the *sensor* frame (Magnetometer::Correct adds
  power·COMP before the rotation), in G/kA for current (numerically equal to mG/A; PX4 divides
  battery current by 1000) or in G per unit thrust, CAL_MAG_COMP_TYP = 2 (battery 0) or 1 (thrust);
* the field norm against the signal (binned medians) before and after removing f·x.

Units: mG, A, throttle 0..1.  Pure numpy.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from estimators.field_model import FieldData, corrected_field, nominal_params
from estimators.rotations import dcm_body_to_ned
from estimators.wmm_fit import WmmFit, WmmFitSettings, fit_wmm

__all__ = ["MotorFieldFit", "fit_motor_field", "motor_compensation_params", "CurrentFieldFit", "fit_current_field"]


@dataclass(frozen=True)
class MotorFieldFit:
    """status: ok | no_motor_signal | insufficient_signal_variation | (any WmmFit status)."""
    status: str
    message: str
    signal: str                         # "current_A" | "throttle"
    motor_mG_per_unit: np.ndarray       # f, physical field per A (or per full throttle), body frame
    motor_sd_mG_per_unit: np.ndarray
    motor_covariance: np.ndarray        # (3,3)
    signal_max: float                   # highest signal among the used samples
    field_at_max_mG: float              # |f|·signal_max
    interference_pct: float             # of the Earth field strength
    norm_bins: dict                     # signal centres, counts, median |c| without and with f·x removed
    wmm: WmmFit                         # the underlying fit (offsets, matrix, covariance, gates)


def _nan_result(status: str, message: str, signal: str, wmm: WmmFit | None) -> MotorFieldFit:
    nan3 = np.full(3, np.nan)
    return MotorFieldFit(status, message, signal, nan3, nan3.copy(), np.full((3, 3), np.nan), float("nan"),
                         float("nan"), float("nan"), {}, wmm)


def _norm_bins(x: np.ndarray, c_with: np.ndarray, c_without: np.ndarray, n_bins: int = 8) -> dict:
    lo, hi = float(np.min(x)), float(np.max(x))
    edges = np.linspace(lo, hi if hi > lo else lo + 1.0, n_bins + 1)
    k = np.clip(np.digitize(x, edges) - 1, 0, n_bins - 1)
    out = {"signal": [], "count": [], "norm_uncompensated_mG": [], "norm_compensated_mG": []}
    for i in range(n_bins):
        sel = k == i
        if sel.sum() == 0:
            continue
        out["signal"].append(float(0.5 * (edges[i] + edges[i + 1])))
        out["count"].append(int(sel.sum()))
        out["norm_uncompensated_mG"].append(float(np.median(np.linalg.norm(c_with[sel], axis=1))))
        out["norm_compensated_mG"].append(float(np.median(np.linalg.norm(c_without[sel], axis=1))))
    return out


def fit_motor_field(t_s, mag_raw_mG, roll_rad, pitch_rad, yaw_rad, field_ned_mG, motor_signal, *,
                    signal: str = "current_A", attitude_rate_deg_s=None, gps_vel_ne_mps=None,
                    corrected_in_force_mG=None, nominal_matrix=None,
                    settings: WmmFitSettings | None = None) -> MotorFieldFit:
    """Field per ampere (signal "current_A") or per full throttle ("throttle", 0..1) of one compass.

    Inputs as ``estimators.wmm_fit.fit_wmm`` (raw body field with the corrections in force
    un-applied, including any COMPASS_MOT compensation).  The motor term is always fitted; it is
    reported ``insufficient_signal_variation`` when its sd is not below supported_ratio × prior sd.
    """
    if settings is None:
        # per full throttle the field is ~100× the per-ampere one: ArduPilot allows ±1000 for COMPASS_MOT
        settings = WmmFitSettings() if signal == "current_A" else WmmFitSettings(
            min_motor_signal_std=0.05, motor_prior_sd_mG_per_unit=300.0, motor_limit_mG_per_unit=1000.0)
    s = settings
    s = replace(s, fit_motor=True)
    if motor_signal is None or not np.any(np.isfinite(np.asarray(motor_signal, float))):
        return _nan_result("no_motor_signal", f"no {signal} in the log", signal, None)
    x_all = np.asarray(motor_signal, float).ravel()
    fit = fit_wmm(t_s, mag_raw_mG, roll_rad, pitch_rad, yaw_rad, field_ned_mG, attitude_rate_deg_s=attitude_rate_deg_s,
                  motor_signal=x_all, gps_vel_ne_mps=gps_vel_ne_mps, corrected_in_force_mG=corrected_in_force_mG,
                  nominal_matrix=nominal_matrix, settings=s)
    if not np.all(np.isfinite(fit.motor_mG_per_unit)):
        return _nan_result(fit.status, fit.message, signal, fit)
    f = fit.motor_mG_per_unit
    sd = fit.motor_sd_mG_per_unit
    cov = fit.covariance[9:12, 9:12]
    raw = np.asarray(mag_raw_mG, float).reshape(-1, 3)
    use = np.all(np.isfinite(raw), axis=1) & np.isfinite(x_all)
    p = nominal_params(fit.matrix, fit.offsets_mG)
    p[9:12] = f
    zeros = np.zeros(int(use.sum()))
    dummy = FieldData(raw[use], zeros, zeros, zeros, x_all[use], np.asarray(field_ned_mG, float))
    c_without = corrected_field(p, dummy)
    c_with = c_without + x_all[use, None] * f
    x_max = float(np.max(x_all[use]))
    H = float(np.linalg.norm(field_ned_mG))
    at_max = float(np.linalg.norm(f) * x_max)
    # the motor field is judged by its own sd; offsets that are only "weak" (not recommended) do not void it
    status, notes = ("ok" if fit.status == "weak" else fit.status), [fit.message]
    if "f_x" not in fit.fitted or np.any(sd > s.supported_ratio * s.motor_prior_sd_mG_per_unit):
        status = "insufficient_signal_variation"
        notes.append(f"motor field sd {np.round(sd, 2).tolist()} mG per unit: the {signal} does not vary enough")
    notes.append(f"motor field {np.linalg.norm(f):.2f} mG per unit, {at_max:.0f} mG at {x_max:.1f} "
                 f"({100 * at_max / H:.1f} % of the Earth field)")
    return MotorFieldFit(status, "; ".join(notes), signal, f.copy(), sd.copy(), cov.copy(), x_max, at_max,
                         100.0 * at_max / H, _norm_bins(x_all[use], c_with, c_without), fit)


def motor_compensation_params(fit: MotorFieldFit, instance: int = 0, px4_slot: int = 0,
                              sensor_to_body: np.ndarray | None = None) -> dict[str, dict[str, float]]:
    """{"ardupilot": COMPASS_MOT{n}_X/Y/Z + COMPASS_MOTCT, "px4": CAL_MAG{slot}_X/Y/ZCOMP + CAL_MAG_COMP_TYP}.
    ``sensor_to_body`` R (body = R · sensor) for PX4's sensor-frame coefficients (default identity)."""
    if not np.all(np.isfinite(fit.motor_mG_per_unit)):
        return {"ardupilot": {}, "px4": {}}
    f = fit.motor_mG_per_unit
    n = "" if instance == 0 else str(instance + 1)
    ap = {f"COMPASS_MOT{n}_{a}": float(-f[i]) for i, a in enumerate("XYZ")}
    ap["COMPASS_MOTCT"] = 2.0 if fit.signal == "current_A" else 1.0
    R = np.eye(3) if sensor_to_body is None else np.asarray(sensor_to_body, float)
    comp = -(R.T @ f)                       # mG/A == G/kA;  mG per full throttle -> G: / 1000
    if fit.signal != "current_A":
        comp = comp / 1000.0
    px4 = {f"CAL_MAG{px4_slot}_{a}COMP": float(comp[i]) for i, a in enumerate("XYZ")}
    px4["CAL_MAG_COMP_TYP"] = 2.0 if fit.signal == "current_A" else 1.0
    return {"ardupilot": ap, "px4": px4}


# ----------------------------------------------------------------------------- calibrated field
@dataclass(frozen=True)
class CurrentFieldFit:
    """``fit_current_field``: f [mG/A] of a field already calibrated with the motors off.
    status: ok | no_motor_signal | insufficient_signal_variation | insufficient_data | not_supported."""
    status: str
    message: str
    motor_mG_per_A: np.ndarray          # (3,) body frame; NaN unless status ok
    motor_sd_mG_per_A: np.ndarray
    field_down_mG: float                # the levelled field's vertical and horizontal parts, fitted
    field_horizontal_mG: float
    n_used: int


def fit_current_field(field_body_mG, current_A, roll_rad, pitch_rad, *, min_current_sd_A: float = 1.0,
                      huber_k: float = 1.345, max_iter: int = 15, max_rel_sd: float = 0.25,
                      max_mG_per_A: float = 20.0, min_improvement: float = 0.75) -> CurrentFieldFit:
    """Field per ampere f of a field that is calibrated except for the motor current, yaw-free.

    Model: the levelled field l = R(φ, θ)·(c − f·I) has a constant vertical part H_d and a constant
    horizontal length H_h whatever the heading, so for each sample
        r₁ = l_d − H_d,   r₂ = |l_NE| − H_h,
    and f, H_d, H_h follow by Gauss-Newton with Huber weights (the yaw-free residuals of PX4's
    mag_compensation.py / ArduPilot's compassmot, without a yaw reference, so an AHRS whose heading
    the motor field itself turned can supply the tilt).  Only the part of f·I that changes with the
    current and the heading is observable: the constant part at the mean current is absorbed by the
    calibration's offsets when the calibration was made with the current on; from a motors-off
    calibration (the rotation dance) f is the whole motor field.
    Units: mG, A, rad.  ``ok`` needs the current to vary by ``min_current_sd_A`` (sd), every
    component's sd below ``max_rel_sd``·|f| (or 0.05 mG/A), |f| ≤ ``max_mG_per_A`` (the
    motor_limit of WmmFitSettings) and the robust residual scale at most ``min_improvement`` of
    the one with f = 0: removing f·I must make the levelled field clearly steadier (on the
    simulated missions it falls to 0.25-0.56 of it; on the real 2.8 Hz dronekit tlog only to 0.83,
    where the heading against the autopilot's got no better, so that is left alone).
    """
    c = np.asarray(field_body_mG, float).reshape(-1, 3)
    cur = np.asarray(current_A, float).ravel()
    roll, pitch = np.asarray(roll_rad, float).ravel(), np.asarray(pitch_rad, float).ravel()
    use = np.all(np.isfinite(c), axis=1) & np.isfinite(cur) & np.isfinite(roll) & np.isfinite(pitch)
    nan3 = np.full(3, np.nan)
    fail = lambda status, msg: CurrentFieldFit(status, msg, nan3, nan3.copy(), np.nan, np.nan, int(use.sum()))  # noqa: E731
    if not use.any():
        return fail("no_motor_signal", "no samples with both a field and a current")
    c, cur, roll, pitch = c[use], cur[use], roll[use], pitch[use]
    if len(cur) < 30:
        return fail("insufficient_data", f"{len(cur)} samples with a field and a current (need 30)")
    if float(np.std(cur)) < min_current_sd_A:
        return fail("insufficient_signal_variation", f"current varies by {np.std(cur):.2f} A (sd) only "
                    f"(need {min_current_sd_A:g})")
    R = dcm_body_to_ned(roll, pitch, np.zeros_like(roll))
    l0 = np.einsum("nij,nj->ni", R, c)
    f, hd, hh = np.zeros(3), float(np.median(l0[:, 2])), float(np.median(np.hypot(l0[:, 0], l0[:, 1])))
    RI = R * cur[:, None, None]                         # ∂l/∂f = −I·R
    scale_without = None                                # robust residual scale with f = 0
    for _ in range(max_iter):
        l = l0 - RI @ f
        lh = np.hypot(l[:, 0], l[:, 1])
        u = l[:, :2] / np.maximum(lh, 1e-9)[:, None]
        r = np.r_[l[:, 2] - hd, lh - hh]
        J = np.zeros((2 * len(l), 5))
        J[:len(l), :3], J[:len(l), 3] = -RI[:, 2, :], -1.0
        J[len(l):, :3], J[len(l):, 4] = -np.einsum("nk,nkj->nj", u, RI[:, :2, :]), -1.0
        scale = 1.4826 * float(np.median(np.abs(r - np.median(r)))) + 1e-9
        scale_without = scale if scale_without is None else scale_without
        a = np.abs(r) / scale
        w = np.where(a <= huber_k, 1.0, huber_k / np.maximum(a, 1e-12))
        JW = J * w[:, None]
        N = JW.T @ J
        step = np.linalg.lstsq(N, -JW.T @ r, rcond=None)[0]
        f, hd, hh = f + step[:3], hd + step[3], hh + step[4]
        if np.max(np.abs(step[:3])) < 1e-4:
            break
    dof = max(len(r) - 5, 1)
    sigma2 = float(np.sum(w * r * r) / dof)
    try:
        sd = np.sqrt(np.diag(np.linalg.inv(N)) * sigma2)[:3]
    except np.linalg.LinAlgError:
        return fail("not_supported", "the current and the attitude do not determine the motor field")
    msg = (f"motor field {np.round(f, 2).tolist()} mG/A (sd {np.round(sd, 2).tolist()}), "
           f"{np.linalg.norm(f) * np.max(cur):.0f} mG at {np.max(cur):.1f} A, from {len(cur)} samples")
    msg += f"; levelled-field residual {scale_without:.1f} -> {scale:.1f} mG"
    why = ("not determined well enough" if not np.all(sd < np.maximum(max_rel_sd * np.linalg.norm(f), 0.05))
           else f"over {max_mG_per_A:g} mG/A" if np.linalg.norm(f) > max_mG_per_A
           else "does not steady the field enough" if scale >= min_improvement * scale_without else "")
    if why:
        return CurrentFieldFit("not_supported", f"{msg}: {why} to remove", nan3, sd, hd, hh, len(cur))
    return CurrentFieldFit("ok", msg, f, sd, hd, hh, len(cur))
