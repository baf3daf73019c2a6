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
from groundstation.io.params import param_value_problem
from groundstation.samples import MissionSample, ParamSample
from groundstation.station.hub.sources import ConflictError

__all__ = ["VehicleLink", "same_float32", "WATCHED_MESSAGES", "RESULT_TEXT", "passive_refusal", "is_compass_param"]

WATCHED_MESSAGES = ("COMMAND_ACK", "MAG_CAL_PROGRESS", "MAG_CAL_REPORT")
RESULT_TEXT = {0: "accepted", 1: "temporarily rejected", 2: "denied", 3: "unsupported", 4: "failed",
               5: "in progress", 6: "cancelled"}


COMPASS_PARAM_PREFIXES = ("COMPASS_", "CAL_MAG")
OWN_COMMAND_EFFECT_S = 10.0     # compass parameters the autopilot saves this soon after our command are its answer
# A vehicle still sending a parameter list answers a PARAM_SET after the list's values queued before
# it (ArduPilot SITL at 8x on a loaded machine: echoes 1-4 s late, the write judged failed although
# every value was stored).  While other PARAM_VALUEs keep coming (gaps < LIST_GAP_S) a try waits
# on, up to LIST_WAIT_FACTOR times its timeout.
LIST_GAP_S = 0.3
LIST_WAIT_FACTOR = 8.0


def is_compass_param(name: str) -> bool:
    """ArduPilot COMPASS_* and PX4 CAL_MAG* parameters: the autopilot's compass calibration."""
    return name.startswith(COMPASS_PARAM_PREFIXES)


def passive_refusal(link) -> str:
    """Why nothing is written on a passive link, and what to do instead."""
    why = getattr(link, "passive_reason", None) or "passive mode"
    return (f"MagStation only listens on this link ({why}): it writes nothing to the vehicle. Export the "
            "parameters (.param) and load them with the other ground station, or start MagStation "
            "without --passive as the only ground station sending to the vehicle")


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
        self._last_command_s = -1e9
        self._last_other_param_s = -1e9      # monotonic time of the last PARAM_VALUE no write awaits
        self.reset(None, {})

    def reset(self, autopilot: str | None, params: dict[str, float]) -> None:
        """A new source: its autopilot (None until the HEARTBEAT says) and parameter table."""
        self.autopilot = autopilot
        self.params: dict[str, float] = dict(params)
        self.changed_elsewhere: dict[str, tuple[float, float]] = {}   # name -> (old, new), not by our writes
        self.refused_values: dict[str, str] = {}      # name -> why its last value was refused
        self.refused_count = 0
        self.changed_by_autopilot: dict[str, tuple[float, float, str]] = {}   # name -> (old, new, why)
        self.mission_items: dict[int, tuple[float, float, float]] = {}   # live: raw sequence numbers

    # ------------------------------------------------------------------ receiving
    def on_param(self, s: ParamSample) -> bool:
        """Cache a PARAM_VALUE; True when it changed a compass parameter we did not write
        (another ground station did: the cached value differs and no write of ours awaits it).
        A value ``param_value_problem`` refuses (NaN, infinite, beyond the autopilot's range) is
        not cached: counted in ``refused_values`` (name -> why) and ``refused_count``."""
        problem = param_value_problem(s.name, s.value)
        if problem is not None:
            self.refused_values[s.name] = problem
            self.refused_count += 1
            return False
        old = self.params.get(s.name)
        self.params[s.name] = s.value
        echoes = self._waiters.get(s.name)
        if echoes is not None:
            echoes.append(s.value)
            return False
        self._last_other_param_s = time.monotonic()
        if old is None or same_float32(old, s.value) or not is_compass_param(s.name):
            return False
        if time.monotonic() - self._last_command_s < OWN_COMMAND_EFFECT_S:
            return False        # the autopilot saving its own calibration after our command
        self.changed_elsewhere[s.name] = (old, s.value)
        return True

    def changed_by_itself(self, name: str, why: str) -> None:
        """A compass parameter the autopilot changed itself: not another station's change."""
        old, new = self.changed_elsewhere.pop(name)
        self.changed_by_autopilot[name] = (old, new, why)

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
        if link is None or getattr(link, "passive", False):
            return
        try:
            link.mav.mav.param_request_list_send(link.decoder.vehicle_sysid or 1, 0)
        except Exception:  # no peer yet (UDP before the first packet): asked again on link up
            pass

    def send_command(self, link, command: int, *params: float) -> bool:
        """COMMAND_LONG to the autopilot (component 1); False when it could not be sent.

        Raises:
            ConflictError: the link is passive (the message says what to do instead).
        """
        if getattr(link, "passive", False):
            raise ConflictError(passive_refusal(link))
        p = [float(v) for v in params] + [0.0] * (7 - len(params))
        self._last_command_s = time.monotonic()
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
        if getattr(link, "passive", False):      # became passive since the write was asked for
            return [], sorted(params), {}
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
            longest = time.monotonic() + timeout_s * LIST_WAIT_FACTOR
            while pending:
                now = time.monotonic()
                listing = now - self._last_other_param_s < LIST_GAP_S     # a list still coming in
                if now >= deadline and not (listing and now < longest):
                    break
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
