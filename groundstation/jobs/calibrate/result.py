"""The calibrate result object (one per compass), its terminal summary and its .param file.

Fields (JSON): file, compass (0-based), device_id, source (the log message), autopilot, status,
message, method ("window" | "wmm_inflight" | null), window_s ([start, end] s of the data the
parameters come from), samples, offsets_mG (b of m_cal = C (m_raw − b)), offsets_sd_mG, matrix (C),
relative_to ("raw": absolute, the parameters to write; "corrections": relative to the corrections
in force recorded in corrections_in_force; "unknown": relative to corrections nobody knows — see
frame.py), corrections_in_force (o, N and the autopilot's parameters of the log), field_strength_mG,
expected_field_mG (WMM), residual_rms_mG, recommended (true / false: write these parameters or not), recommendation (why, in
words, or what flight would make the offsets observable), offsets_covariance_mG2 (3×3, of an in-flight
fit), heading_change_deg ({rms, max}: how far the new calibration turns the heading against the
corrections in force), coverage (of the chosen window's
direction cells, or the heading coverage of an in-flight fit), misalignment_deg, condition_number, attitude_source (the attitude the in-flight fit used: ATT,
AHR2, XKF1, NKF1, ATTITUDE, vehicle_attitude or ahrs, ours from the IMU) and attitude_choice (every
source's held-out residual and why this one), reference_field (the WMM's inclination and the one
refined from the flight with its 1σ, the shift added to the WMM, the compasses that measured it; reference.py), course_check (the heading against the GPS course
in straight fast flight, with the corrections in force and with the new calibration),
ardupilot_params / px4_params (names follow the instance: COMPASS_OFS2_X, CAL_MAG1_XOFF, motor
COMPASS_MOT*, orientation COMPASS_ORIENT* when found), corrections (what the autopilot had in
force and when it changed), windows (every window found, ``chosen`` marked), onboard_report (the
vehicle's MAG_CAL_REPORT), inflight (WMM fit), motor (interference fit), orientation, consistency
(table across the log's compasses), settings (the thresholds applied).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from groundstation.io.params import format_param_file
from groundstation.jobs.words import num, span_s, without_status

from .frame import frame_label
from .settings import DEFAULT_SETTINGS, settings_record

__all__ = ["empty_result", "error_result", "format_summary", "write_param_file"]


def empty_result(source: str, compass: int = 0) -> dict:
    return {"file": source, "compass": compass, "device_id": None, "source": None, "autopilot": None,
            "status": "error", "message": "", "method": None, "window_s": None, "samples": 0,
            "offsets_mG": None, "offsets_sd_mG": None, "matrix": None, "field_strength_mG": None,
            "expected_field_mG": None, "residual_rms_mG": None, "coverage": 0.0, "misalignment_deg": None,
            "condition_number": None, "ardupilot_params": {}, "px4_params": {}, "corrections": None,
            "windows": [], "onboard_report": None, "inflight": None, "motor": None, "orientation": None,
            "consistency": None, "relative_to": None, "corrections_in_force": None, "recommended": None,
            "recommendation": None, "offsets_covariance_mG2": None, "heading_change_deg": None,
            "attitude_source": None, "attitude_choice": None, "course_check": None, "reference_field": None,
            "settings": settings_record(DEFAULT_SETTINGS)}


def error_result(file: str, message: str, status: str = "error") -> dict:
    """The result object for a file that could not be read at all."""
    result = empty_result(str(file))
    result.update(status=status, message=message)
    return result


def _num(v, fmt="{:.1f}", unit=""):
    return num(v, fmt, unit)


def _windows_lines(result: dict) -> list[str]:
    lines = []
    for w in result.get("windows") or []:
        mark = "*" if w.get("chosen") else " "
        lines.append(f"  {mark} window {span_s(w['start_s'], w['end_s'])} ({w['source']}, "
                     f"{w['samples']} samples, {w.get('model') or '-'}, coverage {_num(w.get('coverage'), '{:.0%}')})"
                     + ("" if w.get("sufficient") else f": {w.get('reason')}"))
    return lines


def _checks_lines(result: dict) -> list[str]:
    lines = []
    part = result.get("inflight")
    if part:
        lines.append(f"  in-flight WMM fit: {part['status']}: {without_status(part['status'], part.get('message', ''))}")
        course = result.get("course_check") or {}
        if course.get("verdict"):
            lines.append(f"  GPS course check: {course['verdict']}")
        choice = result.get("attitude_choice") or {}
        if choice.get("note"):
            lines.append(f"  attitude source: {choice['note']}")
    mot = result.get("motor")
    if mot:
        f = [v for v in mot.get("motor_mG_per_unit") or [] if v is not None]
        unit = "A" if mot.get("signal") == "current_A" else "full throttle"
        size = f"{float(np.linalg.norm(f)):.2f} mG per {unit}" if len(f) == 3 else "not determined"
        pct = mot.get("interference_pct")
        at = num(mot.get("signal_max"), "{:.1f}", "A") if unit == "A" else num(mot.get("signal_max"), "{:.0%}", "throttle")
        lines.append(f"  motor field: {mot['status']}: {size}" + (f", {pct:.1f} % of the Earth field at {at}"
                                                                   if pct is not None else ""))
    ori = result.get("orientation")
    if ori:
        lines.append(f"  orientation: {ori['status']}: {without_status(ori['status'], ori['message'])}")
    rep = result.get("onboard_report")
    if rep and rep.get("difference_mG") is not None:
        lines.append(f"  vehicle's MAG_CAL_REPORT at {rep['t_s']:.0f} s: COMPASS_OFS {rep['COMPASS_OFS']}, "
                     f"ours differ by up to {rep['difference_mG']:.1f} mG")
    return lines


def format_summary(result: dict) -> str:
    """Readable multi-line text of one result for the terminal."""
    comp = result.get("compass")
    head = f"{result.get('file')}" + (f" compass {comp}" if comp is not None else "")
    if result.get("device_id"):
        head += f" (device {result['device_id']})"
    frame = f", {frame_label(result)}" if result.get("relative_to") and result.get("status") in ("ok", "weak") else ""
    lines = [f"{head}: {result.get('status')}" + (f" [{result['method']}]" if result.get("method") else "") + frame]
    if result.get("recommendation"):
        lines.append(f"  {result['recommendation']}")
    if result.get("message"):
        lines.append(f"  {result['message']}")
    lines.append(f"  samples {result.get('samples', 0)}, coverage {_num(result.get('coverage'), '{:.0%}')}, "
                 f"residual RMS {_num(result.get('residual_rms_mG'), unit='mG')}"
                 + (f", data {span_s(*result['window_s'])}" if result.get("window_s") else ""))
    lines.append(f"  field {_num(result.get('field_strength_mG'), unit='mG')} fitted, "
                 f"{_num(result.get('expected_field_mG'), unit='mG')} expected (WMM)")
    if result.get("offsets_mG"):
        lines.append("  offsets mG  " + "  ".join(f"{_num(v, '{:.1f}'):>8}" for v in result["offsets_mG"]))
        if result.get("offsets_sd_mG") and None not in result["offsets_sd_mG"]:
            lines.append("  1σ mG      " + "  ".join(f"{_num(v, '{:.1f}'):>8}" for v in result["offsets_sd_mG"]))
        for i, row in enumerate(result["matrix"]):
            lines.append(("  matrix      " if i == 0 else "              ")
                         + "  ".join(f"{_num(v, '{:.4f}'):>8}" for v in row))
    if result.get("misalignment_deg"):
        lines.append("  misalignment deg " + "  ".join(_num(v, "{:.2f}") for v in result["misalignment_deg"]))
    lines += _windows_lines(result) + _checks_lines(result)
    for key, label in (("ardupilot_params", "ArduPilot"), ("px4_params", "PX4")):
        if result.get(key):
            lines.append(f"  {label}: " + ", ".join(f"{k}={v:.6g}" for k, v in result[key].items()))
    return "\n".join(lines)


def format_consistency(table: dict | None) -> str:
    """The consistency table of one log (shared by its compasses' results)."""
    if not table:
        return ""
    lines = []
    for key in ("in_force", "calibrated"):
        part = table.get(key)
        if not part:
            continue
        lines.append(f"  compass consistency ({part['field']}): {part['status']}")
        for p in part["pairs"]:
            lines.append(f"    {p['a']}-{p['b']}: angle median {_num(p['angle_median_deg'], unit='deg')} "
                         f"(95 % {_num(p['angle_p95_deg'])}), strength diff "
                         f"{_num(p['strength_diff_median_mG'], unit='mG')}"
                         + ("" if p["ardupilot_consistent"] else "  FAILS ArduPilot's check"))
        if part.get("disagreeing") is not None:
            lines.append(f"    compass {part['disagreeing']} disagrees with the others")
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
