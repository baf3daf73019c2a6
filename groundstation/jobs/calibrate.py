"""`magstation calibrate`: one log -> the calibration JSON object of issue 3.

Pipeline: un-apply the onboard calibration (autopilot_params) -> reject NaN rows -> planarity
check -> robust ellipsoid fit (estimators.calibration) -> coverage check -> WMM field at the
first good GPS fix -> seed 004 misalignment from the log attitude when possible -> export
ArduPilot / PX4 parameters.  Bad data never raise: they give a status and a message.
"""
from __future__ import annotations

import math
from pathlib import Path
import time

import numpy as np

from estimators.calibration import (apply_calibration, combine_calibration, estimate_misalignment,
                                    fit_ellipsoid_robust, planarity_ratio, sphere_coverage)
from estimators.geomag import EarthField, decimal_year_from_unix, earth_field
from groundstation.io.params import (detect_autopilot, export_params, format_param_file,
                                            unapply_onboard_calibration)
from groundstation.samples import FlightLog, finite_or_none

MIN_SAMPLES = 50
MIN_PLANARITY = 0.10       # sqrt(λmin/λmax) of the raw samples; a single rotation plane is ~0
MIN_COVERAGE = 0.25        # fraction of the ~100 equal-area direction cells
MAX_AXIS_RATIO = 2.5       # largest/smallest singular value of C: beyond that the fit is not credible
MAX_MISALIGNMENT_RESIDUAL_DEG = 10.0


def _empty_result(source: str) -> dict:
    return {"file": source, "status": "error", "message": "", "samples": 0, "offsets_mG": None,
            "matrix": None, "field_strength_mG": None, "expected_field_mG": None, "residual_rms_mG": None,
            "coverage": 0.0, "misalignment_deg": None, "ardupilot_params": {}, "px4_params": {},
            "autopilot": None, "condition_number": None}


def error_result(file: str, message: str, status: str = "error") -> dict:
    """The result object for a file that could not be read at all."""
    result = _empty_result(str(file))
    result.update(status=status, message=message)
    return result


def expected_field(log: FlightLog) -> tuple[EarthField | None, str]:
    """WMM field at the first good GPS fix (fix ≥ 3D, finite, not 0/0) and the log date."""
    gps = log.gps
    if len(gps) == 0:
        return None, "no GPS: expected field unknown"
    ok = (gps[:, 7] >= 3) & np.isfinite(gps[:, 1]) & np.isfinite(gps[:, 2]) & \
         ~((gps[:, 1] == 0) & (gps[:, 2] == 0)) & (np.abs(gps[:, 1]) <= 90) & (np.abs(gps[:, 2]) <= 180)
    if not np.any(ok):
        return None, "no good GPS fix: expected field unknown"
    row = gps[np.argmax(ok)]
    note = ""
    if log.start_unix_s is not None and math.isfinite(log.start_unix_s):
        year = decimal_year_from_unix(log.start_unix_s + row[0])
    else:
        year = decimal_year_from_unix(time.time())
        note = "log date unknown, WMM evaluated for today"
    try:
        return earth_field(float(row[1]), float(row[2]), float(row[3]), year), note
    except Exception as e:  # model outside validity, bad numbers
        return None, f"WMM failed: {e}"


def _attitude_at(log: FlightLog, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(roll, pitch, yaw) (n, 3) interpolated at t_s, and a mask of times inside the attitude span."""
    att = log.attitude
    att = att[np.all(np.isfinite(att), axis=1)]
    if len(att) < 2:
        return np.full((len(t_s), 3), np.nan), np.zeros(len(t_s), bool)
    inside = (t_s >= att[0, 0]) & (t_s <= att[-1, 0])
    out = np.stack([np.interp(t_s, att[:, 0], att[:, 1]), np.interp(t_s, att[:, 0], att[:, 2]),
                    np.interp(t_s, att[:, 0], np.unwrap(att[:, 3]))], axis=1)
    return out, inside


def calibrate_log(log: FlightLog) -> dict:
    """Calibrate the primary magnetometer of a log; returns the issue-3 JSON object (never raises)."""
    result = _empty_result(getattr(log, "source", "?"))
    try:
        return _calibrate(log, result)
    except Exception as e:  # last resort: bad data must not crash the CLI
        result["status"] = "error"
        result["message"] = f"{type(e).__name__}: {e}"
        return result


def _calibrate(log: FlightLog, result: dict) -> dict:
    params = dict(log.params or {})
    result["autopilot"] = log.autopilot or detect_autopilot(params)
    if log.mag is None or len(log.mag) == 0:
        result.update(status="no_data", message="log has no magnetometer samples")
        return result
    raw_all, note = unapply_onboard_calibration(log.mag[:, 1:4], params, result["autopilot"],
                                                getattr(log, "mag_calibration_applied", None))
    finite = np.all(np.isfinite(raw_all), axis=1) & np.isfinite(log.mag[:, 0])
    raw, t_s = raw_all[finite], log.mag[finite, 0]
    notes = [note]
    if (~finite).sum():
        notes.append(f"{int((~finite).sum())} non-finite samples rejected")
    result["samples"] = int(len(raw))
    if len(raw) == 0:
        result.update(status="no_data", message="no finite magnetometer samples")
        return result
    field, field_note = expected_field(log)
    if field_note:
        notes.append(field_note)
    if field is not None:
        result["expected_field_mG"] = finite_or_none(field.field_strength_mG)

    def insufficient(why: str) -> dict:
        result.update(status="insufficient_coverage", message="; ".join([why] + notes))
        return result

    if len(raw) < MIN_SAMPLES:
        return insufficient(f"only {len(raw)} samples (need {MIN_SAMPLES})")
    planarity = planarity_ratio(raw)
    if planarity < MIN_PLANARITY:
        return insufficient(f"samples are nearly planar (thickness ratio {planarity:.3f}): "
                            "rotate the vehicle about all three axes")
    fit = fit_ellipsoid_robust(raw)
    result["condition_number"] = finite_or_none(fit.condition_number)
    if not fit.ok:
        return insufficient(fit.reason)
    cal = apply_calibration(raw[fit.inliers], fit.offsets_mG, fit.matrix)
    coverage = sphere_coverage(cal)
    result["coverage"] = round(coverage, 3)
    result["samples"] = int(fit.n_used)
    sv = np.linalg.svd(fit.matrix, compute_uv=False)
    if coverage < MIN_COVERAGE:
        return insufficient(f"directions cover {coverage:.0%} of the sphere (need {MIN_COVERAGE:.0%})")
    if sv[0] / sv[-1] > MAX_AXIS_RATIO:
        return insufficient(f"fitted ellipsoid axis ratio {sv[0] / sv[-1]:.2f} is not credible")
    if len(raw) - fit.n_used:
        notes.append(f"{len(raw) - fit.n_used} outlier samples rejected")

    C = fit.matrix
    if field is not None and len(log.attitude) >= 2:
        att, inside = _attitude_at(log, t_s[fit.inliers])
        if inside.sum() >= MIN_SAMPLES:
            mis = estimate_misalignment(cal[inside], att[inside, 0], att[inside, 1], att[inside, 2],
                                        field.field_ned_mG)
            if mis.ok and mis.residual_deg <= MAX_MISALIGNMENT_RESIDUAL_DEG:
                C, _ = combine_calibration(fit.offsets_mG, fit.matrix, mis.rotation)
                result["misalignment_deg"] = [round(float(a), 3) for a in mis.angles_deg]
                notes.append(f"misalignment from attitude (residual {mis.residual_deg:.2f} deg)")
            else:
                notes.append("misalignment not estimated: " + (mis.reason or
                             f"attitude/field residual {mis.residual_deg:.1f} deg too large"))
    ap, px4 = export_params(fit.offsets_mG, C, params)
    if any(abs(ap[f"COMPASS_OFS_{a}"]) > 1800 for a in "XYZ"):
        notes.append("offset beyond ArduPilot's default COMPASS_OFFS_MAX (1800 mG)")
    if field is not None:
        notes.append(f"fitted field {fit.field_strength_mG:.0f} mG vs WMM {field.field_strength_mG:.0f} mG")
    result.update(status="ok", message="; ".join(notes),
                  offsets_mG=[finite_or_none(v) for v in fit.offsets_mG],
                  matrix=[[finite_or_none(v) for v in row] for row in C],
                  field_strength_mG=finite_or_none(fit.field_strength_mG), residual_rms_mG=finite_or_none(fit.residual_rms_mG),
                  ardupilot_params={k: finite_or_none(v) for k, v in ap.items()},
                  px4_params={k: finite_or_none(v) for k, v in px4.items()})
    return result


def format_summary(result: dict) -> str:
    """Readable multi-line text of one result for the terminal."""
    def num(v, fmt="{:.1f}"):
        return "n/a" if v is None else fmt.format(v)

    lines = [f"{result.get('file')}: {result.get('status')}"]
    if result.get("message"):
        lines.append(f"  {result['message']}")
    lines.append(f"  samples {result.get('samples', 0)}, coverage {num(result.get('coverage'), '{:.0%}')}, "
                 f"residual RMS {num(result.get('residual_rms_mG'))} mG")
    lines.append(f"  field {num(result.get('field_strength_mG'))} mG fitted, "
                 f"{num(result.get('expected_field_mG'))} mG expected (WMM)")
    if result.get("offsets_mG"):
        lines.append("  offsets mG  " + "  ".join(f"{v:8.1f}" for v in result["offsets_mG"]))
        for i, row in enumerate(result["matrix"]):
            lines.append(("  matrix      " if i == 0 else "              ") + "  ".join(f"{v:8.4f}" for v in row))
    if result.get("misalignment_deg"):
        lines.append("  misalignment deg " + "  ".join(f"{v:.2f}" for v in result["misalignment_deg"]))
    for key, label in (("ardupilot_params", "ArduPilot"), ("px4_params", "PX4")):
        if result.get(key):
            lines.append(f"  {label}: " + ", ".join(f"{k}={v:.6g}" for k, v in result[key].items()))
    return "\n".join(lines)


def write_param_file(result: dict, path: str | Path, autopilot: str | None = None, style: str = "comma") -> Path:
    """Write the result's parameters as a .param file (``NAME,VALUE`` or, style="space", ``NAME VALUE``).
    ``autopilot`` "ardupilot" | "px4"; default: the log's autopilot, else ArduPilot."""
    ap = autopilot or result.get("autopilot") or "ardupilot"
    values = result.get("px4_params" if ap == "px4" else "ardupilot_params") or {}
    if not values:
        raise ValueError(f"no parameters to write ({result.get('status')}: {result.get('message')})")
    path = Path(path)
    path.write_text(format_param_file(values, style))
    return path
