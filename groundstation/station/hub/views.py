"""What readers get from the hub: the state snapshot, the 3-D scene's arrays, plots, the replay
timeline, downloads and the recordings list.  Mixed into ``Session``; every method takes the
hub lock and returns copies, safe to use outside it."""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from estimators.detection import ned_from_lla

from groundstation.jsonsafe import json_default, jsonable
from groundstation.jobs.record import COL
from groundstation.station.hub.display import plot_data, tests_snapshot, vehicle_snapshot
from groundstation.station.hub.sources import ConflictError, NotFoundError, SessionError

__all__ = ["SessionViews", "EVENTS_SHOWN"]

EVENTS_SHOWN = 15
DANCE_WINDOW_S = 20.0          # the replayed vehicle was turned past DANCE_TILT_DEG this recently: a dance
DANCE_TILT_DEG = 60.0


class SessionViews:
    """Reading side of ``Session`` (see module docstring)."""

    def snapshot(self) -> dict:
        with self._lock:
            now = time.time()
            src, flight = self.sources, self.flight
            row = flight.last_row()
            path = src.log_path
            return {
                "version": self.version,
                "wall_unix_s": now,
                "t_s": round(flight.t_s, 3),
                "rx_count": src.rx_count,
                "rx_age_s": None if src.rx_last_unix is None else round(now - src.rx_last_unix, 3),
                "source": src.source_snapshot(self.vehicle.autopilot),
                "replay": src.replay_snapshot(),
                "analysing": src.kind == "replay" and flight.review is None,
                "reorder_delay_s": round(flight.reorder.delay_s, 2),
                "vehicle": dict(vehicle_snapshot(row), attitude_source=flight.attitude_source()),
                "alarm": flight.alarm_snapshot(),
                "alarm_count": len(flight.tracker.alarms),
                "line": flight.line,
                "calibration_in_use": self.calibration.in_use(),
                "calibration_choice": self.in_use.snapshot(),
                "tests": tests_snapshot(row, flight.policy, flight.line),
                "downloads": {"log": path.name if path is not None and path.is_file() else None,
                              "tlog": path is not None and path.suffix.lower() == ".tlog" and path.is_file()},
                "wizard": self.calibration.snapshot(),
                "events": list(self.events)[-EVENTS_SHOWN:],
            }

    def snapshot_json(self) -> str:
        """The snapshot as JSON, built once per state version whatever the number of clients."""
        with self._lock:
            cache = self._json_cache
            if cache is not None and cache[0] == self.version:
                return cache[1]
            text = json.dumps(self.snapshot(), allow_nan=False, default=json_default)
            self._json_cache = (self.version, text)
            return text

    def scene_data(self) -> dict:
        """Arrays for the 3-D view."""
        with self._lock:
            flight = self.flight
            row = flight.last_row()
            rad = (lambda name: math.nan if row is None else math.radians(row[COL[name]]))  # noqa: E731
            route = flight.route().copy()
            origin = flight.origin()
            alarm = flight.alarm_snapshot()
            rows = flight.rows()
            recent = rows[rows[:, COL["t_s"]] >= rows[-1, COL["t_s"]] - DANCE_WINDOW_S] if len(rows) else rows
            tilts = np.abs(recent[:, [COL["roll_deg"], COL["pitch_deg"]]]) if len(recent) else np.zeros((0, 2))
            # a flying vehicle does not roll or pitch past 60°: a dance (turned over by hand) does
            dancing = self.sources.kind == "replay" and bool(np.any(np.nan_to_num(tilts) > DANCE_TILT_DEG))
            return {
                "att": (rad("roll_deg"), rad("pitch_deg"), rad("heading_deg")),
                "ap_att": (rad("ap_roll_deg"), rad("ap_pitch_deg"), rad("ap_heading_deg")),
                **self.calibration.scene_data(dancing),      # cloud, fit, calibrating, coverage
                "route": _route_ne(route, origin),
                "anomalies": _places_ne(flight.anomaly_places(), origin),
                "line": flight.line,
                "origin": origin,
                "alarm": alarm["active"],
                "alarm_text": ", ".join(alarm["evidence"]),
            }

    def alarm_list(self) -> list[dict]:
        with self._lock:
            return self.flight.alarm_list()

    def plot_data(self, window_s: float = 60.0) -> dict:
        """The plots' data: the last ``window_s`` of the flight record (see hub.display)."""
        with self._lock:
            rows = self.flight.rows()
            t = rows[:, COL["t_s"]] if len(rows) else np.zeros(0)
            start = int(np.searchsorted(t, t[-1] - window_s, side="left")) if len(t) else 0
            part = rows[start:].copy()
            alarms = self.flight.tracker.snapshot()
            ef = self.flight.earth_field()
        return plot_data(part, alarms, ef, window_s)

    def timeline(self) -> dict:
        """The replay's whole-log markers (alarms, GPS outages, data gaps, vehicle messages)."""
        with self._lock:
            r = self.sources.replay
            review = self.flight.review
            if r is None:
                raise ConflictError("no replay running")
            return {"duration_s": round(r.duration_s, 2), "ready": review is not None,
                    "markers": [dict(m) for m in review.markers] if review is not None else []}

    # ------------------------------------------------------------------ downloads
    def session_tlog(self) -> Path:
        with self._lock:
            self.sources.flush_recording()
            path = self.sources.recording_path
            if path is None or not path.is_file():
                raise NotFoundError("this session has no .tlog: replays of .bin/.ulg/.csv files are not MAVLink "
                                    "(download the log itself), and a live link records from its first packet")
            return path

    def session_file(self) -> Path:
        """The session's log in its own format: the live recording or the replayed file."""
        with self._lock:
            self.sources.flush_recording()
            path = self.sources.log_path
            if path is None or not path.is_file():
                raise NotFoundError("no log yet: replay a recording, or wait for the live link's first packet")
            return path

    def analysis(self) -> tuple[dict, dict]:
        """analyze_log on the session's log (the live recording or the replayed file), with the
        calibration and preset line in use."""
        from groundstation.io.errors import IngestError
        from groundstation.io.logs import read_log
        from groundstation.jobs.analyze import analyze_log

        with self._lock:
            src = self.sources
            src.flush_recording()
            path = src.log_path
            cal = self.flight.calibration
            line = self.flight.line
        if path is None or not path.is_file():
            raise ConflictError("no session to analyse: replay a recording, or connect and wait for packets")
        try:
            flight_log = read_log(path)
        except IngestError as err:
            raise SessionError(str(err)) from err
        mission = [(line["a"][0], line["a"][1], 0.0), (line["b"][0], line["b"][1], 0.0)] if line else None
        report, table = analyze_log(flight_log, cal, mission)
        return jsonable(report), table

    # ------------------------------------------------------------------ recordings
    def recordings_info(self) -> list[dict]:
        with self._lock:
            live = self.sources.recording_path if self.sources.kind == "live" else None
        return self.recordings.info(recording_now=live)


def _places_ne(places: list[tuple[float, float]], origin) -> np.ndarray:
    """(lat, lon) places -> (n, 2) [north_m, east_m] about ``origin``."""
    if not places or origin is None:
        return np.zeros((0, 2))
    lat, lon = np.array(places, dtype=float).T
    return np.c_[ned_from_lla(lat, lon, origin[0], origin[1])]


def _route_ne(route: np.ndarray, origin) -> np.ndarray:
    """GPS fixes [t, lat, lon, fix, alarm] -> [t, north_m, east_m, alarm] about ``origin``."""
    if not len(route) or origin is None:
        return np.zeros((0, 4))
    n, e = ned_from_lla(route[:, 1], route[:, 2], origin[0], origin[1])
    return np.c_[route[:, 0], n, e, route[:, 4]]
