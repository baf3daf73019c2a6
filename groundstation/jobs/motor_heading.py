"""The best heading of a whole log: the default AHRS on the field with the motor-current field
taken out (analyze's CSV attitude, issue 12).

The detector and the display share one attitude, the default AHRS (``estimators.ahrs.
AhrsSettings``, ``detection_inputs``' chain); here it runs again on the field with the motor-current
field removed.  A calibration from the rotation dance is made with the motors off, so in flight
the field of the motor and battery wires, proportional to the current, turns the compass heading
by several degrees (7° median on the simulated missions at 12-32 A).  When the log carries the
battery current and it varies, ``estimators.motor_field.fit_current_field`` finds the field per
ampere from the tilt of that chain (tilt does not depend on the compass) and the best
chain runs on the field with f·I removed.  The magnetometer-only heading the detector uses
(``mag_heading_deg``) stays on the field as measured: the detector has its own motor model.
"""
from __future__ import annotations

import numpy as np

from estimators.heading import HeadingChainResult, run_heading_chain
from estimators.motor_field import CurrentFieldFit, fit_current_field

from groundstation.jobs.inputs import MOTOR_TIMEOUT_S, hold_last, rounded
from groundstation.samples import FlightLog

__all__ = ["attitude_chain", "best_heading_chain"]


def _report(fit: CurrentFieldFit | None, used: bool, message: str = "") -> dict:
    if fit is None:
        return {"status": "no_motor_signal", "message": message, "removed_from_heading": False}
    vec = lambda v: [rounded(a, 3) for a in np.asarray(v, float)]  # noqa: E731
    return {"status": fit.status, "message": fit.message, "removed_from_heading": used,
            "mG_per_A": vec(fit.motor_mG_per_A), "sd_mG_per_A": vec(fit.motor_sd_mG_per_A), "samples": fit.n_used}


def _current_field(log: FlightLog, x: dict) -> tuple[CurrentFieldFit | None, np.ndarray, str]:
    """(fit or None, current at the magnetometer samples [A], why None)."""
    chain, mag_cal = x["chain"], x["mag_cal"]
    battery = np.asarray(log.battery, dtype=float).reshape(-1, 2)
    if not len(battery) or not len(mag_cal) or not len(chain.t_s) or x["policy"].correction == "none":
        return None, np.zeros(0), "no battery current in the log" if not len(battery) else "no field"
    current = hold_last(battery[:, 0], battery[:, 1:2], mag_cal[:, 0], MOTOR_TIMEOUT_S)[:, 0]
    valid = np.asarray(chain.valid, bool)[:, None]
    tilt = hold_last(chain.t_s, np.where(valid, np.c_[chain.roll_rad, chain.pitch_rad], np.nan), mag_cal[:, 0], np.inf)
    return fit_current_field(mag_cal[:, 1:4], current, tilt[:, 0], tilt[:, 1]), current, ""


def attitude_chain(log: FlightLog, field: np.ndarray, declination_deg: float) -> HeadingChainResult:
    """The default AHRS (``estimators.ahrs.AhrsSettings``) on the log's IMU and a field (M, 4)."""
    return run_heading_chain(np.asarray(log.imu, dtype=float).reshape(-1, 7), field, declination_deg)


def best_heading_chain(log: FlightLog, x: dict, shown: HeadingChainResult) -> tuple[HeadingChainResult, dict]:
    """(the default AHRS on the field with the motor-current field removed when it is found, else
    ``shown``, the default AHRS on the field as measured; report["motor_field"]).  ``x``:
    detection_inputs of the log (its mag_cal, chain and WMM)."""
    fit, current, why = _current_field(log, x)
    if fit is None or fit.status != "ok":
        return shown, _report(fit, False, why)
    field = x["mag_cal"].copy()
    have = np.isfinite(current)
    field[have, 1:4] -= np.outer(current[have], fit.motor_mG_per_A)
    ef = x["ef"]
    return attitude_chain(log, field, ef.declination_deg if ef else 0.0), _report(fit, True, why)
