"""The session hub: one source (live link or replay) -> estimation stack per sample -> state.

One worker thread reads the source, feeds every sample through the estimators (calibration
wizard in ``groundstation.station.wizard``, heading chain, interference detection), and keeps the state
under a lock.  Readers
(the WebSocket pusher, the viser scene, REST) take snapshots; ``add_listener`` callbacks are
called from the worker thread after each batch, so pushers can wake up without polling.

Everything a live link receives is recorded to ``recordings/session-*.tlog`` as it arrives
(LiveLink writes the raw bytes, the hub flushes at least once a second).
"""
from __future__ import annotations

import json
import math
import threading
import time
from collections import deque
from pathlib import Path
from typing import Callable

import numpy as np

from estimators.calibration import apply_calibration
from estimators.detection import cross_track_m, ned_from_lla
from estimators.heading import split_velocity

from groundstation.jobs.analyze import OUTAGE_MIN_S, LiveAnalyzer
from groundstation.io.mavlink import mavlink2
from groundstation.samples import (AttitudeSample, FlightLog, GpsSample, ImuSample, MagSample, MissionSample,
                      ParamSample, Sample, StatusSample, finite_or_none)
from groundstation.station.wizard import CalibrationWizard, GrowingTable, jsonable

RECORDING_SUFFIXES = (".tlog", ".bin", ".ulg", ".csv")
ROUTE_MAX_POINTS = 20_000


class SessionError(Exception):
    """A request the session cannot honour (bad source, no result to accept ...): a 4xx."""


# ------------------------------------------------------------------------------- small helpers

def local_ne_m(lat: float, lon: float, origin: tuple[float, float]) -> tuple[float, float]:
    """North/east metres of (lat, lon) from ``origin`` (the detector's local tangent plane)."""
    n, e = ned_from_lla(lat, lon, origin[0], origin[1])
    return float(n), float(e)


def _deg(rad: float | None) -> float | None:
    return None if rad is None or not math.isfinite(rad) else math.degrees(rad)


# ------------------------------------------------------------------------------ estimator stack

class EstimationStack:
    """Per-sample heading chain and interference detection for the live view.

    The pipeline is groundstation.jobs.analyze.LiveAnalyzer (heading chain of seed 000 sec. 2,
    detector of seed 002), the per-sample twin of ``magstation analyze``, so live and batch
    agree.  This class adds what the display needs: the autopilot's attitude, forward/lateral
    velocity, signed cross-track, field strength.
    """

    def __init__(self) -> None:
        self.calibration: dict | None = None   # in use: accepted wizard result or the log's own fit
        self.line: dict | None = None
        self.start_unix_s: float | None = None
        self.reset()

    def reset(self) -> None:
        """Start over (new source, seek, new calibration): the detector re-learns its noise."""
        self.roll = self.pitch = self.yaw = math.nan
        self.ap = (math.nan, math.nan, math.nan)
        self.heading_mag_deg = math.nan
        self.heading_att_deg = math.nan
        self.v_forward = self.v_lateral = math.nan
        self.cross_track_m = math.nan
        self.field_mG = math.nan
        self.lat = self.lon = math.nan
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

    def calibrated(self, mag: tuple[float, float, float]) -> np.ndarray:
        m = np.asarray(mag, dtype=float)
        cal = self.calibration
        if cal and cal.get("offsets_mG") is not None and cal.get("matrix") is not None:
            return apply_calibration(m, np.asarray(cal["offsets_mG"], dtype=float), np.asarray(cal["matrix"], dtype=float))
        return m

    def on_sample(self, s: Sample) -> None:
        self.analyzer.on_sample(s)
        if isinstance(s, AttitudeSample):
            self.ap = (s.roll_rad, s.pitch_rad, s.yaw_rad)
        elif isinstance(s, MagSample):
            m = self.calibrated(s.mag_body_mG)
            if np.all(np.isfinite(m)):
                self.field_mG = float(np.linalg.norm(m))
        elif isinstance(s, ImuSample):
            st = self.analyzer.last_state
            if st is not None and st.valid:
                self.roll, self.pitch, self.yaw = st.roll_rad, st.pitch_rad, st.heading_true_rad
                self.heading_att_deg = math.degrees(st.heading_true_rad) % 360.0
                self.heading_mag_deg = (math.degrees(st.mag_heading_rad) + self.declination_deg) % 360.0
        elif isinstance(s, GpsSample):
            self.lat, self.lon, self.fix_type = s.lat_deg, s.lon_deg, s.fix_type
            vn, ve = s.vel_ned_mps[0], s.vel_ned_mps[1]
            if math.isfinite(vn) and math.isfinite(ve) and math.isfinite(self.heading_att_deg):
                fwd, lat = split_velocity(vn, ve, math.radians(self.heading_att_deg))
                self.v_forward, self.v_lateral = float(fwd), float(lat)
            if self.line is not None:
                self.cross_track_m = _cross_track_m(s.lat_deg, s.lon_deg, self.line)


def _cross_track_m(lat: float, lon: float, line: dict) -> float:
    a, b = line["a"], line["b"]
    bn, be = local_ne_m(b[0], b[1], (a[0], a[1]))
    pn, pe = local_ne_m(lat, lon, (a[0], a[1]))
    # seed 002 eq. (6), signed here (+ right of A->B) so the live plot shows the side
    d = float(cross_track_m(np.array([pn, pe, 0.0]), np.zeros(3), np.array([bn, be, 0.0]))[0])
    return math.copysign(d, bn * pe - be * pn)


# ------------------------------------------------------------------------------------- sources

class Session:
    """The hub.  Thread-safe; all public methods may be called from any thread."""

    def __init__(self, recordings_dir: str | Path = "recordings", record_live: bool = True) -> None:
        self.recordings_dir = Path(recordings_dir).resolve()
        self.record_live = record_live
        self._lock = threading.RLock()
        self._listeners: list[Callable[[], None]] = []
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.version = 0
        self._json_cache: tuple[int, str] | None = None
        self.source_kind = "none"
        self.source_name = ""
        self.link_state = "n/a"
        self.autopilot: str | None = None
        self.params: dict[str, float] = {}
        self.mission: dict[int, tuple[float, float, float]] = {}
        self.link = None
        self.recorder = None
        self.recording_path: Path | None = None
        self.replay = None   # groundstation.io.replay.Replayer while replaying
        self.replay_path: Path | None = None
        self.rx_count = 0
        self.rx_last_unix: float | None = None
        self.t_s = 0.0
        self.events: deque = deque(maxlen=200)
        self.alarms: list[dict] = []
        self.wizard = CalibrationWizard()
        self.stack = EstimationStack()
        self.route = GrowingTable(4, ROUTE_MAX_POINTS)        # t_s, north_m, east_m, alarm(0/1)
        self.origin: tuple[float, float] | None = None
        self.history = deque(maxlen=600)                   # plot rows (t_s, hdg_mag, hdg_att, vf, vl, xt)
        self._last_hist_t = -math.inf
        self._param_waiters: dict[str, list] = {}
        self._primary: dict[str, int] = {}
        self._last_fix_t: float | None = None
        self._gps_lost = False
        self._log_mission: list | None = None
        self._start_unix_s: float | None = None
        self.log_calibration: dict | None = None

    # ------------------------------------------------------------------ listeners / snapshots
    def add_listener(self, fn: Callable[[], None]) -> None:
        with self._lock:
            self._listeners.append(fn)

    def remove_listener(self, fn: Callable[[], None]) -> None:
        with self._lock:
            if fn in self._listeners:
                self._listeners.remove(fn)

    def _changed(self) -> None:
        self.version += 1
        for fn in list(self._listeners):
            try:
                fn()
            except Exception:
                pass

    def event(self, text: str, level: str = "info") -> None:
        with self._lock:
            self.events.append({"t_s": round(self.t_s, 2), "unix_s": time.time(), "level": level, "text": text})

    # ------------------------------------------------------------------------- sources
    def _stop_source(self) -> None:
        self._stop.set()
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout=5)
        self._thread = None
        if self.link is not None:
            self.link.close()
            self.link = None
        if self.recorder is not None:
            self.recorder.close()
            self.recorder = None
        self.replay = None
        self.source_kind, self.link_state = "none", "n/a"

    def stop(self) -> None:
        with self._lock:
            name = self.source_name
        self._stop_source()
        with self._lock:
            if name:
                self.event(f"stopped {name}")
            self._changed()

    def _reset_flight_state(self) -> None:
        self.stack.reset()
        self.route.clear()
        self.origin = None
        self.history.clear()
        self._last_hist_t = -math.inf
        self.alarms = []
        self._primary: dict[str, int] = {}
        self.t_s = 0.0
        self._last_fix_t: float | None = None     # last 3-D GPS fix (t_s), for outage events
        self._gps_lost = False

    def connect(self, url: str) -> None:
        """Open a live link (pymavlink connection string) and record it to recordings/."""
        from groundstation.io.errors import IngestError
        from groundstation.io.link import LiveLink, validate_connection_string
        from groundstation.io.mavlink import TlogWriter

        try:
            url = validate_connection_string(url)
        except IngestError as err:
            raise SessionError(str(err)) from err
        self._stop_source()
        recorder = None
        path = None
        if self.record_live:
            path = self.recordings_dir / time.strftime("session-%Y%m%d-%H%M%S.tlog", time.gmtime())
            n = 1
            while path.exists():
                path = path.with_name(f"{path.stem.split('_')[0]}_{n}.tlog"); n += 1
            recorder = TlogWriter(path)
        try:
            link = LiveLink(url, recorder=recorder)
        except IngestError as err:
            if recorder is not None:
                recorder.close()
                path.unlink(missing_ok=True)
            raise SessionError(str(err)) from err
        with self._lock:
            self._reset_flight_state()
            self.link, self.recorder, self.recording_path = link, recorder, path
            self.source_kind, self.source_name, self.link_state = "live", url, "waiting"
            self.autopilot = None
            self._start_unix_s = None
            self.stack.start_unix_s = None
            self.log_calibration = None
            self.stack.set_calibration(None)
            self.mission, self._log_mission = {}, None
            self.rx_count = 0
            self.event(f"listening on {url}" + (f", recording to {path.name}" if path else ""))
            self._start_worker(self._run_live)
            self._changed()

    def recording_names(self) -> list[str]:
        if not self.recordings_dir.is_dir():
            return []
        return sorted(p.name for p in self.recordings_dir.iterdir()
                      if p.is_file() and p.suffix.lower() in RECORDING_SUFFIXES)

    def resolve_recording(self, name: str) -> Path:
        """A file name from recordings/ -> its path; anything else (paths, ..) is refused."""
        if not name or "/" in name or "\\" in name or name.startswith(".") or \
                Path(name).suffix.lower() not in RECORDING_SUFFIXES:
            raise SessionError(f"'{name}' is not a recording name (a file name from recordings/)")
        path = (self.recordings_dir / name).resolve()
        if path.parent != self.recordings_dir or not path.is_file():
            raise SessionError(f"no recording named '{name}' (see GET /api/recordings)")
        return path

    def start_replay(self, path: str | Path, speed: float = 1.0, loop: bool = False) -> None:
        """Replay a log paced at real time x speed (any format read_log understands)."""
        from groundstation.io.errors import IngestError
        from groundstation.io.logs import read_log
        from groundstation.io.replay import Replayer

        path = Path(path)
        try:
            log = read_log(path)
        except IngestError as err:
            raise SessionError(str(err)) from err
        replayer = Replayer(log, speed=_check_speed(speed), loop=loop)
        replayer.pause()          # the worker fits the log's calibration first, then plays
        self._stop_source()
        with self._lock:
            self._reset_flight_state()
            self.autopilot = log.autopilot
            self.params = dict(log.params)
            self.mission, self._log_mission = {}, list(log.mission)
            self._start_unix_s = log.start_unix_s
            self.stack.start_unix_s = log.start_unix_s
            self.log_calibration = None
            self.stack.set_calibration(None)
            self.replay = replayer
            self.replay_path = path
            self.source_kind, self.source_name, self.link_state = "replay", path.name, "n/a"
            self.recording_path = path if path.suffix == ".tlog" else None
            self.rx_count = 0
            if log.mission and len(log.mission) >= 2:
                self.set_line(log.mission[0][:2], log.mission[-1][:2], "mission")
            self.event(f"replaying {path.name} ({replayer.duration_s:.0f} s) at x{speed:g}")
            if not len(log.mag):
                self.event(f"{path.name} has no magnetometer samples: no heading, calibration or "
                           "interference tests for this log", level="warning")
            self._start_worker(self._run_replay, log)
            self._changed()

    def _start_worker(self, target, *args) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(target=target, args=(self._stop, *args), daemon=True, name="session")
        self._thread.start()

    # ------------------------------------------------------------------ replay controls
    def _need_replay(self):
        if self.replay is None:
            raise SessionError("no replay running")
        return self.replay

    def replay_pause(self, paused: bool) -> None:
        with self._lock:
            r = self._need_replay()
            r.pause() if paused else r.resume()
            self.event("replay paused" if paused else "replay resumed")
            self._changed()

    def replay_speed(self, speed: float) -> None:
        with self._lock:
            self._need_replay().set_speed(_check_speed(speed))
            self._changed()

    def replay_seek(self, t_s: float) -> None:
        with self._lock:
            r = self._need_replay()
            if not math.isfinite(t_s) or t_s < 0 or t_s > r.duration_s:
                raise SessionError(f"seek time must be within 0..{r.duration_s:.1f} s")
            r.seek(t_s)
            self._restart_flight()
            self.t_s = t_s
            self.event(f"seek to {t_s:.1f} s")
            self._changed()

    def _restart_flight(self) -> None:
        """Estimators start over (samples were skipped); the preset line stays."""
        self._reset_flight_state()

    # ------------------------------------------------------------------ worker loops
    def _run_replay(self, stop: threading.Event, log: FlightLog) -> None:
        cal = _calibration_from_log(log)
        with self._lock:
            if self.replay is None or stop.is_set():
                return
            if cal is not None:
                self.log_calibration = cal
                self.stack.set_calibration(cal)
                self.event(f"using the calibration fitted to this log (residual "
                           f"{cal.get('residual_rms_mG') or 0:.1f} mG)")
            self.replay.resume()
            self._changed()
        del log
        loops = 0
        while not stop.is_set():
            with self._lock:
                r = self.replay
                if r is None:
                    return
                batch = r.due(max_samples=2000)
                if r.loops != loops:
                    loops = r.loops
                    self._restart_flight()
                    self.event("replay looped to the start")
                if batch:
                    for s in batch:
                        self._process(s)
                    self.rx_count += len(batch)
                    self.rx_last_unix = time.time()
                    if r.finished:
                        self.event("replay finished")
                    self._after_batch()
                    self._changed()
                wait = 0.1 if (r.paused or r.finished) else 0.01
            stop.wait(wait)

    def _run_live(self, stop: threading.Event) -> None:
        last_flush = time.monotonic()
        while not stop.is_set():
            link = self.link
            if link is None:
                return
            try:
                link.mav.select(0.05)
            except Exception:
                stop.wait(0.05)
            try:
                samples = link.poll()
            except Exception as err:  # a link read error must not kill the station
                samples = []
                self.event(f"link read error: {type(err).__name__}", "warning")
                stop.wait(0.2)
            with self._lock:
                if self.link is not link:
                    return
                count = self._link_msg_count(link)
                if samples or count != self.rx_count:
                    for s in samples:
                        self._process(s)
                    self.rx_count = count
                    self.rx_last_unix = link.last_rx_unix
                    self._after_batch()
                    self._changed()
                if time.monotonic() - last_flush >= 0.5:
                    last_flush = time.monotonic()
                    if self.recorder is not None:
                        self.recorder.flush()
                    self._changed()   # keeps "age since last packet" moving on the page

    @staticmethod
    def _link_msg_count(link) -> int:
        try:
            return int(link.mav.mav.total_packets_received)
        except Exception:
            return 0

    # ------------------------------------------------------------------ per sample
    def _process(self, s: Sample) -> None:
        self.t_s = max(self.t_s, s.t_s)
        if isinstance(s, StatusSample):
            if s.kind == "autopilot":
                self.autopilot = s.text
                self.event(f"vehicle autopilot: {s.text}")
            elif s.kind == "link":
                up = s.text.startswith("link up")
                if up:
                    self._request_params()
                if up and self.link_state == "lost":
                    self.event("link restored: " + s.text, "info")
                else:
                    self.event(s.text, "info" if up else "warning")
                self.link_state = "up" if up else "lost"
            elif s.kind == "statustext":
                self.event("vehicle: " + s.text)
            return
        if isinstance(s, ParamSample):
            self.params[s.name] = s.value
            echoes = self._param_waiters.get(s.name)
            if echoes is not None:
                echoes.append(s.value)
            return
        if isinstance(s, MissionSample):
            if self._log_mission is None:   # live: raw sequence numbers (ArduPilot 0 = home)
                self.mission[s.seq] = (s.lat_deg, s.lon_deg, s.alt_m)
            return
        if isinstance(s, (MagSample, ImuSample)):
            # one sensor instance each (the lowest number seen: RAW_IMU/primary first)
            kind = type(s).__name__
            primary = self._primary.get(kind)
            if primary is None or s.instance < primary:
                self._primary[kind] = primary = s.instance
            if s.instance != primary:
                return
        self.wizard.on_sample(s)
        self.stack.on_sample(s)
        det = self.stack.detector
        if det is not None and isinstance(s, ImuSample):
            self._alarm_update(bool(det.alarm_active), list(det.alarm_kinds or []), finite_or_none(det.peak))
        self._watch_gps(s)
        if isinstance(s, GpsSample) and math.isfinite(s.lat_deg) and math.isfinite(s.lon_deg):
            if self.origin is None:
                self.origin = (s.lat_deg, s.lon_deg) if self.stack.line is None else tuple(self.stack.line["a"])
            n, e = local_ne_m(s.lat_deg, s.lon_deg, self.origin)
            self.route.append((s.t_s, n, e, 1.0 if self.stack.alarm_active else 0.0))
        if s.t_s - self._last_hist_t >= 0.05:
            self._last_hist_t = s.t_s
            st = self.stack
            self.history.append((s.t_s, st.heading_mag_deg, st.heading_att_deg, st.v_forward,
                                 st.v_lateral, st.cross_track_m))

    def _watch_gps(self, s: Sample) -> None:
        """Events when the 3-D GPS fix goes away while the IMU keeps streaming, and comes back
        (the same rule as ``analyze``'s GPS outages)."""
        if isinstance(s, GpsSample) and s.fix_type >= 3 and math.isfinite(s.lat_deg):
            if self._gps_lost:
                self.event(f"GPS fix back after {s.t_s - self._last_fix_t:.1f} s")
                self._gps_lost = False
            self._last_fix_t = s.t_s
        elif (isinstance(s, ImuSample) and not self._gps_lost and self._last_fix_t is not None
              and s.t_s - self._last_fix_t > OUTAGE_MIN_S):
            self._gps_lost = True
            self.event(f"GPS fix lost (last 3-D fix at {self._last_fix_t:.1f} s): the position and "
                       "path-deviation test are stale", "warning")

    def _after_batch(self) -> None:
        """Wizard completion, once per batch."""
        if self.wizard.ready():
            self.wizard.finish(self.autopilot, self.params)
            r = self.wizard.result or {}
            self.event(f"calibration finished: {r.get('status')} {r.get('message') or ''}".strip())

    def _alarm_update(self, active: bool, kinds: list[str], peak: float | None) -> None:
        st = self.stack
        if active and not st.alarm_active:
            self.alarms.append({"kind": "combined", "evidence": kinds, "start_s": round(self.t_s, 2),
                                "end_s": None, "peak": peak})
            self.event("INTERFERENCE ALARM: " + (", ".join(kinds) or "combined"), "alarm")
        elif active and self.alarms:
            a = self.alarms[-1]
            a["evidence"] = sorted(set(a["evidence"]) | set(kinds))
            if peak is not None:
                a["peak"] = max(a["peak"] or 0.0, peak)
        elif not active and st.alarm_active and self.alarms:
            self.alarms[-1]["end_s"] = round(self.t_s, 2)
            self.event("alarm cleared")
        st.alarm_active, st.alarm_kinds = active, kinds

    # ------------------------------------------------------------------ calibration wizard
    def wizard_start(self) -> None:
        with self._lock:
            if self.wizard.state == "running":
                return  # a second client pressing Start joins the running wizard
            self.wizard.start()
            self._request_params()   # the onboard calibration to un-apply
            self.event("calibration started: turn about X")
            self._changed()

    def _request_params(self) -> None:
        """Ask a live vehicle for its parameter table (PARAM_REQUEST_LIST)."""
        link = self.link
        if link is None:
            return
        try:
            link.mav.mav.param_request_list_send(link.decoder.vehicle_sysid or 1, 0)
        except Exception:  # no peer yet (UDP before the first packet): asked again on link up
            pass

    def wizard_reset(self) -> None:
        with self._lock:
            self.wizard.reset()
            self.event("calibration reset")
            self._changed()

    def wizard_finish_now(self) -> dict:
        with self._lock:
            if self.wizard.state != "running":
                raise SessionError("the calibration wizard is not running")
            return self.wizard.finish(self.autopilot, self.params)

    def wizard_accept(self) -> dict:
        """Use the result for heading; on a live link write it to the vehicle (background)."""
        with self._lock:
            w = self.wizard
            if w.result is None or w.result.get("status") != "ok":
                raise SessionError("no successful calibration result to accept")
            if w.param_write is not None and w.param_write.get("state") == "writing":
                return w.param_write
            self.stack.set_calibration(w.result)     # the detector re-learns with it
            w.state = "accepted"
            autopilot = self.autopilot or "ardupilot"
            params = w.result.get(f"{autopilot}_params") or {}
            if self.link is not None and self.link_state == "up" and params:
                w.param_write = {"state": "writing", "autopilot": autopilot, "total": len(params),
                                 "confirmed": [], "failed": [], "message": "writing parameters"}
                threading.Thread(target=self._write_params, args=(self.link, dict(params)),
                                 daemon=True).start()
            else:
                w.param_write = {"state": "not_connected", "autopilot": autopilot, "total": len(params),
                                 "confirmed": [], "failed": [],
                                 "message": "accepted for this station; no live link, export the parameters"}
            self.event("calibration accepted")
            self._changed()
            return w.param_write

    def _write_params(self, link, params: dict[str, float], tries: int = 3, timeout_s: float = 1.0) -> None:
        pending = dict(params)
        confirmed: list[str] = []
        for _ in range(tries):
            waiters = {}
            with self._lock:
                for name in pending:
                    waiters[name] = self._param_waiters.setdefault(name, [])
                    waiters[name].clear()
            for name, value in pending.items():
                try:
                    link.mav.mav.param_set_send(link.decoder.vehicle_sysid or 1, 1, name.encode()[:16],
                                                float(value), mavlink2.MAV_PARAM_TYPE_REAL32)
                except Exception:
                    pass
            deadline = time.monotonic() + timeout_s
            while time.monotonic() < deadline and pending:
                time.sleep(0.02)
                with self._lock:
                    for name in list(pending):
                        if any(_same_float(v, pending[name]) for v in waiters[name]):
                            confirmed.append(name)
                            del pending[name]
                    self.wizard.param_write = dict(self.wizard.param_write or {}, confirmed=list(confirmed))
            if not pending:
                break
        with self._lock:
            for name in params:
                self._param_waiters.pop(name, None)
            failed = sorted(pending)
            pw = self.wizard.param_write or {}
            pw.update(confirmed=confirmed, failed=failed)
            if failed:
                pw.update(state="failed", message=f"{len(failed)} of {len(params)} parameters did not stick "
                                                  f"after {tries} tries: {', '.join(failed)}")
                self.event(pw["message"], "error")
            else:
                pw.update(state="written", message=f"all {len(params)} parameters written and confirmed")
                self.event(pw["message"])
                # the vehicle now corrects its own field: applying the result here too would
                # correct twice (its onboard calibration was un-applied for the fit)
                self.stack.set_calibration(None)
                for name, value in params.items():
                    self.params[name] = float(np.float32(value))
            self.wizard.param_write = pw
            self._changed()

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
            self.stack.set_line({"a": a, "b": b, "source": source})
            self.event(f"preset line set from {source}")
            self._changed()
            return self.stack.line

    def line_from_mission(self) -> dict:
        with self._lock:
            if self._log_mission is not None:
                wps = list(self._log_mission)
            else:
                wps = [self.mission[k] for k in sorted(self.mission)]
                if self.autopilot == "ardupilot" and 0 in self.mission and len(wps) > 2:
                    wps = wps[1:]
        if len(wps) < 2:
            raise SessionError("no mission with at least two waypoints received")
        return self.set_line(wps[0][:2], wps[-1][:2], "mission")

    # ------------------------------------------------------------------ reading
    def snapshot(self) -> dict:
        with self._lock:
            st = self.stack
            r = self.replay
            now = time.time()
            return {
                "version": self.version,
                "wall_unix_s": now,
                "t_s": round(self.t_s, 3),
                "rx_count": self.rx_count,
                "rx_age_s": None if self.rx_last_unix is None else round(now - self.rx_last_unix, 3),
                "source": {"kind": self.source_kind, "name": self.source_name, "link": self.link_state,
                           "autopilot": self.autopilot,
                           "recording": self.recording_path.name if self.recording_path else None},
                "replay": None if r is None else {
                    "t_s": round(min(r.position_s, r.duration_s), 2), "duration_s": round(r.duration_s, 2),
                    "paused": r.paused, "speed": r.speed, "finished": r.finished, "loop": r.loop},
                "vehicle": {
                    "roll_deg": finite_or_none(_deg(st.roll)), "pitch_deg": finite_or_none(_deg(st.pitch)),
                    "yaw_deg": finite_or_none(_deg(st.yaw)),
                    "ap_roll_deg": finite_or_none(_deg(st.ap[0])), "ap_pitch_deg": finite_or_none(_deg(st.ap[1])),
                    "ap_yaw_deg": finite_or_none(_deg(st.ap[2])),
                    "heading_mag_deg": finite_or_none(st.heading_mag_deg), "heading_att_deg": finite_or_none(st.heading_att_deg),
                    "v_forward_mps": finite_or_none(st.v_forward), "v_lateral_mps": finite_or_none(st.v_lateral),
                    "cross_track_m": finite_or_none(st.cross_track_m), "field_mG": finite_or_none(st.field_mG),
                    "lat_deg": finite_or_none(st.lat), "lon_deg": finite_or_none(st.lon), "fix_type": int(st.fix_type),
                },
                "alarm": {"active": st.alarm_active, "evidence": list(st.alarm_kinds),
                          "since_s": self.alarms[-1]["start_s"] if st.alarm_active and self.alarms else None},
                "alarm_count": len(self.alarms),
                "line": st.line,
                "calibration_in_use": st.calibration is not None,
                "wizard": self.wizard.snapshot(),
                "events": list(self.events)[-15:],
            }

    def snapshot_json(self) -> str:
        """The snapshot as JSON, built once per state version whatever the number of clients."""
        with self._lock:
            cache = self._json_cache
            if cache is not None and cache[0] == self.version:
                return cache[1]
            text = json.dumps(self.snapshot(), allow_nan=False, default=_json_default)
            self._json_cache = (self.version, text)
            return text

    def scene_data(self) -> dict:
        """Arrays for the 3-D view (copies, safe to use outside the lock)."""
        with self._lock:
            w = self.wizard
            est = w._est
            res = w.result if w.result and w.result.get("status") == "ok" else None
            return {
                "att": (self.stack.roll, self.stack.pitch, self.stack.yaw),
                "ap_att": self.stack.ap,
                "cloud": w.mag.view()[:, 1:4].copy(),
                "fit": ({"offsets_mG": res["offsets_mG"], "matrix": res["matrix"],
                         "field_mG": res.get("field_strength_mG")} if res else
                        ({"offsets_mG": est[0].tolist(), "matrix": est[1].tolist(), "field_mG": est[2]} if est else None)),
                "route": self.route.view().copy(),
                "line": self.stack.line,
                "origin": self.origin,
                "alarm": self.stack.alarm_active,
                "alarm_text": ", ".join(self.stack.alarm_kinds),
                "calibrating": w.state != "idle",
                "history": np.array(self.history, dtype=float).reshape(-1, 6),
            }

    def alarm_list(self) -> list[dict]:
        with self._lock:
            return [dict(a) for a in self.alarms]

    def session_tlog(self) -> Path:
        with self._lock:
            if self.recorder is not None:
                self.recorder.flush()
            if self.recording_path is None or not self.recording_path.is_file():
                raise SessionError("this session has no .tlog (replays of .bin/.ulg/.csv are not MAVLink)")
            return self.recording_path

    def analysis(self) -> tuple[dict, np.ndarray]:
        """analyze_log on the session's log (the live recording or the replayed file)."""
        with self._lock:
            if self.recorder is not None:
                self.recorder.flush()
            path = self.recording_path or (self.replay_path if self.replay else None)
            cal = self.stack.calibration
            line = self.stack.line
        if path is None:
            raise SessionError("no session to analyse: connect or replay first")
        from groundstation.jobs.analyze import analyze_log
        from groundstation.io.errors import IngestError
        from groundstation.io.logs import read_log
        try:
            log = read_log(path)
        except IngestError as err:
            raise SessionError(str(err)) from err
        mission = [(line["a"][0], line["a"][1], 0.0), (line["b"][0], line["b"][1], 0.0)] if line else None
        report, table = analyze_log(log, cal, mission)
        return jsonable(report), table

    def close(self) -> None:
        self._stop_source()


def _calibration_from_log(log: FlightLog) -> dict | None:
    """A replayed log that contains a calibration dance calibrates its own magnetometer
    (calibrate_log on the whole log; None unless the fit is 'ok')."""
    from groundstation.jobs.calibrate import calibrate_log

    if len(log.mag) < 200:
        return None
    try:
        result = calibrate_log(log)
    except Exception:
        return None
    return jsonable(result) if result.get("status") == "ok" else None


def _same_float(a: float, b: float) -> bool:
    """PARAM_VALUE echoes a float32: equal to the float32 of what we sent."""
    return abs(float(np.float32(a)) - float(np.float32(b))) <= 1e-6 * max(1.0, abs(b))


def _check_speed(speed: float) -> float:
    speed = float(speed)
    if not math.isfinite(speed) or not 0.05 <= speed <= 100.0:
        raise SessionError("speed must be between 0.05 and 100")
    return speed


def _json_default(o):
    if isinstance(o, (np.floating,)):
        return float(o) if math.isfinite(o) else None
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)
