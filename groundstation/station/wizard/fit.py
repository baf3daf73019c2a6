"""The final fit of one compass: un-apply the vehicle's calibration, fit, find the orientation, judge.

1. Un-apply the onboard calibration of compass k (ArduPilot COMPASS_OFS/DIA/ODI of instance k,
   PX4 CAL_MAGk_*): the samples become the field rotated by the orientation in use, uncorrected.
2. ``groundstation.jobs.calibrate.calibrate_log`` on them (robust ellipsoid, coverage, WMM,
   misalignment from the attitude).
3. Orientation: ``estimators.orientation_check.check_orientation`` (ArduPilot's
   CompassCalibrator::calculate_orientation score) over the standard rotations.  When another
   rotation is clearly best, the samples are rotated into it and fitted again, and the
   orientation parameter goes out with the rest (COMPASS_ORIENTn / CAL_MAGk_ROT).  As in
   ArduPilot, an ambiguous answer fails the compass only when its best guess is not the rotation
   in use.
4. Quality in words (``quality.judge``), the exported parameters of compass k (scaled to the WMM
   intensity as ArduPilot's fix_radius does: ``groundstation.io.params.wmm_scale``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from estimators.calibration import apply_calibration, polar_decomposition
from estimators.orientation_check import check_orientation
from groundstation.io.params import (ardupilot_params_from_calibration, px4_params_from_calibration,
                                     rotation_enum_matrix, unapply_ardupilot, unapply_px4, wmm_scale)
from groundstation.jsonsafe import jsonable
from groundstation.samples import FlightLog
from groundstation.station.wizard.quality import confirmed_disturbances, judge
from groundstation.station.wizard.settings import WizardSettings

__all__ = ["DanceData", "fit_compass", "orientation_param", "ROTATION_NAMES", "attitude_at", "calibrated_in_new_frame",
           "raw_in_result_frame"]

N_ROTATIONS = 38
ROTATION_NAMES = {0: "NONE", 1: "YAW_45", 2: "YAW_90", 3: "YAW_135", 4: "YAW_180", 5: "YAW_225", 6: "YAW_270",
                  7: "YAW_315", 8: "ROLL_180", 9: "ROLL_180_YAW_45", 10: "ROLL_180_YAW_90", 11: "ROLL_180_YAW_135",
                  12: "PITCH_180", 13: "ROLL_180_YAW_225", 14: "ROLL_180_YAW_270", 15: "ROLL_180_YAW_315",
                  16: "ROLL_90", 17: "ROLL_90_YAW_45", 18: "ROLL_90_YAW_90", 19: "ROLL_90_YAW_135",
                  20: "ROLL_270", 21: "ROLL_270_YAW_45", 22: "ROLL_270_YAW_90", 23: "ROLL_270_YAW_135",
                  24: "PITCH_90", 25: "PITCH_270", 26: "PITCH_180_YAW_90", 27: "PITCH_180_YAW_270",
                  28: "ROLL_90_PITCH_90", 29: "ROLL_180_PITCH_90", 30: "ROLL_270_PITCH_90",
                  31: "ROLL_90_PITCH_180", 32: "ROLL_270_PITCH_180", 33: "ROLL_90_PITCH_270",
                  34: "ROLL_180_PITCH_270", 35: "ROLL_270_PITCH_270", 36: "ROLL_90_PITCH_180_YAW_90",
                  37: "ROLL_90_YAW_270"}
_CANDIDATES = [(i, rotation_enum_matrix(i)) for i in range(N_ROTATIONS)]
_NOTE_DROPPED = "no onboard calibration parameters found; samples used as raw"


@dataclass
class DanceData:
    """What was collected besides the compasses (tables as in FlightLog)."""
    attitude: np.ndarray       # t_s, roll, pitch, yaw (rad)
    gps: np.ndarray            # t_s, lat, lon, alt, vn, ve, vd, fix
    start_unix_s: float | None
    field_ned_mG: np.ndarray | None = None    # WMM at the first fix (None without GPS)


def orientation_param(autopilot: str, k: int) -> str:
    return f"CAL_MAG{k}_ROT" if autopilot == "px4" else f"COMPASS_ORIENT{'' if k == 0 else k + 1}"


def _has_calibration(params: dict[str, float], autopilot: str, k: int) -> bool:
    prefix = f"CAL_MAG{k}_" if autopilot == "px4" else f"COMPASS_OFS{'' if k == 0 else k + 1}_"
    return any(name.startswith(prefix) for name in params)


def _unapply(mag: np.ndarray, params: dict[str, float], autopilot: str, k: int) -> tuple[np.ndarray, str]:
    if not _has_calibration(params, autopilot, k):
        return mag, "no onboard calibration known for this compass: samples used as received"
    if autopilot == "px4":
        return unapply_px4(mag, params, k), f"un-applied the vehicle's CAL_MAG{k}_* calibration"
    n = "" if k == 0 else str(k + 1)
    return unapply_ardupilot(mag, params, k), f"un-applied the vehicle's COMPASS_OFS{n}/DIA{n}/ODI{n} calibration"


def attitude_at(attitude: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """(N, 3) roll, pitch, yaw interpolated at t_s (yaw unwrapped); NaN outside the attitude span."""
    att = attitude[np.all(np.isfinite(attitude), axis=1)]
    if len(att) < 2:
        return np.full((len(t_s), 3), np.nan)
    out = np.stack([np.interp(t_s, att[:, 0], att[:, 1]), np.interp(t_s, att[:, 0], att[:, 2]),
                    np.interp(t_s, att[:, 0], np.unwrap(att[:, 3]))], axis=1)
    out[(t_s < att[0, 0]) | (t_s > att[-1, 0])] = np.nan
    return out


def _calibrate(t_s: np.ndarray, raw: np.ndarray, data: DanceData) -> dict:
    from groundstation.jobs.calibrate import calibrate_log

    log = FlightLog(source="calibration wizard", mag=np.column_stack([t_s, raw]), attitude=data.attitude,
                    gps=data.gps, start_unix_s=data.start_unix_s if data.start_unix_s else time.time() - t_s[-1])
    result = jsonable(calibrate_log(log))
    result["message"] = "; ".join(p for p in (result.get("message") or "").replace(_NOTE_DROPPED, "").split("; ") if p)
    return result


def _orientation(result: dict, t_s: np.ndarray, raw: np.ndarray, data: DanceData, current: int) -> dict:
    """check_orientation on the symmetric-calibrated samples (misalignment left out)."""
    _, S = polar_decomposition(np.asarray(result["matrix"], float))
    cal = apply_calibration(raw, np.asarray(result["offsets_mG"], float), S)
    att = attitude_at(data.attitude, t_s)
    step = max(1, len(cal) // 3000)
    if current not in dict(_CANDIDATES):
        current = 0
    chk = check_orientation(cal[::step], att[::step, 0], att[::step, 1], att[::step, 2], _CANDIDATES, current)
    return {"status": chk.status, "message": chk.message, "current": current, "detected": chk.best_id,
            "detected_name": ROTATION_NAMES.get(chk.best_id) if chk.best_id is not None else None,
            "second": chk.second_id, "confidence": None if not np.isfinite(chk.confidence) else round(chk.confidence, 2)}


def fit_compass(k: int, mag: np.ndarray, autopilot: str, params: dict[str, float], data: DanceData,
                settings: WizardSettings, disturbances: int = 0) -> dict:
    """Calibrate compass k from its (t_s, mx, my, mz) table; the per-compass result object."""
    t_s = mag[:, 0]
    raw, note = _unapply(mag[:, 1:4], params, autopilot, k)
    result = _calibrate(t_s, raw, data)
    orient_key = orientation_param(autopilot, k)
    current = max(0, int(params.get(orient_key, 0)))
    orientation = None
    if result.get("status") == "ok" and len(data.attitude) >= 2:
        orientation = _orientation(result, t_s, raw, data, current)
        if orientation["status"] == "rotation_found":
            q = rotation_enum_matrix(orientation["detected"]) @ rotation_enum_matrix(current).T
            result = _calibrate(t_s, raw @ q.T, data)
            result["message"] = (f"orientation {ROTATION_NAMES.get(current, current)} -> "
                                 f"{orientation['detected_name']} applied; " + result["message"]).strip("; ")
    # a failed fit's own reason first: the page shows the message's first part
    parts = (note, result.get("message")) if result.get("status") == "ok" else (result.get("message"), note)
    result["message"] = "; ".join(p for p in parts if p)
    result["compass"] = k
    result["orientation"] = orientation
    if result.get("status") == "ok":       # the live count (``disturbances``) only flags; the final fit confirms
        disturbances, worst = confirmed_disturbances(t_s, calibrated_in_new_frame(result, raw), settings)
        result["disturbances"], result["disturbance_max_mG"] = disturbances, round(worst, 1)
    result.update(judge(result, k, orientation, result.get("disturbances", 0), settings, data.field_ned_mG))
    result["ardupilot_params"], result["px4_params"] = _export(result, k, orientation, current)
    return result


def raw_in_result_frame(result: dict, received: np.ndarray, unapply) -> np.ndarray:
    """Samples as received -> the uncorrected field in the frame the result was fitted in
    (the vehicle's calibration un-applied, a detected orientation applied)."""
    raw = unapply(received)
    o = result.get("orientation") or {}
    if o.get("status") == "rotation_found":
        raw = raw @ (rotation_enum_matrix(o["detected"]) @ rotation_enum_matrix(o["current"]).T).T
    return raw


def calibrated_in_new_frame(result: dict, raw: np.ndarray, as_vehicle: bool = False) -> np.ndarray:
    """Un-applied samples -> calibrated body field with the result (orientation fix included).
    ``as_vehicle``: as the vehicle will correct it with the exported parameters, i.e. the symmetric
    part of the matrix only (COMPASS_DIA/ODI cannot hold a misalignment rotation)."""
    raw = raw_in_result_frame(result, raw, lambda m: m)
    C = np.asarray(result["matrix"], float)
    if as_vehicle:
        _, C = polar_decomposition(C)
    return apply_calibration(raw, np.asarray(result["offsets_mG"], float), C)


def _export(result: dict, k: int, orientation: dict | None, current: int) -> tuple[dict, dict]:
    if result.get("status") != "ok" or result.get("offsets_mG") is None:
        return {}, {}
    b, C = np.asarray(result["offsets_mG"], float), np.asarray(result["matrix"], float)
    rot = current
    if orientation is not None and orientation["status"] == "rotation_found":
        rot = int(orientation["detected"])
    scale = wmm_scale(result.get("field_strength_mG"), result.get("expected_field_mG"))   # ArduPilot's fix_radius
    ap = ardupilot_params_from_calibration(b, C, k, scale)
    px4 = px4_params_from_calibration(b, C, k, rotation_enum_matrix(rot), scale)
    if orientation is not None and orientation["status"] in ("rotation_found", "confirmed"):
        ap[orientation_param("ardupilot", k)] = float(rot)
        px4[orientation_param("px4", k)] = float(rot)
    return jsonable(ap), jsonable(px4)
