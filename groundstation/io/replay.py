"""Replay of a recorded log: as fast as possible (analysis) or paced at real time x speed
(the live view), with pause, seek and speed changes.

The replayer holds the time-ordered samples (``SampleTimeline``: made when due, so a long log
opens and seeks at once) and a log-time cursor.  The server's loop
calls ``due()`` regularly and gets every sample whose time has come; the clock is
injectable so pacing is tested without sleeping.
"""
from __future__ import annotations

import time
from typing import Callable, Iterator

import numpy as np

from groundstation.io.logs.builder import SampleTimeline
from groundstation.samples import FlightLog, Sample


class Replayer:
    def __init__(self, log: FlightLog, speed: float = 1.0, loop: bool = False,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not speed > 0:
            raise ValueError("replay speed must be > 0")
        self.log = log
        self.samples = SampleTimeline(log)
        self._times = self.samples.t_s
        self.loop = loop
        self.clock = clock
        self.speed = float(speed)
        self.paused = False
        self.more_to_come = False     # the log is the first part of a file still being read: hold at its end
        self.index = 0
        self.loops = 0
        self._anchor_wall = clock()
        self._anchor_log_t = float(self._times[0]) if len(self._times) else 0.0

    @property
    def duration_s(self) -> float:
        return float(self._times[-1]) if len(self._times) else 0.0

    @property
    def position_s(self) -> float:
        """Current log time of the cursor."""
        if self.paused:
            return self._anchor_log_t
        return self._anchor_log_t + (self.clock() - self._anchor_wall) * self.speed

    @property
    def finished(self) -> bool:
        return self.index >= len(self.samples) and not self.loop and not self.more_to_come

    def __iter__(self) -> Iterator[Sample]:
        """All remaining samples at once, unpaced (analysis)."""
        while self.index < len(self.samples):
            chunk = self.samples[self.index:self.index + 4096]
            for sample in chunk:
                self.index += 1
                yield sample

    def due(self, max_samples: int = 100_000) -> list[Sample]:
        """Samples whose log time has come since the last call (paced)."""
        if self.paused or not len(self.samples):
            return []
        now_t = self.position_s
        end = min(max(int(np.searchsorted(self._times, now_t, side="right")), self.index), self.index + max_samples)
        out = self.samples[self.index:end]
        self.index = end
        if self.index >= len(self.samples) and self.loop and not self.more_to_come:
            self.loops += 1
            self.seek(0.0)
        return out

    def _reanchor(self, log_t: float) -> None:
        self._anchor_wall = self.clock()
        self._anchor_log_t = log_t

    def pause(self) -> None:
        if not self.paused:
            self._reanchor(self.position_s)
            self.paused = True

    def resume(self) -> None:
        if self.paused:
            self.paused = False
            self._reanchor(self._anchor_log_t)

    def set_speed(self, speed: float) -> None:
        if not speed > 0:
            raise ValueError("replay speed must be > 0")
        self._reanchor(self.position_s)
        self.speed = float(speed)

    def seek(self, t_s: float) -> None:
        """Move the cursor to log time t_s (clamped to the log); the consumer should reset
        its estimators, since samples between the old and new position are skipped."""
        t = min(max(float(t_s), 0.0), self.duration_s)
        self.index = int(np.searchsorted(self._times, t, side="left"))
        self._anchor_log_t = t
        self._anchor_wall = self.clock()

    def continued(self, log: FlightLog) -> "Replayer":
        """A replayer of ``log`` (the whole file this replayer's log is the first part of) that
        goes on where this one is: same clock, speed, pause and loop, the samples already given
        not given again."""
        nxt = Replayer(log, speed=self.speed, loop=self.loop, clock=self.clock)
        nxt.paused, nxt.loops = self.paused, self.loops
        nxt._anchor_wall, nxt._anchor_log_t = self._anchor_wall, self._anchor_log_t
        if self.index > 0:     # past the samples of the last time given, as many as were given at it
            last = self._times[self.index - 1]
            given_at_last = self.index - int(np.searchsorted(self._times, last, side="left"))
            first_at_last = int(np.searchsorted(nxt._times, last, side="left"))
            nxt.index = min(first_at_last + given_at_last, len(nxt._times))
        return nxt
