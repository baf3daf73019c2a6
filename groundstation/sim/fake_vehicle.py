"""A fake autopilot on loopback UDP: streams a simulation as real MAVLink and acts on commands.

Sends the simulation's messages (``[(unix_s, pymavlink message)]``) to the station's
``udpin:`` port at real time x speed, a HEARTBEAT each second saying which autopilot it is
(ArduPilot or PX4), and answers as an autopilot does:

* PARAM_SET / PARAM_REQUEST_READ / PARAM_REQUEST_LIST with PARAM_VALUE from its own table;
  ``param_mode`` "ignore" drops every PARAM_SET (no echo), "corrupt" stores and echoes a wrong
  value; ``reject_params`` names parameters that never stick (the old value is echoed).
* Compass fields are corrected with its own calibration parameters at send time
  (``fake_autopilot.corrected_field``): the mag of RAW_IMU/SCALED_IMU (compass 0), SCALED_IMU2
  (1) and SCALED_IMU3 (2) is what the autopilot would report, so a parameter write shows.
* MAV_CMD_DO_START_MAG_CAL / DO_ACCEPT_MAG_CAL / DO_CANCEL_MAG_CAL: the onboard calibrator
  (ArduPilot only) with MAG_CAL_PROGRESS and MAG_CAL_REPORT; MAV_CMD_FIXED_MAG_CAL_YAW (ArduPilot);
  MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN (param1 = 1): COMMAND_ACK, silence for ``reboot_silence_s``,
  then the boot clock restarts and ``after_reboot`` (if given) is streamed.  Every command gets a
  COMMAND_ACK (UNSUPPORTED for the rest).

The link can be dropped and restored (``set_link``) to exercise the station's reconnect handling.
``rx_datagrams`` counts every datagram the station sent (passive mode must send none); ``mirror``
sends a copy of every packet straight to another address (a latency reference).  With
``signing_key`` it signs what it sends; with ``require_signing`` too it refuses (counts in
``refused_unsigned``, does not act on) every packet without a valid signature, as ArduPilot does
once a key is set.
"""
from __future__ import annotations

import copy
import socket
import threading
import time
from typing import Iterable

import numpy as np

from estimators.geomag import decimal_year_from_unix, earth_field
from groundstation.io.boot_clock import boot_ms_of_usec
from groundstation.io.mavlink import mavlink2, new_encoder
from groundstation.sim.fake_autopilot import (OnboardCalibrator, corrected_field, default_params,
                                              fixed_yaw_params, rotated_raw)
from groundstation.sim.vehicle_streams import COMPASS_MESSAGES

AUTOPILOT_IDS = {"ardupilot": mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, "px4": mavlink2.MAV_AUTOPILOT_PX4}
_M = mavlink2
ACCEPTED, FAILED, UNSUPPORTED = _M.MAV_RESULT_ACCEPTED, _M.MAV_RESULT_FAILED, _M.MAV_RESULT_UNSUPPORTED


class FakeVehicle:
    def __init__(self, messages: Iterable, port: int, speed: float = 1.0, autopilot: str = "ardupilot",
                 host: str = "127.0.0.1", params: dict[str, float] | None = None,
                 reject_params: Iterable[str] = (), loop: bool = False, system_id: int = 1,
                 param_mode: str = "normal", after_reboot: Iterable | None = None,
                 reboot_silence_s: float = 4.0, signing_key: bytes | None = None,
                 require_signing: bool = False) -> None:
        self.messages = self._prepare(messages, speed)
        self.target = (host, int(port))
        self.speed = float(speed)
        self.autopilot = autopilot
        self.n_compasses = 1 + max((COMPASS_MESSAGES.get(m.get_type(), 0) for _, m in self.messages), default=0)
        if params is None:   # the parameters the simulation announces, else a fresh table
            params = {_param_name(m.param_id): float(m.param_value) for _, m in messages
                      if m.get_type() == "PARAM_VALUE"} or default_params(autopilot, self.n_compasses)
        self.params: dict[str, float] = dict(params)
        self.reject_params = set(reject_params)
        self.param_mode = param_mode
        self.after_reboot = None if after_reboot is None else self._prepare(after_reboot, speed)
        self.reboot_silence_s = float(reboot_silence_s)
        self.loop = loop
        self.link_up = True
        self.rebooting = False
        self.reboots = 0
        self.sent = 0                 # messages of the simulation due so far (sent or dropped)
        self.delivered: dict[str, int] = {}   # message type -> packets put on the wire
        self.send_times: list[float] = []   # time.monotonic() of each simulation message sent
        self.record_send_times = False
        self.param_sets: list[tuple[str, float]] = []
        self.param_lists = 0                     # PARAM_REQUEST_LIST received (whole-table downloads)
        self.commands: list[tuple[int, tuple]] = []       # (command, params) received
        self.calibrator = OnboardCalibrator()
        self.last_corrected: dict[int, np.ndarray] = {}   # compass -> last reported field (mG)
        self.last_attitude = (0.0, 0.0, 0.0)
        self.last_position: tuple[float, float, float] | None = None
        self.finished = threading.Event()
        self._reboot_request = threading.Event()
        self.rx_datagrams = 0
        self.refused_unsigned = 0
        self.mirror: tuple[str, int] | None = None    # also send every packet here (latency reference)
        self.send_log: list[tuple[int, float]] = []   # (MAVLink seq, time.monotonic()) with record_send_times
        self.delivered_packets: list[bytes] | None = None   # set to [] to keep every packet put on the wire
        self._enc = new_encoder(system_id, 1)
        self._parser = mavlink2.MAVLink(None)
        self._parser.robust_parsing = True
        if signing_key is not None:
            _sign(self._enc, self._parser, signing_key, require_signing)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind((host, 0))
        self._sock.settimeout(0.1)
        self._send_lock = threading.Lock()
        self._state_lock = threading.RLock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.hold_before: int | None = None    # the stream waits before this message until release()
        self._released = threading.Event()

    @staticmethod
    def _prepare(messages: Iterable, speed: float) -> list:
        return [(float(t), compress_time(m, speed)) for t, m in messages
                if m.get_type() not in ("HEARTBEAT", "PARAM_VALUE")]

    # --------------------------------------------------------------------------------- control
    def start(self) -> "FakeVehicle":
        for target in (self._stream, self._heartbeats, self._receive, self._calibration_reports):
            t = threading.Thread(target=target, daemon=True, name=f"fake-vehicle-{target.__name__}")
            t.start()
            self._threads.append(t)
        return self

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2)
        self._sock.close()

    def release(self) -> None:
        """Let a stream held at ``hold_before`` go on (its timing restarts from there)."""
        self.hold_before = None
        self._released.set()

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
            self._enc.seq = (self._enc.seq + 1) % 256      # pack() alone leaves the sequence number
            if not self.link_up or self.rebooting:
                return
            try:
                self._sock.sendto(buf, self.target)
            except OSError:
                return
            if self.record_send_times:
                self.send_log.append((buf[4] if buf[0] == 0xFD else buf[2], time.monotonic()))
            if self.mirror is not None:
                self._sock.sendto(buf, self.mirror)
            kind = msg.get_type()
            self.delivered[kind] = self.delivered.get(kind, 0) + 1
            if self.delivered_packets is not None:
                self.delivered_packets.append(buf)

    def _vehicle_view(self, msg):
        """The message as the autopilot sends it: compass fields corrected by its parameters;
        the onboard calibrator sees the rotated raw field; attitude/position remembered."""
        kind = msg.get_type()
        k = COMPASS_MESSAGES.get(kind)
        if k is None:
            if kind == "ATTITUDE":
                self.last_attitude = (msg.roll, msg.pitch, msg.yaw)
            elif kind == "GPS_RAW_INT" and msg.fix_type >= 3:
                self.last_position = (msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3)
            return msg
        raw = np.asarray(getattr(msg, "raw_mag_mG", (msg.xmag, msg.ymag, msg.zmag)), float)
        with self._state_lock:
            if self.calibrator.active and self.autopilot == "ardupilot":
                self.calibrator.new_sample(k, rotated_raw(self.params, self.autopilot, k, raw))
            corrected = corrected_field(self.params, self.autopilot, k, raw)
        self.last_corrected[k] = corrected
        out = copy.copy(msg)
        out.xmag, out.ymag, out.zmag = (int(max(-32767, min(32767, round(v)))) for v in corrected)
        return out

    def _stream(self) -> None:
        """Play the simulation; after its end keep answering (heartbeats, commands) and honour a
        reboot: silence, then ``after_reboot`` (or the rest of the simulation)."""
        queue, start = self.messages, 0
        while not self._stop.is_set():
            stopped_at = self._play(queue, start) if start < len(queue) else None
            if self._stop.is_set():
                return
            if stopped_at is None:
                if self.loop and queue:
                    start = 0
                    continue
                self.finished.set()
                while not self._reboot_request.is_set():
                    if self._stop.wait(0.05):
                        return
                stopped_at = len(queue)
            self._stop.wait(self.reboot_silence_s)
            with self._state_lock:
                self.calibrator.cancel()
                self.rebooting = False
                self._reboot_request.clear()
            if self.after_reboot is not None:
                queue, start, self.after_reboot = self.after_reboot, 0, None
            else:
                start = stopped_at

    def _play(self, queue: list, start: int) -> int | None:
        """Send queue[start:] on time; the index where a reboot stopped it, else None."""
        t0, wall0 = queue[start][0], time.monotonic()
        for i in range(start, len(queue)):
            unix, msg = queue[i]
            if self.hold_before is not None and self.sent >= self.hold_before:
                while not self._released.wait(0.05):          # a test holds the vehicle still here
                    if self._stop.is_set():
                        return None
                self._released.clear()
                t0, wall0 = unix, time.monotonic()
            due = wall0 + (unix - t0) / self.speed
            while True:
                if self._reboot_request.is_set():
                    return i
                delay = due - time.monotonic()
                if delay <= 0:
                    break
                if self._stop.wait(min(delay, 0.05)):
                    return None
            self._send(self._vehicle_view(msg))
            self.sent += 1
            if self.record_send_times:
                self.send_times.append(time.monotonic())
        return None

    def _heartbeats(self) -> None:
        while not self._stop.is_set():
            self._send(_M.MAVLink_heartbeat_message(
                _M.MAV_TYPE_QUADROTOR, AUTOPILOT_IDS.get(self.autopilot, 0), 0, 0, _M.MAV_STATE_ACTIVE, 3))
            self._stop.wait(1.0)

    def _calibration_reports(self) -> None:
        """MAG_CAL_PROGRESS (~5 Hz) while the onboard calibrator runs, MAG_CAL_REPORT (~1 Hz) after."""
        tick = 0
        while not self._stop.wait(0.2):
            tick += 1
            with self._state_lock:
                progress = self.calibrator.progress_fields()
                reports = self.calibrator.report_fields(self.params) if tick % 5 == 0 else []
            for fields in progress:
                self._send(_M.MAVLink_mag_cal_progress_message(*fields))
            for fields in reports:
                self._send(_M.MAVLink_mag_cal_report_message(*fields))

    # --------------------------------------------------------------------------------- receiving
    def _receive(self) -> None:
        while not self._stop.is_set():
            try:
                data = self._sock.recv(4096)
            except (socket.timeout, OSError):
                continue
            self.rx_datagrams += 1
            if not self.link_up or self.rebooting:
                continue
            try:
                msgs = self._parser.parse_buffer(data) or []
            except Exception:
                continue
            for msg in msgs:
                if msg.get_type() == "BAD_DATA":
                    self.refused_unsigned += "signature" in str(getattr(msg, "reason", ""))
                    continue
                self._handle(msg)

    def _handle(self, msg) -> None:
        kind = msg.get_type()
        if kind == "PARAM_SET":
            self._param_set(_param_name(msg.param_id), float(msg.param_value))
        elif kind == "PARAM_REQUEST_READ":
            name = _param_name(msg.param_id)
            if msg.param_index >= 0 and not name:
                names = sorted(self.params)
                name = names[msg.param_index] if msg.param_index < len(names) else ""
            if name in self.params:
                self._param_value(name)
        elif kind == "PARAM_REQUEST_LIST":
            self.param_lists += 1
            for name in sorted(self.params):
                self._param_value(name)
        elif kind == "COMMAND_LONG":
            args = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
            self.commands.append((msg.command, args))
            result = self._command(msg.command, args)
            self._send(_M.MAVLink_command_ack_message(msg.command, result, 0, 0, msg.get_srcSystem(),
                                                      msg.get_srcComponent()))

    # --------------------------------------------------------------------------------- parameters
    def _param_value(self, name: str) -> None:
        names = sorted(self.params)
        value = self.params[name]
        self._send(_M.MAVLink_param_value_message(
            name.encode(), float(value), _M.MAV_PARAM_TYPE_REAL32, len(names), names.index(name)))

    def _param_set(self, name: str, value: float) -> None:
        self.param_sets.append((name, value))
        if self.param_mode == "ignore":
            return
        if self.param_mode == "corrupt":
            value = value * 1.5 + 1.0
        with self._state_lock:
            if name not in self.reject_params:
                self.params[name] = value
        if name in self.params:
            self._param_value(name)

    def _save(self, values: dict[str, float]) -> None:
        """Parameters the autopilot sets itself (calibration accepted): stored and announced."""
        with self._state_lock:
            self.params.update(values)
        for name in values:
            self._param_value(name)

    # --------------------------------------------------------------------------------- commands
    def _command(self, command: int, p: tuple) -> int:
        ardupilot = self.autopilot == "ardupilot"
        if command == _M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN and int(p[0]) == 1:
            threading.Timer(0.3, self._reboot).start()       # the ACK goes out first
            return ACCEPTED
        if command == _M.MAV_CMD_DO_START_MAG_CAL and ardupilot:
            with self._state_lock:
                self.calibrator.start(int(p[0]), self.n_compasses, self.params)
            return ACCEPTED
        if command == _M.MAV_CMD_DO_ACCEPT_MAG_CAL and ardupilot:
            with self._state_lock:
                values = self.calibrator.accept(int(p[0]))
            if values is None:
                return FAILED
            self._save(values)
            return ACCEPTED
        if command == _M.MAV_CMD_DO_CANCEL_MAG_CAL and ardupilot:
            with self._state_lock:
                self.calibrator.cancel()
            return ACCEPTED
        if command == _M.MAV_CMD_FIXED_MAG_CAL_YAW and ardupilot:
            return self._fixed_yaw(float(p[0]), int(p[1]), float(p[2]), float(p[3]))
        return UNSUPPORTED

    def _reboot(self) -> None:
        self.rebooting = True
        self.reboots += 1
        self._reboot_request.set()

    def _fixed_yaw(self, yaw_deg: float, mask: int, lat: float, lon: float) -> int:
        if lat == 0 and lon == 0:
            if self.last_position is None:
                return FAILED              # "Mag: no position available"
            lat, lon, alt = self.last_position
        else:
            alt = 0.0
        field = earth_field(lat, lon, alt, decimal_year_from_unix(time.time())).field_ned_mG
        roll, pitch, _ = self.last_attitude
        values: dict[str, float] = {}
        with self._state_lock:
            for k, corrected in sorted(self.last_corrected.items()):
                if mask == 0 or (mask >> k) & 1:
                    values |= fixed_yaw_params(self.params, k, corrected, roll, pitch, yaw_deg, field)
        if not values:
            return FAILED
        self._save(values)
        return ACCEPTED


_RATE_FIELDS = ("xgyro", "ygyro", "zgyro", "rollspeed", "pitchspeed", "yawspeed", "vel", "vx", "vy", "vz")
_INT16 = {"xgyro", "ygyro", "zgyro", "vx", "vy", "vz"}


def compress_time(msg, speed: float):
    """The same motion performed ``speed`` times faster: boot times / speed (time_boot_ms, and
    time_usec where it is a boot time, ``boot_clock.boot_ms_of_usec``), angular rates and velocities
    x speed (a copy; the simulation's message is left alone).  Without this a sped-up stream
    would carry rates that do not match the time between packets, and RAW_IMU's boot clock
    would run ``speed`` times faster than ATTITUDE's on the one clock of the station's reader."""
    if speed == 1.0:
        return msg
    out = copy.copy(msg)
    if hasattr(out, "time_boot_ms"):
        out.time_boot_ms = int(out.time_boot_ms / speed)
    if hasattr(out, "time_usec") and np.isfinite(boot_ms_of_usec(out.time_usec)):
        out.time_usec = int(out.time_usec / speed)
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


def _sign(encoder, parser, key: bytes, require: bool) -> None:
    """MAVLink 2 signing on the vehicle side: sign what it sends; with ``require`` refuse
    unsigned or badly signed packets (ArduPilot with a key set)."""
    epoch_2015 = 1420070400
    for mav in (encoder, parser):
        mav.signing.secret_key = bytes(key)
        mav.signing.link_id = 0
        mav.signing.timestamp = int((time.time() - epoch_2015) * 1e5)
    encoder.signing.sign_outgoing = True
    parser.signing.allow_unsigned_callback = None if require else (lambda _mav, _msg_id: True)


def _param_name(raw) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).rstrip("\x00")
