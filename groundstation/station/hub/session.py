"""The session hub: one lock and one state version over the source, the vehicle and the flight.

The parts each do one job (``sources.SourceControl``: live link or replay and its worker thread;
``recordings.RecordingsFolder``: the logs on disk; ``vehicle.VehicleLink``: autopilot identity,
parameters, confirmed writes; ``flight.FlightState``: the flight record, route and alarms, live or
replayed from one whole-log analysis (``review``, made beside the playing replay, which
shows the causal path's decisions until it is in); ``calibration.CalibrationControl``: the guided
calibration and writing its result).  ``Session`` owns the lock, the version and the event log, routes every
sample to the parts, and builds immutable snapshots for readers (``views.SessionViews``: the
WebSocket pusher, the viser scene, REST).  ``add_listener`` callbacks run on the worker thread
after each batch, so pushers wake without polling; a failing listener is logged.

A new source starts from a clean state: flight, alarms, events, wizard, preset line (the new
log's mission or none) and the vehicle's parameters all start over.  Everything a live link
receives and sends is recorded to ``recordings/session-*.tlog``, from its first packet.
Thread-safe: every public method may be called from any thread.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from pathlib import Path
from typing import Callable

from groundstation.samples import FlightLog, MissionSample, ParamSample, Sample, StatusSample
from groundstation.station.hub.calibration import CalibrationControl
from groundstation.station.hub.flight import FlightState
from groundstation.station.hub.in_use import CalibrationInUse
from groundstation.station.hub.recordings import RecordingsFolder
from groundstation.station.hub.param_watch import autopilot_change, on_compass_params_changed, param_trust
from groundstation.station.hub.review import build_review, log_own_calibration
from groundstation.station.hub.sources import (ConflictError, NotFoundError, SessionError, SourceControl,
                                               check_speed)
from groundstation.station.hub.vehicle import VehicleLink, passive_refusal
from groundstation.station.hub.views import SessionViews

__all__ = ["Session", "SessionError", "NotFoundError", "ConflictError"]

log = logging.getLogger(__name__)
EVENTS_KEPT = 200
DEFAULT_MAX_UPLOAD_BYTES = 512 * 1024 * 1024


class Session(SessionViews):
    """The hub.  Thread-safe; all public methods may be called from any thread."""

    def __init__(self, recordings_dir: str | Path = "recordings", record_live: bool = True,
                 max_upload_bytes: int = DEFAULT_MAX_UPLOAD_BYTES, link_options=None, forwarder=None) -> None:
        self._lock = threading.RLock()
        self._listeners: list[Callable[[], None]] = []
        self.version = 0
        self._json_cache: tuple[int, str] | None = None
        self.events: deque = deque(maxlen=EVENTS_KEPT)
        self.recordings = RecordingsFolder(Path(recordings_dir), max_upload_bytes)
        self.sources = SourceControl(self, self._lock, self.recordings, record_live, link_options, forwarder)
        self.vehicle = VehicleLink(self._lock)
        self.flight = FlightState(self.event)
        self.calibration = CalibrationControl(self._lock, self)
        self.in_use = CalibrationInUse(self)        # the calibration in use and where it came from
        self.log_calibration: dict | None = None
        self._log_mission: list | None = None
        self._review_generation = 0

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

    def event(self, text: str, level: str = "info", t_s: float | None = None) -> None:
        """An entry of the event log, at log time ``t_s`` (default: the flight's time now)."""
        with self._lock:
            t = self.flight.t_s if t_s is None else t_s
            self.events.append({"t_s": round(t, 2), "unix_s": time.time(), "level": level, "text": text})

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
        """Process samples as a live link's worker does (tests and tools feeding a session
        directly); everything fed is analysed, none waits for later samples."""
        with self._lock:
            self.process_batch(samples)
            self.flight.flush_all()
            self.changed()

    def process_batch(self, samples: list[Sample]) -> None:
        live = self.sources.kind != "replay"
        flight_samples = []
        changed_elsewhere: list[str] = []
        for s in samples:
            if isinstance(s, StatusSample) and s.kind == "vehicle":
                flight_samples = []            # the previous vehicle's samples go with its state
                self._new_vehicle(s)
                continue
            if isinstance(s, StatusSample):
                self._on_status(s)
            elif isinstance(s, ParamSample):
                if self.vehicle.on_param(s) and live:
                    why = autopilot_change(self.vehicle, self.sources.link, s.name, time.time())
                    if why is None:
                        changed_elsewhere.append(s.name)
                    else:
                        old, new = self.vehicle.changed_elsewhere[s.name]
                        self.vehicle.changed_by_itself(s.name, why)
                        self.event(f"{s.name} {old:g} -> {new:g} changed by the autopilot itself: {why}")
                if live and self.vehicle.params.get(s.name) == s.value:     # accepted into the cache
                    self.calibration.on_param(s.name, s.value)
            elif isinstance(s, MissionSample):
                if self._log_mission is None:
                    self.vehicle.on_mission_item(s)      # live: the mission comes item by item
            else:
                self.calibration.on_sample(s)           # every compass instance
            flight_samples.append(s)
        if live or self.flight.review is None:      # a replay being analysed: the causal path meanwhile
            self.flight.push(flight_samples)
        if changed_elsewhere:
            on_compass_params_changed(self, changed_elsewhere)
        self.calibration.after_batch()

    def flush_live(self) -> None:
        self.flight.flush_due()

    def _on_status(self, s: StatusSample) -> None:
        if s.kind == "autopilot":
            if s.text != self.vehicle.autopilot:
                self.event(f"vehicle autopilot: {s.text}")
            self.vehicle.autopilot = s.text
        elif s.kind == "link":
            up = s.text.startswith("link up")
            # the first download is on "vehicle_found" (the same batch may hold both); again when restored
            if up and self.sources.link_state == "lost" and getattr(self.sources.link, "sysid", None) is not None:
                self.vehicle.request_params(self.sources.link)
            if up and self.sources.link_state == "lost":
                self.event("link restored: " + s.text, "info")
            else:
                self.event(s.text, "info" if up else "warning")
            self.sources.link_state = "up" if up else "lost"
            self.calibration.on_link(up, s.t_s)
        elif s.kind == "statustext":
            self.event("vehicle: " + s.text)
        elif s.kind in ("passive", "signing", "param_refused", "reboot"):
            self.event(s.text, "warning")
        elif s.kind == "live_data":
            self.event(s.text, "info" if s.text.startswith("live data resumed") else "warning")
        elif s.kind == "mag_unit":
            self.event(s.text)
        elif s.kind == "vehicle_found":
            self.event(s.text)
            self.vehicle.request_params(self.sources.link)

    # ------------------------------------------------------------------ vehicles on the link
    def _new_vehicle(self, s: StatusSample) -> None:
        """The link follows another vehicle: flight, alarms, wizard and parameters start over
        (the events and the recording go on; lock held)."""
        self.flight.new_source(None)
        self.vehicle.reset(None, {})
        self.calibration.new_source()
        self.in_use.new_source()
        self.log_calibration = None
        self._log_mission = None
        self.event(s.text)
        if self.sources.link_state == "up":
            self.vehicle.request_params(self.sources.link)

    def select_vehicle(self, sysid: int) -> dict:
        """Follow vehicle ``sysid`` on the live link (from its next packets, with a clean state).

        Raises:
            ConflictError: no live link.  NotFoundError: no such vehicle heard on the link.
        """
        with self._lock:
            link = self.sources.link
            if link is None or self.sources.kind != "live":
                raise ConflictError("choosing a vehicle needs a live link")
            if int(sysid) not in link.roster.vehicles():
                heard = ", ".join(str(v) for v in link.roster.vehicles()) or "none yet"
                raise NotFoundError(f"no vehicle with system id {sysid} heard on the link (vehicles: {heard})")
            link.select(int(sysid))
            self.changed()
            return self.sources.vehicles_snapshot()

    def vehicles(self) -> dict:
        """The live link's systems, the followed vehicle, passive mode, signing, forwarding, and
        the compass parameters another ground station changed ({name: [old, new]})."""
        with self._lock:
            out = self.sources.vehicles_snapshot()
            out["params_changed_elsewhere"] = {k: list(v) for k, v in self.vehicle.changed_elsewhere.items()}
            out["param_trust"] = param_trust(self)
            return out

    def snapshot(self) -> dict:
        """The state; on a live link whose data stopped while the vehicle's heartbeats go on (a
        reboot, streams not sent), the vehicle shows no attitude (None) and says why
        (``vehicle.no_data``) rather than the last one, frozen."""
        with self._lock:
            snap = super().snapshot()
            snap["vehicles"] = self.vehicles()
            stale = getattr(self.sources.link, "stale_reason", None) if self.sources.kind == "live" else None
            if stale:
                snap["vehicle"] = {k: {"fix_type": 0, "fix_name": "no GPS"}.get(k) for k in snap["vehicle"]}
            snap["vehicle"]["no_data"] = f"no attitude data: {stale}" if stale else None
            return snap

    def restart_flight(self) -> None:
        """The flight starts over (a replay looped); the preset line and calibration stay."""
        if self.flight.review is not None:
            self.flight.show_until(0.0, seek=True)
        else:
            self.flight.reset()

    # ------------------------------------------------------------------ sources
    def connect(self, url: str) -> None:
        """Open a live link (pymavlink connection string), recorded to recordings/ from its
        first packet.  With a source running, that source goes on until the link hears the
        vehicle; a link that cannot open changes nothing."""
        url, link, recording = self.sources.open_link(url)
        with self._lock:
            running = self.sources.kind != "none"
            if running:
                if self.wizard.waiting_for not in (None, url):      # its link is given up for this one
                    self.calibration.link_cancelled()
                self.sources.arm_pending(url, link, recording)
                self.event(f"connecting to {url}: {self.sources.name} goes on until the first packet arrives")
                self.changed()
                return
        self.switch_to_live(url, link, recording, [])

    def switch_to_live(self, url: str, link, recording, samples: list[Sample]) -> None:
        self.sources.stop()
        with self._lock:
            # a calibration started while this link was connecting is meant for its vehicle; a
            # result not yet on a vehicle stays for the new link (reconnect, then write it)
            meant, mode = self.wizard.waiting_for == url and self.wizard.state == "running", self.wizard.mode
            self._new_source(None, None, {}, None, keep_wizard=self.calibration.unwritten_result())
            self.sources.start_live(url, link, recording)
            self.event(f"listening on {url}" + (", recording from the first packet" if recording else ""))
            if samples:
                self.process_batch(samples)      # its first packets: link up, the vehicle found
            if meant:
                self.calibration.start_on_new_link(mode, url)
            self.changed()

    def start_replay(self, path: str | Path, speed: float = 1.0, loop: bool = False,
                     flight_log: FlightLog | None = None) -> None:
        """Replay a log paced at real time x speed (any format read_log understands);
        ``flight_log``: the log of ``path`` already read (tools, benchmarks)."""
        path = Path(path)
        flight_log, replayer = self.sources.load_replay(path, speed, loop, flight_log)
        self.sources.cancel_pending()
        self.sources.stop()
        with self._lock:
            self._new_source(flight_log.start_unix_s, flight_log.autopilot, flight_log.params,
                             list(flight_log.mission))
            self._line_from_log_mission(flight_log)
            self.sources.start_replay(path, flight_log, replayer)
            length = ("from its first part while the rest is read" if replayer.more_to_come else
                      f"({replayer.duration_s:.0f} s)")
            self.event(f"replaying {path.name} {length} at x{speed:g}: analysing it meanwhile", t_s=0.0)
            if not len(flight_log.mag):
                self.event(f"{path.name} has no magnetometer samples: no heading, calibration or "
                           "interference tests for this log", level="warning", t_s=0.0)
            self.changed()

    def _line_from_log_mission(self, flight_log: FlightLog) -> None:
        if len(flight_log.mission) >= 2:
            self.flight.set_line({"a": [float(v) for v in flight_log.mission[0][:2]],
                                  "b": [float(v) for v in flight_log.mission[-1][:2]], "source": "mission"})
            self.event("preset line set from the log's mission", t_s=0.0)

    def whole_replay_read(self, flight_log: FlightLog) -> None:
        """A replay playing from the first part of its file has the whole file now (lock held):
        a mission found after that part sets the preset line, as one at the start does."""
        if flight_log.mission and not self._log_mission:
            self._log_mission = list(flight_log.mission)
            if self.flight.line is None:
                self._line_from_log_mission(flight_log)

    def _new_source(self, start_unix_s: float | None, autopilot: str | None, params: dict,
                    mission: list | None, keep_wizard: bool = False) -> None:
        """Everything of the previous source goes (lock held); ``keep_wizard``: a calibration the
        operator started for this source while it was connecting stays."""
        self.events.clear()
        self.flight.new_source(start_unix_s)
        self.vehicle.reset(autopilot, params)
        if not keep_wizard:
            self.calibration.new_source()
        elif self.calibration.unwritten_result():
            self.event("the calibration result is kept for this link: accept writes it to the vehicle")
        self.log_calibration = None
        self.in_use.new_source()
        self._log_mission = mission
        self._review_generation += 1

    def prepare_replay(self, flight_log: FlightLog) -> tuple:
        """Without the lock: the log's own calibration (if it has a calibration dance) and the
        whole-log analysis with it and the preset line."""
        params_note = self.in_use.fill_params(flight_log)         # serve --params
        if params_note:
            self.event(f"parameters: {params_note}", t_s=0.0)
        own = log_own_calibration(flight_log)
        with self._lock:
            line = self.flight.line
            path = self.sources.replay_path
        choice = self.in_use.for_replay(flight_log, path, own)   # own dance, else the airframe's stored choice
        calibration = (choice or {}).get("calibration")
        return calibration, line, build_review(flight_log, calibration, line), choice, own

    def start_review(self, prepared: tuple) -> None:
        calibration, line, review, choice, own = prepared
        self.in_use.start(choice, own)
        if calibration is not None and calibration is own:
            self.log_calibration = calibration
            self.event(f"using the calibration fitted to this log (residual "
                       f"{calibration.get('residual_rms_mG') or 0:.1f} mG)", t_s=0.0)
        live_calibration = self.flight.calibration
        self.flight.calibration = calibration
        r = self.sources.replay
        self.flight.load_review(review, min(r.position_s, r.duration_s) if r is not None else 0.0)
        self.event("replay analysed: alarms, timeline and the finished log's attitude from here on"
                   + ("" if calibration is live_calibration else
                      " (the alarms so far recomputed with the calibration chosen for it)"))
        if line != self.flight.line:          # the line changed while the log was analysed
            self._review_again()

    def replay_moved(self, t_s: float) -> bool:
        f = self.flight
        if f.review is None:
            return False
        before = (f.n_shown, f.gps_shown)
        f.show_until(t_s)
        return (f.n_shown, f.gps_shown) != before

    def use_calibration(self, calibration: dict | None) -> None:
        """The calibration headings and detection use from now on (lock held); a replay is
        analysed again with it."""
        self.flight.set_calibration(calibration)
        self._review_again()

    def _review_again(self) -> None:
        """Analyse the replayed log again with the current calibration and line (in the
        background; the replay keeps its place)."""
        r = self.sources.replay
        if r is None or not self.flight.needs_review():
            return
        self._review_generation += 1
        gen, flog = self._review_generation, r.log
        calibration, line = self.flight.calibration, self.flight.line

        def run() -> None:
            review = build_review(flog, calibration, line)
            with self._lock:
                if gen != self._review_generation or self.sources.replay is not r:
                    return
                self.flight.load_review(review, min(r.position_s, r.duration_s))
                self.event("replay analysed again with the new calibration or preset line")
                self.changed()

        threading.Thread(target=run, daemon=True, name="review").start()

    def stop(self) -> None:
        with self._lock:
            name = self.sources.name
            self.sources.cancel_pending()
            self.calibration.link_cancelled()
        self.sources.stop()
        with self._lock:
            if name:
                self.event(f"stopped {name}")
            self.changed()

    def recording_names(self) -> list[str]:
        return self.recordings.names()

    def resolve_recording(self, name: str) -> Path:
        try:
            return self.recordings.resolve(name)
        except ValueError as err:
            raise SessionError(str(err)) from None
        except FileNotFoundError as err:
            raise NotFoundError(str(err)) from None

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
        """Move the replay to ``t_s``: route, alarms, plots and vehicle as they were then."""
        with self._lock:
            self.sources.seek(t_s)
            t_s = min(t_s, self.sources.replay.duration_s)
            if self.flight.review is None:       # still analysing: the causal path starts over there
                self.flight.reset()
            self.flight.show_until(t_s, seek=True)
            self.event(f"seek to {t_s:.1f} s ({len(self.flight.tracker.alarms)} alarms so far)", t_s=t_s)
            self.changed()

    # ------------------------------------------------------------------ calibration (hub/calibration.py)
    def wizard_start(self, mode: str = "guided") -> None:
        with self._lock:
            url = self.sources.connecting()
            running = self.wizard.state == "running"
            self.calibration.start(mode, connecting=url)
            r = self.sources.replay
            if r is not None and url is None and not running and mode != "fixed_yaw":
                # a recording cannot follow the steps: it plays its dance from the start, in order,
                # as a vehicle turned by hand would (started mid-log, step 1 met the tumble instead)
                self.replay_seek(0.0)
                r.resume()
                self.event("replay rewound to the start for the calibration: the wizard follows the recorded dance")

    def wizard_reset(self) -> None:
        self.calibration.reset()

    def wizard_finish_now(self) -> dict:
        return self.calibration.finish_now()

    def wizard_accept(self) -> dict:
        """Use the result for heading; on a live link write it to the vehicle (background).

        Raises:
            ConflictError: the link is passive (nothing may be sent): export the .param file.
        """
        link = self.sources.link
        if link is not None and link.passive:
            raise ConflictError(passive_refusal(link))
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
            self.flight.set_line({"a": a, "b": b, "source": source})
            self.event(f"preset line set from {source}")
            self._review_again()
            self.changed()
            return self.flight.line

    def clear_line(self) -> None:
        with self._lock:
            if self.flight.line is None:
                return
            self.flight.set_line(None)
            self.event("preset line cleared: no path-deviation test")
            self._review_again()
            self.changed()

    def line_from_mission(self) -> dict:
        with self._lock:
            wps = list(self._log_mission) if self._log_mission is not None else self.vehicle.mission_waypoints()
        if len(wps) < 2:
            raise ConflictError("no mission with at least two waypoints received")
        return self.set_line(wps[0][:2], wps[-1][:2], "mission")

    def close(self) -> None:
        self.sources.cancel_pending()
        self.sources.stop()
        if self.sources.forwarder is not None:
            self.sources.forwarder.close()
