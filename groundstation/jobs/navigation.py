"""GPS outages in a log and what the seed-003 INS/GPS filter made of each (analyze's `navigation`)."""
from __future__ import annotations

import copy
import dataclasses

import numpy as np

from estimators.detection import DetectionSettings, ned_from_lla
from estimators.ins_gps import MODE_NAMES, InsGpsFilter, InsGpsSettings, run_ins_gps
from estimators.rotations import wrap_angle_rad

from groundstation.jobs.inputs import GPS_TIMEOUT_S, hold_last, rounded
from groundstation.samples import FlightLog

__all__ = ["gps_outages", "ins_runs", "OUTAGE_MIN_S"]

OUTAGE_MIN_S = 2.0          # a longer gap between good GPS fixes (fix_type >= 3) is an outage
INS_LEAD_S = 60.0           # the INS/GPS filter runs from this long before each outage ...
INS_TAIL_S = 10.0           # ... to this long after it


def gps_outages(t_gps_fix: np.ndarray, t_imu: np.ndarray) -> list[tuple[float, float | None]]:
    """(start_s, end_s or None when the log ends without GPS) of gaps longer than OUTAGE_MIN_S
    between good GPS fixes while the IMU kept streaming (a gap in all the data is a telemetry
    dropout, not a GPS outage; fixes that never came are not an outage either)."""
    t = np.sort(np.asarray(t_gps_fix, dtype=float))
    ti = np.sort(np.asarray(t_imu, dtype=float))
    if not len(t) or not len(ti):
        return []
    out: list[tuple[float, float | None]] = []
    gaps = [(float(t[k]), float(t[k + 1])) for k in np.flatnonzero(np.diff(t) > OUTAGE_MIN_S)]
    if ti[-1] - t[-1] > OUTAGE_MIN_S:
        gaps.append((float(t[-1]), None))
    for start, end in gaps:
        stop = end if end is not None else float(ti[-1])
        inside = ti[(ti > start) & (ti < stop)]
        if len(inside) and np.diff(np.r_[start, inside, stop]).max() <= OUTAGE_MIN_S:
            out.append((start, end))
    return out


def ins_runs(log: FlightLog, mag_cal: np.ndarray, declination_deg: float, imu_rate_hz: float,
             settings: DetectionSettings) -> tuple[dict, list]:
    """GPS outages and what the seed-003 INS/GPS filter made of each: it runs from INS_LEAD_S
    before the outage (to learn gyro biases and the Earth field with GPS) through the outage to
    INS_TAIL_S after it, once holding the attitude with field-vector feedback and once open loop
    (gyro integration with the biases learnt before the outage); each heading is compared with
    the autopilot's own.  Both are reported because neither is always better: the feedback bounds
    an unknown gyro-bias change, but a body-fixed field (motor current) that the Earth-field
    set-point absorbed before the outage pulls it off after a turn (see README, Known limits).

    Returns (navigation object, runs): runs are the InsGpsResults of the field-feedback filter
    (the lead with GPS, then through the outage and its tail), the best attitude where they run."""
    imu = np.asarray(log.imu, dtype=float).reshape(-1, 7)
    g = np.asarray(log.gps, dtype=float).reshape(-1, 8)
    good = (g[:, 7] >= 3) & np.all(np.isfinite(g[:, 0:4]), axis=1)
    if not len(imu) or not good.any():
        return {"ins_gps": "off: " + ("no IMU data" if not len(imu) else "no 3-D GPS fix in the log"),
                "gps_outages": []}, []
    g = g[good]
    g = g[np.r_[True, np.diff(g[:, 0]) > 0]]     # a repeated fix time: no velocity from positions
    t_last = float(imu[-1, 0])
    found = gps_outages(g[:, 0], imu[:, 0])
    outages = [{"start_s": rounded(start, 2), "end_s": rounded(end, 2),
                "duration_s": rounded((end if end is not None else t_last) - start, 2),
                "ins_mode": None, "ins_vs_autopilot_heading_deg": None}
               for start, end in found]
    if imu_rate_hz < settings.min_imu_rate_hz:   # telemetry-rate IMU: strapdown integration is meaningless
        return {"ins_gps": f"off: IMU rate {imu_rate_hz:.1f} Hz < {settings.min_imu_rate_hz:g} Hz",
                "gps_outages": outages}, []
    n_m, e_m = ned_from_lla(g[:, 1], g[:, 2], g[0, 1], g[0, 2])
    pos_ned = np.c_[n_m, e_m, g[0, 3] - g[:, 3]]
    vel_ned = g[:, 4:7].copy()
    if len(g) > 1:      # a velocity the receiver did not report (GPS_RAW_INT has no vD): from positions
        for k in range(3):
            vel_ned[:, k] = np.where(np.isfinite(vel_ned[:, k]), vel_ned[:, k], np.gradient(pos_ned[:, k], g[:, 0]))
    gps_ned = np.c_[g[:, 0], pos_ned, vel_ned]
    att = np.asarray(log.attitude, dtype=float).reshape(-1, 4)
    battery = np.asarray(log.battery, dtype=float).reshape(-1, 2)   # motor current: motor-field states
    ins_settings = InsGpsSettings(declination_deg=declination_deg)
    runs = []
    for entry, (start, end) in zip(outages, found):
        stop = (end if end is not None else t_last) + INS_TAIL_S
        entry["ins_vs_autopilot_heading_deg"] = {}
        # one run with GPS up to the outage, then two branches from the same state
        lead = InsGpsFilter(ins_settings)
        before = lambda a: a[(a[:, 0] >= start - INS_LEAD_S) & (a[:, 0] <= start)]  # noqa: E731
        after = lambda a: a[(a[:, 0] > start) & (a[:, 0] <= stop)]  # noqa: E731
        runs.append(run_ins_gps(before(imu), before(gps_ned), before(mag_cal), filt=lead, current=before(battery)))
        for law in ("field_feedback", "open_loop"):
            branch = copy.deepcopy(lead)
            branch.s = dataclasses.replace(ins_settings, field_feedback=law == "field_feedback")
            res = run_ins_gps(after(imu), after(gps_ned), after(mag_cal), filt=branch, current=after(battery))
            inside = (res.t_s > start + GPS_TIMEOUT_S) & (res.t_s < (end if end is not None else np.inf))
            if law == "field_feedback":
                runs.append(res)
                if inside.any():
                    entry["ins_mode"] = MODE_NAMES[int(np.bincount(res.mode[inside]).argmax())]
            ap_yaw = hold_last(att[:, 0], att[:, 3], res.t_s, 0.5) if len(att) else np.full(len(res.t_s), np.nan)
            diff = np.degrees(np.abs(wrap_angle_rad(res.yaw_rad - ap_yaw)))[inside]
            entry["ins_vs_autopilot_heading_deg"][law] = (
                {"median": rounded(np.nanmedian(diff), 2), "max": rounded(np.nanmax(diff), 2)}
                if np.isfinite(diff).any() else None)
    return {"ins_gps": "on: seed-003 INS/GPS over each outage (field-vector feedback and open loop)",
            "gps_outages": outages}, runs
