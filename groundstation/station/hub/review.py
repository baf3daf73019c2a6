"""A replayed log analysed once, read at the replay cursor.

``build_review(log, calibration, line)`` runs ``analyze_flight`` (the detection part of
``magstation analyze``) on the whole log: the flight record per IMU step, the GPS track with the
alarm state at each fix, the GPS outages and the markers of the replay timeline.  The replay
then only moves a cursor over it (``FlightState.show_until``), so what the page shows at any
time is what analyze reports up to that time, and seeking anywhere is a search, not a re-run.
Built outside the hub lock (a few seconds for an hour of 50 Hz data).

The log is finished, so the attitude shown (roll, pitch, heading and the velocity split by it) is
analyze's CSV attitude (``jobs.analyze.finished_log_attitude``: the offline smoother over the whole
log, the INS/GPS filter's around GPS outages), and ``Review.attitude_source`` says per step which
("offline" or "causal"; the vehicle panel's ``attitude_source``).  Every decision (alarms,
evidence, scores, test states) stays the causal one of ``analyze_flight``: a replay alarms where
the live link and analyze do.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from estimators.heading import split_velocity

from groundstation.jobs.analyze import FlightAnalysis, analyze_flight, finished_log_attitude
from groundstation.jobs.inputs import FieldPolicy
from groundstation.jobs.navigation import OUTAGE_MIN_S, gps_outages, ins_runs
from groundstation.jobs.record import COL, evidence_text
from groundstation.jsonsafe import jsonable
from groundstation.samples import FlightLog

logger = logging.getLogger(__name__)

__all__ = ["Review", "build_review", "finished_rows", "line_mission", "log_own_calibration"]

SEGMENT_GAP_S = 2.0          # a gap in all the data this long is a telemetry dropout on the timeline


def line_mission(line: dict | None) -> list | None:
    """The preset line as the two-waypoint mission the detector judges the path against."""
    return [tuple(line["a"]), tuple(line["b"])] if line else None


@dataclass
class Review:
    """What a replay shows, for the whole log (see module docstring).

    rows:    flight record rows (groundstation.jobs.record.RECORD_COLUMNS), time order
    gps:     [t_s, lat_deg, lon_deg, fix_type, alarm] per GPS fix
    events:  [(t_s, text, level)] when the replay passes them (GPS outages)
    markers: [{t_s, end_s, kind, label}] for the timeline (alarms, GPS outages, data gaps, messages)
    """
    rows: np.ndarray
    gps: np.ndarray
    policy: FieldPolicy
    events: list = field(default_factory=list)
    markers: list = field(default_factory=list)
    earth_field: object = None
    calibration: dict | None = None
    line: dict | None = None
    explain_steps: dict | None = None     # per-step inputs of the alarm explanations (jobs.alarm_explain)
    motor_signal: str = "none"
    calibration_note: str | None = None   # how the calibration was applied to this log (jobs.calibrate.frame)
    attitude_source: np.ndarray | None = None   # per row: "offline" (smoother) or "causal" (module docstring)


def build_review(log: FlightLog, calibration: dict | None, line: dict | None) -> Review:
    """Analyse a whole log for replay (see module docstring)."""
    fa: FlightAnalysis = analyze_flight(log, calibration, line_mission(line))
    rows, source = finished_rows(log, fa)
    g = np.asarray(log.gps, dtype=float).reshape(-1, 8)
    alarm_at_fix = np.zeros(len(g))
    if len(rows) and len(g):
        idx = np.searchsorted(rows[:, COL["t_s"]], g[:, 0], side="right") - 1
        alarm_at_fix = np.where(idx >= 0, rows[np.maximum(idx, 0), COL["alarm"]], 0.0)
    gps = np.c_[g[:, 0], g[:, 1], g[:, 2], g[:, 7], alarm_at_fix] if len(g) else np.zeros((0, 5))
    review = Review(rows=rows, gps=gps, policy=fa.x["policy"], earth_field=fa.x["ef"],
                    calibration=calibration, line=line, explain_steps=fa.explain_steps(),
                    motor_signal=fa.x.get("motor_signal", "none"), calibration_note=fa.x.get("calibration_note"),
                    attitude_source=source)
    _outages(review, log)
    review.markers += [{"t_s": a["start_s"], "end_s": a["end_s"], "kind": "alarm",
                        "label": "interference alarm: " + evidence_text(a["evidence"])} for a in fa.combined_alarms()]
    review.markers += _gaps(log) + _messages(log)
    review.markers.sort(key=lambda m: m["t_s"])
    return review


def finished_rows(log: FlightLog, fa: FlightAnalysis) -> tuple[np.ndarray, np.ndarray]:
    """(analyze_flight's record rows with the finished log's attitude in roll_deg, pitch_deg,
    heading_deg, v_forward_mps and v_lateral_mps, attitude_source per row); the other columns,
    every decision among them, are analyze_flight's as they are."""
    x = fa.x
    ef = x["ef"]
    _, runs = ins_runs(log, x["mag_cal"], ef.declination_deg if ef else 0.0, x["imu_rate_hz"], fa.settings)
    best, _, _ = finished_log_attitude(log, fa, runs)
    rows = fa.rows.copy()
    if not len(rows):
        return rows, np.zeros(0, dtype=object)
    heading = best["heading_true_deg"]
    g = x["gps_held"]
    fwd, lat = split_velocity(g[:, 5], g[:, 6], np.radians(heading))
    for name, v in (("roll_deg", best["roll_deg"]), ("pitch_deg", best["pitch_deg"]), ("heading_deg", heading),
                    ("v_forward_mps", fwd), ("v_lateral_mps", lat)):
        rows[:, COL[name]] = v
    return rows, best["attitude_source"]


def _outages(review: Review, log: FlightLog) -> None:
    """GPS outages (the rule of analyze's navigation): events when the replay gets there and
    timeline markers."""
    g = np.asarray(log.gps, dtype=float).reshape(-1, 8)
    good = (g[:, 7] >= 3) & np.all(np.isfinite(g[:, 0:4]), axis=1) if len(g) else np.zeros(0, bool)
    imu_t = np.asarray(log.imu, dtype=float).reshape(-1, 7)[:, 0]
    for start, end in gps_outages(g[good, 0], imu_t):
        review.events.append((start + OUTAGE_MIN_S, f"GPS fix lost (last 3-D fix at {start:.1f} s): the "
                              "position and path-deviation test are stale", "warning"))
        if end is not None:
            review.events.append((end, f"GPS fix back after {end - start:.1f} s", "info"))
        review.markers.append({"t_s": round(start, 2), "end_s": None if end is None else round(end, 2),
                               "kind": "gps", "label": "GPS outage"})
    review.events.sort(key=lambda e: e[0])


def _gaps(log: FlightLog) -> list[dict]:
    """Gaps in all the data (telemetry dropouts, parts of a log)."""
    t = np.unique(np.concatenate([np.asarray(a, dtype=float).reshape(-1, a.shape[1] if a.ndim == 2 else 1)[:, 0]
                                  for a in (log.imu, log.gps, log.attitude, log.mag) if len(a)] or [np.zeros(0)]))
    if len(t) < 2:
        return []
    k = np.flatnonzero(np.diff(t) > SEGMENT_GAP_S)
    return [{"t_s": round(float(t[i]), 2), "end_s": round(float(t[i + 1]), 2), "kind": "gap",
             "label": f"no data for {t[i + 1] - t[i]:.1f} s"} for i in k]


def _messages(log: FlightLog) -> list[dict]:
    """The vehicle's own text messages (STATUSTEXT), at most 200."""
    return [{"t_s": round(s.t_s, 2), "end_s": None, "kind": "message", "label": s.text[:120]}
            for s in log.status if s.kind == "statustext"][:200]


def log_own_calibration(flight_log: FlightLog) -> dict | None:
    """A replayed log that contains a calibration dance calibrates its own magnetometer
    (calibrate_log on the whole log; None unless the fit is 'ok' and from a rotation window)."""
    from groundstation.jobs.calibrate import calibrate_log

    if len(flight_log.mag) < 200:
        return None
    try:
        result = calibrate_log(flight_log)
    except Exception:
        logger.exception("calibration of the replayed log failed")
        return None
    # only a rotation window (a calibration dance) observes every offset axis; an in-flight fit
    # against the WMM from level flight does not beat the autopilot's own correction (on the
    # real ArduCopter log it raised a field alarm the autopilot-corrected field does not)
    ok = result.get("status") == "ok" and result.get("method") == "window"
    return jsonable(result) if ok else None
