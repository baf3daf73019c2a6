"""The flight record: the analysis of a flight per IMU step, in one table.

``record_rows`` turns the heading chain, the detector inputs (``groundstation.jobs.inputs``) and
the detector's decision on some IMU steps into rows of RECORD_COLUMNS; analyze (a whole log at
once), the station's replay (the same rows, read up to the replay cursor) and the live view (one
row per IMU sample, ``groundstation.jobs.live``) all build their rows with it, and all list
their alarms with ``AlarmTracker`` over the rows.  So the page, the report and the live link
show the same numbers and the same alarms for the same samples; only the attitude columns of a
replay are the finished log's (``station.hub.review.finished_rows``: analyze's CSV attitude).

Units as the column names say; headings true, in [0, 360); cross-track signed (+ right of the
preset line's A->B); flags 0/1; NaN where unknown.
"""
from __future__ import annotations

import numpy as np

from estimators.heading import split_velocity

from groundstation.jobs.inputs import heading_deg, rounded

__all__ = ["RECORD_COLUMNS", "COL", "record_rows", "AlarmTracker", "EVIDENCE", "EVIDENCE_TEXT", "evidence_text",
           "COURSE_MIN_SPEED_MPS"]

RECORD_COLUMNS = (
    "t_s", "roll_deg", "pitch_deg", "heading_deg", "mag_heading_deg",
    "ap_roll_deg", "ap_pitch_deg", "ap_heading_deg", "course_deg", "speed_mps",
    "v_forward_mps", "v_lateral_mps", "cross_track_m", "field_mG", "inclination_deg",
    "lat_deg", "lon_deg", "fix_type", "imu_rate_hz", "steep", "heading_on", "field_on", "path_on",
    "alarm", "ev_heading", "ev_path", "ev_field", "score",
)
COL = {name: i for i, name in enumerate(RECORD_COLUMNS)}
EVIDENCE = ("heading_difference", "path_deviation", "field_anomaly")
EVIDENCE_TEXT = {
    "heading_difference": "compass heading departs from the gyro-held heading",
    "path_deviation": "vehicle drifts off the preset line",
    "field_anomaly": "field strength or inclination is off",
}
COURSE_MIN_SPEED_MPS = 2.0     # slower, the GPS course over ground is noise
MERGE_GAP_S = 1.0              # alarms closer than this are one (as estimators.detection.alarm_intervals)
ALARM_UNIT = "score (1 = test threshold)"


def evidence_text(kinds) -> str:
    """Evidence names in words, for people."""
    return "; ".join(EVIDENCE_TEXT.get(k, str(k)) for k in kinds)


def record_rows(t, chain, x: dict, declination_deg, combined, trigger, score, attitude=None) -> np.ndarray:
    """Rows of RECORD_COLUMNS for some IMU steps.

    t (n,); chain: mag_heading_rad, valid (n,) of the detector's heading chain; attitude:
    roll_rad, pitch_rad, heading_true_rad, valid (n,) of the attitude shown (the default AHRS;
    None: the detector's chain); x: ``step_inputs`` output plus gps_held (n, GPS_COLUMNS) and att_held (n, 3)
    (the autopilot's roll, pitch, yaw); declination_deg: scalar or (n,); combined (n,) bool, trigger
    (n, 3) bool and score (n,): the detector's decision, evidence and largest test score.
    """
    t = np.asarray(t, dtype=float)
    rows = np.full((len(t), len(RECORD_COLUMNS)), np.nan)
    att = chain if attitude is None else attitude
    valid = np.asarray(chain.valid, dtype=bool) & np.asarray(att.valid, dtype=bool)
    deg = lambda a: np.where(valid, np.degrees(a), np.nan)  # noqa: E731
    head_rad = np.where(valid, att.heading_true_rad, np.nan)
    g = x["gps_held"]
    ap = x["att_held"]
    vn, ve = g[:, 5], g[:, 6]
    speed = np.hypot(vn, ve)
    fwd, lat = split_velocity(vn, ve, head_rad)
    with np.errstate(invalid="ignore"):
        moving = speed >= COURSE_MIN_SPEED_MPS
    values = {
        "t_s": t, "roll_deg": deg(att.roll_rad), "pitch_deg": deg(att.pitch_rad),
        "heading_deg": np.where(valid, heading_deg(att.heading_true_rad), np.nan),
        "mag_heading_deg": np.where(valid, heading_deg(chain.mag_heading_rad + np.radians(declination_deg)), np.nan),
        "ap_roll_deg": np.degrees(ap[:, 0]), "ap_pitch_deg": np.degrees(ap[:, 1]),
        "ap_heading_deg": np.where(np.isfinite(ap[:, 2]), heading_deg(ap[:, 2]), np.nan),
        "course_deg": np.where(moving, heading_deg(np.arctan2(ve, vn)), np.nan), "speed_mps": speed,
        "v_forward_mps": fwd, "v_lateral_mps": lat, "cross_track_m": g[:, 1],
        "field_mG": x["field_mG"], "inclination_deg": x["inclination_deg"],
        "lat_deg": g[:, 3], "lon_deg": g[:, 4], "fix_type": g[:, 7],
        "imu_rate_hz": np.minimum(x["rate_hz"], 1e6), "steep": x["steep"],
        "heading_on": x["heading_on"], "field_on": x["field_on"],
        "path_on": np.isfinite(x["d"]) & x["trusted"],
        "alarm": combined, "ev_heading": trigger[:, 0], "ev_path": trigger[:, 1], "ev_field": trigger[:, 2],
        "score": score,
    }
    for name, v in values.items():
        rows[:, COL[name]] = v
    return rows


class AlarmTracker:
    """Alarm intervals of the combined decision, fed rows in time order (all at once or a few
    at a time: the result is the same).

    An alarm is a run of steps with the combined flag on; runs less than MERGE_GAP_S apart are
    one alarm (the rule of ``estimators.detection.alarm_intervals``).  Each alarm: kind
    "combined", start_s, end_s (None while on at the last step fed), peak score, evidence (every
    test that fired during it), evidence_at_start.
    """

    def __init__(self) -> None:
        self.alarms: list[dict] = []
        self._last_on_t: float | None = None     # time of the last step with the flag on
        self._on = False                         # flag on at the last step fed
        self._peak = np.nan
        self._evidence = np.zeros(3, bool)

    @property
    def active(self) -> bool:
        return self._on

    def update(self, t: np.ndarray, flag: np.ndarray, trigger: np.ndarray, score: np.ndarray) -> None:
        """Feed rows: t (n,), flag (n,) bool, trigger (n, 3) bool, score (n,)."""
        t = np.asarray(t, dtype=float)
        if not len(t):
            return
        f = np.asarray(flag, dtype=bool)
        edges = np.diff(np.r_[np.int8(self._on), f.astype(np.int8), np.int8(0)])
        starts = np.flatnonzero(edges == 1)
        ends = np.flatnonzero(edges == -1) - 1
        if self._on and f[0]:                 # the open alarm goes on
            starts = np.r_[0, starts]
        elif self._on:                        # ... or ended at the last step of the previous rows
            self.alarms[-1]["end_s"] = rounded(self._last_on_t, 2)
            self._on = False
            ends = ends[1:]
        for a, b in zip(starts, ends):
            self._add_run(t, trigger, score, int(a), int(b), closed=b < len(t) - 1)

    def _add_run(self, t, trigger, score, a: int, b: int, closed: bool) -> None:
        trig = np.asarray(trigger[a:b + 1], dtype=bool)
        sc = np.asarray(score[a:b + 1], dtype=float)
        peak = float(np.nanmax(sc)) if np.isfinite(sc).any() else np.nan
        continues = self._on and a == 0
        merge = bool(self.alarms) and self._last_on_t is not None and (continues or t[a] - self._last_on_t < MERGE_GAP_S)
        if merge:
            alarm = self.alarms[-1]
            self._evidence |= trig.any(axis=0)
            self._peak = np.fmax(self._peak, peak)
        else:
            alarm = {"kind": "combined", "start_s": rounded(t[a], 2), "unit": ALARM_UNIT,
                     "evidence_at_start": [EVIDENCE[k] for k in range(3) if trig[0, k]]}
            self.alarms.append(alarm)
            self._evidence = trig.any(axis=0)
            self._peak = peak
        alarm["evidence"] = [EVIDENCE[k] for k in range(3) if self._evidence[k]]
        alarm["peak"] = rounded(self._peak)
        alarm["end_s"] = rounded(t[b], 2) if closed else None
        self._last_on_t = float(t[b])
        self._on = not closed

    def snapshot(self) -> list[dict]:
        return [dict(a) for a in self.alarms]
