"""What the station knows of the vehicle and says to it: identity, parameters, commands, confirmed writes.

``VehicleLink`` keeps the autopilot type, the parameter table (from the log or PARAM_VALUE) and
the live mission items, and writes parameters: every PARAM_SET is confirmed by its PARAM_VALUE
echo (a float32 equal to what was sent), retried, and the failures listed with what the vehicle
answered (nothing, or another value).  It sends COMMAND_LONG (``send_command``) and hands the
messages the sample stream does not carry (COMMAND_ACK, MAG_CAL_PROGRESS, MAG_CAL_REPORT) to the
hub through ``vehicle_messages``, collected by a pymavlink message hook on the link.  It does not
own a link: the hub passes the current one, and calls ``on_param`` with every PARAM_VALUE.
"""
from __future__ import annotations

import threading
import time
from collections import deque
from typing import Callable

import numpy as np

from groundstation.io.mavlink import mavlink2
from groundstation.samples import MissionSample, ParamSample

__all__ = ["VehicleLink", "same_float32", "WATCHED_MESSAGES", "RESULT_TEXT"]

WATCHED_MESSAGES = ("COMMAND_ACK", "MAG_CAL_PROGRESS", "MAG_CAL_REPORT")
RESULT_TEXT = {0: "accepted", 1: "temporarily rejected", 2: "denied", 3: "unsupported", 4: "failed",
               5: "in progress", 6: "cancelled"}


def same_float32(a: float, b: float) -> bool:
    """PARAM_VALUE echoes a float32: equal to the float32 of what we sent."""
    return abs(float(np.float32(a)) - float(np.float32(b))) <= 1e-6 * max(1.0, abs(b))


class VehicleLink:
    """Autopilot identity, parameter cache, live mission and confirmed parameter writes."""

    def __init__(self, lock: threading.RLock) -> None:
        self._lock = lock
        self._waiters: dict[str, list[float]] = {}
        self._inbox: deque = deque(maxlen=1000)
        self._watched = None
        self.reset(None, {})

    def reset(self, autopilot: str | None, params: dict[str, float]) -> None:
        """A new source: its autopilot (None until the HEARTBEAT says) and parameter table."""
        self.autopilot = autopilot
        self.params: dict[str, float] = dict(params)
        self.mission_items: dict[int, tuple[float, float, float]] = {}   # live: raw sequence numbers

    # ------------------------------------------------------------------ receiving
    def on_param(self, s: ParamSample) -> None:
        self.params[s.name] = s.value
        echoes = self._waiters.get(s.name)
        if echoes is not None:
            echoes.append(s.value)

    def on_mission_item(self, s: MissionSample) -> None:
        self.mission_items[s.seq] = (s.lat_deg, s.lon_deg, s.alt_m)

    def mission_waypoints(self) -> list[tuple[float, float, float]]:
        """The live mission in order (ArduPilot's item 0 is home, not a waypoint)."""
        wps = [self.mission_items[k] for k in sorted(self.mission_items)]
        if self.autopilot == "ardupilot" and 0 in self.mission_items and len(wps) > 2:
            wps = wps[1:]
        return wps

    # ------------------------------------------------------------------ sending
    @staticmethod
    def request_params(link) -> None:
        """Ask a live vehicle for its parameter table (PARAM_REQUEST_LIST)."""
        if link is None:
            return
        try:
            link.mav.mav.param_request_list_send(link.decoder.vehicle_sysid or 1, 0)
        except Exception:  # no peer yet (UDP before the first packet): asked again on link up
            pass

    @staticmethod
    def send_command(link, command: int, *params: float) -> bool:
        """COMMAND_LONG to the autopilot (component 1); False when it could not be sent."""
        p = [float(v) for v in params] + [0.0] * (7 - len(params))
        try:
            link.mav.mav.command_long_send(link.decoder.vehicle_sysid or 1, 1, int(command), 0, *p[:7])
            return True
        except Exception:
            return False

    def vehicle_messages(self, link) -> list:
        """COMMAND_ACK / MAG_CAL_* messages received since the last call (installs the hook once)."""
        if link is not None and link is not self._watched:
            inbox = self._inbox

            def hook(_conn, msg) -> None:
                if msg.get_type() in WATCHED_MESSAGES and msg.get_srcSystem() != 255:
                    inbox.append(msg)

            try:
                link.mav.message_hooks.append(hook)
                self._watched = link
            except AttributeError:
                pass
        out = []
        while self._inbox:
            out.append(self._inbox.popleft())
        return out

    def write_params(self, link, params: dict[str, float], progress: Callable[[list[str]], None],
                     tries: int = 3, timeout_s: float = 1.0) -> tuple[list[str], list[str], dict[str, float]]:
        """PARAM_SET each value until its PARAM_VALUE echo matches; returns (confirmed, failed,
        last echo of each failed name that was answered at all).

        Blocks (run it in a thread); ``progress(confirmed)`` is called under the hub lock as
        echoes arrive.  Confirmed values enter the parameter cache as the vehicle stores them.
        """
        pending = dict(params)
        confirmed: list[str] = []
        echoed: dict[str, float] = {}
        for _ in range(tries):
            with self._lock:
                waiters = {name: self._waiters.setdefault(name, []) for name in pending}
                for w in waiters.values():
                    w.clear()
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
                        if waiters[name]:
                            echoed[name] = waiters[name][-1]
                        if any(same_float32(v, pending[name]) for v in waiters[name]):
                            confirmed.append(name)
                            del pending[name]
                    progress(list(confirmed))
            if not pending:
                break
        with self._lock:
            for name in params:
                self._waiters.pop(name, None)
            if not pending:
                for name, value in params.items():
                    self.params[name] = float(np.float32(value))
        return confirmed, sorted(pending), {n: echoed[n] for n in pending if n in echoed}
