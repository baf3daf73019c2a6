"""What `magstation info` says about the compasses of a log: each one with its source, rate and
device id, the corrections the autopilot had in force and when they changed, the onboard
calibration events, and where the motor current and throttle come from."""
from __future__ import annotations

import numpy as np

from groundstation.jobs.compass_raw import compass_fields
from groundstation.jobs.words import span_s
from groundstation.samples import MAG_CAL_SUCCESS, FlightLog

__all__ = ["compass_lines", "MAX_CHANGES_LISTED"]

MAX_CHANGES_LISTED = 6


def _fmt(v) -> str:
    return "[" + ", ".join(f"{x:.1f}" for x in v) + "]"


def _state(applied: bool | None, status: str) -> str:
    if status == "no_parameters":
        return "corrected by the autopilot, corrections unknown (no offsets in the log)"
    if applied is False:
        return "raw sensor output"
    return "corrected by the autopilot" if applied else "calibration state unknown"


def _changes(cf) -> list[str]:
    name = {"ardupilot": "COMPASS_OFS" + ("" if cf.compass == 0 else str(cf.compass + 1))}.get(cf.autopilot, "offsets")
    if not cf.changes:
        if cf.autopilot == "px4" and len(cf.offsets_in_force_mG):
            return [f"      offsets in force (body frame) {_fmt(cf.offsets_in_force_mG[-1])} mG (CAL_MAG{cf.px4_slot})"]
        return []
    shown = cf.changes[:MAX_CHANGES_LISTED]
    text = ", then ".join(f"{_fmt(o)} " + ("from the start" if i == 0 else f"at {t:.1f} s")
                          for i, (t, o) in enumerate(shown))
    more = len(cf.changes) - len(shown)
    lines = [f"      {name} in force: {text}" + (f" (+{more} more changes)" if more > 0 else "")]
    mot = cf.motor_in_force
    if mot.get("type") and any(abs(v) > 1e-6 for v in mot.get("per_unit", [])):
        lines.append(f"      motor compensation COMPASS_MOTCT={mot['type']}: {_fmt(mot['per_unit'])} mG per "
                     f"{'A' if mot['type'] == 2 else 'full throttle'}")
    return lines


def _mag_cal_lines(log: FlightLog) -> list[str]:
    if not log.mag_cal:
        return []
    starts = [e for e in log.mag_cal if e.kind == "start"]
    reports = [e for e in log.mag_cal if e.kind == "report"]
    progress = [e for e in log.mag_cal if e.kind == "progress"]
    out = [f"  onboard cal     {len(starts)} start command(s), {len(progress)} progress messages, "
           f"{len(reports)} report(s)"]
    for r in reports:
        ok = "success" if r.status == MAG_CAL_SUCCESS else f"status {r.status}"
        out.append(f"      compass {r.compass} at {r.t_s:.1f} s: {ok}, fitness {r.fitness_mG:.1f} mG, "
                   f"COMPASS_OFS {_fmt(r.offsets_mG)}")
    return out


def _signal_line(name: str, table: np.ndarray, unit: str) -> str:
    if len(table) < 2:
        return f"  {name:<15} none"
    return (f"  {name:<15} {len(table)} samples, {float(np.min(table[:, 1])):.1f}–{float(np.max(table[:, 1])):.1f} {unit}")


def compass_lines(log: FlightLog) -> list[str]:
    """Lines for `magstation info` (two-space indented, as its other lines)."""
    fields = compass_fields(log)
    tables = {c.compass: c for c in log.compass_tables()}
    lines = [f"  compasses       {len(fields)}" + (f" (primary: {log.primary_compass})" if len(fields) > 1 else "")]
    for cf in fields:
        table = tables[cf.compass]
        dev = f", device {cf.device_id}" if cf.device_id else ""
        lines.append(f"    compass {cf.compass}: {cf.source}, {len(cf.t_s)} samples, {table.rate_hz:.1f} Hz{dev}, "
                     f"{span_s(cf.t_s[0], cf.t_s[-1])}, {_state(table.calibration_applied, cf.status)}"
                     if len(cf.t_s) else f"    compass {cf.compass}: {cf.source}, no samples")
        lines += _changes(cf)
    if len(log.imus) > 1:
        lines.append("  IMUs            " + ", ".join(f"{k}: {len(v)} samples" for k, v in sorted(log.imus.items())))
    lines += _mag_cal_lines(log)
    lines.append(_signal_line("throttle", log.throttle, "(0..1)"))
    return lines
