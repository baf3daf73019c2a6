"""What every compass of a log shares: the WMM field, attitude, GPS velocity, motor signals and the
onboard-calibration markers, looked up once per log."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from estimators.geomag import EarthField, decimal_year_from_unix, earth_field, field_along_path
from estimators.log_alignment import AttitudeAt, attitude_at, interp_series
from groundstation.samples import MAG_CAL_SUCCESS, FlightLog, MagCalSample

__all__ = ["LogContext", "log_context", "expected_field", "field_for", "attitude_for", "marker_spans", "onboard_report", "WMM_VALID_YEARS"]

WMM_VALID_YEARS = (2025.0, 2030.0)      # estimators.geomag clamps dates to the WMM2025 span


@dataclass(frozen=True)
class LogContext:
    field: EarthField | None
    field_note: str
    log_year: float | None
    attitude: np.ndarray | None = None          # the attitude the in-flight fits use ([t, roll, pitch, yaw]);
    attitude_source: str = ""                   # None: log.attitude.  Chosen per log (inflight.choose_attitude)
    attitude_choice: dict | None = None         # {"chosen", "forced", "scores": {source: held-out mG}, "note"}
    field_shift_ned_mG: np.ndarray | None = None     # added to the WMM: its inclination refined from the flight
    field_cov_ned_mG2: np.ndarray | None = None      # the reference field's covariance (None: the WMM's error model)
    field_refinement: dict | None = None             # what was refined and how (reference.refine_reference)


def expected_field(log: FlightLog) -> tuple[EarthField | None, str]:
    """WMM field at the first good GPS fix (fix ≥ 3D, finite, not 0/0) and the log date; a note
    says when the date is unknown or outside the model's span (WMM2025: the field of 2025 is used)."""
    gps = log.gps
    if len(gps) == 0:
        return None, "no GPS: expected field unknown"
    ok = (gps[:, 7] >= 3) & np.isfinite(gps[:, 1]) & np.isfinite(gps[:, 2]) & \
         ~((gps[:, 1] == 0) & (gps[:, 2] == 0)) & (np.abs(gps[:, 1]) <= 90) & (np.abs(gps[:, 2]) <= 180)
    if not np.any(ok):
        return None, "no good GPS fix: expected field unknown"
    row = gps[np.argmax(ok)]
    note = ""
    if log.start_unix_s is not None and math.isfinite(log.start_unix_s):
        year = decimal_year_from_unix(log.start_unix_s + row[0])
        if not WMM_VALID_YEARS[0] <= year < WMM_VALID_YEARS[1]:
            note = (f"log from {year:.1f}, outside WMM2025's {WMM_VALID_YEARS[0]:.0f}–{WMM_VALID_YEARS[1]:.0f}: "
                    f"the field of {min(max(year, WMM_VALID_YEARS[0]), WMM_VALID_YEARS[1]):.0f} is used "
                    "(secular change: ~0.1 deg and ~0.5 % of the field per 5 years at mid latitudes)")
    else:
        year = decimal_year_from_unix(time.time())
        note = "log date unknown, WMM evaluated for today"
    try:
        return earth_field(float(row[1]), float(row[2]), float(row[3]), year), note
    except Exception as e:  # model outside validity, bad numbers
        return None, f"WMM failed: {e}"


def log_context(log: FlightLog) -> LogContext:
    field, note = expected_field(log)
    year = decimal_year_from_unix(log.start_unix_s) if log.start_unix_s else None
    return LogContext(field, note, year)


def attitude_for(log: FlightLog, t_s: np.ndarray, table: np.ndarray | None = None) -> AttitudeAt:
    """The attitude at t_s: of ``table`` ([t, roll, pitch, yaw], e.g. LogContext.attitude), else the log's."""
    att = np.asarray(log.attitude if table is None else table, float).reshape(-1, 4)
    return attitude_at(t_s, att[:, 0], att[:, 1], att[:, 2], att[:, 3])


def field_for(log: FlightLog, ctx: LogContext, t_s: np.ndarray) -> np.ndarray | None:
    """The reference field (N,3) NED mG at each sample: the WMM along the flight (``_wmm_along``) plus
    ``ctx.field_shift_ned_mG``, its inclination refined from the flight (reference.refine_reference).
    None without ctx.field."""
    H = _wmm_along(log, ctx, t_s)
    return H if H is None or ctx.field_shift_ned_mG is None else H + ctx.field_shift_ned_mG


def _wmm_along(log: FlightLog, ctx: LogContext, t_s: np.ndarray) -> np.ndarray | None:
    """The WMM field (N,3) NED mG at each sample's position, altitude and date (estimators.geomag.
    field_along_path: GPS interpolated to t_s, good fixes only); samples without a position within
    10 s of a fix take the field of the first fix (ctx.field).  None without ctx.field."""
    if ctx.field is None:
        return None
    t = np.asarray(t_s, float).ravel()
    out = np.tile(np.asarray(ctx.field.field_ned_mG, float), (len(t), 1))
    g = np.asarray(log.gps, float).reshape(-1, 8)
    good = (g[:, 7] >= 3) & np.isfinite(g[:, 1:4]).all(axis=1) & ~((g[:, 1] == 0) & (g[:, 2] == 0)) \
        & (np.abs(g[:, 1]) <= 90) & (np.abs(g[:, 2]) <= 180)
    if good.sum() < 2 or len(t) == 0:
        return out
    pos, valid = interp_series(t, g[good, 0], g[good, 1:4], max_gap_s=10.0)
    if log.start_unix_s is not None and math.isfinite(log.start_unix_s):
        year = np.array([decimal_year_from_unix(log.start_unix_s + float(x)) for x in (t[0], t[-1])])
        years = np.interp(t, [t[0], t[-1]], year) if t[-1] > t[0] else np.full(len(t), year[0])
    else:
        years = np.full(len(t), decimal_year_from_unix(time.time()))
    try:
        H = field_along_path(pos[:, 0], pos[:, 1], pos[:, 2], years)
    except Exception:  # model outside validity, bad numbers: the single field stands
        return out
    use = valid & np.isfinite(H).all(axis=1)
    out[use] = H[use]
    return out


def gps_velocity_for(log: FlightLog, t_s: np.ndarray) -> np.ndarray | None:
    g = np.asarray(log.gps, float).reshape(-1, 8)
    if len(g) < 2 or not np.isfinite(g[:, 4:6]).any():
        return None
    vel, _ = interp_series(t_s, g[:, 0], g[:, 4:6], max_gap_s=2.0)
    return vel


def _applies(e: MagCalSample, compass: int) -> bool:
    return e.compass == compass or (e.compass < 0 and (e.mask == 0 or bool(e.mask >> compass & 1)))


def marker_spans(events: list[MagCalSample], compass: int) -> list[tuple[float, float]]:
    """[(start, end)] of each onboard calibration of ``compass``: from MAV_CMD_DO_START_MAG_CAL (or
    the first MAG_CAL_PROGRESS after the previous end) to its MAG_CAL_REPORT (or the last progress,
    or a cancel)."""
    spans: list[tuple[float, float]] = []
    start = last = None
    for e in events:
        if not _applies(e, compass):
            continue
        if e.kind in ("start", "progress") and start is None:
            start = e.t_s
        if e.kind == "progress":
            last = e.t_s
        if e.kind in ("report", "cancel", "accept") and start is not None:
            spans.append((start, e.t_s))
            start = last = None
    if start is not None and last is not None and last > start:
        spans.append((start, last))
    return spans


def onboard_report(events: list[MagCalSample], compass: int) -> dict | None:
    """The vehicle's last successful MAG_CAL_REPORT for ``compass`` (COMPASS_OFS convention)."""
    reports = [e for e in events if e.kind == "report" and e.compass == compass and e.status == MAG_CAL_SUCCESS]
    if not reports:
        return None
    r = reports[-1]
    fin = lambda v: [round(float(x), 4) if math.isfinite(x) else None for x in v]  # noqa: E731
    return {"t_s": round(r.t_s, 2), "COMPASS_OFS": fin(r.offsets_mG), "diag": fin(r.diag), "offdiag": fin(r.offdiag),
            "fitness_mG": round(r.fitness_mG, 2) if math.isfinite(r.fitness_mG) else None,
            "scale_factor": r.scale_factor if math.isfinite(r.scale_factor) else None,
            "autosaved": bool(r.autosaved)}
