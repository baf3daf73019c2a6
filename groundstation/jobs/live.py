"""The live twin of ``analyze_log``: the same heading chain and detector, one sample at a time."""
from __future__ import annotations

import time

import numpy as np

from estimators.detection import DetectionSettings, InterferenceDetector, field_inclination_deg
from estimators.geomag import decimal_year_from_unix, earth_field
from estimators.heading import HeadingChain
from estimators.rotations import wrap_angle_rad

from groundstation.io.params import unapply_onboard_calibration
from groundstation.jobs.inputs import (GPS_TIMEOUT_S, calibration_arrays, cross_track_legs, mission_legs,
                                       rotation_rate, too_steep, uncalibrated)
from groundstation.samples import AttitudeSample, GpsSample, ImuSample, MagSample, ParamSample, StatusSample

__all__ = ["LiveAnalyzer"]


class LiveAnalyzer:
    """Per-sample version of ``analyze_log`` (same chain, same detector) for the live server.

    Feed every sample with ``on_sample``; read ``alarm_active``, ``alarm_kinds`` (evidence names),
    ``peak`` and ``last_step``.  WMM reference and declination are fixed at the first GPS fix
    (date: ``start_unix_s`` or now).  ``set_calibration`` / ``set_mission`` may be called any time.
    """

    def __init__(self, calibration: dict | None = None, mission: list | None = None,
                 start_unix_s: float | None = None, settings: DetectionSettings | None = None) -> None:
        self.settings = settings or DetectionSettings()
        self.start_unix_s = start_unix_s
        self.cal = calibration_arrays(calibration)
        self.legs = mission_legs(mission)
        self.chain = HeadingChain()
        self.detector = InterferenceDetector(self.settings)
        self.earth_field = None
        self._mag: np.ndarray | None = None
        self._mag_t = -np.inf
        self._att: tuple[float, float, float] | None = None
        self._gps: tuple[float, float, bool] | None = None   # (t, cross-track, trusted)
        self.last_step = None
        self.last_state = None
        self.alarm_active = False
        self.alarm_kinds: list[str] = []
        self.peak: float | None = None
        self._last_steep = -np.inf
        self.params: dict[str, float] = {}
        self.autopilot: str | None = None
        self._imu_t: float | None = None
        self._imu_dt: float | None = None

    def set_calibration(self, calibration: dict | None) -> None:
        self.cal = calibration_arrays(calibration)

    def set_mission(self, mission: list | None) -> None:
        self.legs = mission_legs(mission)

    def _start(self, s: GpsSample) -> None:
        """Declination from the WMM at the first fix (detection itself does not need the WMM:
        the field checks compare against the offset learned over the clean start)."""
        start = self.start_unix_s if self.start_unix_s else time.time() - s.t_s
        try:
            ef = earth_field(s.lat_deg, s.lon_deg, s.alt_m, decimal_year_from_unix(start + s.t_s))
        except ValueError:
            return
        self.chain.declination_deg = ef.declination_deg
        self.earth_field = ef

    def on_sample(self, s) -> None:
        if isinstance(s, GpsSample):
            if self.earth_field is None:
                self._start(s)
            if self.legs:
                d = float(cross_track_legs(np.array([s.lat_deg]), np.array([s.lon_deg]), self.legs,
                                            self.legs[0][0])[0])
            else:
                d = float("nan")
            self._gps = (s.t_s, d, s.fix_type >= self.settings.rtk_min_fix)
        elif isinstance(s, AttitudeSample):
            self._att = (s.t_s, s.roll_rad, s.pitch_rad)
        elif isinstance(s, ParamSample):
            self.params[s.name] = s.value
        elif isinstance(s, StatusSample) and s.kind == "autopilot":
            self.autopilot = s.text
        elif isinstance(s, MagSample):
            m = np.asarray(s.mag_body_mG, dtype=float)
            if self.cal is not None:
                raw, _ = unapply_onboard_calibration(m[None, :], self.params, self.autopilot)
                m = self.cal[1] @ (raw[0] - self.cal[0])
            if np.all(np.isfinite(m)):
                self._mag, self._mag_t = m, s.t_s
                self.chain.update_mag(s.t_s, m)
        elif isinstance(s, ImuSample):
            st = self.chain.update_imu(s.t_s, np.asarray(s.gyro_rad_s), np.asarray(s.accel_mps2))
            t = st.t_s
            if self._imu_t is not None and t > self._imu_t:     # running mean IMU interval
                dt = t - self._imu_t
                self._imu_dt = dt if self._imu_dt is None else 0.95 * self._imu_dt + 0.05 * dt
            self._imu_t = t
            slow_imu = self._imu_dt is None or self._imu_dt > 1.0 / self.settings.min_imu_rate_hz
            e = float(wrap_angle_rad(st.mag_heading_rad - st.yaw_rad)) if st.valid and not slow_imu else float("nan")
            if self._mag is not None and t - self._mag_t <= GPS_TIMEOUT_S:
                if self._att is not None and t - self._att[0] <= 0.5:
                    r, p = self._att[1], self._att[2]
                else:
                    r, p = st.roll_rad, st.pitch_rad
                strength = float(np.linalg.norm(self._mag))
                incl = float(field_inclination_deg(self._mag, r, p))
            else:
                r, p = st.roll_rad, st.pitch_rad
                strength = incl = float("nan")
            if self.cal is None and uncalibrated(self):     # raw sensor: no field test
                strength = incl = float("nan")
            if too_steep(r, p, self.settings):
                self._last_steep = t
            if t - self._last_steep <= self.settings.turn_settle_s:
                e = strength = incl = float("nan")
            if self._gps is not None and t - self._gps[0] <= GPS_TIMEOUT_S:
                d, trusted = self._gps[1], self._gps[2]
            else:
                d, trusted = float("nan"), False
            yaw_rate = float(rotation_rate(np.asarray(s.gyro_rad_s, dtype=float)))
            step = self.detector.update(t, e, d, trusted, strength, incl,
                                        st.yaw_rad if st.valid else float("nan"), yaw_rate)
            self.last_step = step
            self.last_state = st       # the heading chain state (for the live display)
            self.alarm_active = self.detector.alarm_active
            self.alarm_kinds = list(self.detector.alarm_kinds)
            self.peak = self.detector.peak
