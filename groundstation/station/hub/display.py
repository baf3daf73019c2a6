"""What the page reads off the flight record: the vehicle panel, the test states, the plots.

Pure functions of record rows (``groundstation.jobs.record``), so the live view and a replay
show a step the same way.  Headings are true, in [0, 360); NaN becomes None (JSON).
"""
from __future__ import annotations

import math

import numpy as np

from estimators.detection import DetectionSettings

from groundstation.jobs.inputs import FieldPolicy
from groundstation.jobs.record import COL
from groundstation.jobs.words import fix_name
from groundstation.samples import finite_or_none

__all__ = ["vehicle_snapshot", "tests_snapshot", "plot_data", "PLOT_SERIES", "PLOT_MAX_POINTS"]

PLOT_MAX_POINTS = 400
PLOT_SERIES = ("heading_deg", "mag_heading_deg", "ap_heading_deg", "course_deg", "field_mG", "inclination_deg",
               "v_forward_mps", "v_lateral_mps", "cross_track_m", "alarm")
VEHICLE_FIELDS = {"roll_deg": "roll_deg", "pitch_deg": "pitch_deg", "yaw_deg": "heading_deg",
                  "ap_roll_deg": "ap_roll_deg", "ap_pitch_deg": "ap_pitch_deg", "ap_yaw_deg": "ap_heading_deg",
                  "heading_mag_deg": "mag_heading_deg", "heading_att_deg": "heading_deg",
                  "course_deg": "course_deg", "speed_mps": "speed_mps",
                  "v_forward_mps": "v_forward_mps", "v_lateral_mps": "v_lateral_mps",
                  "cross_track_m": "cross_track_m", "field_mG": "field_mG", "inclination_deg": "inclination_deg",
                  "lat_deg": "lat_deg", "lon_deg": "lon_deg"}


def vehicle_snapshot(row: np.ndarray | None) -> dict:
    """The vehicle panel at one record row (all None before the first IMU step)."""
    out = {key: (None if row is None else finite_or_none(row[COL[col]])) for key, col in VEHICLE_FIELDS.items()}
    fix = None if row is None else finite_or_none(row[COL["fix_type"]])
    out["fix_type"] = int(fix) if fix is not None else 0
    out["fix_name"] = fix_name(out["fix_type"])
    return out


def _state(state: str, why: str) -> dict:
    return {"state": state, "why": why}


def tests_snapshot(row: np.ndarray | None, policy: FieldPolicy, line: dict | None,
                   settings: DetectionSettings | None = None) -> dict:
    """Each test on, off, paused or untrusted at this step, and why; and what the field is."""
    s = settings or DetectionSettings()
    field = {"kind": policy.correction, "note": policy.note}
    steep = row is not None and row[COL["steep"]] > 0.5
    pause = _state("paused", f"steep attitude or fast rotation: the test waits {s.turn_settle_s:g} s after it")
    if policy.correction == "none":
        heading = _state("off", "no magnetometer data")
    elif not policy.heading_usable:
        heading = _state("off", policy.field_test.removeprefix("off: "))
    elif row is None:
        heading = _state("waiting", "no IMU data yet")
    elif row[COL["heading_on"]] < 0.5:
        rate = finite_or_none(row[COL["imu_rate_hz"]]) or 0.0
        heading = _state("off", f"IMU rate {rate:.1f} Hz < {s.min_imu_rate_hz:g} Hz: the gyro cannot hold a heading "
                                "between samples, so the headings shown here are not a reference")
    else:
        heading = pause if steep else _state("on", f"alarm above {s.sigma_k:g} sigma of the heading difference "
                                                   f"learned over the first {s.learn_s:g} s")
    if not policy.field_on:
        fld = _state("off", policy.field_test.removeprefix("off: "))
    elif row is not None and row[COL["heading_on"]] < 0.5:        # telemetry-rate IMU: our tilt is not trusted
        rate = finite_or_none(row[COL["imu_rate_hz"]]) or 0.0
        fld = _state("off", f"IMU rate {rate:.1f} Hz < {s.min_imu_rate_hz:g} Hz: the field tests need our attitude")
    else:
        fld = pause if steep else _state("on", "field strength and inclination against their values learned per "
                                               "heading sector")
    fix = None if row is None else finite_or_none(row[COL["fix_type"]])
    if line is None:
        path = _state("off", "no preset line")
    elif fix is None:
        path = _state("off", "no recent GPS fix")
    elif fix < s.rtk_min_fix:
        path = _state("untrusted", f"GPS {fix_name(fix)}: the path test needs RTK ({fix_name(s.rtk_min_fix)} or "
                                   "better) and never alarms without it")
    else:
        path = _state("on", f"alarm {s.path_threshold_m:g} m off the preset line")
    return {"heading": heading, "field": fld, "path": path, "field_correction": field}


def _json(a: np.ndarray, nd: int) -> list:
    return [None if not math.isfinite(v) else round(v, nd) for v in np.asarray(a, dtype=float).tolist()]


def plot_data(rows: np.ndarray, alarms: list[dict], earth_field, window_s: float,
              max_points: int = PLOT_MAX_POINTS) -> dict:
    """The last ``window_s`` of the record, at most ``max_points`` steps: series by PLOT_SERIES
    name, the WMM reference of the field plots and the alarm intervals in the window."""
    t_all = rows[:, COL["t_s"]] if len(rows) else np.zeros(0)
    t_end = float(t_all[-1]) if len(t_all) else 0.0
    i0 = int(np.searchsorted(t_all, t_end - window_s, side="left")) if len(t_all) else 0
    sel = rows[i0:]
    step = max(1, math.ceil(len(sel) / max_points))
    idx = np.unique(np.r_[np.arange(0, len(sel), step), len(sel) - 1]) if len(sel) else np.zeros(0, int)
    pick = sel[idx]
    out = {"t_s": _json(pick[:, COL["t_s"]], 2), "t_end_s": round(t_end, 2), "window_s": window_s,
           "series": {name: _json(pick[:, COL[name]], 2) for name in PLOT_SERIES},
           "wmm": {"field_mG": finite_or_none(getattr(earth_field, "field_strength_mG", None)),
                   "inclination_deg": finite_or_none(getattr(earth_field, "inclination_deg", None)),
                   "declination_deg": finite_or_none(getattr(earth_field, "declination_deg", None))},
           "alarms": [{"start_s": a["start_s"], "end_s": a["end_s"]} for a in alarms
                      if a["end_s"] is None or a["end_s"] >= t_end - window_s]}
    return out
