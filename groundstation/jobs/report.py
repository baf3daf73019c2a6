"""Writing analyze results: the per-step CSV and the human-readable summary."""
from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from groundstation.jobs.words import lat_lon, num, score_name, span_s

__all__ = ["CSV_COLUMNS", "write_csv", "format_report"]

CSV_COLUMNS = ("t_s", "roll_deg", "pitch_deg", "yaw_deg", "mag_heading_deg", "heading_true_deg",
               "v_forward_mps", "v_lateral_mps", "cross_track_m", "alarm", "gyro_bias_x_dps", "gyro_bias_y_dps",
               "gyro_bias_z_dps", "acc_rejected", "mag_rejected", "ins_mode", "attitude_source")
INTEGER_COLUMNS = ("alarm", "acc_rejected", "mag_rejected")
TEXT_COLUMNS = ("ins_mode", "attitude_source")
CSV_CHUNK_ROWS = 8192


def write_csv(path: str | Path, columns: dict[str, np.ndarray]) -> Path:
    """Write the analyze CSV (header = CSV_COLUMNS present, then one row per IMU step; an empty
    cell is NaN, or no INS/GPS in ``ins_mode``).

    The text is ``csv.writer``'s (minimal quoting, ``\\r\\n`` rows; numbers ``%.6g``, integer
    columns truncated like ``int``): one ``%`` format per row, NaN and ±inf cells emptied as text
    afterwards, so no Python call is made per cell."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    names = [c for c in CSV_COLUMNS if c in columns] + [c for c in columns if c not in CSV_COLUMNS]
    n = min((len(columns[c]) for c in names), default=0)
    numeric = [c for c in names if c not in TEXT_COLUMNS and c not in INTEGER_COLUMNS]
    row_format = ",".join("%.6g" if c in numeric else "%s" for c in names) + "\r\n"
    with open(path, "w", newline="") as f:
        csv.writer(f).writerow(names)
        for k in range(0, n, CSV_CHUNK_ROWS):      # the text of a chunk of rows at a time, not of the log
            cells = [_cells(c, columns[c][k:k + CSV_CHUNK_ROWS]) for c in names]
            text = "".join(map(row_format.__mod__, zip(*cells)))
            f.write(_empty_not_finite(text) if numeric else text)
    return path


def _empty_not_finite(text: str) -> str:
    """``text`` (whole CSV rows) with every cell that %.6g wrote for NaN or ±inf emptied (text and
    integer cells never read so: ``_cells``).  Plain replaces of the cell with its delimiters, each
    twice since neighbouring cells share a comma."""
    text = "\n" + text
    for word in ("nan", "inf", "-inf"):
        for before, after in ((",", ","), (",", "\r"), ("\n", ",")):
            cell = before + word + after
            while cell in text:
                text = text.replace(cell, before + after)
    return text[1:]


def _cells(name: str, values) -> list:
    """One column's cells for ``write_csv``: floats for the numeric columns, text for the others
    (quoted as ``csv.writer`` would; an empty text where the value is None, or NaN in an integer
    column)."""
    if name in TEXT_COLUMNS:
        texts = values if isinstance(values, np.ndarray) and values.dtype.kind == "U" else \
            np.array(["" if v is None else str(v) for v in values], dtype=object)
        words, index = np.unique(texts, return_inverse=True)
        quoted = np.array([_csv_field(str(w)) for w in words], dtype=object)
        return quoted[index].tolist() if len(words) else []
    numbers = np.asarray(values, dtype=float)
    if name in INTEGER_COLUMNS:
        finite = np.isfinite(numbers)
        return np.where(finite, np.where(finite, numbers, 0).astype(np.int64).astype(str), "").tolist()
    return numbers.tolist()


def _csv_field(text: str) -> str:
    """``text`` as ``csv.writer`` writes one field (quoted when it holds a comma, quote or line
    break); a bare ``nan``/``inf`` quoted, since ``write_csv`` empties those as numbers."""
    if text == "":
        return ""                        # (csv.writer quotes a row of one empty field, not a cell)
    if text in ("nan", "inf", "-inf"):
        return f'"{text}"'               # read back as the same text
    out = io.StringIO()
    csv.writer(out).writerow([text])          # (its line end decides the quoting of line breaks)
    return out.getvalue()[:-2]


def format_report(report: dict) -> str:
    """Human-readable summary of an analyze report."""
    lines = [f"file: {report.get('file')}  ({num(report.get('duration_s'), '{:.1f}', 's')})"]
    if report.get("declination_deg") is not None:
        lines.append(f"WMM: declination {report['declination_deg']:.2f}°, inclination "
                     f"{report['inclination_deg']:.2f}°, field {report['field_strength_mG']:.1f} mG "
                     f"(measured median {num(report.get('measured_field_strength_mG'), unit='mG')})")
    lines.append("calibration: " + (report.get("calibration_in_use")
                                    or ("applied" if report.get("calibration_applied") else "none (raw magnetometer)")))
    lines.append(f"RTK: {'yes' if report.get('rtk') else 'no'};  path test: {report.get('path_test')}")
    lines.append(f"heading test: {report.get('heading_test')};  field test: {report.get('field_test')}")
    if report.get("mission"):
        m = report["mission"]
        lines.append(f"mission A {lat_lon(*m['A'][:2])} -> B {lat_lon(*m['B'][:2])};  "
                     f"max cross-track {num(report.get('max_cross_track_m'), unit='m')}")
    nav = report.get("navigation") or {}
    for o in nav.get("gps_outages", []):
        cmp = "; ".join(f"{law.replace('_', ' ')} median {num(v['median'])}°, max {num(v['max'])}°"
                        for law, v in (o.get("ins_vs_autopilot_heading_deg") or {}).items() if v)
        lines.append(f"GPS outage {span_s(o['start_s'], o['end_s'], '{:.1f}')} "
                     f"({num(o['duration_s'], unit='s')}): " + (f"INS/GPS mode {o['ins_mode']}; heading vs autopilot: {cmp or 'n/a'}"
                                                   if o["ins_mode"] else f"INS/GPS {nav.get('ins_gps')}"))
    motor = report.get("motor_field") or {}
    if motor.get("status") not in (None, "no_motor_signal"):
        lines.append(("heading: motor-current field removed: " if motor.get("removed_from_heading")
                      else "heading: motor-current field not removed: ") + str(motor.get("message")))
    comb = [a for a in report.get("alarms", []) if a["kind"] == "combined"]
    others = [a for a in report.get("alarms", []) if a["kind"] != "combined"]
    lines.append(f"interference detected: {'YES' if report.get('interference_detected') else 'no'}"
                 + (f" (first alarm at {num(report['first_alarm_s'], unit='s')})"
                    if report.get("first_alarm_s") is not None else ""))
    for a in comb:
        lines.append(f"  ALARM {span_s(a['start_s'], a['end_s'], '{:.1f}')}, "
                     f"evidence: {', '.join(score_name(k) for k in a.get('evidence', []))}, "
                     f"peak score {num(a['peak'])}")
        if a.get("explanation_text"):
            lines.append(f"    {a['explanation_text']}")
    if others:
        lines.append("single-test alarms: " + ", ".join(
            f"{score_name(a['kind'])} at {num(a['start_s'], unit='s')}" for a in others[:12]) + (" ..." if len(others) > 12 else ""))
    return "\n".join(lines)
