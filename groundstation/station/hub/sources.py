"""The station's one source at a time: a live MAVLink link (recorded as it arrives) or a replay.

``SourceControl`` opens and closes sources, runs the worker thread that reads them, and paces
replays (pause, speed, seek).  Samples go to the hub through the ``Feed`` it is given; the
hub's lock is held while a batch is processed, so readers see whole batches.
"""
from __future__ import annotations

import math
import threading
import time
from pathlib import Path
from typing import Protocol

from groundstation.io.errors import IngestError
from groundstation.samples import FlightLog, Sample

__all__ = ["SourceControl", "Feed", "RECORDING_SUFFIXES", "check_speed", "SessionError", "NotFoundError",
           "ConflictError"]

RECORDING_SUFFIXES = (".tlog", ".bin", ".ulg", ".csv")
REPLAY_BATCH = 2000
FLUSH_EVERY_S = 0.5


class SessionError(Exception):
    """A request the hub cannot honour (bad value, bad source ...): HTTP 400."""


class NotFoundError(SessionError):
    """The thing asked for does not exist (no such recording, no result yet): HTTP 404."""


class ConflictError(SessionError):
    """Not possible in the current state (no replay running, wizard not running): HTTP 409."""


class Feed(Protocol):
    """What a source worker needs from the hub (called with the hub lock held)."""

    def process_batch(self, samples: list[Sample]) -> None: ...
    def event(self, text: str, level: str = "info") -> None: ...
    def changed(self) -> None: ...
    def fit_log_calibration(self, log: FlightLog) -> dict | None: ...
    def use_log_calibration(self, calibration: dict) -> None: ...
    def restart_flight(self) -> None: ...


def check_speed(speed: float) -> float:
    speed = float(speed)
    if not math.isfinite(speed) or not 0.05 <= speed <= 100.0:
        raise SessionError("speed must be between 0.05 and 100")
    return speed


class SourceControl:
    """Live link or replay, its worker thread and its pacing."""

    def __init__(self, feed: Feed, lock: threading.RLock, recordings_dir: Path, record_live: bool) -> None:
        self._feed = feed
        self._lock = lock
        self.recordings_dir = recordings_dir
        self.record_live = record_live
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.kind = "none"
        self.name = ""
        self.link_state = "n/a"
        self.link = None
        self.recorder = None
        self.recording_path: Path | None = None
        self.replay = None                # groundstation.io.replay.Replayer while replaying
        self.replay_path: Path | None = None
        self.rx_count = 0
        self.rx_last_unix: float | None = None

    # ------------------------------------------------------------------ recordings folder
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
            raise NotFoundError(f"no recording named '{name}' (see GET /api/recordings)")
        return path

    def _new_recording_path(self) -> Path:
        path = self.recordings_dir / time.strftime("session-%Y%m%d-%H%M%S.tlog", time.gmtime())
        n = 1
        while path.exists():
            path = path.with_name(f"{path.stem.split('_')[0]}_{n}.tlog")
            n += 1
        return path

    # ------------------------------------------------------------------ opening / closing
    def open_link(self, url: str):
        """Open a live link (pymavlink connection string) with its recorder; nothing is
        changed when it fails.  Returns (link, recorder, path) for ``start_live``."""
        from groundstation.io.link import LiveLink, validate_connection_string
        from groundstation.io.mavlink import TlogWriter

        try:
            url = validate_connection_string(url)
        except IngestError as err:
            raise SessionError(str(err)) from err
        recorder = path = None
        if self.record_live:
            path = self._new_recording_path()
            recorder = TlogWriter(path)
        try:
            link = LiveLink(url, recorder=recorder)
        except IngestError as err:
            if recorder is not None:
                recorder.close()
                path.unlink(missing_ok=True)
            raise SessionError(str(err)) from err
        return url, link, recorder, path

    def start_live(self, url: str, link, recorder, path: Path | None) -> None:
        """Called with the hub lock held, after ``stop``."""
        self.link, self.recorder, self.recording_path = link, recorder, path
        self.kind, self.name, self.link_state = "live", url, "waiting"
        self.rx_count = 0
        self._start_worker(self._run_live)

    @staticmethod
    def load_replay(path: Path, speed: float, loop: bool):
        """Read a log and make its (paused) replay clock; nothing is changed when it fails."""
        from groundstation.io.logs import read_log
        from groundstation.io.replay import Replayer

        try:
            log = read_log(path)
        except IngestError as err:
            raise SessionError(str(err)) from err
        replayer = Replayer(log, speed=check_speed(speed), loop=loop)
        replayer.pause()          # the worker fits the log's calibration first, then plays
        return log, replayer

    def start_replay(self, path: Path, log: FlightLog, replayer) -> None:
        """Called with the hub lock held, after ``stop``."""
        self.replay, self.replay_path = replayer, path
        self.kind, self.name, self.link_state = "replay", path.name, "n/a"
        self.recording_path = path if path.suffix == ".tlog" else None
        self.rx_count = 0
        self._start_worker(self._run_replay, log)

    def stop(self) -> None:
        """Stop the worker and close the link/recorder (call without holding the hub lock)."""
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
        self.kind, self.link_state = "none", "n/a"

    def _start_worker(self, target, *args) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(target=target, args=(self._stop, *args), daemon=True, name="source")
        self._thread.start()

    # ------------------------------------------------------------------ replay controls
    def need_replay(self):
        if self.replay is None:
            raise ConflictError("no replay running")
        return self.replay

    def seek(self, t_s: float) -> None:
        r = self.need_replay()
        if not math.isfinite(t_s) or t_s < 0 or t_s > r.duration_s:
            raise SessionError(f"seek time must be within 0..{r.duration_s:.1f} s")
        r.seek(t_s)

    def replay_snapshot(self) -> dict | None:
        r = self.replay
        if r is None:
            return None
        return {"t_s": round(min(r.position_s, r.duration_s), 2), "duration_s": round(r.duration_s, 2),
                "paused": r.paused, "speed": r.speed, "finished": r.finished, "loop": r.loop}

    def source_snapshot(self, autopilot: str | None) -> dict:
        return {"kind": self.kind, "name": self.name, "link": self.link_state, "autopilot": autopilot,
                "recording": self.recording_path.name if self.recording_path else None}

    def flush_recording(self) -> None:
        if self.recorder is not None:
            self.recorder.flush()

    # ------------------------------------------------------------------ worker loops
    def _run_replay(self, stop: threading.Event, log: FlightLog) -> None:
        feed = self._feed
        calibration = feed.fit_log_calibration(log)     # slow: outside the lock
        with self._lock:
            if self.replay is None or stop.is_set():
                return
            if calibration is not None:
                feed.use_log_calibration(calibration)
            self.replay.resume()
            feed.changed()
        del log
        loops = 0
        while not stop.is_set():
            with self._lock:
                r = self.replay
                if r is None:
                    return
                batch = r.due(max_samples=REPLAY_BATCH)
                if r.loops != loops:
                    loops = r.loops
                    feed.restart_flight()
                    feed.event("replay looped to the start")
                if batch:
                    feed.process_batch(batch)
                    self.rx_count += len(batch)
                    self.rx_last_unix = time.time()
                    if r.finished:
                        feed.event("replay finished")
                    feed.changed()
                wait = 0.1 if (r.paused or r.finished) else 0.01
            stop.wait(wait)

    def _run_live(self, stop: threading.Event) -> None:
        last_flush = time.monotonic()
        feed = self._feed
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
                feed.event(f"link read error: {type(err).__name__}", "warning")
                stop.wait(0.2)
            with self._lock:
                if self.link is not link:
                    return
                count = _link_msg_count(link)
                if samples or count != self.rx_count:
                    feed.process_batch(samples)
                    self.rx_count = count
                    self.rx_last_unix = link.last_rx_unix
                    feed.changed()
                if time.monotonic() - last_flush >= FLUSH_EVERY_S:
                    last_flush = time.monotonic()
                    self.flush_recording()
                    feed.changed()   # keeps "age since last packet" moving on the page


def _link_msg_count(link) -> int:
    try:
        return int(link.mav.mav.total_packets_received)
    except Exception:
        return 0
