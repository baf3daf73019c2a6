"""Replay of a recorded log: as fast as possible (analysis) or paced at real time x speed
(the live view), with pause, seek and speed changes.

The replayer holds the time-ordered sample list and a log-time cursor.  The server's loop
calls ``due()`` regularly and gets every sample whose time has come; the clock is
injectable so pacing is tested without sleeping.
"""
from __future__ import annotations

import bisect
import time
from typing import Callable, Iterator

from groundstation.io.logs import iter_samples
from groundstation.samples import FlightLog, Sample


class Replayer:
    def __init__(self, log: FlightLog, speed: float = 1.0, loop: bool = False,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not speed > 0:
            raise ValueError("replay speed must be > 0")
        self.log = log
        self.samples: list[Sample] = list(iter_samples(log))
        self._times = [s.t_s for s in self.samples]
        self.loop = loop
        self.clock = clock
        self.speed = float(speed)
        self.paused = False
        self.index = 0
        self.loops = 0
        self._anchor_wall = clock()
        self._anchor_log_t = self._times[0] if self._times else 0.0

    @property
    def duration_s(self) -> float:
        return self._times[-1] if self._times else 0.0

    @property
    def position_s(self) -> float:
        """Current log time of the cursor."""
        if self.paused:
            return self._anchor_log_t
        return self._anchor_log_t + (self.clock() - self._anchor_wall) * self.speed

    @property
    def finished(self) -> bool:
        return self.index >= len(self.samples) and not self.loop

    def __iter__(self) -> Iterator[Sample]:
        """All remaining samples at once, unpaced (analysis)."""
        while self.index < len(self.samples):
            self.index += 1
            yield self.samples[self.index - 1]

    def due(self, max_samples: int = 100_000) -> list[Sample]:
        """Samples whose log time has come since the last call (paced)."""
        if self.paused or not self.samples:
            return []
        now_t = self.position_s
        end = min(bisect.bisect_right(self._times, now_t, lo=self.index), self.index + max_samples)
        out = self.samples[self.index:end]
        self.index = end
        if self.index >= len(self.samples) and self.loop:
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
        self.index = bisect.bisect_left(self._times, t)
        self._anchor_log_t = t
        self._anchor_wall = self.clock()
