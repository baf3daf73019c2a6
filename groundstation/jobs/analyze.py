"""`magstation analyze`: heading chain + interference detection over a whole log.

``analyze_log(log, calibration=None, mission=None) -> (report, columns)``
  report:  the analyze JSON object (file, duration_s, calibration, declination_deg, inclination_deg,
           field_strength_mG, rtk, mission, path_test, max_cross_track_m, compasses (each compass's
           field strength / inclination against the WMM), compass_consistency, alarms,
           first_alarm_s, interference_detected, navigation, detection ...)
  columns: the per-step CSV as {name: array} on the IMU time base (``groundstation.jobs.report``).
The per-sample twin for the live station is ``groundstation.jobs.live.LiveAnalyzer``.

The math lives in estimators (heading chain: seed 000; detection: seed 002); this module turns a
FlightLog into arrays on one time base (``groundstation.jobs.inputs``), looks up the WMM and
builds the report.
"""
from __future__ import annotations

import numpy as np

from estimators.detection import DetectionSettings, alarm_intervals, detect
from estimators.heading import split_velocity

from groundstation.jobs.compass_report import compass_summaries
from groundstation.jobs.inputs import GPS_TIMEOUT_S, detection_inputs, hold_last, rounded
from groundstation.jobs.navigation import navigation
from groundstation.samples import FlightLog

__all__ = ["analyze_log"]


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
    vel = hold_last(g[:, 0], g[:, 4:6], t, GPS_TIMEOUT_S) if len(g) else np.full((n, 2), np.nan)
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

    alarms = alarm_list(t, det, d, settings)
    combined = [a for a in alarms if a["kind"] == "combined"]
    legs_report = None
    if legs:
        (a_ll, b_ll) = legs[0]
        legs_report = {"A": [a_ll[0], a_ll[1]], "B": [b_ll[0], b_ll[1]]}
        if len(legs) > 1:
            legs_report["legs"] = len(legs)
    meas_strength = float(np.nanmedian(strength)) if np.isfinite(strength).any() else None
    compasses, consistency = compass_summaries(log, cal, (calibration or {}).get("compass"), ef, settings)
    report = {
        "file": log.source,
        "duration_s": rounded(log.duration_s, 2),
        "calibration": calibration if calibration else None,
        "calibration_applied": cal is not None,
        "declination_deg": rounded(ef.declination_deg) if ef else None,
        "inclination_deg": rounded(ef.inclination_deg) if ef else None,
        "field_strength_mG": rounded(ef.field_strength_mG, 1) if ef else None,
        "measured_field_strength_mG": rounded(meas_strength, 1),
        "position": {"lat": pos[0], "lon": pos[1], "alt_m": rounded(pos[2], 1)} if pos else None,
        "rtk": rtk,
        "mission": legs_report,
        "path_test": path_test,
        "heading_test": x["heading_test"],
        "field_test": x["field_test"],
        "imu_rate_hz": rounded(x["imu_rate_hz"], 1),
        "max_cross_track_m": rounded(np.nanmax(d_gps)) if len(d_gps) and np.isfinite(d_gps).any() else None,
        "compasses": compasses,
        "compass_consistency": consistency,
        "alarms": alarms,
        "first_alarm_s": combined[0]["start_s"] if combined else None,
        "interference_detected": bool(combined),
        "navigation": navigation(log, x["mag_cal"], ef.declination_deg if ef else 0.0, x["imu_rate_hz"], settings),
        "detection": {
            "heading_sigma_deg": rounded(det.heading_sigma_deg), "heading_threshold_deg": rounded(settings.sigma_k * det.heading_sigma_deg),
            "learn_s": settings.learn_s, "path_threshold_m": settings.path_threshold_m,
            "field_sectors_learned": len(det.sector_offsets),
            "field_thresholds": {"strength_floor_mG": settings.strength_floor_mG,
                                 "inclination_floor_deg": settings.inclination_floor_deg},
        },
    }
    return report, columns


ALARM_UNITS = {"heading_difference": "deg", "path_deviation": "m",
               "field_anomaly": "score (strength or inclination deviation / threshold)",
               "combined": "score (1 = test threshold)"}
TESTS = ("heading_difference", "path_deviation", "field_anomaly")


def alarm_list(t: np.ndarray, det, cross_track_m: np.ndarray, settings: DetectionSettings) -> list[dict]:
    """Every alarm interval of each test and of the combined decision, in time order."""
    dev_h = det.z_heading * settings.sigma_k * det.heading_sigma_deg
    alarms = []
    for kind, flag, value in (("heading_difference", det.heading_alarm, dev_h),
                              ("path_deviation", det.path_alarm, cross_track_m),
                              ("field_anomaly", det.field_alarm, np.fmax(det.z_strength, det.z_inclination)),
                              ("combined", det.combined, np.fmax(np.fmax(det.z_heading, det.z_path), det.z_field))):
        for start, end, peak, i0, i1 in alarm_intervals(t, flag, value):
            a = {"kind": kind, "start_s": rounded(start, 2), "end_s": rounded(end, 2), "peak": rounded(peak),
                 "unit": ALARM_UNITS[kind]}
            if kind == "combined":
                trig = det.trigger[i0:i1 + 1].any(axis=0)
                a["evidence"] = [k for k, on in zip(TESTS, trig) if on]
                a["evidence_at_start"] = det.evidence_at(i0)
            alarms.append(a)
    alarms.sort(key=lambda a: (a["start_s"], a["kind"]))
    return alarms
