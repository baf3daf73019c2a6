"""Flight state of the live view: the per-sample estimation stack and what the page shows of it.

``EstimationStack`` runs the heading chain and interference detector per sample
(``groundstation.jobs.live.LiveAnalyzer``, the per-sample twin of ``magstation analyze``) and
adds what the display needs: the autopilot's attitude, forward/lateral velocity, signed
cross-track, field strength.  ``FlightState`` owns the stack plus the route, plot history,
alarm list and GPS-outage watch, and turns samples into them.  Neither takes a lock: the hub
(``Session``) calls them under its own.
"""
from __future__ import annotations

import math
from collections import deque
from typing import Callable

import numpy as np

from estimators.calibration import apply_calibration
from estimators.detection import cross_track_m, ned_from_lla
from estimators.heading import split_velocity

from groundstation.jobs.live import LiveAnalyzer
from groundstation.jobs.navigation import OUTAGE_MIN_S
from groundstation.samples import (AttitudeSample, GpsSample, ImuSample, MagSample, Sample, finite_or_none)
from groundstation.station.tables import GrowingTable

__all__ = ["EstimationStack", "FlightState", "local_ne_m", "ROUTE_MAX_POINTS"]

ROUTE_MAX_POINTS = 20_000
HISTORY_ROWS = 600
HISTORY_STEP_S = 0.05

EventFn = Callable[..., None]


def local_ne_m(lat: float, lon: float, origin: tuple[float, float]) -> tuple[float, float]:
    """North/east metres of (lat, lon) from ``origin`` (the detector's local tangent plane)."""
    n, e = ned_from_lla(lat, lon, origin[0], origin[1])
    return float(n), float(e)


def _deg(rad: float | None) -> float | None:
    return None if rad is None or not math.isfinite(rad) else math.degrees(rad)


def signed_cross_track_m(lat: float, lon: float, line: dict) -> float:
    """Cross-track distance from the preset line A->B, + right of it (seed 002 eq. 6, signed)."""
    a, b = line["a"], line["b"]
    bn, be = local_ne_m(b[0], b[1], (a[0], a[1]))
    pn, pe = local_ne_m(lat, lon, (a[0], a[1]))
    d = float(cross_track_m(np.array([pn, pe, 0.0]), np.zeros(3), np.array([bn, be, 0.0]))[0])
    return math.copysign(d, bn * pe - be * pn)


class EstimationStack:
    """Per-sample heading chain and interference detection for the live view."""

    def __init__(self) -> None:
        self.calibration: dict | None = None   # in use: accepted wizard result or the log's own fit
        self.line: dict | None = None
        self.start_unix_s: float | None = None
        self.reset()

    def reset(self) -> None:
        """Start over (new source, seek, new calibration): the detector re-learns its noise."""
        self.roll_rad = self.pitch_rad = self.yaw_rad = math.nan
        self.ap_rpy_rad = (math.nan, math.nan, math.nan)
        self.heading_mag_deg = math.nan
        self.heading_att_deg = math.nan
        self.v_forward_mps = self.v_lateral_mps = math.nan
        self.cross_track_m = math.nan
        self.field_mG = math.nan
        self.lat_deg = self.lon_deg = math.nan
        self.fix_type = 0
        self.alarm_active = False
        self.alarm_kinds: list[str] = []
        self.analyzer = LiveAnalyzer(self.calibration, self._mission(), self.start_unix_s)

    def _mission(self) -> list | None:
        return [tuple(self.line["a"]), tuple(self.line["b"])] if self.line else None

    def set_line(self, line: dict | None) -> None:
        self.line = line
        self.analyzer.set_mission(self._mission())

    def set_calibration(self, calibration: dict | None) -> None:
        self.calibration = calibration
        self.reset()

    @property
    def detector(self):
        return self.analyzer.detector

    @property
    def declination_deg(self) -> float:
        return float(self.analyzer.chain.declination_deg)

    def calibrated(self, mag_mG: tuple[float, float, float]) -> np.ndarray:
        m = np.asarray(mag_mG, dtype=float)
        cal = self.calibration
        if cal and cal.get("offsets_mG") is not None and cal.get("matrix") is not None:
            return apply_calibration(m, np.asarray(cal["offsets_mG"], dtype=float), np.asarray(cal["matrix"], dtype=float))
        return m

    def on_sample(self, s: Sample) -> None:
        self.analyzer.on_sample(s)
        if isinstance(s, AttitudeSample):
            self.ap_rpy_rad = (s.roll_rad, s.pitch_rad, s.yaw_rad)
        elif isinstance(s, MagSample):
            m = self.calibrated(s.mag_body_mG)
            if np.all(np.isfinite(m)):
                self.field_mG = float(np.linalg.norm(m))
        elif isinstance(s, ImuSample):
            st = self.analyzer.last_state
            if st is not None and st.valid:
                self.roll_rad, self.pitch_rad, self.yaw_rad = st.roll_rad, st.pitch_rad, st.heading_true_rad
                self.heading_att_deg = math.degrees(st.heading_true_rad) % 360.0
                self.heading_mag_deg = (math.degrees(st.mag_heading_rad) + self.declination_deg) % 360.0
        elif isinstance(s, GpsSample):
            self.lat_deg, self.lon_deg, self.fix_type = s.lat_deg, s.lon_deg, s.fix_type
            vn, ve = s.vel_ned_mps[0], s.vel_ned_mps[1]
            if math.isfinite(vn) and math.isfinite(ve) and math.isfinite(self.heading_att_deg):
                fwd, lat = split_velocity(vn, ve, math.radians(self.heading_att_deg))
                self.v_forward_mps, self.v_lateral_mps = float(fwd), float(lat)
            if self.line is not None:
                self.cross_track_m = signed_cross_track_m(s.lat_deg, s.lon_deg, self.line)

    def vehicle_snapshot(self) -> dict:
        f = finite_or_none
        ap = self.ap_rpy_rad
        return {
            "roll_deg": f(_deg(self.roll_rad)), "pitch_deg": f(_deg(self.pitch_rad)), "yaw_deg": f(_deg(self.yaw_rad)),
            "ap_roll_deg": f(_deg(ap[0])), "ap_pitch_deg": f(_deg(ap[1])), "ap_yaw_deg": f(_deg(ap[2])),
            "heading_mag_deg": f(self.heading_mag_deg), "heading_att_deg": f(self.heading_att_deg),
            "v_forward_mps": f(self.v_forward_mps), "v_lateral_mps": f(self.v_lateral_mps),
            "cross_track_m": f(self.cross_track_m), "field_mG": f(self.field_mG),
            "lat_deg": f(self.lat_deg), "lon_deg": f(self.lon_deg), "fix_type": int(self.fix_type),
        }


class FlightState:
    """Everything the page shows about the flight so far; ``process`` feeds one sample."""

    def __init__(self, event: EventFn) -> None:
        self._event = event
        self.stack = EstimationStack()
        self.route = GrowingTable(4, ROUTE_MAX_POINTS)      # t_s, north_m, east_m, alarm(0/1)
        self.history: deque = deque(maxlen=HISTORY_ROWS)     # t_s, hdg_mag, hdg_att, vf, vl, xt
        self.reset()

    def reset(self) -> None:
        """Start the flight over (new source, seek, loop); the preset line and calibration stay."""
        self.stack.reset()
        self.route.clear()
        self.origin: tuple[float, float] | None = None
        self.history.clear()
        self._last_hist_t = -math.inf
        self.alarms: list[dict] = []
        self._primary: dict[str, int] = {}
        self.t_s = 0.0
        self._last_fix_t: float | None = None     # last 3-D GPS fix (t_s), for outage events
        self._gps_lost = False

    def accepts(self, s: Sample) -> bool:
        """One sensor instance each for mag and IMU (the lowest number seen: RAW_IMU/primary)."""
        if isinstance(s, (MagSample, ImuSample)):
            kind = type(s).__name__
            primary = self._primary.get(kind)
            if primary is None or s.instance < primary:
                self._primary[kind] = primary = s.instance
            return s.instance == primary
        return True

    def process(self, s: Sample) -> None:
        """Estimation, alarms, GPS watch, route and plot history for one sensor sample."""
        st = self.stack
        st.on_sample(s)
        det = st.detector
        if det is not None and isinstance(s, ImuSample):
            self._alarm_update(bool(det.alarm_active), list(det.alarm_kinds or []), finite_or_none(det.peak))
        self._watch_gps(s)
        if isinstance(s, GpsSample) and math.isfinite(s.lat_deg) and math.isfinite(s.lon_deg):
            if self.origin is None:
                self.origin = (s.lat_deg, s.lon_deg) if st.line is None else tuple(st.line["a"])
            n, e = local_ne_m(s.lat_deg, s.lon_deg, self.origin)
            self.route.append((s.t_s, n, e, 1.0 if st.alarm_active else 0.0))
        if s.t_s - self._last_hist_t >= HISTORY_STEP_S:
            self._last_hist_t = s.t_s
            self.history.append((s.t_s, st.heading_mag_deg, st.heading_att_deg, st.v_forward_mps,
                                 st.v_lateral_mps, st.cross_track_m))

    def _watch_gps(self, s: Sample) -> None:
        """Events when the 3-D GPS fix goes away while the IMU keeps streaming, and comes back
        (the same rule as ``analyze``'s GPS outages)."""
        if isinstance(s, GpsSample) and s.fix_type >= 3 and math.isfinite(s.lat_deg):
            if self._gps_lost:
                self._event(f"GPS fix back after {s.t_s - self._last_fix_t:.1f} s")
                self._gps_lost = False
            self._last_fix_t = s.t_s
        elif (isinstance(s, ImuSample) and not self._gps_lost and self._last_fix_t is not None
              and s.t_s - self._last_fix_t > OUTAGE_MIN_S):
            self._gps_lost = True
            self._event(f"GPS fix lost (last 3-D fix at {self._last_fix_t:.1f} s): the position and "
                        "path-deviation test are stale", "warning")

    def _alarm_update(self, active: bool, kinds: list[str], peak: float | None) -> None:
        st = self.stack
        if active and not st.alarm_active:
            self.alarms.append({"kind": "combined", "evidence": kinds, "start_s": round(self.t_s, 2),
                                "end_s": None, "peak": peak})
            self._event("INTERFERENCE ALARM: " + (", ".join(kinds) or "combined"), "alarm")
        elif active and self.alarms:
            a = self.alarms[-1]
            a["evidence"] = sorted(set(a["evidence"]) | set(kinds))
            if peak is not None:
                a["peak"] = max(a["peak"] or 0.0, peak)
        elif not active and st.alarm_active and self.alarms:
            self.alarms[-1]["end_s"] = round(self.t_s, 2)
            self._event("alarm cleared")
        st.alarm_active, st.alarm_kinds = active, kinds

    def alarm_snapshot(self) -> dict:
        st = self.stack
        return {"active": st.alarm_active, "evidence": list(st.alarm_kinds),
                "since_s": self.alarms[-1]["start_s"] if st.alarm_active and self.alarms else None}
