"""What `magstation info` says about the compasses of a log: each one with its source, rate and
device id, the corrections the autopilot had in force and when they changed, the onboard
calibration events, and where the motor current and throttle come from."""
from __future__ import annotations

import numpy as np

from groundstation.jobs.compass_raw import compass_fields
from groundstation.jobs.words import span_s
from groundstation.samples import MAG_CAL_SUCCESS, FlightLog

__all__ = ["compass_lines", "refused_parameter_lines", "MAX_CHANGES_LISTED", "REFUSED_PREFIX", "distinct_reports"]

REFUSED_PREFIX = "parameter value refused: "      # the readers' warning (groundstation.io.params.param_value_problem)

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


def distinct_reports(events) -> list:
    """The onboard calibration's reports, each once: ArduPilot repeats a compass's MAG_CAL_REPORT
    at its stream rate until the result is accepted or a new calibration starts, so a report equal
    to the last one of the same compass (status, fitness, offsets, soft iron) since the last start
    command is the same report again."""
    out, last = [], {}
    for e in events:
        if e.kind == "start":
            last.clear()
        elif e.kind == "report":
            key = (e.status, e.fitness_mG, e.offsets_mG, e.diag, e.offdiag, e.scale_factor)
            if last.get(e.compass) != key:
                last[e.compass] = key
                out.append(e)
    return out


def _mag_cal_lines(log: FlightLog) -> list[str]:
    if not log.mag_cal:
        return []
    starts = [e for e in log.mag_cal if e.kind == "start"]
    messages = sum(1 for e in log.mag_cal if e.kind == "report")
    reports = distinct_reports(log.mag_cal)
    progress = [e for e in log.mag_cal if e.kind == "progress"]
    repeats = f" (in {messages} MAG_CAL_REPORT messages)" if messages != len(reports) else ""
    out = [f"  onboard cal     {len(starts)} start command(s), {len(progress)} progress messages, "
           f"{len(reports)} report(s){repeats}"]
    for r in reports:
        ok = "success" if r.status == MAG_CAL_SUCCESS else f"status {r.status}"
        out.append(f"      compass {r.compass} at {r.t_s:.1f} s: {ok}, fitness {r.fitness_mG:.1f} mG, "
                   f"COMPASS_OFS {_fmt(r.offsets_mG)}")
    return out


def _signal_line(name: str, table: np.ndarray, unit: str) -> str:
    if len(table) < 2:
        return f"  {name:<15} none"
    return (f"  {name:<15} {len(table)} samples, {float(np.min(table[:, 1])):.1f}–{float(np.max(table[:, 1])):.1f} {unit}")


def refused_parameter_lines(log: FlightLog) -> list[str]:
    """`info`'s flag for absurd parameter values: every value the log reader refused (NaN,
    infinite, 3.4e38-style float32 garbage, beyond the autopilot's range), which the rest of the
    project does not use."""
    refused = [(w[len(REFUSED_PREFIX):], n) for w, n in log.warnings.items() if w.startswith(REFUSED_PREFIX)]
    if not refused:
        return []
    total = sum(n for _, n in refused)
    lines = [f"  ABSURD VALUES   {total} parameter value(s) refused and not used:"]
    lines += [f"    {text}" + (f" ({n}×)" if n > 1 else "") for text, n in refused[:10]]
    if len(refused) > 10:
        lines.append(f"    … and {len(refused) - 10} more")
    return lines


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
        if table.source_note:
            lines.append(f"      source: {table.source_note}")
        lines += _changes(cf)
    if len(log.imus) > 1:
        lines.append("  IMUs            " + ", ".join(f"{k}: {len(v)} samples" for k, v in sorted(log.imus.items())))
    lines += _mag_cal_lines(log)
    lines.append(_signal_line("throttle", log.throttle, "(0..1)"))
    return lines
