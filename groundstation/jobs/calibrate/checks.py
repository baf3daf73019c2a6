"""Checks across the calibration: the compass orientation (ArduPilot's COMPASS_AUTO_ROT rule,
estimators.orientation_check) and the consistency of the compasses (ArduPilot's pre-arm rule,
estimators.compass_consistency)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from estimators.calibration import apply_calibration
from estimators.compass_consistency import ConsistencyReport, compass_consistency
from estimators.log_alignment import nearest_series
from estimators.orientation_check import OrientationCheck, check_orientation
from groundstation.io.params import rotation_enum_matrix
from groundstation.jobs.compass_raw import CompassField
from groundstation.samples import FlightLog

from .context import LogContext, attitude_for
from .settings import CalibrateSettings

__all__ = ["orientation_step", "orientation_reference", "orientation_dict", "consistency_table", "ROTATION_CANDIDATES", "reorient"]

ROTATION_CANDIDATES = tuple(range(38))      # ArduPilot/PX4 ROTATION_* 0..37


def orientation_reference(ctx: LogContext, yaw_dependence: float | None, settings: CalibrateSettings) -> str:
    """ArduPilot's "mean" score cannot tell rotations about the vertical apart in level flight (the
    implied earth field is then constant for all of them); when the WMM field is known and the
    attitude's yaw demonstrably does not follow this compass (the in-flight fit's dependence
    slope below ``wmm.yaw_dependence_slope``), the "expected" score against the WMM does."""
    if ctx.field is not None and yaw_dependence is not None and np.isfinite(yaw_dependence) \
            and yaw_dependence < settings.wmm.yaw_dependence_slope:
        return "expected"
    return settings.orientation.reference


def orientation_step(log: FlightLog, cf: CompassField, calibration: tuple[np.ndarray, np.ndarray] | None,
                     ctx: LogContext, settings: CalibrateSettings, reference: str = "mean") -> OrientationCheck | None:
    """Score the standard rotations on the calibrated field (our calibration, else the field as the
    autopilot corrected it) at samples rotating slower than ``orientation_max_rate_deg_s``."""
    if cf.orientation_id is None or cf.orientation_id not in ROTATION_CANDIDATES or len(log.attitude) < 2:
        return None
    mag = apply_calibration(cf.raw_mG, *calibration) if calibration is not None else cf.in_force_mG
    att = attitude_for(log, cf.t_s)
    slow = att.valid & (att.rate_deg_s <= settings.orientation_max_rate_deg_s)
    m = np.where(slow[:, None], mag, np.nan)
    cands = [(i, rotation_enum_matrix(i)) for i in ROTATION_CANDIDATES]
    return check_orientation(m, att.roll_rad, att.pitch_rad, att.yaw_rad, cands, cf.orientation_id,
                             field_ned_mG=None if ctx.field is None else ctx.field.field_ned_mG,
                             settings=replace(settings.orientation, reference=reference))


def reorient(offsets_mG: np.ndarray, matrix: np.ndarray, current_id: int, new_id: int) -> tuple[np.ndarray, np.ndarray]:
    """The calibration in the body frame of another orientation: raw_new = Q raw_cur with
    Q = R_new R_curᵀ, so C(raw_cur − b) seen in the new frame is (Q C Qᵀ)(raw_new − Q b)."""
    Q = rotation_enum_matrix(new_id) @ rotation_enum_matrix(current_id).T
    return Q @ np.asarray(offsets_mG, float), Q @ np.asarray(matrix, float) @ Q.T


def orientation_dict(check: OrientationCheck | None, reference: str = "mean") -> dict | None:
    if check is None:
        return None
    conf = float(check.confidence)
    return {"status": check.status, "message": check.message, "reference": reference, "in_use": check.current_id,
            "best": check.best_id,
            "second": check.second_id, "confidence": round(conf, 2) if np.isfinite(conf) else None,
            "samples": check.n_used}


def _report_dict(rep: ConsistencyReport, which: str, compasses: list[int]) -> dict:
    r = lambda v, nd=2: round(float(v), nd) if np.isfinite(v) else None  # noqa: E731
    return {"field": which, "status": rep.status, "message": rep.message,
            "disagreeing": None if rep.disagreeing is None else compasses[rep.disagreeing],
            "strength_median_mG": {str(compasses[i]): r(s, 1) for i, s in enumerate(rep.strength_median_mG)},
            "pairs": [{"a": compasses[p.a], "b": compasses[p.b], "samples": p.n,
                       "angle_median_deg": r(p.angle_median_deg), "angle_p95_deg": r(p.angle_p95_deg),
                       "xy_angle_median_deg": r(p.xy_angle_median_deg),
                       "xy_length_diff_median_mG": r(p.xy_length_diff_median_mG, 1),
                       "strength_diff_median_mG": r(p.strength_diff_median_mG, 1),
                       "fail_fraction": r(p.fail_fraction, 3), "ardupilot_consistent": bool(p.ardupilot_consistent)}
                      for p in rep.pairs]}


def consistency_table(fields: list[CompassField], calibrations: dict[int, tuple[np.ndarray, np.ndarray]],
                      primary: int, ctx: LogContext, settings: CalibrateSettings) -> dict | None:
    """Compasses compared on the primary's sample times (nearest sample within
    ``consistency_max_dt_s``): the field as the autopilot corrected it (what its pre-arm check
    sees) and, when two or more were calibrated here, with our calibrations."""
    if len(fields) < 2:
        return None
    base = next((f for f in fields if f.compass == primary), fields[0])
    t = base.t_s
    expected = None if ctx.field is None else float(ctx.field.field_strength_mG)
    compasses = [f.compass for f in fields]

    def table(values: list[np.ndarray | None], which: str) -> dict:
        on_t = [None if v is None else nearest_series(t, f.t_s, v, settings.consistency_max_dt_s)[0]
                for f, v in zip(fields, values)]
        return _report_dict(compass_consistency(on_t, expected_strength_mG=expected, settings=settings.consistency),
                            which, compasses)

    out = {"in_force": table([f.in_force_mG for f in fields], "corrected as in force (the autopilot's view)")}
    if sum(f.compass in calibrations for f in fields) >= 2:
        out["calibrated"] = table([apply_calibration(f.raw_mG, *calibrations[f.compass]) if f.compass in calibrations
                                   else None for f in fields], "with the calibrations found here")
    return out
