"""The per-log job of `magstation review`: one log -> one row per compass (``groundstation.io.fleet_db``
columns).  Pure function of the file and the settings; never raises; returns small dicts.

This is the one place that decides what a log contributes to the fleet history.  Per log: content
hash (SHA-256, streamed), ``read_log``, vehicle identity (parameters and status text), date and
place, data quality, ``analyze_log``'s alarms and cross-track.  Per compass (``jobs.compass_raw.
compass_fields``: every compass, raw with the corrections in force un-applied): the corrections in
force, ``jobs.calibrate``'s in-flight WMM fit (``estimators.wmm_fit``) and motor field
(``estimators.motor_field``) — with the review's settings, ``REVIEW_CALIBRATE`` — the window fit
when the log holds a calibration dance, and field strength / inclination / heading residuals
against the WMM and the autopilot's yaw.

``attitude_source`` says which attitude each part used: the alarms are analyze's, decided on the
causal default AHRS (the live station's, ``ATTITUDE_ALARMS``); the field and heading residuals use
the autopilot's own ATTITUDE (``ATTITUDE_RESIDUALS``), the reference they are compared against.
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from estimators.detection import field_inclination_deg
from estimators.heading import tilt_compensated_heading_rad
from estimators.rotations import wrap_angle_deg
from estimators.wmm_fit import WmmFitSettings
from groundstation.io.errors import IngestError
from groundstation.io.fleet_db import empty_row
from groundstation.io.logs import read_log
from groundstation.io.params import detect_autopilot
from groundstation.jobs.airframes import identity_key
from groundstation.jobs.analyze import analyze_log
from groundstation.jobs.calibrate import CalibrateSettings
from groundstation.jobs.calibrate.compass import calibrate_compass
from groundstation.jobs.calibrate.context import attitude_for, log_context
from groundstation.jobs.calibrate.reference import refine_reference
from groundstation.jobs.compass_raw import CompassField, compass_fields, motor_signals
from groundstation.jobs.inputs import field_reference, rounded
from groundstation.process_memory import peak_rss_MB
from groundstation.samples import FlightLog

__all__ = ["ReviewSettings", "REVIEW_CALIBRATE", "review_log", "file_hash", "vehicle_identity", "compass_row",
           "alarm_fields", "ROW_VERSION", "ATTITUDE_ALARMS", "ATTITUDE_RESIDUALS"]

ROW_VERSION = 5      # 4: weak in-flight fits (offsets with their 1σ) carry their offsets; 5: the in-flight
                     # fit independent of its start, the attitude's tilt in its 1σ (2026-12-07)
ATTITUDE_ALARMS = "alarms: causal AHRS (the live detector's)"
ATTITUDE_RESIDUALS = "residuals: autopilot ATTITUDE"
_UID_TEXT = re.compile(r"^\S+\s+([0-9A-Fa-f]{8}\s+[0-9A-Fa-f]{8}\s+[0-9A-Fa-f]{8})\s*$")

# The calibrate job as the review runs it: the in-flight WMM fit estimates the offsets (and the motor
# field) with the correction matrix held at the one in force — the review watches hard iron move
# against the vehicle's calibration; fitting the matrix on a level flight trades the z offset
# against the z scale (measured on the simulated fleet: 25 mG flight-to-flight z scatter with the
# matrix fitted, 8 mG held).  A held matrix leaves the fit's sd larger (2° of misalignment stays
# in the residual), so the sd limit is 15 mG instead of 5; the drift test weighs flights by it.
REVIEW_CALIBRATE = CalibrateSettings(wmm=WmmFitSettings(fit_diagonal=False, fit_offdiagonal=False,
                                                        max_offset_sd_mG=15.0), orientation_check=False)


@dataclass(frozen=True)
class ReviewSettings:
    """What the per-log job does (units in the names).  ``calibrate``: the in-flight fit's settings."""
    calibrate: CalibrateSettings = REVIEW_CALIBRATE
    # the calibration for a log without its own dance (jobs.review_calibration): the history's
    # calibrations ((airframe, unix_s, calibration JSON), ...) and --params values ((name, value), ...)
    calibrations: tuple = ()
    params: tuple = ()
    params_label: str | None = None
    alarm_margin_s: float = 5.0          # samples this close to an alarm are left out of the field residuals
    max_tilt_deg: float = 45.0           # ... and steeper ones (dance, carried)


def file_hash(path: str | os.PathLike, chunk_bytes: int = 1 << 20) -> str:
    """SHA-256 of the file's bytes (hex), read in chunks (never the whole file in memory)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk_bytes):
            h.update(block)
    return h.hexdigest()


def review_log(path: str | os.PathLike, settings: ReviewSettings = ReviewSettings(),
               skip_hashes: frozenset[str] | set[str] = frozenset()) -> list[dict]:
    """Review one log: a list of rows (one per compass; one row with ``status`` "error" when the log
    cannot be read, "skipped" when its hash is in ``skip_hashes``).  Never raises."""
    t0 = (time.perf_counter(), time.thread_time())
    path = Path(path)
    row = empty_row()
    row.update(path=str(path), file_name=path.name, compass=0, row_version=ROW_VERSION, reviewed_unix_s=time.time())
    try:
        row["file_bytes"] = path.stat().st_size
        row["log_hash"] = file_hash(path)
    except OSError as err:
        row.update(status="error", error=f"{path.name}: {err.strerror or err}", log_hash=f"unreadable:{path}")
        return [_finish(row, t0)]
    if row["log_hash"] in skip_hashes:
        return [{"log_hash": row["log_hash"], "path": str(path), "status": "skipped"}]
    try:
        log = read_log(path)
        rows = _log_rows(log, path, row, settings)
    except IngestError as err:
        row.update(status="error", error=str(err))
        rows = [row]
    except Exception as err:  # the job must give a row whatever the log does
        row.update(status="error", error=f"{type(err).__name__}: {err}")
        rows = [row]
    return [_finish(r, t0) for r in rows]


def _finish(row: dict, t0: tuple[float, float]) -> dict:
    """Runtime fields added (wall time and this thread's CPU time since ``t0``: their ratio shows
    how much CPU the worker got); numpy scalars made plain Python (SQLite, pickling, Parquet)."""
    row["review_s"] = round(time.perf_counter() - t0[0], 4)
    row["review_cpu_s"] = round(time.thread_time() - t0[1], 4)
    peak = peak_rss_MB()
    row["worker_peak_rss_MB"] = None if peak is None else round(peak, 1)
    return {k: (v.item() if isinstance(v, np.generic) else v) for k, v in row.items()}


# ------------------------------------------------------------------------------ per log
def vehicle_identity(log: FlightLog, path: Path) -> dict:
    """System id, board serial, board UID and the key that names the vehicle
    (``groundstation.jobs.airframes.identity_key``)."""
    uid = next((m.group(1).upper() for s in log.status if s.kind == "statustext"
                for m in [_UID_TEXT.match(s.text)] if m), None)
    ident = identity_key(log.params, board_uid=uid, folder=path.parent.name or ".")
    return {**ident, "airframe": ident["identity"], "autopilot": log.autopilot or detect_autopilot(log.params)}


def _rate_hz(table: np.ndarray) -> float | None:
    if len(table) < 2 or table[-1, 0] <= table[0, 0]:
        return None
    return round((len(table) - 1) / (table[-1, 0] - table[0, 0]), 2)


def data_quality(log: FlightLog) -> dict:
    """Rates, the longest gap between field (else IMU) samples, corrupt packets and the warnings."""
    t = log.mag[:, 0] if len(log.mag) > 1 else log.imu[:, 0]
    corrupt = sum(v for k, v in log.warnings.items() if "corrupt" in k)
    return {"mag_rate_hz": _rate_hz(log.mag), "imu_rate_hz": _rate_hz(log.imu), "att_rate_hz": _rate_hz(log.attitude),
            "gps_rate_hz": _rate_hz(log.gps), "max_gap_s": rounded(np.max(np.diff(t)), 3) if len(t) > 1 else None,
            "corrupt_packets": int(corrupt),
            "warnings": "; ".join(f"{k} ({v})" for k, v in log.warnings.items()) or None}


def _log_rows(log: FlightLog, path: Path, row: dict, settings: ReviewSettings) -> list[dict]:
    from groundstation.jobs.review_calibration import apply_review_params, review_calibration

    apply_review_params(log, settings)
    row.update(vehicle_identity(log, path))
    row.update(data_quality(log))
    ef, pos = field_reference(log)
    start = log.start_unix_s
    row.update(start_unix_s=start, duration_s=rounded(log.duration_s, 2),
               date=_dt.datetime.fromtimestamp(start, _dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ") if start else None)
    if pos:
        row.update(lat_deg=pos[0], lon_deg=pos[1], alt_m=rounded(pos[2], 1))
    if ef is not None:
        row.update(wmm_strength_mG=rounded(ef.field_strength_mG, 1), wmm_inclination_deg=rounded(ef.inclination_deg),
                   wmm_declination_deg=rounded(ef.declination_deg))
    fields = [cf for cf in compass_fields(log) if len(cf.t_s)]
    if not fields:
        row.update(status="no_mag", compasses=0, error="the log has no magnetometer samples")
        return [row]
    ctx = refine_reference(log, fields, log_context(log), settings.calibrate)   # the reference field, as calibrate
    refined = ctx.field_refinement or {}
    if refined.get("flight_estimate_mG") is not None:       # the inclination the flight measured (with the WMM's)
        row.update(field_inclination_deg=refined["inclination_deg"], field_inclination_sd_deg=refined["inclination_sd_deg"])
    results = {cf.compass: _calibrate(log, cf, ctx, settings) for cf in fields}    # once per compass
    calibration, row["calibration_used"] = review_calibration(log, row["identity"], settings,
                                                              results.get(log.primary_compass))
    report, _ = analyze_log(log, calibration=calibration, columns=False)    # the report alone
    if calibration is None:
        row["calibration_used"] += f" ({report.get('calibration_in_use')})"
    row.update(alarm_fields(report))
    row.update(max_cross_track_m=report.get("max_cross_track_m"), rtk=int(bool(report.get("rtk"))),
               compasses=len(fields), status="ok")
    return [{**row, **compass_row(log, cf, ctx, report, settings, results[cf.compass])} for cf in fields]


def alarm_fields(report: dict) -> dict:
    """Combined alarms (count, first time, every interval, evidence) and the kinds of test that fired.
    ``alarm_intervals_s`` is JSON ``[[start_s, end_s or null, "evidence+..."], ...]``: the first alarm
    alone would hide an interference event that follows an earlier alarm of the same flight."""
    alarms = report.get("alarms") or []
    combined = [a for a in alarms if a["kind"] == "combined"]
    kinds = sorted({a["kind"] for a in alarms if a["kind"] != "combined"})
    evidence = sorted({e for a in combined for e in a.get("evidence", [])})
    intervals = [[a.get("start_s"), a.get("end_s"), "+".join(a.get("evidence", []))] for a in combined]
    return {"alarm_count": len(combined), "alarm_kinds": ",".join(kinds) or None,
            "first_alarm_s": report.get("first_alarm_s"), "alarm_evidence": ",".join(evidence) or None,
            "alarm_intervals_s": json.dumps(intervals) if intervals else None}


# ------------------------------------------------------------------------------ per compass
def _vector(prefix: str, values, unit: str = "mG", nd: int = 2) -> dict:
    return {f"{prefix}_{a}_{unit}": rounded(v, nd) if v is not None else None for a, v in zip("xyz", values)}


def _calibrate(log: FlightLog, cf: CompassField, ctx, settings: ReviewSettings) -> dict:
    """``jobs.calibrate``'s result for this compass (windows, in-flight WMM fit, motor field)."""
    try:
        result, _ = calibrate_compass(log, cf, ctx, settings.calibrate)
        return result
    except Exception as err:  # a compass the calibrate job cannot handle still gets its row
        return {"status": "error", "message": f"{type(err).__name__}: {err}", "method": None,
                "inflight": None, "motor": None}


def _fit_fields(result: dict, in_force_mG: np.ndarray) -> dict:
    """The in-flight WMM fit (offsets against the corrections in force) and the motor field."""
    fit = result.get("inflight") or {}
    out = {"fit_model": fit.get("model"), "fit_status": fit.get("status") or "no_fit",
           "fit_samples": fit.get("samples"), "fit_yaw_dependence": fit.get("yaw_dependence"),
           "fit_heading_coverage": fit.get("heading_coverage"), "fit_residual_rms_mG": fit.get("residual_rms_mG")}
    if result.get("method") == "window":
        out.update(ellipsoid_status=result["status"], **_vector("ellipsoid_ofs", result["offsets_mG"] or [None] * 3))
    if fit.get("status") in ("ok", "weak"):      # weak: offsets with their 1σ, not recommended (drift uses "ok")
        ofs = np.array(fit["offsets_mG"], float)
        out.update(_vector("fit_ofs", ofs))
        out.update(_vector("fit_ofs_sd", fit["offsets_sd_mG"], nd=3))
        out.update(_vector("ofs_change", ofs - in_force_mG))
        out["ofs_change_mG"] = rounded(np.linalg.norm(ofs - in_force_mG), 2)
    motor = result.get("motor") or {}
    out["motor_status"] = motor.get("status")
    if motor.get("status") == "ok":
        out.update(interference_pct=motor["interference_pct"], current_max_A=motor["signal_max"])
        if motor["signal"] == "current_A":
            out.update(_vector("motor", motor["motor_mG_per_unit"], "mG_per_A", 3))
            out["motor_sd_mG_per_A"] = rounded(np.linalg.norm(np.array(motor["motor_sd_mG_per_unit"], float)), 4)
    return out


def compass_row(log: FlightLog, cf: CompassField, ctx, report: dict, settings: ReviewSettings,
                result: dict | None = None) -> dict:
    """One compass: the corrections in force (``jobs.compass_raw``), the calibrate job's in-flight
    WMM fit and motor field, and the field / heading residuals of the field as the autopilot
    corrected it (fitted motor field removed) over level flight away from alarms."""
    in_force = cf.offsets_in_force_mG[-1] if len(cf.offsets_in_force_mG) else np.full(3, np.nan)
    out = {"compass": cf.compass, "device_id": cf.device_id, "compass_source": cf.source, "cal_state": cf.status,
           **_vector("cal_ofs", in_force)}
    result = _calibrate(log, cf, ctx, settings) if result is None else result
    out.update(_fit_fields(result, in_force))
    if ctx.field is None or len(log.attitude) < 2:
        why = "no WMM field" if ctx.field is None else "no autopilot ATTITUDE"
        out["attitude_source"] = f"{ATTITUDE_ALARMS}; residuals: none ({why})"
        return out
    out["attitude_source"] = f"{ATTITUDE_ALARMS}; {ATTITUDE_RESIDUALS}"
    t = cf.t_s
    at = attitude_for(log, t)
    m_c = np.array(cf.in_force_mG, float)
    current, _ = motor_signals(log, t)
    if current is not None and out.get("motor_x_mG_per_A") is not None:
        k = np.array([out[f"motor_{a}_mG_per_A"] for a in "xyz"], float)
        m_c = m_c - np.nan_to_num(current)[:, None] * k
    use = np.cos(at.roll_rad) * np.cos(at.pitch_rad) >= np.cos(np.radians(settings.max_tilt_deg))
    for start, end in _windows(report):
        use &= ~((t >= start - settings.alarm_margin_s) & (t <= end + settings.alarm_margin_s))
    rp = np.column_stack([at.roll_rad, at.pitch_rad])
    out.update(field_residuals(m_c[use], rp[use], at.yaw_rad[use], ctx.field))
    return out


def field_residuals(m_c: np.ndarray, rp: np.ndarray, yaw: np.ndarray, ef) -> dict:
    """Median field strength and inclination minus the WMM's, and the compass heading (corrections in
    force, fitted motor field removed) against the autopilot's yaw: RMS and 99th percentile."""
    strength = np.linalg.norm(m_c, axis=1)
    incl = field_inclination_deg(m_c, rp[:, 0], rp[:, 1])
    good = np.isfinite(strength) & np.isfinite(incl)
    if not good.any():
        return {}
    out = {"strength_resid_mG": rounded(np.median(strength[good]) - ef.field_strength_mG, 2),
           "inclination_resid_deg": rounded(np.median(incl[good]) - ef.inclination_deg, 3)}
    hdg = np.degrees(tilt_compensated_heading_rad(m_c[good], rp[good, 0], rp[good, 1])) + ef.declination_deg
    err = wrap_angle_deg(hdg - np.degrees(yaw[good]))
    err = err[np.isfinite(err)]
    if len(err):
        out["heading_vs_autopilot_rms_deg"] = rounded(np.sqrt(np.mean(err ** 2)), 2)
        out["heading_vs_autopilot_max_deg"] = rounded(np.percentile(np.abs(err), 99), 2)
    return out


def _windows(report: dict) -> list[tuple[float, float]]:
    """(start, end) of each combined alarm; an alarm still on at the end of the log ends at +inf."""
    return [(a["start_s"], np.inf if a["end_s"] is None else a["end_s"])
            for a in report.get("alarms") or [] if a["kind"] == "combined" and a["start_s"] is not None]
