"""The session hub: one lock and one state version over the source, the vehicle and the flight.

The parts each do one job (``sources.SourceControl``: live link or replay and its worker thread;
``vehicle.VehicleLink``: autopilot identity, parameters, confirmed writes; ``flight.FlightState``:
estimation, alarms, route and plots; ``calibration.CalibrationControl``: the guided calibration
and writing its result).  ``Session`` owns the lock, the version and the event log, routes every
sample to the parts, and builds immutable snapshots for readers (the WebSocket pusher, the viser
scene, REST).  ``add_listener`` callbacks run on the worker thread after each batch, so pushers
wake without polling; a failing listener is logged, never silently dropped.

Everything a live link receives is recorded to ``recordings/session-*.tlog`` as it arrives.
Thread-safe: every public method may be called from any thread.
"""
from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections import deque
from pathlib import Path
from typing import Callable

import numpy as np

from groundstation.jsonsafe import json_default, jsonable
from groundstation.samples import FlightLog, MissionSample, ParamSample, Sample, StatusSample
from groundstation.station.hub.calibration import CalibrationControl
from groundstation.station.hub.flight import FlightState
from groundstation.station.hub.sources import (ConflictError, NotFoundError, SessionError, SourceControl,
                                               check_speed)
from groundstation.station.hub.vehicle import VehicleLink

__all__ = ["Session", "SessionError", "NotFoundError", "ConflictError"]

log = logging.getLogger(__name__)
EVENTS_KEPT = 200
EVENTS_SHOWN = 15


class Session:
    """The hub.  Thread-safe; all public methods may be called from any thread."""

    def __init__(self, recordings_dir: str | Path = "recordings", record_live: bool = True) -> None:
        self._lock = threading.RLock()
        self._listeners: list[Callable[[], None]] = []
        self.version = 0
        self._json_cache: tuple[int, str] | None = None
        self.events: deque = deque(maxlen=EVENTS_KEPT)
        self.sources = SourceControl(self, self._lock, Path(recordings_dir).resolve(), record_live)
        self.vehicle = VehicleLink(self._lock)
        self.flight = FlightState(self.event)
        self.calibration = CalibrationControl(self._lock, self)
        self.log_calibration: dict | None = None
        self._log_mission: list | None = None

    # ------------------------------------------------------------------ listeners / events
    def add_listener(self, fn: Callable[[], None]) -> None:
        with self._lock:
            self._listeners.append(fn)

    def remove_listener(self, fn: Callable[[], None]) -> None:
        with self._lock:
            if fn in self._listeners:
                self._listeners.remove(fn)

    def changed(self) -> None:
        """A new state version; wakes the listeners (call with the lock held)."""
        self.version += 1
        for fn in list(self._listeners):
            try:
                fn()
            except Exception:
                log.exception("state listener %r failed", fn)

    def event(self, text: str, level: str = "info") -> None:
        with self._lock:
            self.events.append({"t_s": round(self.flight.t_s, 2), "unix_s": time.time(), "level": level, "text": text})

    @property
    def params(self) -> dict[str, float]:
        return self.vehicle.params

    @property
    def wizard(self):
        return self.calibration.wizard

    @property
    def replay(self):
        return self.sources.replay

    # ------------------------------------------------------------------ samples (lock held)
    def feed(self, samples: list[Sample]) -> None:
        """Process samples as a source worker does (tests and tools feeding a session directly)."""
        with self._lock:
            self.process_batch(samples)
            self.changed()

    def process_batch(self, samples: list[Sample]) -> None:
        for s in samples:
            self._process(s)
        self.calibration.after_batch()

    def _process(self, s: Sample) -> None:
        flight = self.flight
        flight.t_s = max(flight.t_s, s.t_s)
        if isinstance(s, StatusSample):
            self._on_status(s)
        elif isinstance(s, ParamSample):
            self.vehicle.on_param(s)
        elif isinstance(s, MissionSample):
            if self._log_mission is None:   # live: the mission comes item by item
                self.vehicle.on_mission_item(s)
        else:
            self.calibration.on_sample(s)       # every compass instance
            if flight.accepts(s):
                flight.process(s)

    def _on_status(self, s: StatusSample) -> None:
        if s.kind == "autopilot":
            self.vehicle.autopilot = s.text
            self.event(f"vehicle autopilot: {s.text}")
        elif s.kind == "link":
            up = s.text.startswith("link up")
            if up:
                self.vehicle.request_params(self.sources.link)
            if up and self.sources.link_state == "lost":
                self.event("link restored: " + s.text, "info")
            else:
                self.event(s.text, "info" if up else "warning")
            self.sources.link_state = "up" if up else "lost"
            self.calibration.on_link(up, s.t_s)
        elif s.kind == "statustext":
            self.event("vehicle: " + s.text)

    def restart_flight(self) -> None:
        """Estimators start over (samples were skipped); the preset line stays."""
        self.flight.reset()

    # ------------------------------------------------------------------ sources
    def connect(self, url: str) -> None:
        """Open a live link (pymavlink connection string) and record it to recordings/."""
        url, link, recorder, path = self.sources.open_link(url)
        self.sources.stop()
        with self._lock:
            self.flight.reset()
            self.vehicle.reset(None, {})
            self._new_source(start_unix_s=None, mission=None)
            self.sources.start_live(url, link, recorder, path)
            self.event(f"listening on {url}" + (f", recording to {path.name}" if path else ""))
            self.changed()

    def start_replay(self, path: str | Path, speed: float = 1.0, loop: bool = False) -> None:
        """Replay a log paced at real time x speed (any format read_log understands)."""
        path = Path(path)
        flight_log, replayer = self.sources.load_replay(path, speed, loop)
        self.sources.stop()
        with self._lock:
            self.flight.reset()
            self.vehicle.reset(flight_log.autopilot, flight_log.params)
            self._new_source(flight_log.start_unix_s, list(flight_log.mission))
            self.sources.start_replay(path, flight_log, replayer)
            if flight_log.mission and len(flight_log.mission) >= 2:
                self.set_line(flight_log.mission[0][:2], flight_log.mission[-1][:2], "mission")
            self.event(f"replaying {path.name} ({replayer.duration_s:.0f} s) at x{speed:g}")
            if not len(flight_log.mag):
                self.event(f"{path.name} has no magnetometer samples: no heading, calibration or "
                           "interference tests for this log", level="warning")
            self.changed()

    def _new_source(self, start_unix_s: float | None, mission: list | None) -> None:
        stack = self.flight.stack
        stack.start_unix_s = start_unix_s
        self.log_calibration = None
        stack.set_calibration(None)
        self._log_mission = mission

    @staticmethod
    def fit_log_calibration(flight_log: FlightLog) -> dict | None:
        """A replayed log that contains a calibration dance calibrates its own magnetometer
        (calibrate_log on the whole log; None unless the fit is 'ok')."""
        from groundstation.jobs.calibrate import calibrate_log

        if len(flight_log.mag) < 200:
            return None
        try:
            result = calibrate_log(flight_log)
        except Exception:
            log.exception("calibration of the replayed log failed")
            return None
        return jsonable(result) if result.get("status") == "ok" else None

    def use_log_calibration(self, calibration: dict) -> None:
        with self._lock:
            self.log_calibration = calibration
            self.flight.stack.set_calibration(calibration)
            self.event(f"using the calibration fitted to this log (residual "
                       f"{calibration.get('residual_rms_mG') or 0:.1f} mG)")

    def stop(self) -> None:
        with self._lock:
            name = self.sources.name
        self.sources.stop()
        with self._lock:
            if name:
                self.event(f"stopped {name}")
            self.changed()

    def recording_names(self) -> list[str]:
        return self.sources.recording_names()

    def resolve_recording(self, name: str) -> Path:
        return self.sources.resolve_recording(name)

    # ------------------------------------------------------------------ replay controls
    def replay_pause(self, paused: bool) -> None:
        with self._lock:
            r = self.sources.need_replay()
            r.pause() if paused else r.resume()
            self.event("replay paused" if paused else "replay resumed")
            self.changed()

    def replay_speed(self, speed: float) -> None:
        with self._lock:
            self.sources.need_replay().set_speed(check_speed(speed))
            self.changed()

    def replay_seek(self, t_s: float) -> None:
        with self._lock:
            self.sources.seek(t_s)
            self.restart_flight()
            self.flight.t_s = t_s
            self.event(f"seek to {t_s:.1f} s")
            self.changed()

    # ------------------------------------------------------------------ calibration (hub/calibration.py)
    def wizard_start(self, mode: str = "guided") -> None:
        self.calibration.start(mode)

    def wizard_reset(self) -> None:
        self.calibration.reset()

    def wizard_finish_now(self) -> dict:
        return self.calibration.finish_now()

    def wizard_accept(self) -> dict:
        """Use the result for heading; on a live link write it to the vehicle (background)."""
        return self.calibration.accept()

    # ------------------------------------------------------------------ preset line
    def set_line(self, a, b, source: str = "user") -> dict:
        a = [float(a[0]), float(a[1])]
        b = [float(b[0]), float(b[1])]
        for lat, lon in (a, b):
            if not (math.isfinite(lat) and math.isfinite(lon) and -90 <= lat <= 90 and -180 <= lon <= 180):
                raise SessionError("line points must be [lat, lon] in degrees")
        if a == b:
            raise SessionError("line points A and B must differ")
        with self._lock:
            self.flight.stack.set_line({"a": a, "b": b, "source": source})
            self.event(f"preset line set from {source}")
            self.changed()
            return self.flight.stack.line

    def line_from_mission(self) -> dict:
        with self._lock:
            wps = list(self._log_mission) if self._log_mission is not None else self.vehicle.mission_waypoints()
        if len(wps) < 2:
            raise ConflictError("no mission with at least two waypoints received")
        return self.set_line(wps[0][:2], wps[-1][:2], "mission")

    # ------------------------------------------------------------------ reading
    def snapshot(self) -> dict:
        with self._lock:
            now = time.time()
            src = self.sources
            stack = self.flight.stack
            return {
                "version": self.version,
                "wall_unix_s": now,
                "t_s": round(self.flight.t_s, 3),
                "rx_count": src.rx_count,
                "rx_age_s": None if src.rx_last_unix is None else round(now - src.rx_last_unix, 3),
                "source": src.source_snapshot(self.vehicle.autopilot),
                "replay": src.replay_snapshot(),
                "vehicle": stack.vehicle_snapshot(),
                "alarm": self.flight.alarm_snapshot(),
                "alarm_count": len(self.flight.alarms),
                "line": stack.line,
                "calibration_in_use": self.calibration.in_use(),
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
        """Arrays for the 3-D view (copies, safe to use outside the lock)."""
        with self._lock:
            flight, stack = self.flight, self.flight.stack
            return {
                "att": (stack.roll_rad, stack.pitch_rad, stack.yaw_rad),
                "ap_att": stack.ap_rpy_rad,
                "route": flight.route.view().copy(),
                "line": stack.line,
                "origin": flight.origin,
                "alarm": stack.alarm_active,
                "alarm_text": ", ".join(stack.alarm_kinds),
                "history": np.array(flight.history, dtype=float).reshape(-1, 6),
                **self.calibration.scene_data(),
            }

    def alarm_list(self) -> list[dict]:
        with self._lock:
            return [dict(a) for a in self.flight.alarms]

    def session_tlog(self) -> Path:
        with self._lock:
            self.sources.flush_recording()
            path = self.sources.recording_path
            if path is None or not path.is_file():
                raise NotFoundError("this session has no .tlog (replays of .bin/.ulg/.csv are not MAVLink)")
            return path

    def analysis(self) -> tuple[dict, dict]:
        """analyze_log on the session's log (the live recording or the replayed file)."""
        from groundstation.io.errors import IngestError
        from groundstation.io.logs import read_log
        from groundstation.jobs.analyze import analyze_log

        with self._lock:
            src = self.sources
            src.flush_recording()
            path = src.recording_path or (src.replay_path if src.replay else None)
            cal = self.flight.stack.calibration
            line = self.flight.stack.line
        if path is None:
            raise ConflictError("no session to analyse: connect or replay first")
        try:
            flight_log = read_log(path)
        except IngestError as err:
            raise SessionError(str(err)) from err
        mission = [(line["a"][0], line["a"][1], 0.0), (line["b"][0], line["b"][1], 0.0)] if line else None
        report, table = analyze_log(flight_log, cal, mission)
        return jsonable(report), table

    def close(self) -> None:
        self.sources.stop()
