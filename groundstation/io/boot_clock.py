"""The vehicle's boot clock on the log's time base: the time of a MAVLink message that carries
one (time_boot_ms; RAW_IMU's and HIGHRES_IMU's time_usec where it is a boot time).  One rule for
the live decoder (``decode.MavlinkDecoder``, message by message) and the .tlog reader
(``logs.mavlink_columns``, ``BootClock.times`` over whole columns)."""
from __future__ import annotations

import math

import numpy as np

__all__ = ["BOOT_USEC_MAX", "BootClock", "boot_ms_of_usec"]

# RAW_IMU's and HIGHRES_IMU's time_usec is "UNIX epoch or time since system boot" (MAVLink XML).
# Below this it is the boot clock (ArduPilot: AP_HAL::micros64, the clock of every time_boot_ms;
# PX4: hrt_absolute_time); above it, epoch microseconds (over 1.5e15), not a boot time.
BOOT_USEC_MAX = 1e14              # 3.2 years of up-time


def boot_ms_of_usec(time_usec):
    """A time_usec as boot milliseconds (float), NaN where it is not a boot time (0, or at least
    ``BOOT_USEC_MAX``: UNIX epoch).  Scalar or array; the one rule of both MAVLink readers."""
    u = np.asarray(time_usec, dtype=np.float64)
    return np.where((u > 0) & (u < BOOT_USEC_MAX), u / 1000.0, np.nan)


class BootClock:
    """Maps a message's time_boot_ms onto the log's time base.

    Radio links deliver packets in bursts, so arrival times jitter by tens of ms; the
    vehicle's boot clock does not.  t = boot_s + offset, where offset is the smallest
    (arrival - boot) seen so far (a packet never arrives before it is sent).  A reboot (boot
    time going back) re-anchors the offset at once; packets arriving more than
    ``REANCHOR_LATE_S`` late re-anchor it only when they stay that late for ``REANCHOR_AFTER_S``
    of boot time (a vehicle clock that runs slow, e.g. SITL below real time): a station held up
    for a few seconds then reading the backlog in a burst must not move the times forward and
    then back (the tests would restart as after a seek).
    """

    REANCHOR_LATE_S = 2.0
    REANCHOR_AFTER_S = 5.0

    def __init__(self) -> None:
        self.lag_s = 0.0                 # the last message's delay beyond the least seen (arrival - t)
        self.offset_s: float | None = None
        self.last_boot_s = -math.inf
        self._late_since_boot_s: float | None = None
        self._late_offset_s = math.inf

    def __call__(self, boot_ms: float, arrival_s: float) -> float:
        boot_s = boot_ms * 1e-3
        candidate = arrival_s - boot_s
        if self.offset_s is None or boot_s < self.last_boot_s - 1.0:
            self._anchor(candidate)
        elif candidate < self.offset_s:
            self.offset_s = candidate
        if candidate - self.offset_s > self.REANCHOR_LATE_S:
            if self._late_since_boot_s is None:
                self._late_since_boot_s = boot_s
            self._late_offset_s = min(self._late_offset_s, candidate)
            if boot_s - self._late_since_boot_s >= self.REANCHOR_AFTER_S:
                self._anchor(self._late_offset_s)
        else:
            self._late_since_boot_s, self._late_offset_s = None, math.inf
        self.last_boot_s = boot_s
        t = boot_s + self.offset_s
        self.lag_s = arrival_s - t
        return t

    def times(self, boot_ms: np.ndarray, arrival_s: np.ndarray) -> np.ndarray:
        """``self(boot_ms[k], arrival_s[k])`` for every k in order, as one array (the same state
        afterwards).  Between events (a reboot, a late re-anchor) the offset is the running
        minimum of arrival - boot (``np.minimum.accumulate``); each event is one call of the
        per-message step, then the vectorised stretch goes on: linear in the messages."""
        boot = np.asarray(boot_ms, dtype=float) * 1e-3
        arrival = np.asarray(arrival_s, dtype=float)
        cand = arrival - boot
        out = np.empty(len(boot))
        k, window = 0, 256
        while k < len(boot):
            if self.offset_s is None:
                out[k] = self(float(boot_ms[k]), float(arrival[k]))
                k += 1
                continue
            b, c = boot[k:k + window], cand[k:k + window]
            prev_b = np.concatenate(([self.last_boot_s], b[:-1]))
            reboot = b < prev_b - 1.0
            off = np.minimum.accumulate(np.concatenate(([self.offset_s], c)))[1:]
            late = c - off > self.REANCHOR_LATE_S
            # the boot time each late stretch started at (carried in from before the window)
            starts = late & ~np.concatenate(([self._late_since_boot_s is not None], late[:-1]))
            run = np.cumsum(starts)
            start_b = np.where(run > 0, b[np.flatnonzero(starts)][np.maximum(run - 1, 0)] if starts.any() else 0.0,
                               self._late_since_boot_s if self._late_since_boot_s is not None else 0.0)
            reanchor = late & (b - start_b >= self.REANCHOR_AFTER_S)
            events = np.flatnonzero(reboot | reanchor)
            e = int(events[0]) if len(events) else len(b)
            if e:
                out[k:k + e] = b[:e] + off[:e]
                if late[e - 1]:
                    in_run = (run[:e] == run[e - 1]) & late[:e]
                    carried = self._late_offset_s if run[e - 1] == 0 else math.inf
                    self._late_since_boot_s = float(start_b[e - 1])
                    self._late_offset_s = min(carried, float(c[:e][in_run].min()))
                else:
                    self._late_since_boot_s, self._late_offset_s = None, math.inf
                self.offset_s, self.last_boot_s = float(off[e - 1]), float(b[e - 1])
            k += e
            if e < len(b):          # the event: one per-message step
                out[k] = self(float(boot_ms[k]), float(arrival[k]))
                k += 1
                window = 256
            else:
                window = min(window * 2, 1 << 13)         # bounded temporaries
        if len(out):
            self.lag_s = float(arrival[-1] - out[-1])
        return out

    def _anchor(self, offset_s: float) -> None:
        self.offset_s = offset_s
        self._late_since_boot_s, self._late_offset_s = None, math.inf
