"""The guided calibration of every compass at once (the seed 004 handheld procedure, claim 3).

Steps: a full turn about body X, then Y, then Z, then a tumble until the field directions cover
``tumble_coverage`` of the sphere.  A step counts the net angle turned about its own body axis,
from the attitude (``progress.AxisProgress``), only while it is the current step.  Every compass
(``compass.CompassTrack``) collects its samples and keeps a live fit; at the end each is fitted
(``fit.fit_compass``: onboard calibration un-applied, robust ellipsoid, orientation, quality)
and the included ones are compared (``consistency``).  A link drop pauses the steps (``on_link``).

Modes: "guided" (our dance and fit), "onboard" (the vehicle's ArduPilot calibrator runs on the
same dance, ours beside it; ``onboard.OnboardCalibration``), "fixed_yaw" (large vehicles,
``largevehicle.FixedYawCalibration``).  After accepting: parameter write, reboot, heading check
(``aftercheck``), whose state the hub (station.hub.calibration) drives and this object holds.
"""
from __future__ import annotations

import math
import time
from collections import deque

import numpy as np

from estimators.calibration import coverage_cells
from estimators.geomag import decimal_year_from_unix, earth_field
from groundstation.io.decode import preferred_source
from groundstation.samples import AttitudeSample, GpsSample, ImuSample, MagSample, Sample, finite_or_none
from groundstation.station.tables import GrowingTable
from groundstation.station.wizard.compass import MAX_POINTS, CompassTrack, compass_index
from groundstation.station.wizard.coverage import body_field_directions, field_unit_ned, next_pose
from groundstation.station.wizard.param_check import CompassParamCheck
from groundstation.station.wizard.progress import AxisProgress
from groundstation.station.wizard.results import build_results, merged_result
from groundstation.station.wizard.settings import DEFAULT_SETTINGS, WizardSettings
from groundstation.station.wizard.texts import STEP_TEXT, instruction, live_warnings

__all__ = ["CalibrationWizard", "WIZARD_STEPS", "MODES"]

WIZARD_STEPS = ("x", "y", "z", "tumble")
RECENT_MAG_SAMPLES = 25
MODES = ("guided", "onboard", "fixed_yaw")


class CalibrationWizard:
    """Dance, per-compass fits and the after-write state.  Not thread-safe: the hub locks."""

    def __init__(self, settings: WizardSettings = DEFAULT_SETTINGS) -> None:
        self.settings = settings
        self.att = GrowingTable(4, MAX_POINTS * 2)       # t_s, roll, pitch, yaw (rad)
        self.imu = GrowingTable(7, MAX_POINTS * 4)       # primary IMU: t_s, gyro rad/s, accel m/s²
        self.gps = GrowingTable(8, 100_000)
        self.progress = AxisProgress(settings.still_window_s)
        self.reset()

    # ------------------------------------------------------------------ lifecycle
    def reset(self) -> None:
        self.state, self.mode = "idle", "guided"
        self.waiting_for: str | None = None  # started for a link still connecting: its name
        self.att.clear(); self.imu.clear(); self.gps.clear()
        self.progress.reset()
        self.tracks: dict[int, CompassTrack] = {}
        self.step_index = 0
        self.paused = False
        self.banner: dict | None = None
        self.cells = np.zeros(100, bool)
        self._cells_rows = 0
        self.field_ned_mG: np.ndarray | None = None
        self.declination_deg: float | None = None
        self.expected_field_mG: float | None = None
        self.results: dict[int, dict] = {}
        self.consistency: dict | None = None
        self.deviation: dict | None = None
        self.result: dict | None = None
        self.param_write: dict | None = None
        self.onboard = None                 # onboard.OnboardCalibration
        self.fixed_yaw = None               # largevehicle.FixedYawCalibration
        self.reboot: dict | None = None
        self.heading_check = None           # aftercheck.HeadingCheck
        self.in_use: str | None = None      # "station" | "vehicle"
        self.param_check = CompassParamCheck()   # the corrections in force, re-read (hub: param_watch)
        self._imu_instance: int | None = None
        self._fast_until = -math.inf
        self._last_gyro_deg_s = 0.0
        self._last_t = 0.0
        self._last_imu_t = 0.0
        self._lost_at: float | None = None
        self._coverage_at = -math.inf
        self.latest_att = (math.nan, math.nan, math.nan)
        self.latest_mag: dict[int, deque] = {}     # the last few samples of each compass (still vehicle)
        self.start_unix_s: float | None = None

    def start(self, mode: str = "guided") -> None:
        keep = (self.field_ned_mG, self.declination_deg, self.expected_field_mG)
        self.reset()
        self.field_ned_mG, self.declination_deg, self.expected_field_mG = keep
        self.mode = mode
        self.state = "running"
        self.start_unix_s = time.time()
        self.progress.set_axis(0 if mode != "fixed_yaw" else None)

    @property
    def step(self) -> str | None:
        if self.state == "idle":
            return None
        if self.state != "running":
            return "done"
        if self.mode == "fixed_yaw":
            return None
        return WIZARD_STEPS[min(self.step_index, 3)]

    # ------------------------------------------------------------------ samples
    def on_sample(self, s: Sample) -> None:
        if self.waiting_for is not None:  # the current source's vehicle is not the one meant
            return
        if self.state == "idle":          # nothing to collect: only the WMM field at the first fix
            if isinstance(s, GpsSample):
                self._on_gps(s)
            return
        self._dispatch(s)

    def _dispatch(self, s: Sample) -> None:
        self._last_t = max(self._last_t, s.t_s)
        if isinstance(s, MagSample):
            self._on_mag(s)
        elif isinstance(s, ImuSample):
            self._on_imu(s)
        elif isinstance(s, AttitudeSample):
            self._on_attitude(s)
        elif isinstance(s, GpsSample):
            self._on_gps(s)

    def _collecting(self) -> bool:
        return self.state == "running" and not self.paused and self.mode != "fixed_yaw"

    def _on_mag(self, s: MagSample) -> None:
        k = compass_index(s.instance)
        if k is None or not all(math.isfinite(v) for v in s.mag_body_mG):
            return
        track = self.tracks.get(k)
        if track is None or preferred_source(track.instance, s.instance) != track.instance:
            # RAW_IMU, SCALED_IMU and HIGHRES_IMU may all carry compass 1: keep the lowest heard
            # (the live analysis' rule), starting over when it comes after another one
            track = self.tracks[k] = CompassTrack(k, s.instance, self.settings)
            self.latest_mag.pop(k, None)
        if s.instance != track.instance:
            return
        recent = self.latest_mag.setdefault(k, deque(maxlen=RECENT_MAG_SAMPLES))
        recent.append(np.asarray(s.mag_body_mG, float))
        if self._collecting():
            track.on_mag(s.t_s, s.mag_body_mG)

    def _on_imu(self, s: ImuSample) -> None:
        self._imu_instance = preferred_source(self._imu_instance, s.instance)
        if s.instance != self._imu_instance or not self._collecting():
            return
        g = np.asarray(s.gyro_rad_s, float)
        if not np.all(np.isfinite(g)):
            return
        self.imu.append((s.t_s, *s.gyro_rad_s, *s.accel_mps2))
        self._last_imu_t = s.t_s
        self.progress.on_gyro(s.t_s, g)
        rate = float(np.linalg.norm(g))
        if rate > self.settings.too_fast_rad_s:
            self._fast_until = s.t_s + 1.0
            self._last_gyro_deg_s = math.degrees(rate)

    def _on_attitude(self, s: AttitudeSample) -> None:
        self.latest_att = (s.roll_rad, s.pitch_rad, s.yaw_rad)
        if not self._collecting():
            return
        self.att.append((s.t_s, s.roll_rad, s.pitch_rad, s.yaw_rad))
        self.progress.on_attitude(s.t_s, s.roll_rad, s.pitch_rad, s.yaw_rad)
        if s.t_s - self._coverage_at > 0.25:
            self._coverage_at = s.t_s
            self._update_cells()
            self.advance()

    def _on_gps(self, s: GpsSample) -> None:
        if self._collecting():
            self.gps.append((s.t_s, s.lat_deg, s.lon_deg, s.alt_m, *s.vel_ned_mps, s.fix_type))
        if self.field_ned_mG is None and s.fix_type >= 3 and math.isfinite(s.lat_deg):
            try:
                ef = earth_field(s.lat_deg, s.lon_deg, s.alt_m, decimal_year_from_unix(time.time()))
            except ValueError:
                return
            self.field_ned_mG, self.declination_deg = np.array(ef.field_ned_mG), ef.declination_deg
            self.expected_field_mG = ef.field_strength_mG
            self._cells_rows = 0                      # redo the coverage with the real field
            self.cells[:] = False

    def _update_cells(self) -> None:
        att = self.att.view()[self._cells_rows:]
        if len(att):
            d = body_field_directions(att[:, 1], att[:, 2], att[:, 3], field_unit_ned(self.field_ned_mG))
            self.cells |= coverage_cells(d)
            self._cells_rows = self.att.n

    @property
    def coverage(self) -> float:
        return float(self.cells.mean())

    def advance(self) -> None:
        """Count the queued attitude samples; the next step once the current one is complete."""
        self.progress.flush()
        s = self.settings
        if self.step_index < 3 and self.progress.progress_deg[self.step_index] >= s.turn_target_deg - s.turn_tolerance_deg:
            self.step_index += 1
            self.progress.set_axis(self.step_index if self.step_index < 3 else None)

    # ------------------------------------------------------------------ link drops
    def on_link(self, up: bool, t_s: float) -> str | None:
        """Pause on a drop, resume (short gap) or restart the step (long gap); the event text."""
        if self.state != "running" or self.mode == "fixed_yaw":
            return None
        self.advance()
        if not up and not self.paused:
            self.paused, self._lost_at = True, self._last_t
            step = self.step
            self.banner = {"level": "warning", "text": f"Link lost during step {STEP_TEXT[step]['short']}: calibration "
                           "paused. Keep the vehicle still; the step continues when the link returns."}
            return f"calibration paused: link lost during step {STEP_TEXT[step]['short']}"
        if up and self.paused:
            self.paused = False
            self.progress.gap()
            gap = max(0.0, t_s - (self._lost_at or t_s))
            step = STEP_TEXT[self.step]["short"]
            if gap > self.settings.resume_max_gap_s and self.step_index < 3:
                self.progress.restart_axis(self.step_index)
                text = f"link back after {gap:.0f} s: step {step} restarts (the turn was interrupted too long)"
            else:
                text = f"link back after {gap:.0f} s: step {step} resumes (the turn during the gap is not counted)"
            self.banner = {"level": "info", "text": text[0].upper() + text[1:] + "."}
            return "calibration " + text
        return None

    # ------------------------------------------------------------------ finishing
    def ready(self) -> bool:
        if self.state != "running" or self.paused:
            return False
        self.advance()
        if self.mode == "onboard":
            return self.onboard is not None and self.onboard.state in ("reported", "refused") and \
                self.primary_samples() >= 50
        return self.mode == "guided" and self.step_index >= 3 and self.coverage >= self.settings.tumble_coverage

    def primary_samples(self) -> int:
        t = self.tracks.get(0) or next(iter(self.tracks.values()), None)
        return 0 if t is None else int(t.mag.n)

    def finish(self, autopilot: str | None, params: dict[str, float]) -> dict:
        """Fit every compass; the wizard moves to 'result'."""
        self.results, self.consistency, self.deviation = build_results(self, autopilot or "ardupilot", dict(params))
        self.state = "result"
        self.banner = None
        self.rebuild_result(autopilot)
        return self.result

    def rebuild_result(self, autopilot: str | None = None) -> None:
        """The combined result of the included compasses (after finish, leaving one out, or a new
        fitness level)."""
        self.result = merged_result(self, autopilot or (self.result or {}).get("autopilot") or "ardupilot")

    # ------------------------------------------------------------------ reading
    def live_warnings(self) -> list[str]:
        return live_warnings(self)

    def hint(self) -> str | None:
        if not self._collecting() or self.mode == "fixed_yaw":
            return None
        rate = self.progress.rate_deg_s()
        if rate is not None and rate < self.settings.still_rate_deg_s:
            step = self.step
            return (f"No motion: the vehicle is still. {STEP_TEXT[step]['short'].capitalize()} now."
                    if step else "No motion.")
        return None

    def _current_direction(self) -> list[float] | None:
        """Unit field direction in the body frame now (from the latest attitude)."""
        roll, pitch, yaw = self.latest_att
        if self.state == "idle" or not all(math.isfinite(v) for v in self.latest_att):
            return None
        d = body_field_directions(roll, pitch, yaw, field_unit_ned(self.field_ned_mG))
        return [round(float(v), 3) for v in d]

    def snapshot(self) -> dict:
        if self.state == "running":
            self.advance()
        step = self.step
        primary = self.tracks.get(0)
        live = primary.live if primary is not None else None
        pose = next_pose(self.cells, field_unit_ned(self.field_ned_mG)) if self._collecting() and self.step_index >= 3 else None
        return {
            "state": self.state, "mode": self.mode, "paused": self.paused, "banner": self.banner,
            "waiting_for": self.waiting_for,
            "step": step, "step_index": self.step_index if self.state == "running" else (-1 if self.state == "idle" else 4),
            "instruction": instruction(self, pose), "hint": self.hint(),
            "progress_deg": {a: round(float(v), 1) for a, v in zip("xyz", self.progress.progress_deg)},
            "turn_target_deg": self.settings.turn_target_deg,
            "coverage": math.floor(self.coverage * 100) / 100, "coverage_target": self.settings.tumble_coverage,
            "coverage_cells": "".join("1" if c else "0" for c in self.cells),
            "next_pose": pose,
            "current_direction": self._current_direction(),
            "samples": self.primary_samples(),
            "live_offsets_mG": None if live is None else [round(float(v), 1) for v in live.offsets_mG],
            "live_field_mG": None if live is None else round(live.field_mG, 1),
            "expected_field_mG": finite_or_none(self.expected_field_mG),
            "declination_deg": finite_or_none(self.declination_deg),
            "warnings": self.live_warnings(),
            "compasses": [t.snapshot() for _, t in sorted(self.tracks.items())],
            "consistency": self.consistency, "deviation": self.deviation,
            "fitness_level": self.settings.fitness_level,
            "result": self.result, "param_write": self.param_write,
            "onboard": None if self.onboard is None else self.onboard.snapshot(),
            "fixed_yaw": None if self.fixed_yaw is None else self.fixed_yaw.snapshot(),
            "reboot": self.reboot,
            "heading_check": None if self.heading_check is None else self.heading_check.snapshot(),
            "in_use": self.in_use,
            "param_check": self.param_check.snapshot(),
            "settings": self.settings.as_dict(),
        }
