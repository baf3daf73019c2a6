"""`magstation calibrate`: one log -> a calibration result per compass.

``calibrate_compasses(log, settings) -> list[dict]``: every compass of the log (the result
object of ``result.py``; the compasses' consistency table in each).  ``calibrate_log(log,
settings) -> dict``: the primary compass alone (the station's replay waits for it and the
calibration wizard uses it), by default without the motor fit and the orientation check
(``QUICK_SETTINGS``; pass DEFAULT_SETTINGS for everything).  ``calibrate_path(path, settings) -> list[dict]``: read and calibrate, a pure
function of path and settings (an unreadable file gives ``[error_result]``).

Per log: the attitude source (inflight.choose_attitude), then the reference field, the WMM with its
inclination refined from the flight (reference.refine_reference).  Pipeline per compass (compass.py): raw field with the corrections in force at each sample
un-applied (jobs.compass_raw) -> calibration windows (markers or rotation segmentation) -> else
the in-flight fit against the WMM -> motor field -> orientation check -> ArduPilot / PX4
parameters named after the instance.  Bad data never raise: they give a status and a message
(ok | weak: offsets with their 1σ, not recommended | insufficient_coverage | no_data |
attitude_depends_on_compass | offsets_out_of_range | error; a log without its corrections in force gives a relative fit, status ok).
"""
from __future__ import annotations

import os
from pathlib import Path

from groundstation.io.errors import IngestError
from groundstation.io.logs import read_log
from groundstation.jobs.compass_raw import compass_fields
from groundstation.samples import FlightLog

from .checks import consistency_table
from .compass import calibrate_compass
from .inflight import choose_attitude
from .context import expected_field, log_context
from .reference import refine_reference
from .result import empty_result, error_result, format_consistency, format_summary, write_param_file
from .settings import DEFAULT_SETTINGS, QUICK_SETTINGS, CalibrateSettings

__all__ = ["calibrate_log", "calibrate_compasses", "calibrate_path", "error_result", "format_summary",
           "format_consistency", "write_param_file", "expected_field", "CalibrateSettings", "DEFAULT_SETTINGS",
           "QUICK_SETTINGS"]


def _guarded(log: FlightLog, settings: CalibrateSettings, only: int | None = None) -> list[dict]:
    fields = compass_fields(log)
    if only is not None:
        fields = [f for f in fields if f.compass == only]
    if not fields:
        r = empty_result(log.source, log.primary_compass)
        r.update(status="no_data", message="log has no magnetometer samples", autopilot=log.autopilot)
        return [r]
    ctx = choose_attitude(log, fields, log_context(log), settings)   # the attitude of the in-flight fits, per log
    ctx = refine_reference(log, fields, ctx, settings)              # their reference field, per log
    results, calibrations = [], {}
    for cf in fields:
        try:
            r, cal = calibrate_compass(log, cf, ctx, settings)
        except Exception as e:  # last resort: bad data must not crash the CLI
            r, cal = empty_result(log.source, cf.compass), None
            r.update(status="error", message=f"{type(e).__name__}: {e}", source=cf.source, device_id=cf.device_id)
        results.append(r)
        if cal is not None:
            calibrations[cf.compass] = cal
    table = consistency_table(fields, calibrations, log.primary_compass, ctx, settings)
    for r in results:
        r["consistency"] = table
    return results


def calibrate_compasses(log: FlightLog, settings: CalibrateSettings = DEFAULT_SETTINGS) -> list[dict]:
    """A result per compass of the log, in compass order (never raises)."""
    try:
        return _guarded(log, settings)
    except Exception as e:  # corrections history or a reader quirk we did not foresee
        r = empty_result(getattr(log, "source", "?"), getattr(log, "primary_compass", 0))
        r.update(status="error", message=f"{type(e).__name__}: {e}")
        return [r]


def calibrate_log(log: FlightLog, settings: CalibrateSettings = QUICK_SETTINGS) -> dict:
    """The primary compass's result (the one ``log.mag`` holds; no consistency table); never raises."""
    try:
        results = _guarded(log, settings, only=log.primary_compass)
    except Exception as e:  # as calibrate_compasses
        r = empty_result(getattr(log, "source", "?"), getattr(log, "primary_compass", 0))
        r.update(status="error", message=f"{type(e).__name__}: {e}")
        return r
    return results[0]


def calibrate_path(path: str | os.PathLike, settings: CalibrateSettings = DEFAULT_SETTINGS) -> list[dict]:
    """Read a log and calibrate every compass; an unreadable file gives ``[error_result]``."""
    try:
        log = read_log(Path(path))
    except IngestError as err:
        return [error_result(str(path), str(err))]
    return calibrate_compasses(log, settings)
