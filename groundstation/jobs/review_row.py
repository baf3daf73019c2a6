"""The per-log job of `magstation review`: one log -> one row per compass (``groundstation.io.fleet_db``
columns).  Pure function of the file and the settings; never raises; returns small dicts.

This is the one place that decides what a log contributes to the fleet history: swap the pieces
here (``compass_fields``) when the calibrate job gains every compass and the WMM / motor fits.

Per log: content hash (SHA-256, streamed), ``read_log``, vehicle identity (parameters and status
text), date and place, data quality; per compass: the corrections in force, the in-flight fit
(``groundstation.jobs.review_fit``), field strength / inclination against the WMM with the
corrections in force, heading against the autopilot's yaw, and ``analyze_log``'s alarms and
cross-track.  A log with a calibration dance also gets the ellipsoid fit of ``calibrate_log``.
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estimators.detection import field_inclination_deg
from estimators.heading import tilt_compensated_heading_rad
from estimators.rotations import wrap_angle_deg
from groundstation.io.errors import IngestError
from groundstation.io.fleet_db import empty_row
from groundstation.io.logs import read_log
from groundstation.io.params import (ardupilot_matrix, ardupilot_never_calibrated, detect_autopilot, px4_matrix,
                                     px4_slot, unapply_onboard_calibration)
from groundstation.jobs.airframes import identity_key
from groundstation.jobs.analyze import analyze_log
from groundstation.jobs.calibrate import calibrate_log
from groundstation.jobs.inputs import field_reference, rounded
from groundstation.jobs.review_fit import FIT_MODELS, InflightFitSettings, fit_compass
from estimators.log_alignment import attitude_at, interp_series
from groundstation.samples import FlightLog

__all__ = ["ReviewSettings", "review_log", "file_hash", "vehicle_identity", "corrections_in_force", "ROW_VERSION"]

ROW_VERSION = 1
_UID_TEXT = re.compile(r"^\S+\s+([0-9A-Fa-f]{8}\s+[0-9A-Fa-f]{8}\s+[0-9A-Fa-f]{8})\s*$")


@dataclass(frozen=True)
class ReviewSettings:
    """What the per-log job does (units in the names).  ``fit_model``: see ``review_fit.FIT_MODELS``."""
    fit_model: str = "residual_matrix"
    fit: InflightFitSettings = field(default_factory=InflightFitSettings)
    alarm_margin_s: float = 5.0          # samples this close to an alarm are not fitted
    max_tilt_deg: float = 45.0           # steeper samples (dance, carried) are not fitted

    def __post_init__(self) -> None:
        if self.fit_model not in FIT_MODELS:
            raise ValueError(f"unknown in-flight fit {self.fit_model!r} (choose from {', '.join(FIT_MODELS)})")


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
    t0 = time.perf_counter()
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


def _finish(row: dict, t0: float) -> dict:
    """Runtime fields added; numpy scalars made plain Python (SQLite, pickling, Parquet)."""
    row["review_s"] = round(time.perf_counter() - t0, 4)
    row["worker_peak_rss_MB"] = _peak_rss_MB()
    return {k: (v.item() if isinstance(v, np.generic) else v) for k, v in row.items()}


def _peak_rss_MB() -> float | None:
    """High-water mark of this process's resident memory (a worker's, when run on Dask)."""
    try:
        import resource
        return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)   # kB on Linux
    except (ImportError, OSError):
        return None


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
    if not len(log.mag):
        row.update(status="no_mag", compasses=0, error="the log has no magnetometer samples")
        return [row]
    report, _ = analyze_log(log)
    row.update(alarm_fields(report))
    row.update(max_cross_track_m=report.get("max_cross_track_m"), rtk=int(bool(report.get("rtk"))), compasses=1)
    cal = calibrate_log(log)
    row["ellipsoid_status"] = cal["status"]
    if cal.get("offsets_mG"):
        row.update({f"ellipsoid_ofs_{a}_mG": rounded(v, 2) for a, v in zip("xyz", cal["offsets_mG"])})
    row.update(compass_fields(log, report, ef, settings))
    row["status"] = "ok"
    return [row]


def alarm_fields(report: dict) -> dict:
    """Combined alarms (count, first time, evidence) and the kinds of test that fired."""
    alarms = report.get("alarms") or []
    combined = [a for a in alarms if a["kind"] == "combined"]
    kinds = sorted({a["kind"] for a in alarms if a["kind"] != "combined"})
    evidence = sorted({e for a in combined for e in a.get("evidence", [])})
    return {"alarm_count": len(combined), "alarm_kinds": ",".join(kinds) or None,
            "first_alarm_s": report.get("first_alarm_s"), "alarm_evidence": ",".join(evidence) or None}


# ------------------------------------------------------------------------------ per compass
def corrections_in_force(params: dict, autopilot: str | None) -> tuple[np.ndarray, np.ndarray, str]:
    """(b mG, C, state) of the onboard calibration in the body-aligned raw frame: m_cal = C (raw − b).
    state: "calibrated" | "never calibrated" | "unknown"."""
    ap = autopilot or detect_autopilot(params)
    if ap == "ardupilot" and any(k.startswith("COMPASS_OFS") for k in params):
        ofs, M, scale = ardupilot_matrix(params)
        return -ofs, M * scale, "never calibrated" if ardupilot_never_calibrated(params) else "calibrated"
    if ap == "px4" and any(k.startswith("CAL_MAG") for k in params):
        off, S, R = px4_matrix(params, px4_slot(params))
        return R @ off * 1000.0, R @ S @ R.T, "calibrated" if np.any(off) else "never calibrated"
    return np.zeros(3), np.eye(3), "unknown"


def compass_fields(log: FlightLog, report: dict, ef, settings: ReviewSettings) -> dict:
    """Corrections in force, in-flight fit, field and heading residuals of the primary compass."""
    b, C, state = corrections_in_force(log.params, log.autopilot)
    raw, _ = unapply_onboard_calibration(log.mag[:, 1:4], log.params, log.autopilot, log.mag_calibration_applied)
    t = log.mag[:, 0]
    m_c = (raw - b) @ C.T
    a = log.attitude
    at = attitude_at(t, a[:, 0], a[:, 1], a[:, 2], a[:, 3]) if len(a) >= 2 else None
    att = (np.column_stack([at.roll_rad, at.pitch_rad, at.yaw_rad, at.rate_deg_s]) if at is not None
           else np.full((len(t), 4), np.nan))
    out: dict = {"cal_state": state, **{f"cal_ofs_{a}_mG": rounded(v, 2) for a, v in zip("xyz", b)}}
    use = np.cos(att[:, 0]) * np.cos(att[:, 1]) >= np.cos(np.radians(settings.max_tilt_deg))
    for start, end in _windows(report):
        use &= ~((t >= start - settings.alarm_margin_s) & (t <= end + settings.alarm_margin_s))
    if ef is None:
        out["fit_status"] = "no_expected_field"
        return out
    current = None
    if len(log.battery) >= 10:
        cur, ok = interp_series(t, log.battery[:, 0], log.battery[:, 1], max_gap_s=1.0)
        current = np.where(ok, cur[:, 0], np.nan)
    fit = fit_compass(settings.fit_model, t[use], raw[use], b, C, att[use], ef.field_ned_mG,
                      current[use] if current is not None else None, m_c[use], settings.fit)
    out.update(fit_model=fit.model, fit_status=fit.status, fit_samples=fit.samples,
               fit_yaw_dependence=rounded(fit.yaw_dependence, 3))
    if current is not None and np.all(np.isfinite(fit.motor_mG_per_A)):
        m_c = m_c - np.nan_to_num(current)[:, None] * fit.motor_mG_per_A   # the fitted motor field removed
    out.update(field_residuals(m_c[use], att[use, :2], att[use, 2], ef))
    if fit.status != "ok":
        return out
    out.update({f"fit_ofs_{a}_mG": rounded(v, 2) for a, v in zip("xyz", fit.offsets_mG)})
    out.update({f"fit_ofs_sd_{a}_mG": rounded(v, 3) for a, v in zip("xyz", fit.offsets_sd_mG)})
    out.update({f"ofs_change_{a}_mG": rounded(v, 2) for a, v in zip("xyz", fit.offsets_mG - b)})
    out.update(ofs_change_mG=rounded(np.linalg.norm(fit.offsets_mG - b), 2),
               fit_residual_rms_mG=rounded(fit.residual_rms_mG, 2), current_max_A=rounded(fit.current_max_A, 2),
               interference_pct=rounded(fit.interference_pct, 2))
    if np.all(np.isfinite(fit.motor_mG_per_A)):
        out.update({f"motor_{a}_mG_per_A": rounded(v, 3) for a, v in zip("xyz", fit.motor_mG_per_A)})
        out["motor_sd_mG_per_A"] = rounded(np.linalg.norm(fit.motor_sd_mG_per_A), 4)
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
