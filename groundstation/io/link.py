"""Live MAVLink links (UDP/TCP/serial through pymavlink) as a typed sample stream."""
from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field

from .decode import MAV_CMD_SET_MESSAGE_INTERVAL, MavlinkDecoder
from .endpoints import Endpoint, open_endpoint, parse_connection_string, validate_connection_string
from .mavlink import mavlink2
from .roster import SystemRoster, is_signed_packet
from .streams import IMU_MESSAGES, STREAMS, StreamTracker
from .udp_datagrams import parse_each_datagram_alone
from ..samples import Sample, StatusSample

__all__ = ["LiveLink", "LinkOptions", "STREAMS", "Endpoint", "parse_connection_string", "validate_connection_string",
           "open_endpoint"]

NO_HEARTBEAT_FOLLOW_S = 3.0      # without an autopilot heartbeat, follow the busiest system after this
MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN = 246
STALE_AFTER_S = 1.0              # no IMU message this long while heartbeats arrive: the data is stale
HEARTBEAT_GAP_S = 2.5            # the vehicle's 1 Hz heartbeat missing this long: it was away (a reboot?)
REBOOT_GAP_S = 1.2               # ... this long once the vehicle acknowledged a reboot command
REREQUEST_EVERY_S = 2.0          # stale streams are asked again at most this often
BOOT_BACK_S = 1.0                # the vehicle's time_boot_ms going back more than this: it rebooted


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
    the followed vehicle for every stream the station decodes with SET_MESSAGE_INTERVAL, each at
    its rate, checks the ACKs and the arrivals (``streams``, ``streams_snapshot``: what is missing
    and why), and falls back to REQUEST_DATA_STREAM when the vehicle acknowledges none.  A reboot
    (boot time going back, a heartbeat gap, the ACK of a reboot command) makes it ask again; no IMU
    data for STALE_AFTER_S while heartbeats arrive is stale data (``stale_reason``, a "live_data"
    status), asked again every REREQUEST_EVERY_S.  What it sends is recorded too.
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
        parse_each_datagram_alone(self.mav)
        self.recorder = recorder
        self._lock_writes(self.mav)
        self.signing = None
        if self.options.signing_key is not None:
            from .signing import LinkSigning
            self.signing = LinkSigning(self.options.signing_key)
            self.signing.install(self.mav)
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
        self.param_sets_seen: dict[str, tuple[int, float]] = {}   # PARAM_SET by another GCS: name -> (sysid, unix)
        self._told_signed = False
        self._link_up_unix = 0.0
        self._last_heartbeat = 0.0
        self.streams = StreamTracker()
        self._units_told = 0
        self._streams_requested_at: float | None = None
        self._last_vehicle_heartbeat: float | None = None
        self._last_boot_ms: float | None = None
        self._reboot_acked_unix: float | None = None
        self.stale_reason: str | None = None     # why the live data stopped (None: fresh or none yet)
        self._record_lock = threading.Lock()
        self._last_recorded_unix = 0.0
        self._rx: deque = deque()
        self._rx_ready = threading.Event()
        self._reader_stop = threading.Event()
        self._reader = threading.Thread(target=self._read_loop, daemon=True, name="link-reader")
        self._reader.start()

    def t_s(self, unix_s: float | None = None) -> float:
        return (time.time() if unix_s is None else unix_s) - self.t0_unix

    # ------------------------------------------------------------------ reading
    def _lock_writes(self, conn) -> None:
        """One sender at a time (the worker and parameter writes both send), packing and writing
        together: a message's sequence number and signature timestamp are taken when it is packed,
        and a vehicle that checks signatures refuses a timestamp older than the last it accepted,
        so two threads must not pack in one order and write in the other.  Each packet written
        is also recorded (a .tlog holds both directions), once the link has heard something."""
        raw_write, raw_send, lock = conn.write, conn.mav.send, threading.RLock()

        def write(buf):
            with lock:
                sent = raw_write(buf)
                if getattr(self, "last_rx_unix", None) is not None and buf and buf[0] in (0xFD, 0xFE):
                    self._record(bytes(buf), time.time())
                return sent

        def send(mavmsg, *args, **kwargs):
            with lock:
                return raw_send(mavmsg, *args, **kwargs)

        conn.write = write
        conn.mav.send = send

    def _record(self, packet: bytes, unix: float) -> None:
        """One packet into the session recording, in time order whichever thread sends (a
        stamp earlier than the last one written is moved up to it)."""
        if self.recorder is None:
            return
        with self._record_lock:
            unix = max(unix, self._last_recorded_unix)
            self._last_recorded_unix = unix
            self.recorder.write_packet(packet, unix)

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
            arrival = getattr(msg, "_arrival_unix", None)      # the kernel's stamp (UDP), else now
            got.append((msg, bytes(msg.get_msgbuf()), time.time() if arrival is None else arrival))
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
            self._record(packet, unix)
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
            if msg.get_type() == "PARAM_SET" and src != self.mav.mav.srcSystem:
                name = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else str(msg.param_id)
                self.param_sets_seen[name] = (src, unix)
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
        if self.param_guard is not None:
            why, say = self.param_guard.check(msg, getattr(msg, "_src_addr", None), unix)
            if why is not None:
                self.decoder.warnings["PARAM_VALUE refused (not from the vehicle's component/address)"] += 1
                if say:
                    out.append(StatusSample(self.t_s(unix), "param_refused", why))
                return
        self._watch_vehicle(msg, unix, out)
        out.extend(self.decoder.decode(msg, self.t_s(unix)))
        units = self.decoder.mag_units
        if len(units) != self._units_told:
            for name in list(units)[self._units_told:]:
                out.append(StatusSample(self.t_s(unix), "mag_unit", f"{name} magnetometer: {units[name]['why']}"))
            self._units_told = len(units)

    def _watch_vehicle(self, msg, unix: float, out: list[Sample]) -> None:
        """Stream arrivals and acknowledgements; a reboot (boot time going back, a heartbeat gap,
        the ACK of a reboot command) restarts the stream requests; fresh IMU data after stale."""
        mtype = msg.get_type()
        self.streams.seen(mtype, unix)
        if mtype == "COMMAND_ACK":
            if msg.command == MAV_CMD_SET_MESSAGE_INTERVAL:
                self.streams.ack(msg.result)
            elif msg.command == MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN and msg.result == 0:
                self._reboot_acked_unix = unix
        elif mtype == "HEARTBEAT" and msg.type != 6 and msg.autopilot != 8:
            last, self._last_vehicle_heartbeat = self._last_vehicle_heartbeat, unix
            gap_s = REBOOT_GAP_S if (self._reboot_acked_unix is not None
                                     and unix - self._reboot_acked_unix < 60) else HEARTBEAT_GAP_S
            if last is not None and unix - last > gap_s:
                self._vehicle_restarted(unix, out, f"no heartbeat for {unix - last:.1f} s"
                                        + (" after the reboot command" if gap_s == REBOOT_GAP_S else ""))
        boot_ms = getattr(msg, "time_boot_ms", None)
        if boot_ms is not None and mtype in ("ATTITUDE", "SYSTEM_TIME", "SCALED_IMU2", "SCALED_IMU3", "SCALED_IMU"):
            if self._last_boot_ms is not None and boot_ms < self._last_boot_ms - BOOT_BACK_S * 1e3:
                self._vehicle_restarted(unix, out, f"its boot time went back from {self._last_boot_ms / 1e3:.1f} s "
                                        f"to {boot_ms / 1e3:.1f} s")
            self._last_boot_ms = float(boot_ms)
        if mtype in IMU_MESSAGES and self.stale_reason is not None:
            self.stale_reason = None
            out.append(StatusSample(self.t_s(unix), "live_data", "live data resumed"))

    def _vehicle_restarted(self, unix: float, out: list[Sample], why: str) -> None:
        """The vehicle rebooted (or was away): its stream rates are its defaults again, so every
        stream is asked for again now."""
        self._reboot_acked_unix = None
        self._last_boot_ms = None
        self.streams.restart()
        self._streams_requested_at = None
        out.append(StatusSample(self.t_s(unix), "reboot", f"vehicle {self.sysid} restarted ({why}): "
                                "streams asked for again"))

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
        self.streams = StreamTracker()
        self._units_told = 0
        self._streams_requested_at = None
        self._last_vehicle_heartbeat = self._last_boot_ms = None
        self.stale_reason = None
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
                "forwarding": self.forwarder.snapshot() if self.forwarder is not None else None,
                "streams": self.streams_snapshot(now) if self.sysid is not None else None}

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
            if self.connected and self.sysid is not None:
                self._check_stale(now, out)
            return
        if now - self._last_heartbeat >= 1.0:
            self._last_heartbeat = now
            try:
                self.mav.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS,
                                            mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            except OSError:
                pass  # UDP-in before the vehicle has spoken has no peer yet
        if self.connected and self.sysid is not None:
            self._keep_streams(now, out)

    def _keep_streams(self, now: float, out: list[Sample]) -> None:
        """Ask for every stream once a vehicle is followed (and after a reboot or stale data), again
        for those accepted but not arriving, and with REQUEST_DATA_STREAM when SET_MESSAGE_INTERVAL
        gets no answer at all (older firmware)."""
        tracker = self.streams
        if self._streams_requested_at is None:
            self._request_streams(now, [s.name for s in STREAMS])
            return
        if tracker.unanswered_since(now) and tracker.fallback_sent_unix is None:
            self._request_data_stream_fallback(now)
        retry = tracker.retry_due(now)
        if retry:
            self._request_streams(now, retry)
        self._check_stale(now, out)

    def _check_stale(self, now: float, out: list[Sample]) -> None:
        """No IMU message for STALE_AFTER_S while heartbeats arrive: say so (the page shows "no
        attitude data", not the last attitude) and ask for the streams again every REREQUEST_EVERY_S."""
        last_imu = self.streams.last_imu_unix()
        heartbeat = self._last_vehicle_heartbeat
        if heartbeat is None or now - heartbeat > self.LOST_AFTER_S:
            return                       # the vehicle itself is silent: the link-lost rule
        if last_imu is not None and now - last_imu <= STALE_AFTER_S:
            return
        if last_imu is None and now - (self._streams_requested_at or now) <= STALE_AFTER_S + 1.0:
            return                       # just asked: give the first samples time to come
        if self.stale_reason is None:
            self.stale_reason = ("no IMU data for " + (f"{now - last_imu:.1f} s" if last_imu is not None else
                                 "since the streams were asked for") + " while the vehicle's heartbeats arrive")
            out.append(StatusSample(self.t_s(now), "live_data", "no attitude data: " + self.stale_reason +
                                    ("" if self.passive else "; streams asked for again")))
        if not self.passive and now - (self._streams_requested_at or 0.0) >= REREQUEST_EVERY_S:
            self.streams.restart()
            self._request_streams(now, [s.name for s in STREAMS])

    def _request_streams(self, now: float, names: list[str]) -> None:
        """SET_MESSAGE_INTERVAL for each of ``names`` at its own rate (STREAMS)."""
        self._streams_requested_at = now
        names = self.streams.to_ask(names)
        autopilot = self.decoder.autopilot
        specs = {s.name: s for s in STREAMS}
        sent = []
        skipped = [n for n in names if specs[n].rate_for(autopilot) <= 0]
        self.streams.skipped(skipped)
        for name in names:
            if name in skipped:
                continue
            msg_id = getattr(mavlink2, "MAVLINK_MSG_ID_" + name)
            interval_us = 1e6 / specs[name].rate_for(autopilot)
            try:
                self.mav.mav.command_long_send(self.sysid, 0, MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                               msg_id, interval_us, 0, 0, 0, 0, 0)
            except OSError:
                break
            sent.append(name)
        self.streams.requested(sent, now)

    def _request_data_stream_fallback(self, now: float) -> None:
        self.streams.fallback_sent_unix = now
        try:
            # MAV_DATA_STREAM_ALL (0) at our rate: the pre-MAVLink-2 way ArduPilot still honours.
            self.mav.mav.request_data_stream_send(self.sysid, 0, 0, self.RATE_HZ, 1)
        except OSError:
            pass

    def streams_snapshot(self, now: float | None = None) -> dict:
        """Each stream the station uses: arriving, or missing and why (see groundstation.io.streams);
        ``stale``: why the live data stopped, None while it flows."""
        now = time.time() if now is None else now
        out = self.streams.snapshot(now, self.passive)
        out["stale"] = self.stale_reason
        out["mag_units"] = dict(self.decoder.mag_units)
        return out

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
