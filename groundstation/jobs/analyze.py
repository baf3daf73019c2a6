"""`magstation analyze`: heading chain + interference detection over a whole log.

``analyze_log(log, calibration=None, mission=None) -> (report, columns)``
  report:  the analyze JSON object (file, duration_s, calibration, declination_deg, inclination_deg,
           field_strength_mG, rtk, mission, path_test, max_cross_track_m, compasses (each compass's
           field strength / inclination against the WMM), compass_consistency, alarms,
           first_alarm_s, interference_detected, navigation, detection ...)
  columns: the per-step CSV as {name: array} on the IMU time base (``groundstation.jobs.report``).
``analyze_flight(log, calibration=None, mission=None) -> FlightAnalysis`` is its detection part
alone (no INS/GPS over outages): the flight record (``groundstation.jobs.record``) the station's
replay reads; the per-sample twin for a live link is ``groundstation.jobs.live.LiveAnalyzer``.

The math lives in estimators (heading chain: seed 000; detection: seed 002); this module turns a
FlightLog into arrays on one time base (``groundstation.jobs.inputs``), looks up the WMM and
builds the report.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimators.detection import DetectionResult, DetectionSettings, alarm_intervals, detect
from estimators.heading import HeadingChainResult, split_velocity
from estimators.ins_gps import MODE_NAMES

from groundstation.jobs.alarm_explain import STEP_KEYS, explain_span, explanation_text
from groundstation.jobs.compass_report import compass_summaries
from groundstation.jobs.flight_plot import vector_test_status
from groundstation.jobs.calibrate.frame import for_log, relative_to
from groundstation.jobs.calibration_check import calibration_arrays
from groundstation.jobs.inputs import detection_inputs, heading_deg, primary_field, rounded
from groundstation.jobs.motor_heading import best_heading_chain, motor_correction
from groundstation.jobs.navigation import ins_runs
from groundstation.jobs.record import AlarmTracker, record_rows
from groundstation.samples import FlightLog

__all__ = ["analyze_log", "analyze_flight", "FlightAnalysis", "detector_score", "explanation_text",
           "calibration_for_log", "finished_log_attitude"]


def detector_score(z_heading, z_path, z_field, z_vector=np.nan) -> np.ndarray:
    """The largest test score of each step (NaN where no test has one)."""
    best = np.fmax(np.fmax(np.asarray(z_heading, float), np.asarray(z_path, float)), np.asarray(z_field, float))
    return np.fmax(best, np.asarray(z_vector, float))


@dataclass
class FlightAnalysis:
    """The detection part of analyze on a whole log: inputs (``detection_inputs``), the
    detector's result and the flight record rows (``groundstation.jobs.record``; None when not
    asked for: the report alone needs none)."""
    x: dict
    det: DetectionResult
    rows: np.ndarray | None
    settings: DetectionSettings
    attitude: HeadingChainResult | None = None     # the default AHRS on the field as measured: shown

    def combined_alarms(self) -> list[dict]:
        """The alarms of the combined decision, as the flight record's rows give them (its t_s,
        alarm, evidence and score columns are these arrays)."""
        tracker = AlarmTracker()
        det = self.det
        tracker.update(self.x["t"], np.asarray(det.combined, bool), np.asarray(det.trigger, bool),
                       detector_score(det.z_heading, det.z_path, det.z_field, det.z_vector))
        for alarm in tracker.alarms:
            alarm["explanation"] = self.explain(alarm["start_s"], alarm["end_s"])
            alarm["explanation_text"] = explanation_text(alarm["explanation"], self.x.get("motor_signal", "none"))
        return tracker.alarms

    def explain(self, start_s: float, end_s: float | None) -> dict | None:
        """The disturbance, growth, tests and likely kind of the alarm (``jobs.alarm_explain``)."""
        return explain_span(self.explain_steps(), start_s, end_s)

    def explain_steps(self) -> dict:
        """Per-step explanation inputs (``jobs.alarm_explain.STEP_KEYS``) of the whole log."""
        x, det = self.x, self.det
        r = x["vector"].residual_mG
        gps = x["gps_held"]
        return dict(zip(STEP_KEYS, (x["t"], r[:, 0], r[:, 1], r[:, 2], x["motor_held"], gps[:, 3], gps[:, 4],
                                    gps[:, 8], det.z_heading, det.z_path, det.z_field, det.z_vector)))


def motor_field_report(x: dict) -> dict | None:
    """The motor field per unit of the motor signal as learned in flight: its last value and its
    trend (the value at each quarter of the flight)."""
    if x.get("motor_signal", "none") == "none":
        return None
    f = x["vector"].motor_mG_per_unit
    if not (x["vector"].status == 0).any():
        return None
    unit = "mG/A" if x["motor_signal"] == "current_A" else "mG/%"
    quarters = [[round(float(v), 2) for v in f[min(len(f) - 1, k * len(f) // 4)]] for k in (1, 2, 3, 4)]
    return {"signal": x["motor_signal"], "unit": unit, "estimate": quarters[-1], "trend": quarters}


def calibration_for_log(log: FlightLog, calibration: dict | None) -> tuple[dict | None, str | None]:
    """The calibration in the frame of this log's primary field (``jobs.calibrate.frame.for_log``:
    absolute as it is, relative on top of the log's corrections in force) and one line saying how
    it was applied; (calibration, None) when it is not usable or the log has no field."""
    arrays = calibration_arrays(calibration)
    if arrays is None or not len(log.mag):
        return calibration, None
    cf = primary_field(log)
    end = len(cf.offsets_in_force_mG) - 1
    applied = for_log(arrays[0], arrays[1], calibration, cf.status,
                      cf.offsets_in_force_mG[end] if end >= 0 else None, cf.nominal_matrix)
    out = dict(calibration, offsets_mG=applied.offsets_mG.tolist(), matrix=applied.matrix.tolist())
    return out, applied.note


def analyze_flight(log: FlightLog, calibration: dict | None = None, mission: list | None = None,
                   settings: DetectionSettings | None = None, record: bool = True) -> FlightAnalysis:
    """Detector inputs, detection and the flight record of a whole log (see module docstring); a
    relative calibration is applied on top of the log's corrections in force (``calibration_for_log``).
    ``record`` False: no flight record rows (RECORD_COLUMNS per IMU step: 80 MB for a 2-hour
    50 Hz log), for the report alone."""
    settings = settings or DetectionSettings()
    calibration, note = calibration_for_log(log, calibration)
    x = detection_inputs(log, calibration, mission, settings)
    x["calibration_note"] = note
    ef = x["ef"]
    det = detect(x["t"], x["e"], x["d"], x["trusted"], x["strength"], x["incl"], x["heading"], x["yaw_rate"],
                 ef.field_strength_mG if ef else np.nan, ef.inclination_deg if ef else np.nan, settings,
                 z_vector=x["z_vector"])
    shown = x["chain"]          # one attitude (issue 30): the detector's reference is the AHRS shown
    rows = record_rows(x["t"], x["chain"], x, ef.declination_deg if ef else 0.0, det.combined, det.trigger,
                       detector_score(det.z_heading, det.z_path, det.z_field, det.z_vector),
                       attitude=shown) if record else None
    return FlightAnalysis(x, det, rows, settings, shown)


def analyze_log(log: FlightLog, calibration: dict | None = None, mission: list | None = None,
                settings: DetectionSettings | None = None, columns: bool = True) -> tuple[dict, dict[str, np.ndarray]]:
    """Heading chain + interference detection on a whole log; see module docstring.  ``columns``
    False: the report alone (the same), no per-step columns ({}), and the finished log's attitude
    that only they need (the offline smoother) not made (the fleet review, analyze without --csv)."""
    settings = settings or DetectionSettings()
    fa = analyze_flight(log, calibration, mission, settings, record=False)    # the flight record is the station's
    combined_alarms = fa.combined_alarms()
    x, det = fa.x, fa.det
    t, d, ef, chain, valid = (x[k] for k in ("t", "d", "ef", "chain", "valid"))
    declination = ef.declination_deg if ef else 0.0
    nav, runs = ins_runs(log, x["mag_cal"], declination, x["imu_rate_hz"], settings)
    if not columns:
        _, motor = motor_correction(log, x)
        report, cal = _report(log, fa, calibration, nav, motor, combined_alarms), x["cal"]
        del fa, x, det, t, d, chain, valid, runs      # the per-step arrays go before the compasses' are made
        return _with_compasses(report, log, cal, calibration, ef, settings), {}
    best, best_chain, motor = finished_log_attitude(log, fa, runs)
    gps = x["gps_held"]
    v_fwd, v_lat = split_velocity(gps[:, 5], gps[:, 6], np.radians(best["heading_true_deg"]))
    table = {
        "t_s": t,
        "roll_deg": best["roll_deg"], "pitch_deg": best["pitch_deg"],
        "yaw_deg": best["yaw_deg"], "mag_heading_deg": np.where(valid, heading_deg(chain.mag_heading_rad), np.nan),
        "heading_true_deg": best["heading_true_deg"],
        "v_forward_mps": v_fwd, "v_lateral_mps": v_lat,
        "cross_track_m": d, "alarm": det.combined.astype(int),
        **bias_and_rejection(best_chain, valid), "ins_mode": best["ins_mode"],
        "attitude_source": best["attitude_source"],
    }
    report = _report(log, fa, calibration, nav, motor, combined_alarms)
    return _with_compasses(report, log, x["cal"], calibration, ef, settings), table


def _with_compasses(report: dict, log: FlightLog, cal, calibration: dict | None, ef, settings: DetectionSettings) -> dict:
    """The report's "compasses" and "compass_consistency" (``compass_summaries``: every compass
    over the whole log), made after the rest so that the caller can let the flight's per-step
    arrays go first (a 2-hour log's are over 200 MB)."""
    report["compasses"], report["compass_consistency"] = compass_summaries(
        log, cal, (calibration or {}).get("compass"), ef, settings)
    return report


def _report(log: FlightLog, fa: FlightAnalysis, calibration: dict | None, nav: dict, motor: dict,
            combined_alarms: list[dict]) -> dict:
    """analyze_log's report (see module docstring) of the analysed flight ``fa``, but for its
    compasses (``_with_compasses``)."""
    x, det, settings = fa.x, fa.det, fa.settings
    t, d, ef, pos = (x[k] for k in ("t", "d", "ef", "pos"))
    d_gps, legs, rtk, path_test, cal = (x[k] for k in ("d_gps", "legs", "rtk", "path_test", "cal"))
    strength = x["strength"]
    alarms = alarm_list(t, det, d, settings) + combined_alarms
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
        "duration_s": rounded(log.duration_s, 2),
        "calibration": calibration if calibration else None,
        "calibration_applied": cal is not None,
        "calibration_relative_to": relative_to(calibration) if cal is not None else None,
        "calibration_in_use": x["calibration_note"] if cal is not None else x["policy"].note,
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
        "field_vector_test": vector_test_status(x["vector"].status),
        "motor_field_learned": motor_field_report(x),
        "imu_rate_hz": rounded(x["imu_rate_hz"], 1),
        "max_cross_track_m": rounded(np.nanmax(d_gps)) if len(d_gps) and np.isfinite(d_gps).any() else None,
        "compasses": None,                  # _with_compasses
        "compass_consistency": None,
        "alarms": alarms,
        "first_alarm_s": combined[0]["start_s"] if combined else None,
        "interference_detected": bool(combined),
        "navigation": nav,
        "motor_field": motor,
        "detection": {
            "heading_sigma_deg": rounded(det.heading_sigma_deg), "heading_threshold_deg": rounded(settings.sigma_k * det.heading_sigma_deg),
            "learn_s": settings.learn_s, "path_threshold_m": settings.path_threshold_m,
            "field_sectors_learned": len(det.sector_offsets),
            "field_thresholds": {"strength_floor_mG": settings.strength_floor_mG,
                                 "inclination_floor_deg": settings.inclination_floor_deg},
        },
    }
    return report


ALARM_UNITS = {"heading_difference": "deg", "path_deviation": "m",
               "field_anomaly": "score (strength or inclination deviation / threshold)"}


def finished_log_attitude(log: FlightLog, fa: FlightAnalysis, runs: list) -> tuple[dict, HeadingChainResult, dict]:
    """The attitude of a finished log, as analyze's CSV and the station's review of a log show it:
    (``best_attitude``'s dict plus ``attitude_source`` per step, the heading chain it came from,
    report["motor_field"]).  The offline smoother over the whole log (the future is known) on the
    field with the significant motor field removed (``best_heading_chain``), the INS/GPS filter's
    attitude where it runs (``runs``: ``jobs.navigation.ins_runs``).  ``attitude_source`` is
    "offline" (the smoother) or "causal" (a causal filter: the INS/GPS one there, or the causal
    AHRS when the smoother could not run).  The detector's decisions stay on the causal AHRS
    (``fa.x["chain"]``): live = replay = analyze."""
    x = fa.x
    ef = x["ef"]
    declination = ef.declination_deg if ef else 0.0
    chain, motor = best_heading_chain(log, x, fa.attitude, offline=True)
    best = best_attitude(x["t"], chain, x["valid"], runs, declination)
    best["attitude_source"] = np.where((best["ins_mode"] == "") & (chain.estimator == "offline"),
                                       "offline", "causal").astype(object)
    return best, chain, motor


def best_attitude(t: np.ndarray, chain, valid: np.ndarray, runs: list, declination_deg: float) -> dict:
    """The best attitude on every step: the heading chain (AHRS), and where the seed-003 INS/GPS
    filter runs (around GPS outages, ``jobs.navigation.ins_runs``) its attitude; ``ins_mode`` the
    filter's mode there ("" elsewhere).  Degrees, headings in [0, 360)."""
    roll, pitch = np.where(valid, chain.roll_rad, np.nan), np.where(valid, chain.pitch_rad, np.nan)
    yaw_true = np.where(valid, chain.heading_true_rad, np.nan)
    mode = np.full(len(t), "", dtype=object)
    for res in runs:
        k = np.searchsorted(t, res.t_s)
        hit = (k < len(t)) & (t[np.minimum(k, len(t) - 1)] == res.t_s) if len(t) else np.zeros(0, bool)
        k, sel = k[hit], np.flatnonzero(hit)
        roll[k], pitch[k], yaw_true[k] = res.roll_rad[sel], res.pitch_rad[sel], res.yaw_rad[sel]
        mode[k] = [MODE_NAMES[int(m)] for m in res.mode[sel]]
    return {"roll_deg": np.degrees(roll), "pitch_deg": np.degrees(pitch),
            "yaw_deg": heading_deg(yaw_true - np.radians(declination_deg)), "heading_true_deg": heading_deg(yaw_true),
            "ins_mode": mode}


def bias_and_rejection(chain, valid: np.ndarray) -> dict:
    """The AHRS's gyro bias in effect [°/s] and its rejection flags (0/1) per step (issue 12)."""
    bias = np.degrees(np.asarray(chain.gyro_bias_rad_s, dtype=float).reshape(-1, 3))
    if len(bias) != len(valid):
        bias = np.zeros((len(valid), 3))
    flag = lambda a: (np.asarray(a, bool) if len(a) == len(valid) else np.zeros(len(valid), bool)).astype(int)  # noqa: E731
    return {"gyro_bias_x_dps": np.where(valid, bias[:, 0], np.nan), "gyro_bias_y_dps": np.where(valid, bias[:, 1], np.nan),
            "gyro_bias_z_dps": np.where(valid, bias[:, 2], np.nan),
            "acc_rejected": flag(chain.acc_rejected), "mag_rejected": flag(chain.mag_rejected)}


def alarm_list(t: np.ndarray, det, cross_track_m: np.ndarray, settings: DetectionSettings) -> list[dict]:
    """The alarm intervals of each test alone that are evidence of a combined alarm (overlap one;
    the combined decision's own: ``FlightAnalysis``).  A test alone, uncorroborated, fires far more
    often than the combined rule on calm flights (real logs: a heading-difference alarm every 3-5 s)
    and is not shown: where it is significant on its own the combined rule alarms too."""
    dev_h = det.z_heading * settings.sigma_k * det.heading_sigma_deg
    on = [(a, np.inf if b is None else b) for a, b, *_ in alarm_intervals(t, det.combined)]
    alarms = []
    for kind, flag, value in (("heading_difference", det.heading_alarm, dev_h),
                              ("path_deviation", det.path_alarm, cross_track_m),
                              ("field_anomaly", det.field_alarm, np.fmax(det.z_strength, det.z_inclination))):
        for start, end, peak, _, _ in alarm_intervals(t, flag, value):
            if not any(a <= (np.inf if end is None else end) and start <= b for a, b in on):
                continue
            alarms.append({"kind": kind, "start_s": rounded(start, 2), "end_s": rounded(end, 2),
                           "peak": rounded(peak), "unit": ALARM_UNITS[kind]})
    return alarms
