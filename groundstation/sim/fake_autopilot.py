"""What the fake vehicle's autopilot does with its compasses, modelled on ArduPilot (and PX4).

* ``default_params`` — a fresh parameter table for up to three compasses (never calibrated).
* ``corrected_field`` / ``rotated_raw`` — the autopilot's correction of a raw sensor reading:
  ArduPilot rotates by COMPASS_ORIENTn, then M·(rot_raw + OFS) (AP_Compass_Backend);
  PX4 R·S·(raw − off) with R from CAL_MAGn_ROT (groundstation.io.params has both).
* ``OnboardCalibrator`` — ArduPilot's CompassCalibrator as seen from the ground: samples are
  accepted when far enough from every earlier one (the same circle-packing distance), 300 fill
  step one, the buffer is thinned with the fitted radius, and refilled to 300 in step two;
  completion is 33.3 % · n/300, then 33.3 % plus 65.7 % of the refill; each accepted sample sets
  its geodesic section in the 80-bit completion mask; the fit (our robust ellipsoid) passes when
  the radius is 150–950 mG, offsets under COMPASS_OFFS_MAX, DIA 0.2–5, |ODI| < 1 and the RMS
  residual (the *fitness*) is at most COMPASS_CAL_FIT (twice that for compasses other than the
  first).  Accept saves OFS/DIA/ODI; cancel forgets.
* ``fixed_yaw_params`` — MAV_CMD_FIXED_MAG_CAL_YAW as Compass::mag_cal_fixed_yaw: the WMM field
  rotated into the body with the current roll/pitch and the given yaw, OFS = expected −
  uncorrected field, DIA 1, ODI 0.
"""
from __future__ import annotations

import math

import numpy as np

from estimators.calibration import fit_ellipsoid_robust, polar_decomposition
from estimators.rotations import dcm_body_to_ned
from groundstation.io.magcal import mask_from_sections, section_of
from groundstation.io.params import apply_ardupilot, apply_px4, rotation_enum_matrix, unapply_ardupilot

__all__ = ["default_params", "corrected_field", "rotated_raw", "OnboardCalibrator", "fixed_yaw_params",
           "ap_suffix"]

NUM_SAMPLES = 300
# ArduPilot's acceptance angle for 300 samples: theta = ½ acos(cos a / (1 − cos a)), a = 4π/3F + π/3
_FACES = 2 * NUM_SAMPLES - 4
_A = 4.0 * math.pi / (3.0 * _FACES) + math.pi / 3.0
_THETA = 0.5 * math.acos(math.cos(_A) / (1.0 - math.cos(_A)))


def ap_suffix(k: int) -> str:
    """ArduPilot's parameter suffix of compass k: '' for the first, '2', '3' for the others."""
    return "" if k == 0 else str(k + 1)


def default_params(autopilot: str = "ardupilot", n_compasses: int = 3) -> dict[str, float]:
    if autopilot == "px4":
        p = {"CAL_MAG_PRIME": 0.0, "SENS_BOARD_ROT": 0.0}
        for k in range(n_compasses):
            p |= {f"CAL_MAG{k}_ID": float(100 + k), f"CAL_MAG{k}_ROT": 0.0}
            p |= {f"CAL_MAG{k}_{a}OFF": 0.0 for a in "XYZ"} | {f"CAL_MAG{k}_{a}SCALE": 1.0 for a in "XYZ"}
            p |= {f"CAL_MAG{k}_{a}ODIAG": 0.0 for a in "XYZ"}
        return p
    p = {"COMPASS_USE": 1.0, "COMPASS_CAL_FIT": 16.0, "COMPASS_OFFS_MAX": 1800.0, "COMPASS_AUTO_ROT": 2.0}
    for k in range(n_compasses):
        n = ap_suffix(k)
        p |= {f"COMPASS_ORIENT{n}": 0.0, f"COMPASS_EXTERN{n}" if k else "COMPASS_EXTERNAL": float(k == 0)}
        p |= {f"COMPASS_OFS{n}_{a}": 0.0 for a in "XYZ"} | {f"COMPASS_DIA{n}_{a}": 1.0 for a in "XYZ"}
        p |= {f"COMPASS_ODI{n}_{a}": 0.0 for a in "XYZ"} | {f"COMPASS_SCALE{n}": 1.0}
    return p


def _orientation(params: dict[str, float], autopilot: str, k: int) -> np.ndarray:
    key = f"CAL_MAG{k}_ROT" if autopilot == "px4" else f"COMPASS_ORIENT{ap_suffix(k)}"
    try:
        return rotation_enum_matrix(max(0, int(params.get(key, 0))))
    except ValueError:
        return np.eye(3)


def rotated_raw(params: dict[str, float], autopilot: str, k: int, raw_sensor_mG) -> np.ndarray:
    """The reading rotated into the body frame by the orientation parameter (no calibration)."""
    return _orientation(params, autopilot, k) @ np.asarray(raw_sensor_mG, float)


def corrected_field(params: dict[str, float], autopilot: str, k: int, raw_sensor_mG) -> np.ndarray:
    """What the autopilot reports for compass k (RAW_IMU / SCALED_IMU2 / SCALED_IMU3 mag)."""
    if autopilot == "px4":
        return apply_px4(np.asarray(raw_sensor_mG, float), params, k)
    return apply_ardupilot(rotated_raw(params, autopilot, k, raw_sensor_mG), params, k)


class _CompassCal:
    """One compass's calibrator state (ArduPilot CompassCalibrator, ground-visible parts)."""

    def __init__(self, tolerance_mG: float, offs_max_mG: float) -> None:
        self.tolerance_mG, self.offs_max_mG = tolerance_mG, offs_max_mG
        self.samples: list[np.ndarray] = []
        self._stacked: np.ndarray | None = None      # self.samples as one array, made again after a change
        self.status, self.thinned, self.radius = 2, 0, 200.0
        self.offsets, self.softiron = np.zeros(3), np.eye(3)
        self.sections: set[int] = set()
        self.report: dict | None = None

    def completion_pct(self) -> float:
        n = len(self.samples)
        if self.status == 2:
            return 33.3 * n / NUM_SAMPLES
        if self.status == 3:     # the share of the samples step two still needed after thinning
            kept = NUM_SAMPLES - self.thinned
            return 33.3 + 65.7 * max(0, n - kept) / max(1, NUM_SAMPLES - kept)
        return 100.0 if self.status == 4 else 0.0

    def _accept(self, v: np.ndarray) -> bool:
        if not self.samples:
            return True
        if self._stacked is None or len(self._stacked) != len(self.samples):
            self._stacked = np.asarray(self.samples)
        d = np.linalg.norm(self._stacked - v, axis=1)
        return bool(d.min() >= self.radius * 2 * math.sin(_THETA / 2))

    def _mark(self, vs: np.ndarray) -> None:
        corrected = (np.atleast_2d(vs) + self.offsets) @ self.softiron.T
        self.sections |= {int(s) for s in section_of(corrected) if s >= 0}

    def new_sample(self, v: np.ndarray) -> None:
        if self.status not in (2, 3) or len(self.samples) >= NUM_SAMPLES or not self._accept(v):
            return
        self.samples.append(v)
        self._mark(v)
        if len(self.samples) == NUM_SAMPLES:
            self._fit_step()

    def _fit_step(self) -> None:
        fit = fit_ellipsoid_robust(np.asarray(self.samples))
        if not fit.ok:
            self._finish(5, None)
            return
        _, S = polar_decomposition(fit.matrix)
        S = S / np.cbrt(np.linalg.det(S))
        self.offsets, self.softiron = -fit.offsets_mG, S
        self.radius = float(np.mean(np.linalg.norm((np.asarray(self.samples) + self.offsets) @ S.T, axis=1)))
        if self.status == 2:               # thin with the fitted radius, go on collecting
            kept: list[np.ndarray] = []
            for v in self.samples:
                if not kept or np.linalg.norm(np.asarray(kept) - v, axis=1).min() >= self.radius * 2 * math.sin(_THETA / 2):
                    kept.append(v)
            self.thinned = len(self.samples) - len(kept)
            self.samples, self.status, self.sections = kept, 3, set()
            self._stacked = None
            self._mark(np.asarray(kept))
            return
        residual = self.radius - np.linalg.norm((np.asarray(self.samples) + self.offsets) @ S.T, axis=1)
        self._finish(4, float(np.sqrt(np.mean(residual ** 2))))

    def _finish(self, status: int, fitness: float | None) -> None:
        S, ofs = self.softiron, self.offsets
        ok = (status == 4 and fitness is not None and 150 < self.radius < 950
              and np.all(np.abs(ofs) < self.offs_max_mG) and np.all((np.diag(S) > 0.2) & (np.diag(S) < 5))
              and abs(S[0, 1]) < 1 and abs(S[0, 2]) < 1 and abs(S[1, 2]) < 1 and fitness <= self.tolerance_mG)
        self.status = 4 if ok else 5
        self.report = {"fitness": fitness if fitness is not None else 1e3, "ofs": ofs.copy(),
                       "diag": np.diag(S).copy(), "offdiag": np.array([S[0, 1], S[0, 2], S[1, 2]])}


class OnboardCalibrator:
    """MAV_CMD_DO_START_MAG_CAL … DO_ACCEPT_MAG_CAL / DO_CANCEL_MAG_CAL for up to three compasses."""

    def __init__(self) -> None:
        self.cals: dict[int, _CompassCal] = {}
        self.mask = 0

    @property
    def active(self) -> bool:
        return bool(self.cals)

    def start(self, mask: int, n_compasses: int, params: dict[str, float]) -> None:
        fit = float(params.get("COMPASS_CAL_FIT", 16.0))
        offs_max = float(params.get("COMPASS_OFFS_MAX", 1800.0))
        wanted = [k for k in range(n_compasses) if mask == 0 or (mask >> k) & 1]
        # the first compass, when external, gets COMPASS_CAL_FIT; the others twice (AP_Compass_Calibration)
        self.cals = {k: _CompassCal(fit if (k == 0 and params.get("COMPASS_EXTERNAL", 1.0)) else 2 * fit, offs_max)
                     for k in wanted}
        self.mask = sum(1 << k for k in wanted)

    def new_sample(self, k: int, rot_raw_mG: np.ndarray) -> None:
        cal = self.cals.get(k)
        if cal is not None:
            cal.new_sample(np.asarray(rot_raw_mG, float))

    def progress_fields(self) -> list[tuple]:
        """MAG_CAL_PROGRESS arguments of every compass still running."""
        out = []
        for k, c in self.cals.items():
            if c.status in (2, 3):
                out.append((k, self.mask, c.status, 1, max(0, min(100, int(c.completion_pct()))),
                            mask_from_sections(c.sections),
                            0.0, 0.0, 0.0))
        return out

    def report_fields(self, params: dict[str, float]) -> list[tuple]:
        """MAG_CAL_REPORT arguments of every compass that finished."""
        out = []
        for k, c in self.cals.items():
            if c.report is None:
                continue
            r = c.report
            orient = int(params.get(f"COMPASS_ORIENT{ap_suffix(k)}", 0))
            out.append((k, self.mask, c.status, 0, float(r["fitness"]), *map(float, r["ofs"]), *map(float, r["diag"]),
                        *map(float, r["offdiag"]), 0.0, orient, orient, 0.0))
        return out

    def accept(self, mask: int) -> dict[str, float] | None:
        """Parameters of the successful compasses in the mask; None if one of them did not succeed."""
        out: dict[str, float] = {}
        for k, c in list(self.cals.items()):
            if mask and not (mask >> k) & 1:
                continue
            if c.status != 4 or c.report is None:
                return None
            n = ap_suffix(k)
            for i, a in enumerate("XYZ"):
                out[f"COMPASS_OFS{n}_{a}"] = float(c.report["ofs"][i])
                out[f"COMPASS_DIA{n}_{a}"] = float(c.report["diag"][i])
                out[f"COMPASS_ODI{n}_{a}"] = float(c.report["offdiag"][i])
        self.cals.clear()
        return out

    def cancel(self) -> None:
        self.cals.clear()


def fixed_yaw_params(params: dict[str, float], k: int, corrected_mG: np.ndarray, roll_rad: float,
                     pitch_rad: float, yaw_deg: float, field_ned_mG: np.ndarray) -> dict[str, float]:
    """OFS/DIA/ODI of compass k after MAV_CMD_FIXED_MAG_CAL_YAW (Compass::mag_cal_fixed_yaw)."""
    expected = dcm_body_to_ned(roll_rad, pitch_rad, math.radians(yaw_deg)).T @ np.asarray(field_ned_mG, float)
    uncorrected = unapply_ardupilot(np.asarray(corrected_mG, float), params, k)   # M⁻¹·corrected − OFS
    ofs = expected - uncorrected
    n = ap_suffix(k)
    out = {f"COMPASS_OFS{n}_{a}": float(ofs[i]) for i, a in enumerate("XYZ")}
    out |= {f"COMPASS_DIA{n}_{a}": 1.0 for a in "XYZ"} | {f"COMPASS_ODI{n}_{a}": 0.0 for a in "XYZ"}
    return out
