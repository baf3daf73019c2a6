"""The station's one source at a time: a live MAVLink link (recorded as it arrives) or a replay.

``SourceControl`` opens and closes sources, runs the worker thread that reads them, and paces
replays (pause, speed, seek).  A replay plays as soon as its file is read: its samples go
through the hub's causal path (as a live link's) while the whole-log analysis
(``Feed.prepare_replay``) runs in a thread beside it; once that is in, the replay moves a cursor
over it (``Feed.replay_moved``) and its samples still go to the hub (status, calibration
wizard).  Connecting while a source runs arms the new link: the running source goes on until
the link hears its first packet, so a connect that reaches nothing stops nothing.  Samples go to
the hub through the ``Feed`` it is given, with the hub's lock held, so readers see whole batches.
"""
from __future__ import annotations

import logging
import math
import socket
import threading
import time
from pathlib import Path
from typing import Protocol

from groundstation.io.errors import IngestError
from groundstation.samples import FlightLog, Sample
from groundstation.station.hub.recordings import RECORDING_SUFFIXES, LazyRecording, RecordingsFolder

__all__ = ["SourceControl", "Feed", "RECORDING_SUFFIXES", "check_speed", "SessionError", "NotFoundError",
           "ConflictError"]

logger = logging.getLogger(__name__)
REPLAY_BATCH = 2000
# a log larger than START_ABOVE_BYTES plays from its first START_BYTES while the rest is read
# (opening a 100 MB log: playing in ~0.3 s instead of after the ~2.5 s read of the whole file)
START_BYTES = 8 << 20
START_ABOVE_BYTES = 24 << 20
FLUSH_EVERY_S = 0.5
TCP_PROBE_TIMEOUT_S = 2.0


class SessionError(Exception):
    """A request the hub cannot honour (bad value, bad source ...): HTTP 400."""


class NotFoundError(SessionError):
    """The thing asked for does not exist (no such recording, no result yet): HTTP 404."""


class ConflictError(SessionError):
    """Not possible in the current state (no replay running, wizard not running): HTTP 409."""


class Feed(Protocol):
    """What a source worker needs from the hub (called with the hub lock held unless noted)."""

    def process_batch(self, samples: list[Sample]) -> None: ...
    def event(self, text: str, level: str = "info", t_s: float | None = None) -> None: ...
    def changed(self) -> None: ...
    def prepare_replay(self, log: FlightLog): ...              # without the lock (slow)
    def whole_replay_read(self, log: FlightLog) -> None: ...
    def start_review(self, prepared) -> None: ...
    def replay_moved(self, t_s: float) -> bool: ...
    def restart_flight(self) -> None: ...
    def flush_live(self) -> None: ...
    def switch_to_live(self, url: str, link, recording, samples: list[Sample]) -> None: ...   # without the lock


def check_speed(speed: float) -> float:
    speed = float(speed)
    if not math.isfinite(speed) or not 0.05 <= speed <= 100.0:
        raise SessionError("speed must be between 0.05 and 100")
    return speed


def probe_tcp(url: str) -> None:
    """A tcp: link to a port nobody listens on fails here, quickly and in one line (pymavlink
    would retry and print each refusal).  Raises SessionError."""
    rest = url.split(":", 1)[1]
    host, _, port = rest.rpartition(":")
    try:
        with socket.create_connection((host, int(port)), timeout=TCP_PROBE_TIMEOUT_S):
            pass
    except OSError as err:
        reason = "connection refused" if isinstance(err, ConnectionRefusedError) else (err.strerror or str(err))
        raise SessionError(f"cannot connect to {host}:{port}: {reason} (is the vehicle or SITL listening there?)") \
            from None


class SourceControl:
    """Live link or replay, its worker thread and its pacing."""

    def __init__(self, feed: Feed, lock: threading.RLock, folder: RecordingsFolder, record_live: bool,
                 link_options=None, forwarder=None) -> None:
        self._feed = feed
        self.link_options = link_options          # groundstation.io.link.LinkOptions (None: defaults)
        self.forwarder = forwarder                # groundstation.io.forward.Forwarder or None
        self._lock = lock
        self.folder = folder
        self.recordings_dir = folder.dir
        self.record_live = record_live
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.kind = "none"
        self.name = ""
        self.link_state = "n/a"
        self.link = None
        self.recording: LazyRecording | None = None
        self.replay = None                # groundstation.io.replay.Replayer while replaying
        self.replay_path: Path | None = None
        self.rx_count = 0
        self.rx_last_unix: float | None = None
        self.pending: tuple | None = None  # (url, link, recording, stop event) armed while a source runs
        # the url of the armed link that heard its vehicle, from leaving ``pending`` until the hub
        # has switched to it (under the hub lock): a Start pressed in between is meant for it too
        self.switching: str | None = None
        self._finished_told = False

    @property
    def recording_path(self) -> Path | None:
        """The live session's .tlog once its first packet came, else the replayed .tlog."""
        if self.recording is not None:
            return self.recording.path
        if self.replay_path is not None and self.replay_path.suffix.lower() == ".tlog":
            return self.replay_path
        return None

    @property
    def log_path(self) -> Path | None:
        """The session's log file in its own format (live recording or the replayed file)."""
        if self.recording is not None:
            return self.recording.path
        return self.replay_path

    # ------------------------------------------------------------------ opening / closing
    def open_link(self, url: str):
        """Open a live link (pymavlink connection string) with its lazy recording; nothing is
        changed when it fails.  Returns (url, link, recording)."""
        from groundstation.io.link import LiveLink, validate_connection_string
        from groundstation.station.hub.param_watch import ParamSourceGuard

        try:
            url = validate_connection_string(url)
        except IngestError as err:
            raise SessionError(str(err)) from err
        if url.startswith("tcp:"):
            probe_tcp(url)
        recording = LazyRecording(self.folder.new_session_path) if self.record_live else None
        try:
            link = LiveLink(url, recorder=recording, options=self.link_options, forwarder=self.forwarder)
        except IngestError as err:
            raise SessionError(str(err)) from err
        link.param_guard = ParamSourceGuard()       # PARAM_VALUEs only from the vehicle's component/address
        return url, link, recording

    def start_live(self, url: str, link, recording) -> None:
        """Called with the hub lock held, after ``stop``."""
        self.link, self.recording = link, recording
        link.attach_forwarder(self.forwarder)
        self.replay = self.replay_path = None
        self.kind, self.name, self.link_state = "live", url, "waiting"
        self.switching = None                  # switched
        self.rx_count, self.rx_last_unix = 0, None
        self._start_worker(self._run_live)

    def arm_pending(self, url: str, link, recording) -> None:
        """Keep the running source until ``link`` hears its first packet (then the hub switches)."""
        self.cancel_pending()
        stop = threading.Event()
        self.pending = (url, link, recording, stop)
        threading.Thread(target=self._run_pending, args=(stop, url, link, recording), daemon=True,
                         name="pending-link").start()

    def cancel_pending(self) -> None:
        pending, self.pending = self.pending, None
        if pending is not None:
            pending[3].set()
            pending[1].close()
            if pending[2] is not None:
                pending[2].close()

    @staticmethod
    def load_replay(path: Path, speed: float, loop: bool, log: FlightLog | None = None):
        """Read a log (unless given) and make its (paused) replay clock; nothing is changed
        when it fails.  A large .tlog/.bin is read in its first START_BYTES only: its replayer
        has ``more_to_come`` and the worker reads the rest (``_read_rest``)."""
        from groundstation.io.logs import START_SUFFIXES, read_log, read_log_start
        from groundstation.io.replay import Replayer

        in_parts = False
        try:
            if log is None:
                in_parts = path.suffix.lower() in START_SUFFIXES and path.stat().st_size > START_ABOVE_BYTES
                log = read_log_start(path, START_BYTES) if in_parts else read_log(path)
        except (IngestError, OSError) as err:
            raise SessionError(str(err)) from err
        replayer = Replayer(log, speed=check_speed(speed), loop=loop)
        replayer.more_to_come = in_parts
        replayer.pause()          # the worker starts it
        return log, replayer

    def start_replay(self, path: Path, log: FlightLog, replayer) -> None:
        """Called with the hub lock held, after ``stop``."""
        self.replay, self.replay_path = replayer, path
        self.recording = None
        self.kind, self.name, self.link_state = "replay", path.name, "n/a"
        self.rx_count, self.rx_last_unix = 0, None
        self._finished_told = False
        self._start_worker(self._run_replay, log)

    def stop(self) -> None:
        """Stop the worker and close the link/recording (call without holding the hub lock)."""
        self._stop.set()
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout=5)
        self._thread = None
        if self.link is not None:
            self.link.close()
            self.link = None
        if self.recording is not None:
            self.recording.close()
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
        if not math.isfinite(t_s) or t_s < 0 or t_s > r.duration_s + 0.01:     # the page has it rounded
            raise SessionError(f"seek time must be within 0..{r.duration_s:.1f} s")
        r.seek(min(t_s, r.duration_s))
        self._finished_told = False

    def replay_snapshot(self) -> dict | None:
        r = self.replay
        if r is None:
            return None
        return {"t_s": round(min(r.position_s, r.duration_s), 2), "duration_s": round(r.duration_s, 2),
                "paused": r.paused, "speed": r.speed, "finished": r.finished, "loop": r.loop,
                "reading": r.more_to_come}

    def source_snapshot(self, autopilot: str | None) -> dict:
        path = self.log_path
        return {"kind": self.kind, "name": self.name, "link": self.link_state, "autopilot": autopilot,
                "recording": path.name if path is not None and self.recording is not None else
                (path.name if path is not None and path.suffix.lower() == ".tlog" else None),
                "log_file": path.name if path is not None else None,
                "pending": self.pending[0] if self.pending else None}

    def vehicles_snapshot(self) -> dict:
        """The systems heard on the live link, the one followed, passive mode, signing, forwarding."""
        link = self.link
        if link is not None:
            return link.vehicles_snapshot()
        options = self.link_options
        return {"selected": getattr(options, "sysid", None), "systems": [],
                "passive": bool(getattr(options, "passive", False)), "passive_reason": None,
                "signing": {"on": getattr(options, "signing_key", None) is not None},
                "forwarding": self.forwarder.snapshot() if self.forwarder is not None else None}

    def flush_recording(self) -> None:
        if self.recording is not None:
            self.recording.flush()

    # ------------------------------------------------------------------ worker loops
    def _run_replay(self, stop: threading.Event, log: FlightLog) -> None:
        """Play at once; the whole-log analysis runs beside it (``_analyse``) and the hub takes
        it over from the replay's causal path when it is in."""
        feed = self._feed
        with self._lock:
            replayer = self.replay
            if replayer is None or stop.is_set():
                return
            replayer.resume()
            feed.changed()
        if replayer.more_to_come:
            threading.Thread(target=self._read_rest, args=(stop, replayer), daemon=True,
                             name="replay-read").start()
        else:
            threading.Thread(target=self._analyse, args=(stop, replayer, log), daemon=True,
                             name="replay-analysis").start()
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
                    feed.event("replay looped to the start", t_s=0.0)
                if batch:
                    feed.process_batch(batch)
                    self.rx_count += len(batch)
                    self.rx_last_unix = time.time()
                moved = feed.replay_moved(min(r.position_s, r.duration_s))
                if r.finished and not self._finished_told:
                    self._finished_told = True
                    feed.event("replay finished")
                if batch or moved:
                    feed.changed()
                wait = 0.1 if (r.paused or r.finished) else 0.02
            stop.wait(wait)

    def _read_rest(self, stop: threading.Event, replayer) -> None:
        """Read the whole file of a replay playing from its first part, go on with it where the
        replay is (``Replayer.continued``), then analyse it.  If the rest cannot be read the
        replay ends with the part read and that part is analysed."""
        from groundstation.io.logs import read_log

        feed, path = self._feed, self.replay_path
        try:
            log = read_log(path)
        except IngestError as err:
            with self._lock:
                if self.replay is not replayer or stop.is_set():
                    return
                replayer.more_to_come = False
                feed.event(f"{err}: the replay ends with the first {START_BYTES >> 20} MB read", "warning")
                feed.changed()
            self._analyse(stop, replayer, replayer.log)
            return
        with self._lock:
            if self.replay is not replayer or stop.is_set():
                return
            whole = replayer.continued(log)
            self.replay = whole
            feed.whole_replay_read(log)
            feed.event(f"{path.name} read to its end ({whole.duration_s:.0f} s)")
            feed.changed()
        del replayer
        self._analyse(stop, whole, log)

    def _analyse(self, stop: threading.Event, replayer, log: FlightLog) -> None:
        """The replay's whole-log analysis (slow: outside the lock), handed to the hub if the
        replay still runs when it is done."""
        feed = self._feed
        try:
            prepared = feed.prepare_replay(log)
        except Exception as err:      # the replay goes on on its causal path
            logger.exception("analysis of the replayed log failed")
            with self._lock:
                if self.replay is replayer and not stop.is_set():
                    feed.event(f"the whole-log analysis failed ({type(err).__name__}): the replay shows the "
                               "live path's decisions only", "warning")
                    feed.changed()
            return
        with self._lock:
            if self.replay is not replayer or stop.is_set():
                return
            feed.start_review(prepared)
            feed.changed()

    def _run_live(self, stop: threading.Event) -> None:
        last_flush = time.monotonic()
        feed = self._feed
        while not stop.is_set():
            link = self.link
            if link is None:
                return
            samples = _poll(link, feed, stop)
            with self._lock:
                if self.link is not link:
                    return
                count = _link_msg_count(link)
                if samples or count != self.rx_count:
                    feed.process_batch(samples)
                    self.rx_count = count
                    self.rx_last_unix = link.last_rx_unix
                    feed.changed()
                feed.flush_live()
                if time.monotonic() - last_flush >= FLUSH_EVERY_S:
                    last_flush = time.monotonic()
                    self.flush_recording()
                    feed.changed()   # keeps "age since last packet" moving on the page

    def _run_pending(self, stop: threading.Event, url: str, link, recording) -> None:
        """Poll an armed link until it hears the vehicle, then hand it to the hub."""
        got: list[Sample] = []
        while not stop.is_set():
            got += _poll(link, self._feed, stop)
            if link.last_rx_unix is not None:
                with self._lock:
                    if self.pending is None or self.pending[1] is not link:
                        return
                    self.switching = url           # set before pending is cleared: no gap
                    self.pending = None
                self._feed.switch_to_live(url, link, recording, got)
                return

    def connecting(self) -> str | None:
        """The url of the link being connected or switched to, whose vehicle a calibration started
        now is meant for; None: the current source's.  Read under the hub lock."""
        pending = self.pending
        return pending[0] if pending is not None else self.switching


def _poll(link, feed: Feed, stop: threading.Event) -> list[Sample]:
    link.wait(0.05)
    try:
        return link.poll()
    except Exception as err:  # a link read error must not kill the station
        feed.event(f"link read error: {type(err).__name__}", "warning")
        stop.wait(0.2)
        return []


def _link_msg_count(link) -> int:
    try:
        return int(link.mav.mav.total_packets_received)
    except Exception:
        return 0
