"""Every compass in the analyze report: field strength and inclination against the WMM, and the
compasses' consistency (ArduPilot's pre-arm rule, estimators.compass_consistency).

Each compass is seen as the autopilot corrected it (its corrections in force at each sample,
jobs.compass_raw); the compass a given calibration belongs to (its ``compass`` key, else the
primary) is seen with that calibration.  Only samples in flight attitude (tilt below the
detector's ``max_tilt_deg``, rotating slower than ``MAX_RATE_DEG_S``) count: a dance is not a
field measurement.
"""
from __future__ import annotations

import numpy as np

from estimators.compass_consistency import compass_consistency
from estimators.detection import DetectionSettings, field_inclination_deg
from estimators.log_alignment import attitude_at, nearest_series
from groundstation.jobs.compass_raw import CompassField, compass_fields
from groundstation.samples import FlightLog, finite_or_none

__all__ = ["compass_summaries", "MAX_RATE_DEG_S", "COMMON_DT_S"]

MAX_RATE_DEG_S = 30.0
COMMON_DT_S = 0.6


def _r(v, nd=2):
    v = finite_or_none(v)
    return None if v is None else round(v, nd)


def _field(cf: CompassField, cal: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
    return cf.in_force_mG if cal is None else (cf.raw_mG - cal[0]) @ cal[1].T


def _summary(log: FlightLog, cf: CompassField, m: np.ndarray, ef, settings: DetectionSettings, given: bool) -> dict:
    att = np.asarray(log.attitude, float).reshape(-1, 4)
    a = attitude_at(cf.t_s, att[:, 0], att[:, 1], att[:, 2], att[:, 3])
    tilt_ok = np.cos(a.roll_rad) * np.cos(a.pitch_rad) >= np.cos(np.radians(settings.max_tilt_deg))
    use = a.valid & tilt_ok & (a.rate_deg_s <= MAX_RATE_DEG_S) & np.all(np.isfinite(m), axis=1)
    strength = np.linalg.norm(m[use], axis=1)
    incl = field_inclination_deg(m[use], a.roll_rad[use], a.pitch_rad[use])
    out = {"compass": cf.compass, "source": cf.source, "device_id": cf.device_id, "samples": int(len(cf.t_s)),
           "flight_samples": int(use.sum()), "field": "given calibration" if given else "autopilot's corrections in force",
           "field_strength_median_mG": _r(np.median(strength), 1) if len(strength) else None,
           "inclination_median_deg": _r(np.median(incl)) if len(incl) else None,
           "strength_residual_mG": None, "inclination_residual_deg": None}
    if ef is not None and len(strength):
        out["strength_residual_mG"] = _r(np.median(strength) - ef.field_strength_mG, 1)
        out["inclination_residual_deg"] = _r(np.median(incl) - ef.inclination_deg)
    return out


def compass_summaries(log: FlightLog, calibration_arrays: tuple[np.ndarray, np.ndarray] | None,
                      calibration_compass: int | None, ef, settings: DetectionSettings) -> tuple[list[dict], dict | None]:
    """(per-compass summaries, consistency across compasses or None with fewer than two)."""
    fields = [cf for cf in compass_fields(log) if len(cf.t_s)]
    target = log.primary_compass if calibration_compass is None else calibration_compass
    values, out = [], []
    for cf in fields:
        cal = calibration_arrays if cf.compass == target else None
        m = _field(cf, cal)
        values.append(m)
        out.append(_summary(log, cf, m, ef, settings, cal is not None))
    if len(fields) < 2:
        return out, None
    base = next((f for f in fields if f.compass == log.primary_compass), fields[0])
    on_t = [nearest_series(base.t_s, cf.t_s, m, COMMON_DT_S)[0] for cf, m in zip(fields, values)]
    rep = compass_consistency(on_t, expected_strength_mG=None if ef is None else ef.field_strength_mG)
    comps = [cf.compass for cf in fields]
    table = {"status": rep.status, "message": rep.message,
             "disagreeing": None if rep.disagreeing is None else comps[rep.disagreeing],
             "pairs": [{"a": comps[p.a], "b": comps[p.b], "angle_median_deg": _r(p.angle_median_deg),
                        "strength_diff_median_mG": _r(p.strength_diff_median_mG, 1),
                        "ardupilot_consistent": bool(p.ardupilot_consistent)} for p in rep.pairs]}
    return out, table
