"""In-flight fits of one compass against the WMM (estimators.wmm_fit) and its motor/current
interference (estimators.motor_field), for logs with no dance and for the COMPASS_MOT numbers."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from estimators.motor_field import MotorFieldFit, fit_motor_field, motor_compensation_params
from estimators.wmm_fit import WmmFit, fit_wmm, heldout_residual_mG
from groundstation.jobs.compass_raw import CompassField, motor_signals
from groundstation.samples import FlightLog

from .context import LogContext, attitude_for, field_for, gps_velocity_for
from .settings import CalibrateSettings

__all__ = ["FlightInputs", "flight_inputs", "inflight_step", "motor_step", "wmm_dict", "motor_dict", "offsets_covariance",
           "heading_change", "motor_signal", "attitude_sources", "choose_attitude", "log_attitude_name", "AHRS_SOURCE"]

AHRS_SOURCE = "ahrs"                # our AHRS (estimators.ahrs_batch) on the log's IMU and field
AHRS_MIN_IMU_RATE_HZ = 10.0         # slower IMU logs (telemetry) do not carry the rotation between samples
SCORE_MARGIN = 0.25                 # another source replaces the log's own attitude only when its score is this much lower
# (the log's own is the autopilot's active estimator; on the ArduPilot SITL circle flight DCM's AHR2 scored
# 15 % lower than EKF3's ATT and gave 16 mG error against ATT's 4.9: a tilt bias in a steady turn is consistent)
MIN_SCORED_FRACTION = 0.7           # a source is scored on at least this fraction of the best-covered one's samples


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
    field_ned_mG: np.ndarray | None = None      # (N,3) WMM at each sample (None: the one field of LogContext)


def motor_signal(log: FlightLog, cf: CompassField) -> tuple[np.ndarray | None, str]:
    """The motor signal ArduPilot would use at every sample of the compass, and its name: throttle
    when COMPASS_MOTCT = 1, else the current, else the throttle."""
    current, throttle = motor_signals(log, cf.t_s)
    has = lambda x: x is not None and np.isfinite(x).sum() > 1  # noqa: E731
    if cf.motor_in_force.get("type") == 1 and has(throttle):
        return throttle, "throttle"
    if has(current):
        return current, "current_A"
    if has(throttle):
        return throttle, "throttle"
    return None, ""


def flight_inputs(log: FlightLog, cf: CompassField, max_samples: int, ctx: LogContext | None = None
                  ) -> FlightInputs | None:
    """The fit's inputs at every k-th sample: the attitude ``ctx`` chose (else the log's) and, with
    ``ctx``, the WMM along the flight."""
    table = log.attitude if ctx is None or ctx.attitude is None else ctx.attitude
    if len(table) < 2:
        return None
    idx = np.arange(0, len(cf.t_s), max(1, int(np.ceil(len(cf.t_s) / max(max_samples, 1)))))
    t = cf.t_s[idx]
    att = attitude_for(log, t, table)
    signal, name = motor_signal(log, cf)
    return FlightInputs(idx, att.roll_rad, att.pitch_rad, att.yaw_rad, att.rate_deg_s, gps_velocity_for(log, t),
                        None if signal is None else signal[idx], name, None if ctx is None else field_for(log, ctx, t))


def _field(x: FlightInputs, ctx: LogContext) -> np.ndarray:
    return ctx.field.field_ned_mG if x.field_ned_mG is None else x.field_ned_mG


def log_attitude_name(log: FlightLog) -> str:
    """The name of ``log.attitude``'s source: the message it was read from."""
    for name in ("ATT", "ATTITUDE", "ATTITUDE_QUATERNION", "vehicle_attitude"):
        if log.message_counts.get(name):
            return name
    return "attitude"


def _ahrs_attitude(log: FlightLog) -> np.ndarray | None:
    """Our AHRS (estimators.ahrs_batch.run_ahrs) on the log's IMU and primary field as the autopilot
    corrected it, at ≤ 20 Hz: roll and pitch from its gravity stage (gyro and accelerometer), the
    yaw from the field (it needs one to start; the yaw-free fit uses the yaw only to sort samples
    into heading sectors).  None when the IMU is logged slower than AHRS_MIN_IMU_RATE_HZ."""
    imu = np.asarray(log.imu, float).reshape(-1, 7)
    if len(imu) < 100 or len(log.mag) < 10:
        return None
    span = float(imu[-1, 0] - imu[0, 0])
    rate = (len(imu) - 1) / span if span > 0 else 0.0
    if rate < AHRS_MIN_IMU_RATE_HZ:
        return None
    from estimators.ahrs_batch import run_ahrs
    res = run_ahrs(imu, np.asarray(log.mag, float))
    step = max(1, int(rate // 20))
    keep = res.valid[::step]
    table = np.column_stack([res.t_s, res.roll_rad, res.pitch_rad, res.yaw_rad])[::step][keep]
    return table if len(table) >= 2 else None


def attitude_sources(log: FlightLog, with_ahrs: bool = True) -> dict[str, np.ndarray]:
    """Every attitude the log has, by name: its own (ATT / ATTITUDE / vehicle_attitude), the other
    estimators it recorded (DataFlash AHR2 = DCM, XKF1 = EKF3, NKF1 = EKF2, EKF1), and ours from the
    IMU (``AHRS_SOURCE``) when the IMU is logged fast enough."""
    out = {}
    if len(log.attitude) >= 2:
        out[log_attitude_name(log)] = np.asarray(log.attitude, float)
    for name, table in log.attitudes.items():
        if len(table) >= 2:
            out[name] = np.asarray(table, float)
    if with_ahrs:
        ahrs = _ahrs_attitude(log)
        if ahrs is not None:
            out[AHRS_SOURCE] = ahrs
    return out


def choose_attitude(log: FlightLog, fields: list[CompassField], ctx: LogContext, settings: CalibrateSettings
                    ) -> LogContext:
    """The attitude source of the in-flight fits, chosen per log by the held-out residual
    (estimators.wmm_fit.heldout_residual_mG) of the primary compass's fit (the log's own attitude
    unless another scores ``SCORE_MARGIN`` lower; the first whose fit answers), or the one
    ``settings.attitude_source`` names.  Returns ctx with ``attitude``, ``attitude_source`` and
    ``attitude_choice`` (every source's score, the reason) filled in."""
    forced = settings.attitude_source not in ("", "auto")
    sources = attitude_sources(log, with_ahrs=not forced or settings.attitude_source == AHRS_SOURCE)
    if not sources or ctx.field is None or not settings.inflight_fit:
        return ctx
    default = next(iter(sources))
    if forced:
        if settings.attitude_source not in sources:
            note = (f"attitude {settings.attitude_source!r} asked for is not in this log (it has "
                    f"{', '.join(sources)}): {default} used")
            return replace(ctx, attitude=sources[default], attitude_source=default,
                           attitude_choice={"chosen": default, "forced": True, "scores": {}, "note": note})
        name = settings.attitude_source
        return replace(ctx, attitude=sources[name], attitude_source=name,
                       attitude_choice={"chosen": name, "forced": True, "scores": {}, "note": f"{name}, as asked"})
    scores: dict[str, float | None] = {}
    counts: dict[str, int] = {}
    base = next((f for f in fields if f.compass == log.primary_compass), fields[0] if fields else None)
    if base is not None and len(sources) > 1:
        for name, table in sources.items():
            probe = replace(ctx, attitude=table)
            x = flight_inputs(log, base, settings.inflight_max_samples, probe)
            score, counts[name] = float("nan"), 0
            if x is not None:
                i = x.idx
                score, counts[name] = heldout_residual_mG(base.t_s[i], base.raw_mG[i], x.roll, x.pitch, x.yaw, _field(x, probe),
                                               attitude_rate_deg_s=x.rate_deg_s, motor_signal=x.signal,
                                               nominal_matrix=base.nominal_matrix, settings=settings.wmm)
            scores[name] = round(score, 2) if np.isfinite(score) else None
    # a source is compared on (nearly) as many samples as the best-covered one: a source whose rate
    # gate drops the hard samples must not win on the easy ones
    most = max(counts.values(), default=0)
    finite = {k: v for k, v in scores.items() if v is not None and counts.get(k, 0) >= MIN_SCORED_FRACTION * most}
    # best score first (the log's own attitude unless another is clearly better); the first whose fit of
    # the primary compass gives an answer (ok / weak) is taken: a consistent attitude whose headings
    # leave the offsets unobservable is no use
    order = sorted(finite, key=lambda k: finite[k] * (1.0 if k == default else 1.0 + SCORE_MARGIN))
    chosen = order[0] if order else default
    unanswered = []
    for name in order if len(order) > 1 else []:
        x = flight_inputs(log, base, settings.inflight_max_samples, replace(ctx, attitude=sources[name]))
        if x is not None and inflight_step(base, x, ctx, settings).status in ("ok", "weak"):
            chosen = name
            break
        unanswered.append(name)
    else:
        chosen = order[0] if order else default
    if len(sources) == 1:
        note = f"{chosen}, the only attitude in the log"
    elif not finite:
        note = f"{chosen}: no source could be scored (too few usable samples)"
    else:
        note = (f"{chosen}: by the held-out residual of compass {base.compass}'s fit (the log's own attitude "
                f"unless another is {SCORE_MARGIN:.0%} lower)"
                + (f" among those giving an answer ({', '.join(unanswered)} did not)" if unanswered else "")
                + "".join(f"; {k} judged on too few samples" for k, v in scores.items() if v is not None and k not in finite)
                + " ("
                + ", ".join(f"{k} {v:.2f} mG on {counts[k]} samples" if v is not None else f"{k} -"
                            for k, v in scores.items()) + ")")
    return replace(ctx, attitude=sources[chosen], attitude_source=chosen,
                   attitude_choice={"chosen": chosen, "forced": False, "scores": scores, "samples": counts, "note": note})


def inflight_step(cf: CompassField, x: FlightInputs, ctx: LogContext, settings: CalibrateSettings,
                  profile_direction_ned: np.ndarray | None = None) -> WmmFit:
    """The in-flight fit of one compass against ctx's reference field (with its covariance)."""
    i = x.idx
    return fit_wmm(cf.t_s[i], cf.raw_mG[i], x.roll, x.pitch, x.yaw, _field(x, ctx),
                   attitude_rate_deg_s=x.rate_deg_s, motor_signal=x.signal, gps_vel_ne_mps=x.vel_ne_mps,
                   corrected_in_force_mG=cf.in_force_mG[i], nominal_matrix=cf.nominal_matrix,
                   field_cov_ned_mG2=ctx.field_cov_ned_mG2, profile_direction_ned=profile_direction_ned,
                   settings=settings.wmm)


def motor_step(cf: CompassField, x: FlightInputs, ctx: LogContext, inflight: WmmFit | None = None) -> MotorFieldFit:
    """The motor field: the in-flight fit with the motor term forced, under the motor fit's own
    settings (estimators.motor_field.motor_settings: soft iron fitted where supported; `review`'s
    in-flight fit holds it, and its motor field then came 39 % off on a simulated fleet flight where
    this one is within 35 %) and the same reference field; ``inflight`` itself when it kept the term
    under those settings."""
    i = x.idx
    return fit_motor_field(cf.t_s[i], cf.raw_mG[i], x.roll, x.pitch, x.yaw, _field(x, ctx), x.signal,
                           signal=x.signal_name, attitude_rate_deg_s=x.rate_deg_s, gps_vel_ne_mps=x.vel_ne_mps,
                           corrected_in_force_mG=cf.in_force_mG[i], nominal_matrix=cf.nominal_matrix,
                           field_cov_ned_mG2=ctx.field_cov_ned_mG2, inflight=inflight)


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
            "heading_change_deg": heading_change(fit), "sphere_coverage": _r(fit.sphere_coverage, 3),
            "course_check": fit.course}


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
