"""In-flight fits of one compass against the WMM (estimators.wmm_fit) and its motor/current
interference (estimators.motor_field), for logs with no dance and for the COMPASS_MOT numbers."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimators.motor_field import MotorFieldFit, fit_motor_field, motor_compensation_params
from estimators.wmm_fit import WmmFit, fit_wmm
from groundstation.jobs.compass_raw import CompassField, motor_signals
from groundstation.samples import FlightLog

from .context import LogContext, attitude_for, gps_velocity_for
from .settings import CalibrateSettings

__all__ = ["FlightInputs", "flight_inputs", "inflight_step", "motor_step", "wmm_dict", "motor_dict", "offsets_covariance",
           "heading_change"]


@dataclass(frozen=True)
class FlightInputs:
    """A compass's samples (``idx`` into CompassField: every k-th sample, at most
    ``CalibrateSettings.inflight_max_samples``) with the attitude, GPS velocity and motor signal
    at their times."""
    idx: np.ndarray
    roll: np.ndarray
    pitch: np.ndarray
    yaw: np.ndarray
    rate_deg_s: np.ndarray
    vel_ne_mps: np.ndarray | None
    signal: np.ndarray | None
    signal_name: str            # "current_A" | "throttle" | ""


def _signal(log: FlightLog, cf: CompassField) -> tuple[np.ndarray | None, str]:
    """The motor signal ArduPilot would use: throttle when COMPASS_MOTCT = 1, else the current,
    else the throttle."""
    current, throttle = motor_signals(log, cf.t_s)
    has = lambda x: x is not None and np.isfinite(x).sum() > 1  # noqa: E731
    if cf.motor_in_force.get("type") == 1 and has(throttle):
        return throttle, "throttle"
    if has(current):
        return current, "current_A"
    if has(throttle):
        return throttle, "throttle"
    return None, ""


def flight_inputs(log: FlightLog, cf: CompassField, max_samples: int) -> FlightInputs | None:
    if len(log.attitude) < 2:
        return None
    idx = np.arange(0, len(cf.t_s), max(1, int(np.ceil(len(cf.t_s) / max(max_samples, 1)))))
    t = cf.t_s[idx]
    att = attitude_for(log, t)
    signal, name = _signal(log, cf)
    return FlightInputs(idx, att.roll_rad, att.pitch_rad, att.yaw_rad, att.rate_deg_s, gps_velocity_for(log, t),
                        None if signal is None else signal[idx], name)


def inflight_step(cf: CompassField, x: FlightInputs, ctx: LogContext, settings: CalibrateSettings) -> WmmFit:
    i = x.idx
    return fit_wmm(cf.t_s[i], cf.raw_mG[i], x.roll, x.pitch, x.yaw, ctx.field.field_ned_mG,
                   attitude_rate_deg_s=x.rate_deg_s, motor_signal=x.signal, gps_vel_ne_mps=x.vel_ne_mps,
                   corrected_in_force_mG=cf.in_force_mG[i], nominal_matrix=cf.nominal_matrix, settings=settings.wmm)


def motor_step(cf: CompassField, x: FlightInputs, ctx: LogContext) -> MotorFieldFit:
    i = x.idx
    return fit_motor_field(cf.t_s[i], cf.raw_mG[i], x.roll, x.pitch, x.yaw, ctx.field.field_ned_mG, x.signal,
                           signal=x.signal_name, attitude_rate_deg_s=x.rate_deg_s, gps_vel_ne_mps=x.vel_ne_mps,
                           corrected_in_force_mG=cf.in_force_mG[i], nominal_matrix=cf.nominal_matrix)


def _r(v, nd=2):
    v = float(v)
    return round(v, nd) if np.isfinite(v) else None


def _vec(v, nd=2):
    return [_r(x, nd) for x in np.asarray(v, float).ravel()]


def wmm_dict(fit: WmmFit, t_s: np.ndarray) -> dict:
    return {"status": fit.status, "message": fit.message, "model": fit.model or None,
            "offsets_mG": _vec(fit.offsets_mG, 1), "offsets_sd_mG": _vec(fit.offsets_sd_mG),
            "matrix": [_vec(row, 5) for row in fit.matrix], "motor_mG_per_unit": _vec(fit.motor_mG_per_unit, 3),
            "fitted": list(fit.fitted), "residual_rms_mG": _r(fit.residual_rms_mG), "samples": fit.n_used,
            "rejected": {k: int(v) for k, v in fit.rejected.items()},
            "heading_coverage": _r(fit.heading_coverage, 3), "yaw_dependence": _r(fit.yaw_dependence, 3),
            "yaw_disagreement_deg": _r(fit.yaw_disagreement_deg), "recommended": bool(fit.recommended),
            "recommendation": fit.reason, "offsets_covariance_mG2": offsets_covariance(fit),
            "heading_change_deg": heading_change(fit), "sphere_coverage": _r(fit.sphere_coverage, 3)}


def offsets_covariance(fit: WmmFit) -> list | None:
    """The offsets' 3×3 covariance [mG²] (marginal over the terms held at nominal), None when no fit."""
    c = np.asarray(fit.covariance, float)[:3, :3]
    return [_vec(row, 2) for row in c] if np.all(np.isfinite(c)) else None


def heading_change(fit: WmmFit) -> dict | None:
    """How much the new calibration would turn the heading against the corrections in force [deg]."""
    rms, worst = fit.heading_change_deg
    return None if not np.isfinite(worst) else {"rms": _r(rms), "max": _r(worst)}


def motor_dict(fit: MotorFieldFit, compass: int, px4_slot: int | None, sensor_to_body: np.ndarray | None = None) -> dict:
    out = {"status": fit.status, "message": fit.message, "signal": fit.signal,
           "motor_mG_per_unit": _vec(fit.motor_mG_per_unit, 3), "motor_sd_mG_per_unit": _vec(fit.motor_sd_mG_per_unit, 3),
           "signal_max": _r(fit.signal_max), "field_at_max_mG": _r(fit.field_at_max_mG, 1),
           "interference_pct": _r(fit.interference_pct), "norm_vs_signal": {k: [_r(v, 2) for v in vals]
                                                                           for k, vals in fit.norm_bins.items()}}
    params = motor_compensation_params(fit, compass, px4_slot or 0, sensor_to_body) if fit.status == "ok" else {"ardupilot": {}, "px4": {}}
    out["ardupilot_params"] = params["ardupilot"]
    out["px4_params"] = params["px4"]
    return out
