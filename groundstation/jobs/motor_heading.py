"""The best heading of a whole log: the default AHRS on the field with the motor-current field
taken out (analyze's CSV attitude, issue 12).

One motor-field model (issue 30): the field per ampere f the field-vector test learns online from
the current's changes (``estimators.residual_trackers.FieldModelFilter``, inside
``estimators.field_consistency``), with its standard error, serves the detector, the alarm
explanations (the test's residual has f·Δx removed) and this heading.  A calibration from the
rotation dance is made with the motors off, so in flight the field of the motor and battery
wires, proportional to the current, turns the compass heading by several degrees (7° median on the
simulated missions at 12-32 A).  Here the default AHRS (``estimators.ahrs.AhrsSettings``, the
detector's own attitude) runs again on the field with f(t)·I(t) removed, f as learned up to each
step (causal: the live station could do the same) and only where it is significant
(|f| ≥ MOTOR_SIGNIFICANT_SIGMA |sd|).  The current is held with the one motor-signal timeout
(``jobs.inputs.MOTOR_TIMEOUT_S``).  The magnetometer-only heading the detector uses
(``mag_heading_deg``) stays on the field as measured: the detector has the model inside its test.
"""
from __future__ import annotations

import numpy as np

from estimators.attitude_smoother import smooth_heading_chain
from estimators.heading import HeadingChainResult, run_heading_chain

from groundstation.jobs.inputs import MOTOR_TIMEOUT_S, hold_last, rounded
from groundstation.samples import FlightLog

__all__ = ["attitude_chain", "best_heading_chain", "motor_correction", "motor_field_steps", "MOTOR_SIGNIFICANT_SIGMA"]

MOTOR_SIGNIFICANT_SIGMA = 3.0      # f is removed once |f| is this many standard errors


def motor_field_steps(x: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(f (N, 3) [mG per unit], sd (N, 3), significant (N,)) on the IMU steps of ``detection_inputs``
    output ``x``: the field-vector test's motor field as learned up to each step."""
    vec = x["vector"]
    f = np.asarray(vec.motor_mG_per_unit, dtype=float).reshape(-1, 3)
    sd = vec.motor_sd_mG_per_unit
    sd = np.full_like(f, np.inf) if sd is None else np.asarray(sd, dtype=float).reshape(-1, 3)
    with np.errstate(invalid="ignore"):
        sig = np.linalg.norm(f, axis=1) >= MOTOR_SIGNIFICANT_SIGMA * np.linalg.norm(sd, axis=1)
    return f, sd, sig & np.isfinite(sd).all(axis=1) & (np.linalg.norm(f, axis=1) > 0)


def _report(status: str, message: str, used: bool, f=None, sd=None, n: int = 0) -> dict:
    out = {"status": status, "message": message, "removed_from_heading": used}
    if f is not None:
        vec = lambda v: [rounded(a, 3) for a in np.asarray(v, float)]  # noqa: E731
        out.update({"mG_per_A": vec(f), "sd_mG_per_A": vec(sd), "samples": int(n)})
    return out


def attitude_chain(log: FlightLog, field: np.ndarray, declination_deg: float,
                   offline: bool = False) -> HeadingChainResult:
    """The default AHRS (``estimators.ahrs.AhrsSettings``) on the log's IMU and a field (M, 4);
    ``offline``: its forward-backward smoother over the whole log (estimators/attitude_smoother.py)."""
    imu = np.asarray(log.imu, dtype=float).reshape(-1, 7)
    run = smooth_heading_chain if offline else run_heading_chain
    return run(imu, field, declination_deg)


def motor_correction(log: FlightLog, x: dict) -> tuple[np.ndarray | None, dict]:
    """(the field (M, 4) with the significant motor-current field removed, None where none is
    removed; report["motor_field"]).  ``x``: detection_inputs of the log (its mag_cal, field-vector
    test and WMM)."""
    battery = np.asarray(log.battery, dtype=float).reshape(-1, 2)
    mag_cal = x["mag_cal"]
    if x["policy"].correction == "none" or not len(mag_cal):
        return None, _report("no_motor_signal", "no field", False)
    if x.get("motor_signal") != "current_A" or not len(battery):
        return None, _report("no_motor_signal", "no battery current that varies in the log", False)
    t = np.asarray(x["t"], dtype=float)
    f, sd, sig = motor_field_steps(x)
    if not len(t) or not sig.any():
        last = (f[-1], sd[-1]) if len(f) else (np.full(3, np.nan), np.full(3, np.inf))
        return None, _report("not_significant", f"motor field {np.round(last[0], 2).tolist()} mG/A not "
                             f"significant (sd {np.round(last[1], 2).tolist()}; the field-vector test learns it from "
                             "the current's changes at IMU rates >= 10 Hz)", False, *last)
    current = hold_last(battery[:, 0], battery[:, 1], mag_cal[:, 0], MOTOR_TIMEOUT_S)
    f_mag = hold_last(t, np.where(sig[:, None], f, 0.0), mag_cal[:, 0], np.inf)
    use = np.isfinite(current) & np.all(np.isfinite(f_mag), axis=1)
    field = mag_cal.copy()
    field[use, 1:4] -= f_mag[use] * current[use, None]
    k = int(np.flatnonzero(sig)[-1])
    i_max = float(np.nanmax(battery[:, 1]))
    msg = (f"motor field {np.round(f[k], 2).tolist()} mG/A (sd {np.round(sd[k], 2).tolist()}), "
           f"{np.linalg.norm(f[k]) * i_max:.0f} mG at {i_max:.1f} A; significant from "
           f"{t[np.flatnonzero(sig)[0]]:.1f} s, removed from {int(use.sum())} field samples")
    return field, _report("ok" if sig[-1] else "not_significant", msg, True, f[k], sd[k], int(use.sum()))


def best_heading_chain(log: FlightLog, x: dict, shown: HeadingChainResult,
                       offline: bool = False) -> tuple[HeadingChainResult, dict]:
    """(the default AHRS on the field with the significant motor-current field removed
    (``motor_correction``), else ``shown``, the default AHRS on the field as measured;
    report["motor_field"]).  ``offline``: the offline smoother instead of the causal AHRS (a
    finished log's best estimate), on the field as measured too."""
    ef = x["ef"]
    decl = ef.declination_deg if ef else 0.0
    field, report = motor_correction(log, x)
    if field is None:               # the smoother only where it is the answer
        return (attitude_chain(log, x["mag_cal"], decl, True) if offline else shown), report
    return attitude_chain(log, field, decl, offline), report
