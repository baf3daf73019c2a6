"""The flight as the page shows it: the flight record so far, the route, the alarms.

Two ways in, one state (the hub calls both under its lock):
  * live: ``push(samples)`` puts a link's samples in time order (``ReorderBuffer``) and through
    ``LiveAnalyzer``, one record row per IMU sample; GPS outages by ``GpsOutageWatch``;
  * replay: ``load_review(review, t)`` takes the whole log analysed at once
    (``groundstation.station.hub.review``) and ``show_until(t)`` moves the cursor (forward as the
    replay plays, anywhere on a seek).  Until the analysis is in (a replay plays as soon as its
    file is read), the replay's samples take the live way, so the page shows the causal decisions
    meanwhile and the whole-log ones from when it lands.
Either way the alarms are ``AlarmTracker`` over the rows, so the page lists what analyze
reports.  Readers (snapshots, plots, scene) go through ``rows()``, ``route()`` and
``groundstation.station.hub.display``.
"""
from __future__ import annotations

import math
import time
from typing import Callable

import numpy as np

from groundstation.jobs.alarm_explain import explain_span, explanation_text
from groundstation.jobs.live import GpsOutageWatch, LiveAnalyzer, ReorderBuffer
from groundstation.jobs.record import COL, RECORD_COLUMNS, AlarmTracker, evidence_text
from groundstation.samples import GpsSample, Sample
from groundstation.station.hub.review import Review, line_mission
from groundstation.station.tables import GrowingTable

__all__ = ["FlightState", "ROUTE_MAX_POINTS", "LIVE_ROWS_MAX"]

ROUTE_MAX_POINTS = 200_000          # live GPS fixes kept (11 h at 5 Hz)
ANALYSE_EVERY_S = 0.02              # live: due samples are analysed together at most this often
LIVE_ROWS_MAX = 360_000             # live record rows kept (2 h at 50 Hz); the oldest quarter goes first
EVIDENCE_COLS = slice(COL["ev_heading"], COL["ev_field"] + 1)   # ev_heading, ev_path, ev_field: adjacent


EventFn = Callable[..., None]


class FlightState:
    """Record, route and alarms of the current source (see module docstring).  No lock: the
    hub calls it under its own."""

    def __init__(self, event: EventFn) -> None:
        self._event = event
        self.calibration: dict | None = None   # in use: accepted wizard result or the log's own fit
        self.line: dict | None = None
        self.start_unix_s: float | None = None
        self.review: Review | None = None
        self.reset()

    # ------------------------------------------------------------------ configuration
    def reset(self) -> None:
        """The flight starts over (new source, replay loop): nothing shown yet."""
        self._rows = GrowingTable(len(RECORD_COLUMNS), LIVE_ROWS_MAX)
        self._route = GrowingTable(5, ROUTE_MAX_POINTS)        # t_s, lat, lon, fix_type, alarm
        self.analyzer = LiveAnalyzer(self.calibration, line_mission(self.line), self.start_unix_s)
        self.reorder = ReorderBuffer()
        self._due: list[Sample] = []
        self._analysed_at = -math.inf
        self.watch = GpsOutageWatch()
        self.tracker = AlarmTracker()
        self._explanations: dict = {}
        self.t_s = 0.0
        self.n_shown = 0                   # review: rows up to the cursor
        self.gps_shown = 0
        self._events_done = 0

    def new_source(self, start_unix_s: float | None) -> None:
        """A new source: no review, no line, no calibration until the source brings them."""
        self.start_unix_s = start_unix_s
        self.calibration = None
        self.line = None
        self.review = None
        self.reset()

    def set_line(self, line: dict | None) -> None:
        self.line = line
        self.analyzer.set_mission(line_mission(line))

    def set_calibration(self, calibration: dict | None) -> None:
        """Live: the analyzer starts over with it (the detector learns again); a replay is
        analysed again by the hub (``needs_review``)."""
        self.calibration = calibration
        self.analyzer = self.analyzer.restarted(calibration)

    def needs_review(self) -> bool:
        """The replay's analysis was made with another calibration or line than the current."""
        r = self.review
        return r is not None and (r.calibration is not self.calibration or r.line != self.line)

    @property
    def policy(self):
        return self.review.policy if self.review is not None else self.analyzer.policy

    # ------------------------------------------------------------------ live
    def push(self, samples: list[Sample]) -> None:
        """Live samples (any order); those due go through the analyzer, a few at a time (at a
        high IMU rate one call per packet would cost more than the analysis itself)."""
        # the primary IMU/compass is chosen in arrival order (the lowest instance heard): RAW_IMU
        # and SCALED_IMU2 of one loop arrive in that order, but their boot times may lie either
        # way round (ArduPilot's time_usec against a truncated time_boot_ms)
        self._due += self.reorder.push([s for s in samples if self.analyzer.accepts(s)])
        self.flush_due()

    def flush_due(self) -> None:
        self._due += self.reorder.due()
        now = time.monotonic()
        if self._due and (now - self._analysed_at >= ANALYSE_EVERY_S or len(self._due) > 500):
            self._analysed_at = now
            due, self._due = self._due, []
            self._live(due)

    def flush_all(self) -> None:
        """Everything waiting, now (the stream ended)."""
        due, self._due = self._due + self.reorder.flush(), []
        self._live(due)

    def _live(self, samples: list[Sample]) -> None:
        samples = [s for s in samples if self.analyzer.accepts(s)]
        if not samples:
            return
        self.t_s = max(self.t_s, max(s.t_s for s in samples))
        before = self.tracker.active
        rows = self.analyzer.on_samples(samples)
        for s in samples:
            change = self.watch.on_sample(s)
            if change is not None:
                self._gps_event(*change, t_s=s.t_s)
        if len(rows):
            if self._rows.n + len(rows) > LIVE_ROWS_MAX:
                self._rows.drop_oldest(LIVE_ROWS_MAX // 4)
            for row in rows:
                self._rows.append(row)
            self._track(rows)
        for s in samples:
            if isinstance(s, GpsSample) and math.isfinite(s.lat_deg) and math.isfinite(s.lon_deg):
                k = int(np.searchsorted(rows[:, COL["t_s"]], s.t_s, side="right")) - 1 if len(rows) else -1
                alarm = rows[k, COL["alarm"]] > 0.5 if k >= 0 else before
                self._route.append((s.t_s, s.lat_deg, s.lon_deg, s.fix_type, 1.0 if alarm else 0.0))

    def _gps_event(self, what: str, value: float, t_s: float) -> None:
        if what == "lost":
            self._event(f"GPS fix lost (last 3-D fix at {value:.1f} s): the position and path-deviation test "
                        "are stale", "warning", t_s=t_s)
        else:
            self._event(f"GPS fix back after {value:.1f} s", t_s=t_s)

    # ------------------------------------------------------------------ replay
    def load_review(self, review: Review, t_s: float) -> None:
        """A replay's whole-log analysis; shown up to ``t_s``."""
        self.review = review
        self.show_until(t_s, seek=True)

    def show_until(self, t_s: float, seek: bool = False) -> None:
        """Move the replay cursor: forward as the replay plays (events for what it passes), or
        anywhere on a seek (the state at that time, rebuilt at once)."""
        r = self.review
        if r is None:
            self.t_s = t_s
            return
        t = r.rows[:, COL["t_s"]]
        n = int(np.searchsorted(t, t_s, side="right"))
        if seek or n < self.n_shown:
            self.tracker = AlarmTracker()
            self._explanations = {}
            self.n_shown = 0
            self._events_done = sum(1 for e in r.events if e[0] <= t_s)
            self._track(r.rows[:n], quiet=True)
        else:
            self._track(r.rows[self.n_shown:n])
            while self._events_done < len(r.events) and r.events[self._events_done][0] <= t_s:
                et, text, level = r.events[self._events_done]
                self._event(text, level, t_s=et)
                self._events_done += 1
        self.n_shown = n
        self.gps_shown = int(np.searchsorted(r.gps[:, 0], t_s, side="right"))
        self.t_s = t_s

    # ------------------------------------------------------------------ alarms
    def _track(self, rows: np.ndarray, quiet: bool = False) -> None:
        tr = self.tracker
        before, was_on = len(tr.alarms), tr.active
        tr.update(rows[:, COL["t_s"]], rows[:, COL["alarm"]] > 0.5, rows[:, EVIDENCE_COLS] > 0.5, rows[:, COL["score"]])
        if quiet:
            return
        for a in tr.alarms[before:]:
            self._event("INTERFERENCE ALARM: " + (evidence_text(a["evidence_at_start"]) or "combined"), "alarm",
                        t_s=a["start_s"])
        if was_on and len(tr.alarms) == before and not tr.active:
            text = self._explained(tr.alarms[-1])["explanation_text"]
            self._event("alarm cleared" + (f" ({text})" if text else ""), t_s=tr.alarms[-1]["end_s"])

    def alarm_snapshot(self) -> dict:
        tr = self.tracker
        a = tr.alarms[-1] if tr.active and tr.alarms else None
        return {"active": a is not None, "evidence": list(a["evidence"]) if a else [],
                "evidence_text": evidence_text(a["evidence"]) if a else "",
                "since_s": a["start_s"] if a else None}

    def alarm_list(self) -> list[dict]:
        """The alarms so far, each with its evidence and its explanation (disturbance vector, growth,
        tests, likely kind, place: ``groundstation.jobs.alarm_explain``) in numbers and in words."""
        return [dict(a, evidence_text=evidence_text(a["evidence"]), **self._explained(a)) for a in self.tracker.alarms]

    def anomaly_places(self) -> list[tuple[float, float]]:
        """(lat, lon) [deg] of every ended alarm explained as "fixed in place" (a magnetic anomaly
        on the ground, drawn on the route)."""
        out = []
        for a in self.tracker.alarms:
            e = self._explained(a)["explanation"] if a["end_s"] is not None else None
            if e and e["kind"] == "fixed in place" and e.get("position"):
                out.append((e["position"]["lat"], e["position"]["lon"]))
        return out

    def _explained(self, alarm: dict) -> dict:
        """{explanation, explanation_text} of one alarm: the replay's whole-log steps up to the
        cursor, or the live link's history; a closed alarm's is kept."""
        key = (alarm["start_s"], alarm["end_s"])
        if key in self._explanations:
            return self._explanations[key]
        r = self.review
        if r is not None:
            steps, signal = r.explain_steps, r.motor_signal
            end = alarm["end_s"] if alarm["end_s"] is not None else self.t_s
        else:
            steps, signal, end = self.analyzer.explain_history.steps(), self.analyzer.motor_signal, alarm["end_s"]
        e = explain_span(steps, alarm["start_s"], end) if steps is not None else None
        out = {"explanation": e, "explanation_text": explanation_text(e, signal)}
        if alarm["end_s"] is not None:
            self._explanations[key] = out
        return out

    # ------------------------------------------------------------------ reading
    def rows(self) -> np.ndarray:
        """Record rows shown so far (a view: copy before leaving the lock)."""
        if self.review is not None:
            return self.review.rows[:self.n_shown]
        return self._rows.view()

    def last_row(self) -> np.ndarray | None:
        rows = self.rows()
        return rows[-1] if len(rows) else None

    def attitude_source(self) -> str | None:
        """Which estimate the attitude of the last row shown is: "offline" (a replayed log's
        smoother, ``hub.review``) or "causal" (the live link's AHRS, a replay's INS/GPS stretch)."""
        r = self.review
        if r is not None:
            src = r.attitude_source
            return str(src[self.n_shown - 1]) if src is not None and 0 < self.n_shown <= len(src) else None
        return "causal" if self._rows.n else None

    def route(self) -> np.ndarray:
        """GPS fixes shown so far: [t_s, lat_deg, lon_deg, fix_type, alarm]."""
        if self.review is not None:
            return self.review.gps[:self.gps_shown]
        return self._route.view()

    def origin(self) -> tuple[float, float] | None:
        """Local tangent-plane origin of the route: the preset line's A, else the first fix."""
        if self.line is not None:
            return tuple(self.line["a"])
        route = self.route()
        return (float(route[0, 1]), float(route[0, 2])) if len(route) else None

    def earth_field(self):
        return self.review.earth_field if self.review is not None else self.analyzer.earth_field
