"""What a calibration is relative to, and how it is applied to the field of another log.

A calibration ``(b, C)`` maps a field ``x`` to the calibrated field ``m_cal = C (x − b)`` (mG).
Which field ``x`` is, is the calibration's ``relative_to``:

* ``"raw"`` — **absolute**: x is the raw sensor field (body-aligned, the autopilot's corrections
  un-applied).  Its ArduPilot / PX4 parameters are the ones to write.  Old calibrate JSON files
  (no ``relative_to``, status "ok") are absolute.
* ``"corrections"`` — **relative** to the corrections in force, recorded in ``corrections_in_force``
  (``offsets_mG`` o and ``matrix`` N in our convention: the autopilot's field is
  ``K(raw) = N (raw − o)``; ArduPilot o = −COMPASS_OFS, N = SCALE·M(DIA, ODI); PX4 o = R·CAL_MAGn_OFF,
  N = R S Rᵀ — see groundstation.io.params).
* ``"unknown"`` — **relative** to corrections in force that nobody knows (a log without
  COMPASS_OFS / PARAM_VALUE): right for logs flown with the same corrections in force.

Applying to a log (``for_log``): the log's raw field is known (its corrections were in the log, a
``--params`` file or ``--assume-uncalibrated``) or it is not (then the field as logged stands in).
The composition through raw is exact (motor compensation aside, which stays as the autopilot
applied it):  C (N (raw − o) − b) = (C N) (raw − (o + N⁻¹ b)),  i.e. b' = o + N⁻¹ b,  C' = C N.

| calibration \\ log | raw known                                   | raw unknown                           |
| absolute           | C (raw − b)                                 | on the logged field (said)            |
| relative, known    | composed with its own K_c: exact            | on the logged field (same K assumed)  |
| relative, unknown  | composed with the log's K_l (same K assumed) | on the logged field (same K assumed)  |
Pure numpy; no I/O.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["RELATIVE_TO", "relative_to", "is_relative", "corrections_record", "compose", "for_log", "Applied",
           "frame_label", "LOG_RAW_UNKNOWN_STATUSES", "compact", "from_params"]

RELATIVE_TO = ("raw", "corrections", "unknown")
# CompassField statuses whose raw field is the logged one, corrections unknown (jobs.compass_raw)
LOG_RAW_UNKNOWN_STATUSES = ("no_parameters",)


def relative_to(calibration: dict) -> str:
    """"raw" | "corrections" | "unknown" of a calibration object (old files: "raw"; an old
    ``no_parameters`` result: "unknown"; a "corrections" one without usable corrections: "unknown")."""
    rel = calibration.get("relative_to")
    if rel is None:
        return "unknown" if calibration.get("status") == "no_parameters" else "raw"
    if rel == "corrections" and _corrections(calibration.get("corrections_in_force")) is None:
        return "unknown"
    return rel if rel in RELATIVE_TO else "unknown"


def is_relative(calibration: dict) -> bool:
    return relative_to(calibration) != "raw"


def frame_label(calibration: dict) -> str:
    """One short phrase: "absolute" | "relative to the corrections in force (recorded)" | "... (unknown)"."""
    rel = relative_to(calibration)
    return {"raw": "absolute", "corrections": "relative to the corrections in force (recorded)",
            "unknown": "relative to the corrections in force (unknown)"}[rel]


def corrections_record(offsets_mG, matrix, params: dict[str, float] | None = None) -> dict | None:
    """``corrections_in_force`` of a calibration: o, N (see the module docstring) and the autopilot's
    own parameter values when known; None when o or N is not finite."""
    o, N = np.asarray(offsets_mG, float).reshape(-1), np.asarray(matrix, float)
    if o.shape != (3,) or N.shape != (3, 3) or not (np.all(np.isfinite(o)) and np.all(np.isfinite(N))):
        return None
    return {"offsets_mG": [round(float(v), 4) for v in o], "matrix": [[round(float(v), 7) for v in r] for r in N],
            "params": {k: float(v) for k, v in sorted((params or {}).items()) if math.isfinite(float(v))}}


def _corrections(rec) -> tuple[np.ndarray, np.ndarray] | None:
    if not isinstance(rec, dict):
        return None
    try:
        o, N = np.asarray(rec.get("offsets_mG"), float), np.asarray(rec.get("matrix"), float)
    except (TypeError, ValueError):
        return None
    if o.shape != (3,) or N.shape != (3, 3) or not (np.all(np.isfinite(o)) and np.all(np.isfinite(N))):
        return None
    if abs(np.linalg.det(N)) < 1e-6:
        return None
    return o, N


def compose(b, C, o, N) -> tuple[np.ndarray, np.ndarray]:
    """(b', C') with C' (raw − b') = C (N (raw − o) − b): a relative calibration on top of the
    corrections K(raw) = N (raw − o), as an absolute one.  b' = o + N⁻¹ b, C' = C N."""
    b, C, o, N = (np.asarray(v, float) for v in (b, C, o, N))
    return o + np.linalg.solve(N, b), C @ N


@dataclass(frozen=True)
class Applied:
    """A calibration as it applies to one log's primary field (``jobs.compass_raw.compass_field``'s
    raw_mG): ``offsets_mG``, ``matrix``; ``exact`` False when an assumption was needed (``note``)."""
    offsets_mG: np.ndarray
    matrix: np.ndarray
    exact: bool
    note: str


def for_log(offsets_mG, matrix, calibration: dict, log_status: str, log_offsets_mG=None,
            log_matrix=None) -> Applied:
    """The calibration (its checked ``offsets_mG``/``matrix``) in the frame of a log's primary field.

    ``log_status`` is the CompassField status of the log's compass (``LOG_RAW_UNKNOWN_STATUSES``:
    its field is the logged one, corrections unknown); ``log_offsets_mG`` / ``log_matrix`` its
    corrections in force at the end (o, N), used for a relative calibration of unknown corrections."""
    b, C = np.asarray(offsets_mG, float), np.asarray(matrix, float)
    rel = relative_to(calibration)
    log_known = log_status not in LOG_RAW_UNKNOWN_STATUSES
    if rel == "raw":
        if log_known:
            return Applied(b, C, True, "absolute calibration applied to the raw field")
        return Applied(b, C, False, "absolute calibration applied to the field as logged: the log's corrections in "
                                    "force are unknown (right only if the vehicle was never calibrated; give --params)")
    if not log_known:
        return Applied(b, C, False, "relative calibration applied on top of the log's "
                       "corrections in force (both unknown here: assumed the same as when it was fitted)"
                       if rel == "unknown" else "relative calibration applied on top of the log's corrections "
                       "in force (the log's are unknown: assumed those the calibration records)")
    if rel == "corrections":
        o, N = _corrections(calibration.get("corrections_in_force"))
        b2, C2 = compose(b, C, o, N)
        return Applied(b2, C2, True, "relative calibration converted exactly to the raw field through the "
                                     "corrections it records")
    lo, lN = (None, None) if log_offsets_mG is None else (np.asarray(log_offsets_mG, float),
                                                         np.asarray(log_matrix, float))
    if lo is None or lo.shape != (3,) or not np.all(np.isfinite(lo)) or lN is None or lN.shape != (3, 3) \
            or not np.all(np.isfinite(lN)) or abs(np.linalg.det(lN)) < 1e-6:
        return Applied(b, C, False, "relative calibration applied to the raw field: the log's corrections in force "
                                    "are not usable, the calibration's unknown")
    b2, C2 = compose(b, C, lo, lN)
    return Applied(b2, C2, False, "relative calibration applied on top of the log's corrections in force (the "
                                  "calibration's own are unknown: assumed the same)")


COMPACT_KEYS = ("file", "compass", "device_id", "autopilot", "status", "method", "offsets_mG", "matrix",
                "relative_to", "corrections_in_force", "residual_rms_mG", "field_strength_mG", "expected_field_mG",
                "coverage", "window_s", "ardupilot_params", "px4_params", "message")


def compact(calibration: dict) -> dict:
    """The calibration object without its diagnostics (windows, fits, consistency): what the
    history keeps and the station passes around; ``relative_to`` always set."""
    out = {k: calibration.get(k) for k in COMPACT_KEYS if k in calibration}
    out["relative_to"] = relative_to(calibration)
    if isinstance(out.get("message"), str):
        out["message"] = out["message"][:500]
    return out


def from_params(params: dict[str, float], autopilot: str | None, compass: int = 0) -> dict | None:
    """The absolute calibration that a vehicle's parameters hold for compass ``compass`` (what its
    autopilot does to the raw field: ArduPilot b = −COMPASS_OFS, C = SCALE·M(DIA, ODI); PX4
    b = R·CAL_MAGn_OFF, C = R S Rᵀ), as a compact calibration object; None without offsets."""
    from estimators.compass_corrections import ardupilot_param_names
    from groundstation.io.params import ardupilot_matrix, detect_autopilot, px4_matrix, px4_slot

    ap = autopilot or detect_autopilot(params)
    if ap == "px4":
        slot = px4_slot(params, None, compass)
        if not all(f"CAL_MAG{slot}_{a}OFF" in params for a in "XYZ"):
            return None
        off, S, R = px4_matrix(params, slot)
        b, C = R @ off * 1000.0, R @ S @ R.T
        names = {k: v for k, v in params.items() if k.startswith(f"CAL_MAG{slot}_")}
        key = "px4_params"
    else:
        names_all = ardupilot_param_names(compass)
        if not all(k in params for k in names_all["offsets"]):
            return None
        ofs, M, scale = ardupilot_matrix(params, compass)
        b, C = -ofs, scale * M
        wanted = {n for group in names_all.values() for n in group}
        names, key, ap = {k: v for k, v in params.items() if k in wanted}, "ardupilot_params", "ardupilot"
    if not (np.all(np.isfinite(b)) and np.all(np.isfinite(C))) or abs(np.linalg.det(C)) < 1e-6:
        return None
    return {"status": "ok", "method": "parameters", "compass": compass, "autopilot": ap, "relative_to": "raw",
            "offsets_mG": [float(v) for v in b], "matrix": [[float(v) for v in r] for r in C],
            key: {k: float(v) for k, v in names.items()}, "corrections_in_force": None,
            "message": "the autopilot's own calibration parameters"}
