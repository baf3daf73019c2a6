"""`magstation analyze`: heading chain + interference detection over a whole log (issue 5).

``analyze_log(log, calibration=None, mission=None) -> (report, columns)``
  report:  the issue-5 JSON object (file, duration_s, calibration, declination_deg, inclination_deg,
           field_strength_mG, rtk, mission, path_test, max_cross_track_m, alarms, first_alarm_s,
           interference_detected, ...)
  columns: the issue-4 CSV as {name: array} on the IMU time base (t_s, roll_deg, pitch_deg, yaw_deg,
           mag_heading_deg, heading_true_deg, v_forward_mps, v_lateral_mps, cross_track_m, alarm).
``write_csv(path, columns)``; ``format_report(report) -> str``.
``LiveAnalyzer``: the same pipeline per sample (``on_sample``) for the live server.

The math lives in estimators (heading chain: seed 000; detection: seed 002); this module turns a
FlightLog into arrays on one time base, looks up the WMM and formats the results.
"""
from __future__ import annotations

import copy
import csv
import dataclasses
import math
import time
from pathlib import Path

import numpy as np

from estimators.detection import (DetectionSettings, InterferenceDetector, alarm_intervals, cross_track_m,
                                  detect, field_inclination_deg, ned_from_lla)
from estimators.geomag import decimal_year_from_unix, earth_field
from estimators.heading import HeadingChain, run_heading_chain, split_velocity
from estimators.ins_gps import MODE_NAMES, InsGpsFilter, InsGpsSettings, run_ins_gps
from estimators.rotations import wrap_angle_rad

from groundstation.io.params import ardupilot_never_calibrated, unapply_onboard_calibration
from groundstation.samples import (AttitudeSample, FlightLog, GpsSample, ImuSample, MagSample, ParamSample, StatusSample,
                      finite_or_none)

__all__ = ["analyze_log", "detection_inputs", "write_csv", "format_report", "LiveAnalyzer", "CSV_COLUMNS", "mission_legs"]

CSV_COLUMNS = ("t_s", "roll_deg", "pitch_deg", "yaw_deg", "mag_heading_deg", "heading_true_deg",
               "v_forward_mps", "v_lateral_mps", "cross_track_m", "alarm")
GPS_TIMEOUT_S = 1.0
OUTAGE_MIN_S = 2.0          # a longer gap between good GPS fixes (fix_type >= 3) is an outage
INS_LEAD_S = 60.0           # the INS/GPS filter runs from this long before each outage ...
INS_TAIL_S = 10.0           # ... to this long after it


# ------------------------------------------------------------------------------ helpers
def _calibration_arrays(calibration: dict | None) -> tuple[np.ndarray, np.ndarray] | None:
    if not calibration:
        return None
    off, mat = calibration.get("offsets_mG"), calibration.get("matrix")
    if off is None or mat is None:
        return None
    off, mat = np.asarray(off, dtype=float).reshape(3), np.asarray(mat, dtype=float).reshape(3, 3)
    if not (np.all(np.isfinite(off)) and np.all(np.isfinite(mat))):
        return None
    return off, mat


def mission_legs(points: list | None) -> list[tuple[tuple[float, float], tuple[float, float]]]:
    """Consecutive waypoint pairs [(A, B), ...] as (lat, lon) tuples; empty if fewer than two."""
    pts = [(float(p[0]), float(p[1])) for p in (points or []) if len(p) >= 2
           and np.isfinite(p[0]) and np.isfinite(p[1])]
    return [(pts[k], pts[k + 1]) for k in range(len(pts) - 1) if pts[k] != pts[k + 1]]


def _cross_track_legs(lat, lon, legs, origin) -> np.ndarray:
    """Horizontal seed 002 eq. (6) distance to the nearest leg (chosen by distance to the segment)."""
    n, e = ned_from_lla(lat, lon, origin[0], origin[1])
    x = np.stack([n, e, np.zeros_like(n)], axis=1)
    best_seg = np.full(len(x), np.inf)
    best_d = np.full(len(x), np.nan)
    for (a, b) in legs:
        an, ae = ned_from_lla(a[0], a[1], origin[0], origin[1])
        bn, be = ned_from_lla(b[0], b[1], origin[0], origin[1])
        A, B = np.array([an, ae, 0.0]), np.array([bn, be, 0.0])
        ab = B - A
        u = np.clip(((x - A) @ ab) / max(ab @ ab, 1e-12), 0.0, 1.0)
        seg = np.linalg.norm(x - (A + u[:, None] * ab), axis=1)
        d = cross_track_m(x, A, B)
        better = seg < best_seg
        best_seg = np.where(better, seg, best_seg)
        best_d = np.where(better, d, best_d)
    return best_d


def _hold(t_src: np.ndarray, v_src: np.ndarray, t: np.ndarray, timeout_s: float) -> np.ndarray:
    """Latest source value at or before each t (NaN when none within timeout)."""
    v_src = np.asarray(v_src, dtype=float)
    out_shape = (len(t),) + v_src.shape[1:]
    if len(t_src) == 0:
        return np.full(out_shape, np.nan)
    idx = np.searchsorted(t_src, t, side="right") - 1
    ok = (idx >= 0) & (t - t_src[np.maximum(idx, 0)] <= timeout_s)
    out = v_src[np.maximum(idx, 0)].astype(float)
    out[~ok] = np.nan
    return out


def _field_reference(log: FlightLog):
    """WMM at the log's median GPS position and date (None when the position is unknown)."""
    g = log.gps
    if not len(g):
        return None, None
    lat, lon, alt = float(np.median(g[:, 1])), float(np.median(g[:, 2])), float(np.median(g[:, 3]))
    start = log.start_unix_s if log.start_unix_s else time.time()
    try:
        return earth_field(lat, lon, alt, decimal_year_from_unix(start)), (lat, lon, alt)
    except ValueError:
        return None, None


def _uncalibrated(log: FlightLog) -> bool:
    """The log's field is the raw sensor output: raw samples (PX4 sensor_mag), or ArduPilot with
    COMPASS_OFS_* all zero (never calibrated; a calibrated compass has non-zero offsets)."""
    return getattr(log, "mag_calibration_applied", None) is False or ardupilot_never_calibrated(log.params)


def _too_steep(roll_rad, pitch_rad, settings: DetectionSettings):
    """Not a flight attitude (calibration dance, vehicle carried): detection does not look there."""
    cos_tilt = np.cos(roll_rad) * np.cos(pitch_rad)
    return ~(cos_tilt >= np.cos(np.radians(settings.max_tilt_deg)))


def _rotation_rate(gyro_rad_s: np.ndarray) -> np.ndarray:
    """|ω| [rad/s]: turns and other fast rotations gate the heading-difference evidence."""
    return np.linalg.norm(np.nan_to_num(np.asarray(gyro_rad_s, dtype=float)), axis=-1)


def _r(x, nd=3):
    v = finite_or_none(x)
    return None if v is None else round(v, nd)


# ------------------------------------------------------------------------------ batch
def detection_inputs(log: FlightLog, calibration: dict | None = None, mission: list | None = None,
                     settings: DetectionSettings | None = None) -> dict:
    """Everything the detector needs, on the IMU time base (heading chain, field, cross-track).

    Keys: t, e (heading difference rad), d (cross-track m), trusted, strength, incl, heading,
    yaw_rate, ef (EarthField or None), pos, chain, valid, g (GPS table), d_gps, legs, rtk,
    path_test, cal.
    """
    settings = settings or DetectionSettings()
    cal = _calibration_arrays(calibration)
    mag = np.asarray(log.mag, dtype=float).reshape(-1, 4)
    imu = np.asarray(log.imu, dtype=float).reshape(-1, 7)
    mag_cal = mag.copy()
    field_test = "on"
    if cal is not None and len(mag):
        # the calibration (issue 3) is relative to the raw sensor: un-apply the autopilot's own first
        raw, _ = unapply_onboard_calibration(mag[:, 1:4], log.params, log.autopilot,
                                             getattr(log, "mag_calibration_applied", None))
        mag_cal[:, 1:4] = (raw - cal[0]) @ cal[1].T
    elif _uncalibrated(log):
        field_test = "off: magnetometer not calibrated (give a calibration; the log has no onboard offsets)"
    ef, pos = _field_reference(log)
    decl = ef.declination_deg if ef else 0.0

    chain = run_heading_chain(imu, mag_cal, decl)
    t = chain.t_s
    n = len(t)
    valid = chain.valid
    e = np.where(valid, wrap_angle_rad(chain.mag_heading_rad - chain.yaw_rad), np.nan)

    # field strength / inclination of the latest magnetometer sample at each IMU step
    m_held = _hold(mag_cal[:, 0], mag_cal[:, 1:4], t, GPS_TIMEOUT_S) if n else np.zeros((0, 3))
    att = np.asarray(log.attitude, dtype=float).reshape(-1, 4)
    rp = _hold(att[:, 0], att[:, 1:3], t, 0.5) if len(att) else np.full((n, 2), np.nan)
    roll_f = np.where(np.isfinite(rp[:, 0]), rp[:, 0], chain.roll_rad)
    pitch_f = np.where(np.isfinite(rp[:, 1]), rp[:, 1], chain.pitch_rad)
    strength = np.linalg.norm(m_held, axis=1)
    incl = field_inclination_deg(m_held, roll_f, pitch_f)
    steep = _too_steep(roll_f, pitch_f, settings)
    if n:   # ... and for turn_settle_s after it
        last = np.maximum.accumulate(np.where(steep, t, -np.inf))
        steep = t - last <= settings.turn_settle_s
    e = np.where(steep, np.nan, e)
    imu_rate = 1.0 / float(np.median(np.diff(t))) if n > 10 and np.median(np.diff(t)) > 0 else 0.0
    heading_test = "on"
    if imu_rate < settings.min_imu_rate_hz:
        # the gyro cannot follow the rotation between samples: the filter heading is not a reference
        e = np.full(n, np.nan)
        heading_test = (f"off: IMU rate {imu_rate:.1f} Hz < {settings.min_imu_rate_hz:g} Hz"
                        if n else "off: no IMU data")
    if not len(mag):
        heading_test = field_test = "off: no magnetometer data in the log"
    strength = np.where(steep, np.nan, strength)
    incl = np.where(steep, np.nan, incl)
    if field_test != "on" or not n:
        strength = np.full(n, np.nan)
        incl = np.full(n, np.nan)

    # path: cross-track from GPS, nearest mission leg
    points = mission if mission else log.mission
    legs = mission_legs(points)
    g = np.asarray(log.gps, dtype=float).reshape(-1, 8)
    rtk = bool(len(g) and np.mean(g[:, 7] >= settings.rtk_min_fix) > 0.5)
    if legs and len(g):
        d_gps = _cross_track_legs(g[:, 1], g[:, 2], legs, legs[0][0])
        d = _hold(g[:, 0], d_gps, t, GPS_TIMEOUT_S)
        trusted = _hold(g[:, 0], (g[:, 7] >= settings.rtk_min_fix).astype(float), t, GPS_TIMEOUT_S) == 1.0
        path_test = "on" if rtk else "untrusted: no RTK fix (fix_type < 5), path deviation never alarms"
    else:
        d_gps = np.zeros(0)
        d = np.full(n, np.nan)
        trusted = np.zeros(n, bool)
        path_test = ("off: no mission" if not legs else "off: no GPS position in the log")

    yaw_rate = _rotation_rate(imu[:, 1:4]) if n else np.zeros(0)
    heading = np.where(valid, chain.yaw_rad, np.nan)
    return dict(t=t, e=e, d=d, trusted=trusted, strength=strength, incl=incl, heading=heading, mag_cal=mag_cal,
                yaw_rate=yaw_rate, ef=ef, pos=pos, chain=chain, valid=valid, g=g, d_gps=d_gps, legs=legs,
                rtk=rtk, path_test=path_test, heading_test=heading_test, field_test=field_test, imu_rate_hz=imu_rate, cal=cal)


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


def _navigation(log: FlightLog, mag_cal: np.ndarray, declination_deg: float, imu_rate_hz: float,
                settings: DetectionSettings) -> dict:
    """GPS outages and what the seed-003 INS/GPS filter made of each: it runs from INS_LEAD_S
    before the outage (to learn gyro biases and the Earth field with GPS) through the outage to
    INS_TAIL_S after it, once holding the attitude with field-vector feedback and once open loop
    (gyro integration with the biases learnt before the outage); each heading is compared with
    the autopilot's own.  Both are reported because neither is always better: the feedback bounds
    an unknown gyro-bias change, but a body-fixed field (motor current) that the Earth-field
    set-point absorbed before the outage pulls it off after a turn (see README, Known limits)."""
    imu = np.asarray(log.imu, dtype=float).reshape(-1, 7)
    g = np.asarray(log.gps, dtype=float).reshape(-1, 8)
    good = (g[:, 7] >= 3) & np.all(np.isfinite(g[:, 0:4]), axis=1)
    if not len(imu) or not good.any():
        return {"ins_gps": "off: " + ("no IMU data" if not len(imu) else "no 3-D GPS fix in the log"),
                "gps_outages": []}
    g = g[good]
    t_last = float(imu[-1, 0])
    found = gps_outages(g[:, 0], imu[:, 0])
    outages = [{"start_s": _r(start, 2), "end_s": _r(end, 2),
                "duration_s": _r((end if end is not None else t_last) - start, 2),
                "ins_mode": None, "ins_vs_autopilot_heading_deg": None}
               for start, end in found]
    if imu_rate_hz < settings.min_imu_rate_hz:   # telemetry-rate IMU: strapdown integration is meaningless
        return {"ins_gps": f"off: IMU rate {imu_rate_hz:.1f} Hz < {settings.min_imu_rate_hz:g} Hz",
                "gps_outages": outages}
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
    for entry, (start, end) in zip(outages, found):
        stop = (end if end is not None else t_last) + INS_TAIL_S
        entry["ins_vs_autopilot_heading_deg"] = {}
        # one run with GPS up to the outage, then two branches from the same state
        lead = InsGpsFilter(ins_settings)
        before = lambda a: a[(a[:, 0] >= start - INS_LEAD_S) & (a[:, 0] <= start)]  # noqa: E731
        after = lambda a: a[(a[:, 0] > start) & (a[:, 0] <= stop)]  # noqa: E731
        run_ins_gps(before(imu), before(gps_ned), before(mag_cal), filt=lead, current=before(battery))
        for law in ("field_feedback", "open_loop"):
            branch = copy.deepcopy(lead)
            branch.s = dataclasses.replace(ins_settings, field_feedback=law == "field_feedback")
            res = run_ins_gps(after(imu), after(gps_ned), after(mag_cal), filt=branch, current=after(battery))
            inside = (res.t_s > start + GPS_TIMEOUT_S) & (res.t_s < (end if end is not None else np.inf))
            if law == "field_feedback" and inside.any():
                entry["ins_mode"] = MODE_NAMES[int(np.bincount(res.mode[inside]).argmax())]
            ap_yaw = _hold(att[:, 0], att[:, 3], res.t_s, 0.5) if len(att) else np.full(len(res.t_s), np.nan)
            diff = np.degrees(np.abs(wrap_angle_rad(res.yaw_rad - ap_yaw)))[inside]
            entry["ins_vs_autopilot_heading_deg"][law] = (
                {"median": _r(np.nanmedian(diff), 2), "max": _r(np.nanmax(diff), 2)}
                if np.isfinite(diff).any() else None)
    return {"ins_gps": "on: seed-003 INS/GPS over each outage (field-vector feedback and open loop)",
            "gps_outages": outages}


def analyze_log(log: FlightLog, calibration: dict | None = None, mission: list | None = None,
                settings: DetectionSettings | None = None) -> tuple[dict, dict[str, np.ndarray]]:
    """Heading chain + interference detection on a whole log; see module docstring."""
    settings = settings or DetectionSettings()
    x = detection_inputs(log, calibration, mission, settings)
    t, e, d, trusted, ef, pos, chain, valid, g = (x[k] for k in ("t", "e", "d", "trusted", "ef", "pos", "chain", "valid", "g"))
    d_gps, legs, rtk, path_test, cal = (x[k] for k in ("d_gps", "legs", "rtk", "path_test", "cal"))
    strength = x["strength"]
    n = len(t)
    det = detect(t, e, d, trusted, strength, x["incl"], x["heading"], x["yaw_rate"],
                 ef.field_strength_mG if ef else np.nan, ef.inclination_deg if ef else np.nan, settings)

    # velocity split with the true heading (seed 000 sec. 3.3)
    vel = _hold(g[:, 0], g[:, 4:6], t, GPS_TIMEOUT_S) if len(g) else np.full((n, 2), np.nan)
    hdg_true = np.where(valid, chain.heading_true_rad, np.nan)
    v_fwd, v_lat = split_velocity(vel[:, 0], vel[:, 1], hdg_true)
    deg = lambda x: np.where(valid, np.degrees(x), np.nan)  # noqa: E731
    columns = {
        "t_s": t,
        "roll_deg": deg(chain.roll_rad), "pitch_deg": deg(chain.pitch_rad),
        "yaw_deg": deg(chain.yaw_rad), "mag_heading_deg": deg(chain.mag_heading_rad),
        "heading_true_deg": deg(chain.heading_true_rad),
        "v_forward_mps": v_fwd, "v_lateral_mps": v_lat,
        "cross_track_m": d, "alarm": det.combined.astype(int),
    }

    dev_h = det.z_heading * settings.sigma_k * det.heading_sigma_deg
    alarms = []
    for kind, flag, value in (("heading_difference", det.heading_alarm, dev_h),
                              ("path_deviation", det.path_alarm, d),
                              ("field_anomaly", det.field_alarm, np.fmax(det.z_strength, det.z_inclination)),
                              ("combined", det.combined, np.fmax(np.fmax(det.z_heading, det.z_path), det.z_field))):
        for start, end, peak, i0, i1 in alarm_intervals(t, flag, value):
            a = {"kind": kind, "start_s": _r(start, 2), "end_s": _r(end, 2), "peak": _r(peak)}
            if kind == "heading_difference":
                a["unit"] = "deg"
            elif kind == "path_deviation":
                a["unit"] = "m"
            elif kind == "field_anomaly":
                a["unit"] = "score (strength or inclination deviation / threshold)"
            else:
                a["unit"] = "score (1 = test threshold)"
                trig = det.trigger[i0:i1 + 1].any(axis=0)
                a["evidence"] = [k for k, on in zip(("heading_difference", "path_deviation", "field_anomaly"), trig) if on]
                a["evidence_at_start"] = det.evidence_at(i0)
            alarms.append(a)
    alarms.sort(key=lambda a: (a["start_s"], a["kind"]))
    combined = [a for a in alarms if a["kind"] == "combined"]
    legs_report = None
    if legs:
        (a_ll, b_ll) = legs[0]
        legs_report = {"A": [a_ll[0], a_ll[1]], "B": [b_ll[0], b_ll[1]]}
        if len(legs) > 1:
            legs_report["legs"] = len(legs)
    meas_strength = float(np.nanmedian(strength)) if np.isfinite(strength).any() else None
    report = {
        "file": log.source,
        "duration_s": _r(log.duration_s, 2),
        "calibration": calibration if calibration else None,
        "calibration_applied": cal is not None,
        "declination_deg": _r(ef.declination_deg) if ef else None,
        "inclination_deg": _r(ef.inclination_deg) if ef else None,
        "field_strength_mG": _r(ef.field_strength_mG, 1) if ef else None,
        "measured_field_strength_mG": _r(meas_strength, 1),
        "position": {"lat": pos[0], "lon": pos[1], "alt_m": _r(pos[2], 1)} if pos else None,
        "rtk": rtk,
        "mission": legs_report,
        "path_test": path_test,
        "heading_test": x["heading_test"],
        "field_test": x["field_test"],
        "imu_rate_hz": _r(x["imu_rate_hz"], 1),
        "max_cross_track_m": _r(np.nanmax(d_gps)) if len(d_gps) and np.isfinite(d_gps).any() else None,
        "alarms": alarms,
        "first_alarm_s": combined[0]["start_s"] if combined else None,
        "interference_detected": bool(combined),
        "navigation": _navigation(log, x["mag_cal"], ef.declination_deg if ef else 0.0, x["imu_rate_hz"], settings),
        "detection": {
            "heading_sigma_deg": _r(det.heading_sigma_deg), "heading_threshold_deg": _r(settings.sigma_k * det.heading_sigma_deg),
            "learn_s": settings.learn_s, "path_threshold_m": settings.path_threshold_m,
            "field_sectors_learned": len(det.sector_offsets),
            "field_thresholds": {"strength_floor_mG": settings.strength_floor_mG,
                                 "inclination_floor_deg": settings.inclination_floor_deg},
        },
    }
    return report, columns


def write_csv(path: str | Path, columns: dict[str, np.ndarray]) -> Path:
    """Write the issue-4 CSV (header = CSV_COLUMNS, then one row per IMU step; empty cell = NaN)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    names = [c for c in CSV_COLUMNS if c in columns] + [c for c in columns if c not in CSV_COLUMNS]
    arr = np.column_stack([np.asarray(columns[c], dtype=float) for c in names]) if names else np.zeros((0, 0))
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(names)
        for row in arr.tolist():
            w.writerow(["" if not math.isfinite(v) else (str(int(v)) if c == "alarm" else f"{v:.6g}")
                        for c, v in zip(names, row)])
    return path


def format_report(report: dict) -> str:
    """Human-readable summary of an analyze report."""
    lines = [f"file: {report.get('file')}  ({report.get('duration_s')} s)"]
    if report.get("declination_deg") is not None:
        lines.append(f"WMM: declination {report['declination_deg']:.2f}°, inclination "
                     f"{report['inclination_deg']:.2f}°, field {report['field_strength_mG']:.1f} mG "
                     f"(measured median {report.get('measured_field_strength_mG')} mG)")
    lines.append("calibration: " + ("applied" if report.get("calibration_applied") else "none (raw magnetometer)"))
    lines.append(f"RTK: {'yes' if report.get('rtk') else 'no'};  path test: {report.get('path_test')}")
    lines.append(f"heading test: {report.get('heading_test')};  field test: {report.get('field_test')}")
    if report.get("mission"):
        m = report["mission"]
        lines.append(f"mission A {m['A']} -> B {m['B']};  max cross-track {report.get('max_cross_track_m')} m")
    nav = report.get("navigation") or {}
    for o in nav.get("gps_outages", []):
        cmp = "; ".join(f"{law.replace('_', ' ')} median {v['median']}°, max {v['max']}°"
                        for law, v in (o.get("ins_vs_autopilot_heading_deg") or {}).items() if v)
        lines.append(f"GPS outage {o['start_s']}–{o['end_s'] if o['end_s'] is not None else 'end'} s "
                     f"({o['duration_s']} s): " + (f"INS/GPS mode {o['ins_mode']}; heading vs autopilot: {cmp or 'n/a'}"
                                                   if o["ins_mode"] else f"INS/GPS {nav.get('ins_gps')}"))
    comb = [a for a in report.get("alarms", []) if a["kind"] == "combined"]
    others = [a for a in report.get("alarms", []) if a["kind"] != "combined"]
    lines.append(f"interference detected: {'YES' if report.get('interference_detected') else 'no'}"
                 + (f" (first alarm at {report['first_alarm_s']} s)" if report.get("first_alarm_s") is not None else ""))
    for a in comb:
        lines.append(f"  ALARM {a['start_s']}–{a['end_s'] if a['end_s'] is not None else 'end'} s, "
                     f"evidence: {', '.join(a.get('evidence', []))}, peak score {a['peak']}")
    if others:
        lines.append("single-test alarms: " + ", ".join(
            f"{a['kind']}@{a['start_s']}s" for a in others[:12]) + (" ..." if len(others) > 12 else ""))
    return "\n".join(lines)


# ------------------------------------------------------------------------------ live
class LiveAnalyzer:
    """Per-sample version of ``analyze_log`` (same chain, same detector) for the live server.

    Feed every sample with ``on_sample``; read ``alarm_active``, ``alarm_kinds`` (evidence names),
    ``peak`` and ``last_step``.  WMM reference and declination are fixed at the first GPS fix
    (date: ``start_unix_s`` or now).  ``set_calibration`` / ``set_mission`` may be called any time.
    """

    def __init__(self, calibration: dict | None = None, mission: list | None = None,
                 start_unix_s: float | None = None, settings: DetectionSettings | None = None) -> None:
        self.settings = settings or DetectionSettings()
        self.start_unix_s = start_unix_s
        self.cal = _calibration_arrays(calibration)
        self.legs = mission_legs(mission)
        self.chain = HeadingChain()
        self.detector = InterferenceDetector(self.settings)
        self.earth_field = None
        self._mag: np.ndarray | None = None
        self._mag_t = -np.inf
        self._att: tuple[float, float, float] | None = None
        self._gps: tuple[float, float, bool] | None = None   # (t, cross-track, trusted)
        self.last_step = None
        self.last_state = None
        self.alarm_active = False
        self.alarm_kinds: list[str] = []
        self.peak: float | None = None
        self._last_steep = -np.inf
        self.params: dict[str, float] = {}
        self.autopilot: str | None = None
        self._imu_t: float | None = None
        self._imu_dt: float | None = None

    def set_calibration(self, calibration: dict | None) -> None:
        self.cal = _calibration_arrays(calibration)

    def set_mission(self, mission: list | None) -> None:
        self.legs = mission_legs(mission)

    def _start(self, s: GpsSample) -> None:
        """Declination from the WMM at the first fix (detection itself does not need the WMM:
        the field checks compare against the offset learned over the clean start)."""
        start = self.start_unix_s if self.start_unix_s else time.time() - s.t_s
        try:
            ef = earth_field(s.lat_deg, s.lon_deg, s.alt_m, decimal_year_from_unix(start + s.t_s))
        except ValueError:
            return
        self.chain.declination_deg = ef.declination_deg
        self.earth_field = ef

    def on_sample(self, s) -> None:
        if isinstance(s, GpsSample):
            if self.earth_field is None:
                self._start(s)
            if self.legs:
                d = float(_cross_track_legs(np.array([s.lat_deg]), np.array([s.lon_deg]), self.legs,
                                            self.legs[0][0])[0])
            else:
                d = float("nan")
            self._gps = (s.t_s, d, s.fix_type >= self.settings.rtk_min_fix)
        elif isinstance(s, AttitudeSample):
            self._att = (s.t_s, s.roll_rad, s.pitch_rad)
        elif isinstance(s, ParamSample):
            self.params[s.name] = s.value
        elif isinstance(s, StatusSample) and s.kind == "autopilot":
            self.autopilot = s.text
        elif isinstance(s, MagSample):
            m = np.asarray(s.mag_body_mG, dtype=float)
            if self.cal is not None:
                raw, _ = unapply_onboard_calibration(m[None, :], self.params, self.autopilot)
                m = self.cal[1] @ (raw[0] - self.cal[0])
            if np.all(np.isfinite(m)):
                self._mag, self._mag_t = m, s.t_s
                self.chain.update_mag(s.t_s, m)
        elif isinstance(s, ImuSample):
            st = self.chain.update_imu(s.t_s, np.asarray(s.gyro_rad_s), np.asarray(s.accel_mps2))
            t = st.t_s
            if self._imu_t is not None and t > self._imu_t:     # running mean IMU interval
                dt = t - self._imu_t
                self._imu_dt = dt if self._imu_dt is None else 0.95 * self._imu_dt + 0.05 * dt
            self._imu_t = t
            slow_imu = self._imu_dt is None or self._imu_dt > 1.0 / self.settings.min_imu_rate_hz
            e = float(wrap_angle_rad(st.mag_heading_rad - st.yaw_rad)) if st.valid and not slow_imu else float("nan")
            if self._mag is not None and t - self._mag_t <= GPS_TIMEOUT_S:
                if self._att is not None and t - self._att[0] <= 0.5:
                    r, p = self._att[1], self._att[2]
                else:
                    r, p = st.roll_rad, st.pitch_rad
                strength = float(np.linalg.norm(self._mag))
                incl = float(field_inclination_deg(self._mag, r, p))
            else:
                r, p = st.roll_rad, st.pitch_rad
                strength = incl = float("nan")
            if self.cal is None and _uncalibrated(self):     # raw sensor: no field test
                strength = incl = float("nan")
            if _too_steep(r, p, self.settings):
                self._last_steep = t
            if t - self._last_steep <= self.settings.turn_settle_s:
                e = strength = incl = float("nan")
            if self._gps is not None and t - self._gps[0] <= GPS_TIMEOUT_S:
                d, trusted = self._gps[1], self._gps[2]
            else:
                d, trusted = float("nan"), False
            yaw_rate = float(_rotation_rate(np.asarray(s.gyro_rad_s, dtype=float)))
            step = self.detector.update(t, e, d, trusted, strength, incl,
                                        st.yaw_rad if st.valid else float("nan"), yaw_rate)
            self.last_step = step
            self.last_state = st       # the heading chain state (for the live display)
            self.alarm_active = self.detector.alarm_active
            self.alarm_kinds = list(self.detector.alarm_kinds)
            self.peak = self.detector.peak
