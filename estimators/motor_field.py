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

This is the offline calibration product (a raw-field fit against the WMM, like compassmot).  In
flight the one motor-field model of a calibrated field, serving the detector, the heading and the
explanations, is the online one learnt from the current's changes with its uncertainty
(estimators.residual_trackers.FieldModelFilter, used by estimators.field_consistency and
groundstation.jobs.motor_heading).

Units: mG, A, throttle 0..1.  Pure numpy.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from estimators.field_model import FieldData, corrected_field, nominal_params
from estimators.wmm_fit import WmmFit, WmmFitSettings, fit_wmm

__all__ = ["MotorFieldFit", "fit_motor_field", "motor_settings", "motor_compensation_params"]


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


def motor_settings(settings: WmmFitSettings | None, signal: str) -> WmmFitSettings:
    """The in-flight fit's settings for a motor signal: per ampere as given (default ``WmmFitSettings()``);
    per full throttle the field is ~100× the per-ampere one, so the motor prior, limit and the signal's
    least variation are ArduPilot's per-throttle ones (COMPASS_MOT ±1000)."""
    s = WmmFitSettings() if settings is None else settings
    if signal == "current_A":
        return s
    return replace(s, min_motor_signal_std=0.05, motor_prior_sd_mG_per_unit=300.0, motor_limit_mG_per_unit=1000.0)


def fit_motor_field(t_s, mag_raw_mG, roll_rad, pitch_rad, yaw_rad, field_ned_mG, motor_signal, *,
                    signal: str = "current_A", attitude_rate_deg_s=None, gps_vel_ne_mps=None,
                    corrected_in_force_mG=None, nominal_matrix=None, field_cov_ned_mG2=None,
                    settings: WmmFitSettings | None = None, inflight: WmmFit | None = None) -> MotorFieldFit:
    """Field per ampere (signal "current_A") or per full throttle ("throttle", 0..1) of one compass.

    Inputs as ``estimators.wmm_fit.fit_wmm`` (raw body field with the corrections in force
    un-applied, including any COMPASS_MOT compensation); ``settings`` the in-flight fit's (default
    ``WmmFitSettings()``; per full throttle its motor prior and limits are ArduPilot's ±1000).  The
    fit is the in-flight fit with the motor term forced; it is reported
    ``insufficient_signal_variation`` when its sd is not below supported_ratio × prior sd.
    ``inflight``: the in-flight fit of the same inputs; when it kept the motor term under the same
    settings it is that fit (a forced term the data support takes the same path as a chosen one:
    the terms dropped, the clamps and the covariance are the same), so it is not solved again.
    """
    s = replace(motor_settings(settings, signal), fit_motor=True)
    if motor_signal is None or not np.any(np.isfinite(np.asarray(motor_signal, float))):
        return _nan_result("no_motor_signal", f"no {signal} in the log", signal, None)
    x_all = np.asarray(motor_signal, float).ravel()
    if inflight is not None and "f_x" in inflight.fitted and replace(inflight.settings, fit_motor=True) == s:
        fit = inflight
    else:
        fit = fit_wmm(t_s, mag_raw_mG, roll_rad, pitch_rad, yaw_rad, field_ned_mG,
                      attitude_rate_deg_s=attitude_rate_deg_s, motor_signal=x_all, gps_vel_ne_mps=gps_vel_ne_mps,
                      corrected_in_force_mG=corrected_in_force_mG, nominal_matrix=nominal_matrix,
                      field_cov_ned_mG2=field_cov_ned_mG2, settings=s)
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
    Hf = np.asarray(field_ned_mG, float)
    dummy = FieldData(raw[use], zeros, zeros, zeros, x_all[use], Hf.ravel() if Hf.size == 3 else Hf[use])
    c_without = corrected_field(p, dummy)
    c_with = c_without + x_all[use, None] * f
    x_max = float(np.max(x_all[use]))
    H = float(np.mean(np.linalg.norm(Hf.reshape(-1, 3), axis=1)))
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
