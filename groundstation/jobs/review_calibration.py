"""Which calibration `magstation review` analyses a log with, and saying which.

Order: (1) the log's own calibration dance (``calibrate_log``: a rotation window fit, absolute or
relative to the log's corrections in force); (2) the airframe's calibration in force at the log's
date in the fleet history (the latest record at or before the log's start; with none before it,
the earliest one after, said so); (3) with ``--params`` / ``--assume-uncalibrated`` alone, the
autopilot's corrections from those values; (4) none: the field as the autopilot corrected it.
The choice is the row's ``calibration_used`` (one short line).
"""
from __future__ import annotations

import datetime as _dt
import json

from groundstation.samples import FlightLog

__all__ = ["review_calibration", "apply_review_params", "history_calibrations"]


def apply_review_params(log: FlightLog, settings) -> None:
    """--params / --assume-uncalibrated as the log's parameters in force where it has none."""
    if not settings.params and settings.params_label != "--assume-uncalibrated":
        return
    from groundstation.io.param_file import apply_to_log, uncalibrated_params

    values = uncalibrated_params(log.autopilot) if settings.params_label == "--assume-uncalibrated" \
        else dict(settings.params)
    apply_to_log(log, values, settings.params_label or "--params")


def _date(unix_s) -> str:
    try:
        return _dt.datetime.fromtimestamp(float(unix_s), _dt.timezone.utc).strftime("%Y-%m-%d %H:%M")
    except (TypeError, ValueError, OverflowError, OSError):
        return "undated"


def _history_choice(identity: str, start_unix_s: float | None, calibrations: tuple) -> tuple[dict | None, str]:
    mine = sorted(((float(t or 0.0), c) for a, t, c in calibrations if a == identity), key=lambda x: x[0])
    if not mine:
        return None, ""
    before = [m for m in mine if start_unix_s is None or m[0] <= start_unix_s]
    when, text = before[-1] if before else mine[0]
    try:
        cal = json.loads(text)
    except ValueError:
        return None, ""
    rel = cal.get("relative_to") or "raw"
    kind = "absolute" if rel == "raw" else f"relative ({'recorded' if rel == 'corrections' else 'unknown'} corrections)"
    tail = "" if before else " (the earliest, made after this log)"
    return cal, f"history: {identity}'s calibration of {_date(when)}, {kind}{tail}"


def review_calibration(log: FlightLog, identity: str, settings, own: dict | None = None) -> tuple[dict | None, str]:
    """(calibration or None, the line saying which) for one log (see the module docstring); ``own``:
    the calibrate job's result for the primary compass when the caller has it (else fitted here)."""
    from groundstation.jobs.calibrate import calibrate_log

    if len(log.mag) >= 200:
        own = calibrate_log(log) if own is None else own
        if own.get("status") == "ok" and own.get("method") == "window":
            w = own.get("window_s") or [0, 0]
            return own, f"own dance {w[0]:.0f}-{w[1]:.0f} s ({'absolute' if own.get('relative_to') == 'raw' else 'relative'})"
    cal, text = _history_choice(identity, log.start_unix_s, settings.calibrations)
    if cal is not None:
        return cal, text
    if settings.params_label:
        return None, f"none, the autopilot's corrections from {settings.params_label}"
    return None, "none"


def history_calibrations(con) -> tuple:
    """((airframe, unix_s, calibration JSON), ...) of every history record that holds one."""
    try:
        rows = con.execute("SELECT airframe, unix_s, calibration_json FROM calibrations "
                           "WHERE calibration_json IS NOT NULL ORDER BY unix_s, id").fetchall()
    except Exception:          # an older read-only history without the column
        return ()
    return tuple((r[0], r[1], r[2]) for r in rows)
