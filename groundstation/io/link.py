"""Live MAVLink links (UDP/TCP/serial through pymavlink) as a typed sample stream."""
from __future__ import annotations

import socket
import threading
import time
from collections import deque
from dataclasses import dataclass, field

from .decode import MAV_CMD_SET_MESSAGE_INTERVAL, MavlinkDecoder
from .endpoints import Endpoint, open_endpoint, parse_connection_string, validate_connection_string
from .mavlink import mavlink2
from .roster import SystemRoster, is_signed_packet
from ..samples import Sample, StatusSample

__all__ = ["LiveLink", "LinkOptions", "STREAMED_MESSAGES", "Endpoint", "parse_connection_string", "validate_connection_string",
           "open_endpoint"]

UDP_RECEIVE_BUFFER_BYTES = 4 << 20
NO_HEARTBEAT_FOLLOW_S = 3.0      # without an autopilot heartbeat, follow the busiest system after this
STREAMED_MESSAGES = ("SCALED_IMU", "RAW_IMU", "ATTITUDE", "GPS_RAW_INT", "GLOBAL_POSITION_INT",
                     "HIGHRES_IMU")


def _parse_each_datagram_alone(conn) -> None:
    """UDP carries whole MAVLink packets in each datagram (one or several), so every datagram is
    parsed on its own: bytes left over from one (garbage, or a packet cut short) must not be joined
    to the next, or a good packet would be read as the tail of a bad one and lost to its CRC.
    pymavlink's mavudp keeps one byte buffer across datagrams; this replaces its recv_msg for the
    link (serial/TCP are byte streams and keep pymavlink's parser as it is)."""
    from pymavlink import mavutil

    if not isinstance(conn, mavutil.mavudp):
        return
    try:    # room for ~1 s of a busy link while the station is held up (capped by net.core.rmem_max)
        conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, UDP_RECEIVE_BUFFER_BYTES)
    except OSError:
        pass
    conn.port = _AddressRecordingSocket(conn.port)
    parser = conn.mav
    pending: deque = deque()

    def forget_partial() -> None:
        parser.buf = bytearray()
        parser.buf_index = 0
        parser.expected_length = mavlink2.HEADER_LEN_V1 + 2
        parser.have_prefix_error = False

    def recv_msg():
        while not pending:
            conn.pre_message()
            data = conn.recv()
            if not data:
                return None
            if conn.first_byte:
                conn.auto_mavlink_version(data)
            forget_partial()        # what the last datagram left (garbage, a cut-short packet)
            for m in parser.parse_buffer(data) or ():
                m._src_addr = conn.port.last_from      # who sent it (the link's param_guard asks)
                pending.append(m)
        msg = pending.popleft()
        conn.post_message(msg)
        return msg

    conn.recv_msg = recv_msg


class _AddressRecordingSocket:
    """A UDP socket that remembers the address of the last datagram it received (pymavlink's
    mavudp keeps no per-datagram address in udpin mode); everything else is the socket's."""

    def __init__(self, sock) -> None:
        self._sock = sock
        self.last_from = None

    def recvfrom(self, *args):
        data, addr = self._sock.recvfrom(*args)
        self.last_from = addr
        return data, addr

    def __getattr__(self, name):
        return getattr(self._sock, name)


@dataclass(frozen=True)
class LinkOptions:
    """How the station behaves on a live link.

    sysid:        the vehicle to follow (None: the first autopilot heard).
    passive:      send nothing (no heartbeat, stream-rate or parameter requests, no writes);
                  also switched on by itself when another ground station's heartbeat is heard.
    signing_key:  MAVLink 2 signing key (32 bytes) or None; never shown (repr off).
    """
    sysid: int | None = None
    passive: bool = False
    signing_key: bytes | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.sysid is not None and not 1 <= int(self.sysid) <= 255:
            raise ValueError(f"a MAVLink system id is 1..255, not {self.sysid}")


class LiveLink:
    """A live MAVLink link through a pymavlink connection string.

    ``udpin:127.0.0.1:14550``, ``tcp:HOST:PORT``, ``/dev/ttyUSB0,57600`` (checked by
    ``parse_connection_string``; refused strings raise IngestError).  With a ``forwarder``
    (``groundstation.io.forward.Forwarder``) the link is opened in the forwarding process, which
    passes its packets to the other ground stations without waiting for this one
    (``attach_forwarder``) and this link reads and writes through it.  A reader thread takes every
    packet off the link as it arrives;
    ``poll`` records each (raw bytes, through ``recorder``), lists its system (``roster``) and
    decodes the packets of the followed vehicle only (``options.sysid``, else the first autopilot
    heard; ``select`` changes it).  Unless passive, it sends a GCS heartbeat every second, asks
    the followed vehicle for the streams we need with SET_MESSAGE_INTERVAL and falls back to
    REQUEST_DATA_STREAM when the vehicle does not acknowledge it.
    """

    RATE_HZ = 50
    LOST_AFTER_S = 3.0

    def __init__(self, url: str, recorder=None, *, listen_any: bool = True,
                 options: LinkOptions | None = None, forwarder=None) -> None:
        endpoint = parse_connection_string(url, listen_any=listen_any)
        self.options = options or LinkOptions()
        self.url = endpoint.text
        self._relay = forwarder
        if forwarder is not None:
            self._relay_id, self.mav = forwarder.open_vehicle(endpoint.text, listen_any=listen_any)
        else:
            self._relay_id, self.mav = None, open_endpoint(endpoint)
        _parse_each_datagram_alone(self.mav)
        self._lock_writes(self.mav)
        self.signing = None
        if self.options.signing_key is not None:
            from .signing import LinkSigning
            self.signing = LinkSigning(self.options.signing_key)
            self.signing.install(self.mav)
        self.recorder = recorder
        self.roster = SystemRoster()
        self.sysid: int | None = self.options.sysid
        self.decoder = MavlinkDecoder(vehicle_sysid=self.sysid)
        self.passive = self.options.passive
        self.passive_reason = "started with --passive" if self.passive else None
        self.forwarder = None
        self.param_guard = None     # station.hub.param_watch.ParamSourceGuard: which PARAM_VALUEs to trust
        self.t0_unix = time.time()
        self.last_rx_unix: float | None = None
        self.connected = False
        self.bad_packets = 0
        self._select_request: int | None = None
        self._told_signed = False
        self._link_up_unix = 0.0
        self._last_heartbeat = 0.0
        self._streams_requested_at: float | None = None
        self._interval_acked = False
        self._fallback_sent = False
        self._rx: deque = deque()
        self._rx_ready = threading.Event()
        self._reader_stop = threading.Event()
        self._reader = threading.Thread(target=self._read_loop, daemon=True, name="link-reader")
        self._reader.start()

    def t_s(self, unix_s: float | None = None) -> float:
        return (time.time() if unix_s is None else unix_s) - self.t0_unix

    # ------------------------------------------------------------------ reading
    @staticmethod
    def _lock_writes(conn) -> None:
        """One sender at a time (the worker and parameter writes both send), packing and writing
        together: a message's sequence number and signature timestamp are taken when it is packed,
        and a vehicle that checks signatures refuses a timestamp older than the last it accepted,
        so two threads must not pack in one order and write in the other."""
        raw_write, raw_send, lock = conn.write, conn.mav.send, threading.RLock()

        def write(buf):
            with lock:
                return raw_write(buf)

        def send(mavmsg, *args, **kwargs):
            with lock:
                return raw_send(mavmsg, *args, **kwargs)

        conn.write = write
        conn.mav.send = send

    def _read_loop(self) -> None:
        while not self._reader_stop.is_set():
            try:
                self.mav.select(0.05)
            except Exception:
                self._reader_stop.wait(0.05)
            got = self._read_available()
            if got:
                self._rx.extend(got)
                self._rx_ready.set()

    def _read_available(self, max_messages: int = 1000) -> list[tuple]:
        got = []
        for _ in range(max_messages):
            try:
                msg = self.mav.recv_msg()
            except (OSError, ValueError, TypeError, IndexError) as err:
                if self._reader_stop.is_set():
                    break
                self.bad_packets += 1
                self.decoder.warnings[f"link read error: {type(err).__name__}"] += 1
                break
            if msg is None:
                break
            if msg.get_type() == "BAD_DATA":
                self.bad_packets += 1
                continue
            got.append((msg, bytes(msg.get_msgbuf()), time.time()))
        return got

    def wait(self, timeout_s: float) -> None:
        """Until packets are waiting for ``poll`` (or ``timeout_s``)."""
        self._rx_ready.wait(timeout_s)

    def attach_forwarder(self, forwarder) -> None:
        """Pass this link's packets to the forwarding outputs and theirs to this link (the
        ``forwarder`` it was opened through; None stops).

        Raises:
            ValueError: the link was not opened through ``forwarder``.
        """
        if forwarder is not None and forwarder is not self._relay:
            raise ValueError("a link forwards through the Forwarder it was opened with (LiveLink(forwarder=...))")
        if forwarder is None and self.forwarder is not None:
            self.forwarder.forward(None)
        self.forwarder = forwarder
        if forwarder is not None:
            forwarder.forward(self._relay_id)

    def select(self, sysid: int) -> None:
        """Follow another vehicle from the next ``poll`` on (which says so with a "vehicle" status first)."""
        self._select_request = int(sysid)

    def poll(self, max_messages: int = 1000) -> list[Sample]:
        """Everything that arrived since the last call (non-blocking), as samples."""
        now = time.time()
        out: list[Sample] = []
        if self._select_request is not None:
            self._follow(self._select_request, now, out)
        elif self.sysid is None and self.connected and now - self._link_up_unix > NO_HEARTBEAT_FOLLOW_S:
            self._follow_busiest(now, out)
        self._housekeeping(now, out)
        self._rx_ready.clear()
        for _ in range(min(max_messages, len(self._rx))):
            msg, packet, unix = self._rx.popleft()
            if self.recorder is not None:
                self.recorder.write_packet(packet, unix)
            self._route(msg, packet, unix, out)
        if self._rx:
            self._rx_ready.set()
        return out

    def _route(self, msg, packet: bytes, unix: float, out: list[Sample]) -> None:
        """Roster every packet; decode only the followed vehicle's."""
        found = self.roster.observe(msg, unix, packet)
        src = msg.get_srcSystem()
        if found == "gcs" and not self.passive:
            self.passive = True
            self.passive_reason = f"another ground station (system {src}) is on this link"
            out.append(StatusSample(self.t_s(unix), "passive", f"{self.passive_reason}: MagStation now only "
                                    "listens (no stream-rate requests, heartbeats or parameter writes)"))
        elif found == "vehicle" and self.sysid is None:
            self._follow(src, unix, out)
        if self.roster.systems[src].is_gcs or src == 255:
            return
        if self.signing is None and not self._told_signed and is_signed_packet(packet):
            self._told_signed = True
            out.append(StatusSample(self.t_s(unix), "signing", f"system {src} signs its packets (MAVLink 2 "
                                    "signing): parameter writes and commands need its key (--signing-key-file)"))
        self.last_rx_unix = unix
        if not self.connected:
            self.connected = True
            self._link_up_unix = unix
            out.append(StatusSample(self.t_s(unix), "link", f"link up on {self.url}"))
        if src != self.sysid:
            return
        mtype = msg.get_type()
        if self.param_guard is not None:
            why, say = self.param_guard.check(msg, getattr(msg, "_src_addr", None), unix)
            if why is not None:
                self.decoder.warnings["PARAM_VALUE refused (not from the vehicle's component/address)"] += 1
                if say:
                    out.append(StatusSample(self.t_s(unix), "param_refused", why))
                return
        if mtype == "COMMAND_ACK" and msg.command == MAV_CMD_SET_MESSAGE_INTERVAL and msg.result == 0:
            self._interval_acked = True
        out.extend(self.decoder.decode(msg, self.t_s(unix)))

    def _follow(self, sysid: int, unix: float, out: list[Sample]) -> None:
        """Decode ``sysid`` from now on.  A switch from another vehicle is a "vehicle" status (the
        hub starts over); the first vehicle followed is a "vehicle_found" status."""
        self._select_request = None
        switch = self.sysid is not None and sysid != self.sysid
        if sysid == self.sysid and not switch and self.decoder.vehicle_sysid == sysid:
            return
        self.sysid = sysid
        self.decoder = MavlinkDecoder(vehicle_sysid=sysid)
        if self.param_guard is not None:
            self.param_guard.reset()
        self._streams_requested_at = None
        out.append(StatusSample(self.t_s(unix), "vehicle" if switch else "vehicle_found",
                                f"following vehicle {sysid}" + (" (switched)" if switch else "")))

    def _follow_busiest(self, now: float, out: list[Sample]) -> None:
        """No autopilot heartbeat yet (some bridges send none): follow the system heard most."""
        heard = [s for s in self.roster.systems.values() if not s.is_gcs and s.sysid != 255]
        if heard:
            self._follow(max(heard, key=lambda s: s.packets).sysid, now, out)

    def vehicles_snapshot(self) -> dict:
        now = time.time()
        return {"selected": self.sysid, "systems": self.roster.snapshot(now), "passive": self.passive,
                "passive_reason": self.passive_reason,
                "signing": self.signing.snapshot() if self.signing is not None else {"on": False},
                "forwarding": self.forwarder.snapshot() if self.forwarder is not None else None}

    # ------------------------------------------------------------------ sending
    def _housekeeping(self, now: float, out: list[Sample]) -> None:
        from pymavlink import mavutil

        relay = self._relay
        if self.connected and relay is not None and not relay.running:     # it owned the link
            self.connected = False
            out.append(StatusSample(self.t_s(now), "link", f"link lost: {relay.error or 'forwarding stopped'}"))
        if self.connected and self.last_rx_unix is not None and now - self.last_rx_unix > self.LOST_AFTER_S:
            self.connected = False
            self._streams_requested_at = None
            out.append(StatusSample(self.t_s(now), "link",
                                    f"link lost: nothing heard for {self.LOST_AFTER_S:.0f} s, waiting"))
        if self.passive:
            return
        if now - self._last_heartbeat >= 1.0:
            self._last_heartbeat = now
            try:
                self.mav.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS,
                                            mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            except OSError:
                pass  # UDP-in before the vehicle has spoken has no peer yet
        if self.connected and self.sysid is not None:
            if self._streams_requested_at is None:
                self._request_streams(now)
            elif (not self._interval_acked and not self._fallback_sent
                  and now - self._streams_requested_at > 2.0):
                self._request_data_stream_fallback()

    def _request_streams(self, now: float) -> None:
        self._streams_requested_at = now
        self._interval_acked = False
        self._fallback_sent = False
        interval_us = 1e6 / self.RATE_HZ
        for name in STREAMED_MESSAGES:
            msg_id = getattr(mavlink2, "MAVLINK_MSG_ID_" + name)
            try:
                self.mav.mav.command_long_send(self.sysid, 0, MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                               msg_id, interval_us, 0, 0, 0, 0, 0)
            except OSError:
                return

    def _request_data_stream_fallback(self) -> None:
        self._fallback_sent = True
        try:
            # MAV_DATA_STREAM_ALL (0) at our rate: the pre-MAVLink-2 way ArduPilot still honours.
            self.mav.mav.request_data_stream_send(self.sysid, 0, 0, self.RATE_HZ, 1)
        except OSError:
            pass

    def close(self) -> None:
        self._reader_stop.set()
        if self._reader is not threading.current_thread():
            self._reader.join(timeout=2)
        self.forwarder = None
        if self._relay is not None:
            self._relay.close_vehicle(self._relay_id)       # stops its forwarding too
        try:
            self.mav.close()
        except Exception:
            pass
        if self.recorder is not None:
            self.recorder.flush()
