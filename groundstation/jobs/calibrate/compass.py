"""One compass of a log: windows, else the in-flight WMM fit; motor field; orientation; export.

Order: (1) the calibration windows (onboard-calibration markers, else rotation segmentation); the
chosen window's fit gives the offsets and matrix; (2) without a sufficient window, the in-flight
fit against the WMM (with its motor term when the log's current supports it); (3) the motor field
per ampere (or per throttle) on the whole flight, exported when determined; (4) the orientation
check on the calibrated field.  Bad data never raise here: each step reports a status.
"""
from __future__ import annotations

import numpy as np

from estimators.cal_windows import CalWindow, WindowSettings, judge_window
from estimators.calibration import apply_calibration
from estimators.compass_corrections import ardupilot_param_names
from groundstation.io.params import export_params, px4_rotation, rotation_enum_matrix, wmm_scale
from groundstation.jobs.compass_raw import CompassField
from groundstation.samples import FlightLog, finite_or_none

from .checks import orientation_dict, orientation_reference, orientation_step, reorient
from .context import LogContext, onboard_report
from .frame import LOG_RAW_UNKNOWN_STATUSES, corrections_record
from .inflight import (flight_inputs, heading_change, inflight_step, motor_dict, motor_signal, motor_step, offsets_covariance,
                       wmm_dict)
from .result import empty_result
from .settings import CalibrateSettings, settings_record
from .windows import misalignment, window_dict, window_dicts, window_mask, window_step

__all__ = ["calibrate_compass", "motor_free_window", "SPECIFIC_INFLIGHT_STATUSES"]

# in-flight statuses that say more than "not enough data" (otherwise the window verdict is reported)
SPECIFIC_INFLIGHT_STATUSES = ("attitude_depends_on_compass", "offsets_out_of_range")


def _vec(v, nd=3):
    return [finite_or_none(round(float(x), nd)) for x in np.asarray(v, float).ravel()]


def _corrections_dict(cf: CompassField) -> dict:
    convention = "COMPASS_OFS" if cf.autopilot == "ardupilot" else "offsets_mG (raw − b)"
    end = cf.offsets_in_force_mG[-1] if len(cf.offsets_in_force_mG) else np.full(3, np.nan)
    return {"status": cf.status, "note": cf.note, "orientation_in_use": cf.orientation_id, "px4_slot": cf.px4_slot,
            "offsets_in_force_end_mG": _vec(end, 2), "offsets_convention": convention, "motor_in_force": cf.motor_in_force,
            "changes": [{"t_s": round(t, 2), "offsets": _vec(o, 2)} for t, o in cf.changes]}


def _params_of(log: FlightLog, cf: CompassField) -> dict:
    """The compass's own calibration parameters of the log (their last values)."""
    params = log.params or {}
    if cf.autopilot == "px4":
        pre = f"CAL_MAG{cf.px4_slot if cf.px4_slot is not None else cf.compass}_"
        return {k: v for k, v in params.items() if k.startswith(pre)}
    names = {n for group in ardupilot_param_names(cf.compass).values() for n in group}
    return {k: v for k, v in params.items() if k in names}


def _start(log: FlightLog, cf: CompassField, ctx: LogContext, settings: CalibrateSettings) -> dict:
    r = empty_result(log.source, cf.compass)
    r.update(device_id=cf.device_id, source=cf.source, autopilot=cf.autopilot, corrections=_corrections_dict(cf),
             onboard_report=onboard_report(log.mag_cal, cf.compass), settings=settings_record(settings))
    if ctx.field is not None:
        r["expected_field_mG"] = finite_or_none(ctx.field.field_strength_mG)
    r.update(attitude_source=ctx.attitude_source or None, attitude_choice=ctx.attitude_choice,
             reference_field=ctx.field_refinement)
    return r


def _from_window(r: dict, w: CalWindow, sel: np.ndarray, cf: CompassField) -> tuple:
    fit = w.fit
    r.update(method="window", window_s=[round(float(cf.t_s[sel][0]), 2), round(float(cf.t_s[sel][-1]), 2)], samples=int(fit.n_used),
             coverage=round(float(w.coverage), 3), field_strength_mG=finite_or_none(fit.field_strength_mG),
             residual_rms_mG=finite_or_none(fit.residual_rms_mG), condition_number=finite_or_none(fit.condition_number),
             offsets_sd_mG=_vec(w.offsets_sd_mG, 2))
    return np.asarray(fit.offsets_mG, float), np.asarray(fit.matrix, float)


def _from_inflight(r: dict, fit, cf: CompassField, signal: np.ndarray | None) -> tuple:
    """The in-flight fit's answer.  Its field strength is the Earth field's the calibration gives,
    C (m − b) − f·x with the fitted motor field out (``signal`` x at cf's samples): with it in, the
    ArduPilot SITL route flights read 16–19 % above the WMM at 35–40 A, and the WMM scale of the
    export (``wmm_scale``) took 15 % off every exported DIA."""
    used = cf.t_s[cf.valid]
    cal = apply_calibration(cf.raw_mG, fit.offsets_mG, fit.matrix)
    f = np.nan_to_num(np.asarray(fit.motor_mG_per_unit, float))
    if np.any(f):
        x = np.full(len(cal), np.nan) if signal is None else np.asarray(signal, float)
        cal = cal - x[:, None] * f               # samples without the motor signal drop out of the median
    r.update(method="wmm_inflight", window_s=[round(float(used[0]), 2), round(float(used[-1]), 2)],
             samples=int(fit.n_used), coverage=round(float(fit.heading_coverage), 3),
             field_strength_mG=finite_or_none(np.nanmedian(np.linalg.norm(cal, axis=1))),
             residual_rms_mG=finite_or_none(fit.residual_rms_mG), offsets_sd_mG=_vec(fit.offsets_sd_mG, 2),
             recommended=bool(fit.recommended), recommendation=fit.reason, offsets_covariance_mG2=offsets_covariance(fit),
             course_check=fit.course,
             heading_change_deg=heading_change(fit))
    return np.asarray(fit.offsets_mG, float), np.asarray(fit.matrix, float)


LOW_SIGNAL_SHARE = 0.1      # motor field unknown: "low" = the bottom tenth of the window's signal range
LOW_SIGNAL_MAX_FRACTION = 0.9  # ... and refitted only when the rest (powered samples) is more than a tenth


def motor_free_window(window, cf: CompassField, signal: np.ndarray | None, signal_name: str, wmm, limit_mG: float,
                      ws: WindowSettings) -> tuple[CalWindow | None, np.ndarray | None, str]:
    """The calibration window to use, the samples its fit takes, and a note.  A window fit has no
    motor term, so a window flown with the motors drawing current carries the motor field f·I in
    its offsets.  Measured on ArduPilot SITL (SIM_MAG_MOT (−2.2, −3.1, −4.9) mG/A, 24 A): a window
    fit recommended with 1σ ≤ 1 mG and 80 mG off; on the simulated demo (a dance at 0 A, then a
    mission at 20 A, one window), 20 mG off.

    With the in-flight fit's motor term f (mG per ampere or per unit throttle): when |f| × the
    window's mean |signal| exceeds ``limit_mG``, the window is fitted again on its samples where
    |f|·|signal| ≤ ``limit_mG`` and judged as any window (estimators.cal_windows.judge_window);
    (None, None, why) when those are not sufficient.  Without it (f unknown), a window holding both
    low-signal samples (the bottom ``LOW_SIGNAL_SHARE`` of its signal range) and more than a tenth of
    powered ones is fitted on the low-signal ones when they are sufficient, else used whole.
    The window unchanged (its whole time span) when there is no signal."""
    whole = (window, None if window is None else window_mask(cf, window), "")
    if window is None or signal is None:
        return whole
    inside = whole[1] & np.isfinite(signal)
    if not inside.any():
        return whole
    unit = "A" if signal_name == "current_A" else "throttle"
    level = float(np.mean(np.abs(signal[inside])))
    known = wmm is not None and "f_x" in wmm.fitted
    if known:
        per_unit = float(np.linalg.norm(wmm.motor_mG_per_unit))
        if per_unit * level <= limit_mG:
            return whole
        why = (f"calibration window {window.start_s:.0f}-{window.end_s:.0f} s flown at {level:.3g} {unit}: its "
               f"offsets carry {per_unit * level:.0f} mG of motor field (limit {limit_mG:g} mG)")
        low = inside & (per_unit * np.abs(signal) <= limit_mG)
        below = f"{limit_mG / per_unit:.3g} {unit}"
    else:
        lo, hi = float(np.min(np.abs(signal[inside]))), float(np.max(np.abs(signal[inside])))
        low = inside & (np.abs(signal) <= lo + LOW_SIGNAL_SHARE * (hi - lo))
        if not hi > lo or low.sum() > LOW_SIGNAL_MAX_FRACTION * inside.sum():
            return whole
        why = (f"calibration window {window.start_s:.0f}-{window.end_s:.0f} s flown at {lo:.3g}-{hi:.3g} {unit} with "
               "the motor field unknown (the in-flight fit has no motor term)")
        below = f"{lo + LOW_SIGNAL_SHARE * (hi - lo):.3g} {unit}"
    t = cf.t_s[low]
    refit = judge_window(float(t[0]), float(t[-1]), window.source + "+low_signal", cf.raw_mG[low], ws) \
        if low.sum() >= ws.min_samples else None
    if refit is None or not refit.sufficient:
        detail = (f"only {int(low.sum())} samples at ≤ {below}" if refit is None else
                  f"its {refit.n_samples} samples at ≤ {below} are not enough ({refit.reason})")
        if known:
            return None, None, f"{why}; not used: {detail} (the in-flight fit has the motor term)"
        return window, whole[1], f"{why}; used whole: {detail}"
    return refit, low, (f"{why}: fitted again on its {refit.n_samples} samples at ≤ {below}"
                        + (f" (motor field ≤ {limit_mG:g} mG; " if known else " (")
                        + f"coverage {refit.coverage:.0%}, offsets 1σ ≤ {np.max(refit.offsets_sd_mG):.1f} mG)")


def _failure_status(step, wmm, notes: list[str]) -> str:
    """The reason named when neither a window nor the in-flight fit gave offsets."""
    if wmm is not None and wmm.status in SPECIFIC_INFLIGHT_STATUSES:
        return wmm.status
    if step.search.status == "no_data":
        return "no_data"
    return "insufficient_coverage"


def _motor(r: dict, log: FlightLog, cf: CompassField, x, ctx: LogContext, settings: CalibrateSettings, wmm):
    if x is None or x.signal is None or not settings.motor_fit:
        return None
    fit = motor_step(cf, x, ctx, wmm)
    R = None
    if cf.px4_slot is not None:
        try:
            R = px4_rotation(log.params, cf.px4_slot)
        except ValueError:
            R = None
    r["motor"] = motor_dict(fit, cf.compass, cf.px4_slot if cf.px4_slot is not None else cf.compass, R)
    return fit if fit.status == "ok" else None


def _orientation_export(r: dict, log: FlightLog, cf: CompassField, b, C, check, notes: list[str]):
    """COMPASS_ORIENTn (with the offsets and matrix re-expressed in that frame) / CAL_MAGn_ROT when
    another rotation fits clearly best."""
    if check is None or check.status != "rotation_found" or check.best_id is None:
        return b, C
    if cf.autopilot == "ardupilot":
        n = "" if cf.compass == 0 else str(cf.compass + 1)
        ext = log.params.get("COMPASS_EXTERNAL" if cf.compass == 0 else f"COMPASS_EXTERN{n}", 1.0)
        if not ext:
            notes.append(f"internal compass: rotation {check.best_id} fits best; check AHRS_ORIENTATION, "
                         "COMPASS_ORIENT does not apply")
            return b, C
        r["ardupilot_params"][f"COMPASS_ORIENT{n}"] = float(check.best_id)
        notes.append(f"COMPASS_ORIENT{n} = {check.best_id} exported; offsets and matrix re-expressed in that frame")
        return reorient(b, C, cf.orientation_id, check.best_id)
    if cf.autopilot == "px4" and cf.px4_slot is not None and log.params.get(f"CAL_MAG{cf.px4_slot}_ROT", -1) >= 0:
        r["px4_params"][f"CAL_MAG{cf.px4_slot}_ROT"] = float(check.best_id)
        notes.append(f"CAL_MAG{cf.px4_slot}_ROT = {check.best_id} exported (sensor-frame offsets unchanged)")
    return b, C


def _export(r: dict, log: FlightLog, cf: CompassField, b, C, motor, check, notes: list[str]) -> None:
    k = wmm_scale(r.get("field_strength_mG"), r.get("expected_field_mG"))    # ArduPilot's fix_radius
    ap, px4 = export_params(b, C, log.params, compass=cf.compass, device_id=cf.device_id, scale=k)
    r["ardupilot_params"], r["px4_params"] = dict(ap), dict(px4)
    if motor is not None:
        r["ardupilot_params"].update(r["motor"]["ardupilot_params"])
        r["px4_params"].update(r["motor"]["px4_params"])
    elif r["method"] == "wmm_inflight" and any(cf.motor_in_force.get("per_unit") or []):
        notes.append("COMPASS_MOT in force was un-applied and not re-fitted: the offsets include the mean motor field")
    b2, C2 = _orientation_export(r, log, cf, b, C, check, notes)
    if b2 is not b:
        ap2, _ = export_params(b2, C2, log.params, compass=cf.compass, device_id=cf.device_id, scale=k)
        r["ardupilot_params"].update(ap2)
    ofs = [v for k, v in ap.items() if "_OFS" in k]
    if any(abs(v) > 1800 for v in ofs):
        notes.append("offset beyond ArduPilot's default COMPASS_OFFS_MAX (1800 mG)")


def _compare_report(r: dict) -> None:
    """Largest per-axis difference between our COMPASS_OFS and the vehicle's MAG_CAL_REPORT."""
    rep = r.get("onboard_report")
    if rep is None or r["offsets_mG"] is None or None in (rep.get("COMPASS_OFS") or [None]):
        return
    ours = -np.asarray(r["offsets_mG"], float)
    rep["difference_mG"] = round(float(np.max(np.abs(ours - np.asarray(rep["COMPASS_OFS"], float)))), 2)


def calibrate_compass(log: FlightLog, cf: CompassField, ctx: LogContext, settings: CalibrateSettings
                      ) -> tuple[dict, tuple[np.ndarray, np.ndarray] | None]:
    """The result object of one compass and its calibration (b, C) when one was found."""
    r = _start(log, cf, ctx, settings)
    notes = [cf.note] + ([ctx.field_note] if ctx.field_note else [])
    valid = cf.valid
    if (~valid).sum():
        notes.append(f"{int((~valid).sum())} samples without a finite raw field rejected")
    r["samples"] = int(valid.sum())
    if not valid.any():
        r.update(status="no_data", message="; ".join(["no finite magnetometer samples"] + notes))
        return r, None
    logged = np.asarray(cf.logged_mG, float)
    fin = np.all(np.isfinite(logged), axis=1)
    if fin.any() and not np.any(logged[fin]):
        r.update(status="no_data", recommended=False, recommendation="no answer: no compass data",
                 message=f"no compass data: this compass reads 0 in all {int(fin.sum())} samples "
                         "(not fitted; disabled, unplugged or not logged)")
        return r, None
    step = window_step(log, cf, ctx, settings)
    r["windows"] = window_dicts(step.search, cf.t_s)
    x = flight_inputs(log, cf, settings.inflight_max_samples, ctx) if ctx.field is not None and settings.inflight_fit else None
    wmm = inflight_step(cf, x, ctx, settings) if x is not None else None
    r["inflight"] = wmm_dict(wmm, cf.t_s) if wmm is not None else None
    signal, signal_name = motor_signal(log, cf) if x is not None else (None, "")
    window, mask, why = motor_free_window(step.search.chosen_window, cf, signal, signal_name, wmm,
                                          settings.window_max_motor_field_mG, step.search.settings)
    refitted = window is not step.search.chosen_window
    if why:
        notes.append(why)
    if refitted:
        r["windows"][step.search.chosen].update(chosen=False, reason=why)
        if window is not None:
            r["windows"].append(window_dict(window, True, cf.t_s))
    cal = _from_window(r, window, mask, cf) if window is not None else None
    motor = _motor(r, log, cf, x, ctx, settings, wmm)
    used = None
    if cal is not None:
        r.update(recommended=True, recommendation=f"recommended: fitted on a calibration window "
                 f"(coverage {r['coverage']:.0%}" + (", its low-current samples)" if refitted else ")"))
    elif motor is not None and motor.wmm is not None and motor.wmm.status == "ok":
        used = motor.wmm
        cal = _from_inflight(r, motor.wmm, cf, signal)
    elif wmm is not None and wmm.status in ("ok", "weak"):
        used = wmm          # weak: an answer with its 1σ, marked not recommended (status "weak")
        cal = _from_inflight(r, wmm, cf, signal)
        motor = None if wmm is None or "f_x" not in wmm.fitted else motor
    r, cal = _finish(r, log, cf, ctx, settings, step, (window, mask), wmm, motor, cal, notes)
    if cal is None:
        r.update(recommended=False, recommendation=r.get("recommendation") or (wmm.reason if wmm is not None else
                 "no answer: " + r["message"].split("; ")[0]))
    elif used is not None and used.status == "weak":
        r["status"] = "weak"            # not a calibration to use: the station and review take status "ok" only
        return r, None
    return r, cal


def _body_matrix(r: dict, log: FlightLog, cf: CompassField, ctx: LogContext, settings: CalibrateSettings,
                 window: tuple, cal: tuple, check, notes: list[str]) -> np.ndarray:
    """The result's matrix maps the log's raw frame to the body: with the rotation the orientation
    check found (Q = R_best R_inuseᵀ), else with the small misalignment estimated from the
    attitude on a calibration window (seed 004), else the fitted symmetric matrix."""
    b, C = cal
    if check is not None and check.status == "rotation_found" and check.best_id is not None:
        Q = rotation_enum_matrix(check.best_id) @ rotation_enum_matrix(cf.orientation_id).T
        return Q @ C
    if r["method"] != "window":
        return C
    R, angles, note = misalignment(log, cf, ctx, *window, C, settings)
    if note:
        notes.append(note)
    if R is None:
        return C
    r["misalignment_deg"] = angles
    return R @ C


def _orientation_without_calibration(r: dict, log: FlightLog, cf: CompassField, ctx: LogContext,
                                     settings: CalibrateSettings, wmm) -> list[str]:
    """No calibration: the orientation check on the field as the autopilot corrected it (a wrong
    COMPASS_ORIENT is a common reason for an in-flight fit that does not converge); reported only."""
    if not settings.orientation_check:
        return []
    ref = orientation_reference(ctx, None if wmm is None else wmm.yaw_dependence, settings)
    check = orientation_step(log, cf, None, ctx, settings, ref)
    r["orientation"] = orientation_dict(check, ref)
    if check is not None and check.status == "rotation_found":
        return [f"the field as corrected fits rotation {check.best_id} clearly better than the one in use "
                f"({check.current_id}): check the compass orientation, then calibrate again"]
    return []


def _finish(r, log, cf, ctx, settings, step, window, wmm, motor, cal, notes) -> tuple[dict, tuple | None]:
    if cal is None:
        why = [f"calibration windows: {step.search.message}"]
        if wmm is not None:
            why.append(f"in-flight fit: {wmm.status}: {wmm.message}")
        elif ctx.field is None or len(log.attitude) < 2:
            why.append("no in-flight fit (needs the attitude and a GPS position for the WMM)")
        best = max(step.search.windows, key=lambda w: w.n_samples, default=None)
        why += _orientation_without_calibration(r, log, cf, ctx, settings, wmm)
        r.update(status=_failure_status(step, wmm, notes), message="; ".join(why + notes),
                 coverage=round(float(best.coverage), 3) if best is not None else 0.0)
        return r, None
    b, C = cal
    ref = orientation_reference(ctx, None if wmm is None else wmm.yaw_dependence, settings)
    check = orientation_step(log, cf, (b, C), ctx, settings, ref) if settings.orientation_check else None
    r["orientation"] = orientation_dict(check, ref)
    C_body = _body_matrix(r, log, cf, ctx, settings, window, (b, C), check, notes)
    r.update(offsets_mG=_vec(b, 4), matrix=[_vec(row, 6) for row in C_body])
    if cf.status in LOG_RAW_UNKNOWN_STATUSES:
        r.update(status="ok", relative_to="unknown", corrections_in_force=None, message="; ".join(
            [cf.note + ": the fit is relative to the corrections in force (unknown), right for logs flown with "
             "the same corrections; nothing to write (give --params FILE or --assume-uncalibrated for the "
             "parameters)"] + notes[1:]))
        return r, (b, C_body)
    end = len(cf.offsets_in_force_mG) - 1
    r.update(relative_to="raw", corrections_in_force=corrections_record(
        cf.offsets_in_force_mG[end] if end >= 0 else np.full(3, np.nan), cf.nominal_matrix, _params_of(log, cf)))
    _export(r, log, cf, b, C, motor, check, notes)
    if ctx.field is not None and r["field_strength_mG"] is not None:
        notes.append(f"fitted field {r['field_strength_mG']:.0f} mG vs WMM {ctx.field.field_strength_mG:.0f} mG")
    r.update(status="ok", message="; ".join(notes))
    _compare_report(r)
    return r, (b, C_body)
