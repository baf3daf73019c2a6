"""Guided three-axis rotation calibration (seed 004 handheld procedure) for the live station.

The wizard collects raw magnetometer, IMU, attitude and GPS samples while the operator turns the
vehicle about X, Y and Z and tumbles it, shows live progress (degrees per axis from the gyro,
sphere coverage, the seed-000 RLS fit converging) and warnings, and at the end runs the batch
calibration of ``groundstation.jobs.calibrate`` to give the issue-3 result object.
"""
from __future__ import annotations

import math
import time

import numpy as np

from estimators.calibration import RlsEllipsoidCalibrator, rotation_progress_deg, sphere_coverage
from estimators.geomag import decimal_year_from_unix, earth_field

from groundstation.jsonsafe import jsonable
from groundstation.samples import AttitudeSample, FlightLog, GpsSample, ImuSample, MagSample, Sample, finite_or_none
from groundstation.station.tables import GrowingTable

MAX_CLOUD_POINTS = 200_000      # raw mag points kept for the fit (display decimates further)
WIZARD_STEPS = ("x", "y", "z", "tumble")
STEP_TEXT = {
    "x": "Hold the vehicle level, then turn it one full turn (360 deg) about its X axis "
         "(nose axis: roll it over).",
    "y": "Now turn it one full turn about its Y axis (right-wing axis: pitch it nose over tail).",
    "z": "Now turn it one full turn about its Z axis (vertical: yaw it round, flat).",
    "tumble": "Now tumble it slowly in every direction until the sphere is covered.",
    "done": "Done: check the result, then accept, export the parameters or redo.",
}
TURN_DEG = 360.0
TUMBLE_COVERAGE = 0.6
TOO_FAST_RAD_S = 3.0           # ~170 deg/s: samples get sparse and the IMU/mag timing skews
DISTURBANCE_FRACTION = 0.12     # |m_cal| off the fitted sphere by this much -> something nearby
WMM_MISMATCH_FRACTION = 0.15


# --------------------------------------------------------------------------- calibration wizard

class CalibrationWizard:
    """Guided three-axis rotation calibration (seed 004, handheld procedure, claim 3 step 11).

    Steps: full turn about X, then Y, then Z, then a tumble until the sphere is covered.  A
    step counts degrees turned about its own axis from the gyro (|omega_axis| dt), so a turn
    done early (before its step) still counts.  The live fit is the seed 000 RLS ellipsoid
    (per sample); at the end the robust fit of groundstation.jobs.calibrate runs on the
    collected samples and gives the result object of issue 3.
    """

    def __init__(self) -> None:
        self.state = "idle"
        self.mag = GrowingTable(4, MAX_CLOUD_POINTS)       # t_s, raw mx, my, mz (mG)
        self.imu = GrowingTable(7, MAX_CLOUD_POINTS * 8)
        self.att = GrowingTable(4, MAX_CLOUD_POINTS * 4)
        self.gps = GrowingTable(8, 100_000)
        self.reset()

    def reset(self) -> None:
        self.state = "idle"
        self.mag.clear(); self.imu.clear(); self.att.clear(); self.gps.clear()
        self.turned_deg = np.zeros(3)
        self.coverage = 0.0
        self.result: dict | None = None
        self.param_write: dict | None = None
        self.rls = None
        self._progress_at = -math.inf
        self.rls_estimate_cached = None
        self._fast_until = -math.inf
        self._disturbed_until = -math.inf
        self._last_t = 0.0
        self._coverage_at = -math.inf
        self.expected_field_mG: float | None = None
        self.warnings: list[str] = []

    def start(self) -> None:
        self.reset()
        self.state = "running"
        try:
            self.rls = RlsEllipsoidCalibrator(field_strength_mG=self.expected_field_mG or 500.0)
        except Exception:
            self.rls = None

    @property
    def step(self) -> str | None:
        if self.state == "idle":
            return None
        if self.state != "running":
            return "done"
        for i, axis in enumerate("xyz"):
            if self.turned_deg[i] < TURN_DEG:
                return axis
        return "tumble"

    def rls_estimate(self) -> tuple[np.ndarray, np.ndarray, float] | None:
        """(offsets_mG, matrix, field_mG) of the running seed 000 RLS fit once it is valid.

        The RLS model normalises by an assumed H0; the field it measures is H0 times the
        geometric mean of the fitted scales, and the matrix is rescaled so |C (m - b)| = field.
        """
        rls = self.rls
        if rls is None or self.mag.n < 50:
            return None
        try:
            if not rls.valid:
                return None
            off = np.asarray(rls.offsets_mG, dtype=float)
            scales = np.asarray(rls.scales, dtype=float)
            field = float(rls.field_strength_mG * np.cbrt(np.prod(scales)))
            matrix = np.diag(1.0 / scales) * (field / rls.field_strength_mG)
            if np.all(np.isfinite(off)) and np.all(np.isfinite(matrix)) and math.isfinite(field) and field > 0:
                return off, matrix, field
        except Exception:
            return None
        return None

    def on_sample(self, s: Sample) -> None:
        if self.state != "running":
            return
        self._last_t = s.t_s
        if isinstance(s, MagSample):
            if not all(math.isfinite(v) for v in s.mag_body_mG):
                return
            self.mag.append((s.t_s, *s.mag_body_mG))
            if self.rls is not None:
                try:
                    self.rls.update(np.asarray(s.mag_body_mG, dtype=float))
                except Exception:
                    pass
            est = self.rls_estimate_cached if self.mag.n > 300 else None
            if est is not None:
                off, matrix, field = est
                r = float(np.linalg.norm(matrix @ (np.asarray(s.mag_body_mG) - off)))
                if abs(r - field) > DISTURBANCE_FRACTION * field:
                    self._disturbed_until = s.t_s + 1.0
            if s.t_s - self._coverage_at > 0.25:
                self._coverage_at = s.t_s
                self._update_coverage()
        elif isinstance(s, ImuSample):
            g = np.asarray(s.gyro_rad_s, dtype=float)
            if not np.all(np.isfinite(g)):
                return
            self.imu.append((s.t_s, *s.gyro_rad_s, *s.accel_mps2))
            if s.t_s - self._progress_at > 0.2:
                self._progress_at = s.t_s
                imu = self.imu.view()
                self.turned_deg = rotation_progress_deg(imu[:, 1:4], imu[:, 0])
            if float(np.linalg.norm(g)) > TOO_FAST_RAD_S:
                self._fast_until = s.t_s + 1.0
        elif isinstance(s, AttitudeSample):
            self.att.append((s.t_s, s.roll_rad, s.pitch_rad, s.yaw_rad))
        elif isinstance(s, GpsSample):
            self.gps.append((s.t_s, s.lat_deg, s.lon_deg, s.alt_m, *s.vel_ned_mps, s.fix_type))
            if self.expected_field_mG is None:
                self.expected_field_mG = _expected_field(s.lat_deg, s.lon_deg, s.alt_m)

    def _update_coverage(self) -> None:
        """Sphere coverage of the field directions about the current centre (4 Hz, all points)."""
        pts = self.mag.view()[:, 1:4]
        self.rls_estimate_cached = est = self.rls_estimate()
        center = est[0] if est is not None else (pts.max(axis=0) + pts.min(axis=0)) / 2
        self.coverage = sphere_coverage(pts - center)

    def live_warnings(self) -> list[str]:
        out = []
        if self.state == "running":
            if self._last_t < self._fast_until:
                out.append("Turning too fast: slow down (under ~120 deg/s).")
            if self._last_t < self._disturbed_until:
                out.append("Magnetic disturbance: field strength jumped off the fitted sphere; "
                           "move away from metal, cars, power cables.")
        field = None
        if self.result is not None:
            field = self.result.get("field_strength_mG")
        elif self.rls_estimate_cached is not None:
            field = self.rls_estimate_cached[2]
        exp = self.expected_field_mG
        if self.result is not None and self.result.get("expected_field_mG"):
            exp = self.result["expected_field_mG"]
        if field and exp and abs(field - exp) > WMM_MISMATCH_FRACTION * exp:
            out.append(f"Field strength {field:.0f} mG is far from the WMM {exp:.0f} mG here: "
                       "nearby iron, or the sensor scale is off.")
        return out + self.warnings

    def ready(self) -> bool:
        return self.state == "running" and self.step == "tumble" and self.coverage >= TUMBLE_COVERAGE

    def finish(self, autopilot: str | None, params: dict[str, float]) -> dict:
        """Run the robust fit on what was collected; the wizard moves to 'result'."""
        log = FlightLog(source="calibration wizard", mag=self.mag.view().copy(),
                        imu=self.imu.view().copy(), attitude=self.att.view().copy(),
                        gps=self.gps.view().copy(), params=dict(params), autopilot=autopilot,
                        start_unix_s=time.time() - self._last_t)
        try:
            from groundstation.jobs.calibrate import calibrate_log
            result = calibrate_log(log)
        except ImportError:
            result = {"status": "error", "message": "calibration module not available yet"}
        except Exception as err:  # a fit failing must not take the station down
            result = {"status": "error", "message": f"fit failed: {type(err).__name__}: {err}"}
        result = jsonable(result)
        result.setdefault("samples", int(self.mag.n))
        if result.get("coverage") is None:
            result["coverage"] = self.coverage
        result["heading_error_deg"] = _heading_error_estimate(result, self.gps.view())
        self.result = result
        self.state = "result"
        return result

    def snapshot(self) -> dict:
        est = self.rls_estimate_cached
        step = self.step
        return {
            "state": self.state,
            "step": step,
            "step_index": (WIZARD_STEPS.index(step) if step in WIZARD_STEPS else
                           (len(WIZARD_STEPS) if step == "done" else -1)),
            "instruction": STEP_TEXT.get(step or "", "Press Start, then follow the steps."),
            "progress_deg": {a: round(float(min(v, 9999.0)), 1) for a, v in zip("xyz", self.turned_deg)},
            "turn_target_deg": TURN_DEG,
            "coverage": round(self.coverage, 3),
            "coverage_target": TUMBLE_COVERAGE,
            "samples": int(self.mag.n),
            "rls_offsets_mG": None if est is None else [round(float(v), 1) for v in est[0]],
            "rls_field_mG": None if est is None else round(est[2], 1),
            "expected_field_mG": finite_or_none(self.expected_field_mG),
            "warnings": self.live_warnings(),
            "result": self.result,
            "param_write": self.param_write,
        }


def _expected_field(lat: float, lon: float, alt: float) -> float | None:
    try:
        return earth_field(lat, lon, alt, decimal_year_from_unix(time.time())).field_strength_mG
    except ValueError:
        return None


def _heading_error_estimate(result: dict, gps: np.ndarray) -> float | None:
    """Heading error (deg) a field-magnitude residual of rms r gives: atan(r / H_horizontal).

    H_horizontal = F cos(inclination) from WMM at the first fix, else the fitted F with a
    mid-latitude 60 deg inclination.  A worst-case-direction bound, not a measurement.
    """
    r = finite_or_none(result.get("residual_rms_mG"))
    field = finite_or_none(result.get("expected_field_mG")) or finite_or_none(result.get("field_strength_mG"))
    if r is None or not field:
        return None
    incl = 60.0
    if len(gps):
        try:
            incl = earth_field(gps[0, 1], gps[0, 2], gps[0, 3], decimal_year_from_unix(time.time())).inclination_deg
        except ValueError:
            pass
    horizontal = field * math.cos(math.radians(incl))
    return round(math.degrees(math.atan2(r, max(horizontal, 1e-6))), 3)
