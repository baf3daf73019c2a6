"""A fake autopilot on loopback UDP: streams a simulation as real MAVLink and keeps parameters.

Sends the simulation's messages (``[(unix_s, pymavlink message)]``) to the station's
``udpin:`` port at real time x speed, a HEARTBEAT each second saying which autopilot it is
(ArduPilot or PX4), and answers PARAM_SET / PARAM_REQUEST_READ / PARAM_REQUEST_LIST with
PARAM_VALUE from its own table, as an autopilot does.  Used by tests and benchmarks/live.py.

The link can be dropped and restored (``set_link``) to exercise the station's reconnect
handling; ``reject_params`` names parameters that never stick (to test the failure path).
"""
from __future__ import annotations

import copy
import socket
import threading
import time
from typing import Iterable

from groundstation.io.mavlink import mavlink2, new_encoder

AUTOPILOT_IDS = {"ardupilot": mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, "px4": mavlink2.MAV_AUTOPILOT_PX4}


class FakeVehicle:
    def __init__(self, messages: Iterable, port: int, speed: float = 1.0, autopilot: str = "ardupilot",
                 host: str = "127.0.0.1", params: dict[str, float] | None = None,
                 reject_params: Iterable[str] = (), loop: bool = False, system_id: int = 1) -> None:
        self.messages = [(float(t), compress_time(m, speed)) for t, m in messages if m.get_type() != "HEARTBEAT"]
        self.target = (host, int(port))
        self.speed = float(speed)
        self.autopilot = autopilot
        if params is None:   # start from the parameters the simulation announces
            params = {_param_name(m.param_id): float(m.param_value) for _, m in self.messages
                      if m.get_type() == "PARAM_VALUE"}
        self.params: dict[str, float] = dict(params)
        self.reject_params = set(reject_params)
        self.loop = loop
        self.link_up = True
        self.sent = 0                 # messages of the simulation due so far (sent or dropped)
        self.delivered: dict[str, int] = {}   # message type -> packets put on the wire
        self.send_times: list[float] = []   # time.monotonic() of each simulation message sent
        self.record_send_times = False
        self.param_sets: list[tuple[str, float]] = []
        self.finished = threading.Event()
        self._enc = new_encoder(system_id, 1)
        self._parser = mavlink2.MAVLink(None)
        self._parser.robust_parsing = True
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind((host, 0))
        self._sock.settimeout(0.1)
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    # --------------------------------------------------------------------------------- control
    def start(self) -> "FakeVehicle":
        for target in (self._stream, self._heartbeats, self._receive):
            t = threading.Thread(target=target, daemon=True, name=f"fake-vehicle-{target.__name__}")
            t.start()
            self._threads.append(t)
        return self

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2)
        self._sock.close()

    def set_link(self, up: bool) -> None:
        """Drop (False) or restore (True) the radio link: nothing is sent or heard while down."""
        self.link_up = up

    def send_raw(self, data: bytes) -> None:
        """Put arbitrary bytes on the wire (garbage tests)."""
        self._sock.sendto(data, self.target)

    def __enter__(self) -> "FakeVehicle":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # --------------------------------------------------------------------------------- sending
    def _send(self, msg) -> None:
        with self._send_lock:
            buf = bytes(msg.pack(self._enc))
            if not self.link_up:
                return
            try:
                self._sock.sendto(buf, self.target)
            except OSError:
                return
            kind = msg.get_type()
            self.delivered[kind] = self.delivered.get(kind, 0) + 1

    def _stream(self) -> None:
        while not self._stop.is_set():
            if not self.messages:
                break
            t0 = self.messages[0][0]
            wall0 = time.monotonic()
            for unix, msg in self.messages:
                due = wall0 + (unix - t0) / self.speed
                delay = due - time.monotonic()
                if delay > 0 and self._stop.wait(delay):
                    return
                self._send(msg)
                self.sent += 1
                if self.record_send_times:
                    self.send_times.append(time.monotonic())
            if not self.loop:
                break
        self.finished.set()

    def _heartbeats(self) -> None:
        while not self._stop.is_set():
            self._send(mavlink2.MAVLink_heartbeat_message(
                mavlink2.MAV_TYPE_QUADROTOR, AUTOPILOT_IDS.get(self.autopilot, 0), 0, 0,
                mavlink2.MAV_STATE_ACTIVE, 3))
            self._stop.wait(1.0)

    # --------------------------------------------------------------------------------- parameters
    def _param_value(self, name: str) -> None:
        names = sorted(self.params)
        value = self.params[name]
        self._send(mavlink2.MAVLink_param_value_message(
            name.encode(), float(value), mavlink2.MAV_PARAM_TYPE_REAL32, len(names), names.index(name)))

    def _receive(self) -> None:
        while not self._stop.is_set():
            try:
                data = self._sock.recv(4096)
            except (socket.timeout, OSError):
                continue
            if not self.link_up:
                continue
            try:
                msgs = self._parser.parse_buffer(data) or []
            except Exception:
                continue
            for msg in msgs:
                self._handle(msg)

    def _handle(self, msg) -> None:
        kind = msg.get_type()
        if kind == "PARAM_SET":
            name = _param_name(msg.param_id)
            self.param_sets.append((name, msg.param_value))
            if name not in self.reject_params:
                self.params[name] = float(msg.param_value)
            if name in self.params:
                self._param_value(name)
        elif kind == "PARAM_REQUEST_READ":
            name = _param_name(msg.param_id)
            if msg.param_index >= 0 and not name:
                names = sorted(self.params)
                name = names[msg.param_index] if msg.param_index < len(names) else ""
            if name in self.params:
                self._param_value(name)
        elif kind == "PARAM_REQUEST_LIST":
            for name in sorted(self.params):
                self._param_value(name)


_RATE_FIELDS = ("xgyro", "ygyro", "zgyro", "rollspeed", "pitchspeed", "yawspeed", "vel", "vx", "vy", "vz")
_INT16 = {"xgyro", "ygyro", "zgyro", "vx", "vy", "vz"}


def compress_time(msg, speed: float):
    """The same motion performed ``speed`` times faster: boot times / speed, angular rates and
    velocities x speed (a copy; the simulation's message is left alone).  Without this a sped-up
    stream would carry rates that do not match the time between packets."""
    if speed == 1.0:
        return msg
    out = copy.copy(msg)
    if hasattr(out, "time_boot_ms"):
        out.time_boot_ms = int(out.time_boot_ms / speed)
    for name in _RATE_FIELDS:
        value = getattr(out, name, None)
        if value is None or (name == "vel" and value == 65535):
            continue
        if isinstance(value, int):
            limit = 32767 if name in _INT16 else 65534
            value = max(-limit, min(limit, int(round(value * speed))))
        else:
            value = value * speed
        setattr(out, name, value)
    return out


def _param_name(raw) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).rstrip("\x00")
