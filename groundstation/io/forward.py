"""MAVLink forwarding: the station owns the vehicle link and passes it on to other ground stations.

``Forwarder`` opens the outputs (``udpout:HOST:PORT`` sends to a ground station listening there,
``tcpin:127.0.0.1:PORT`` lets ground stations connect), sends every packet the vehicle link
receives to all of them (``to_outputs``, called by the link's reader thread as each packet
arrives) and passes what they send back to the vehicle (its own thread, through the writer the
live link attaches).  Packets are passed as received, bytes unchanged (signed packets stay
signed, unknown message ids pass): ``MavlinkFramer`` only cuts a byte stream into whole packets
by their header (length, signature flag), it does not check CRCs or decode.
"""
from __future__ import annotations

import select
import socket
import sys
import threading
from typing import Callable

from .errors import IngestError
from .endpoints import Endpoint, parse_connection_string

__all__ = ["Forwarder", "MavlinkFramer", "parse_forward_url", "FORWARD_KINDS"]

FORWARD_KINDS = ("udpout", "tcpin")
MAX_TCP_CLIENTS = 8
FORWARD_SWITCH_INTERVAL_S = 0.001
STX_V1, STX_V2 = 0xFE, 0xFD
SIGNATURE_LEN = 13


def parse_forward_url(url: str, *, listen_any: bool = False) -> Endpoint:
    """Check a forwarding output: ``udpout:HOST:PORT`` or ``tcpin:HOST:PORT`` (loopback unless
    ``listen_any``), with the same checks as the vehicle link (``parse_connection_string``).

    Raises:
        IngestError: one line saying why the string is refused.
    """
    endpoint = parse_connection_string(url, listen_any=listen_any)
    if endpoint.kind not in FORWARD_KINDS:
        raise IngestError(f"{endpoint.text} cannot be a forwarding output: use udpout:HOST:PORT (send to a ground "
                          "station listening there) or tcpin:127.0.0.1:PORT (ground stations connect to it)")
    return endpoint


class MavlinkFramer:
    """Cuts a MAVLink 1/2 byte stream into whole packets (header-length framing, no CRC check);
    bytes before a start marker are skipped and counted."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.skipped_bytes = 0

    def feed(self, data: bytes) -> list[bytes]:
        self._buf += data
        out: list[bytes] = []
        buf = self._buf
        while buf:
            if buf[0] not in (STX_V1, STX_V2):
                nxt = min((i for i in (buf.find(STX_V1), buf.find(STX_V2)) if i > 0), default=len(buf))
                self.skipped_bytes += nxt
                del buf[:nxt]
                continue
            if len(buf) < 3:
                break
            if buf[0] == STX_V2:
                size = 10 + buf[1] + 2 + (SIGNATURE_LEN if buf[2] & 0x01 else 0)
            else:
                size = 6 + buf[1] + 2
            if len(buf) < size:
                break
            out.append(bytes(buf[:size]))
            del buf[:size]
        return out


class _UdpOutput:
    """Sends to one ground station's UDP port; its answers (from that address only) come back."""

    def __init__(self, endpoint: Endpoint) -> None:
        self.name = endpoint.text
        self.address = (socket.gethostbyname(endpoint.host), endpoint.port)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1" if self.address[0].startswith("127.") else "0.0.0.0", 0))
        self.sock.setblocking(False)
        self.sent = self.received = self.dropped = 0

    def sockets(self) -> list[socket.socket]:
        return [self.sock]

    def send(self, packet: bytes) -> None:
        try:
            self.sock.sendto(packet, self.address)
            self.sent += 1
        except OSError:          # nobody listening yet (ICMP refused), buffer full
            self.dropped += 1

    def readable(self, sock: socket.socket) -> list[bytes]:
        try:
            data, source = sock.recvfrom(65535)
        except OSError:
            return []
        if source != self.address:
            return []        # only the ground station we send to may talk to the vehicle
        packets = MavlinkFramer().feed(data)
        self.received += len(packets)
        return packets

    def close(self) -> None:
        self.sock.close()

    def snapshot(self) -> dict:
        return {"url": self.name, "clients": 1, "to_gcs": self.sent, "from_gcs": self.received,
                "dropped": self.dropped}


class _TcpInOutput:
    """A TCP port ground stations connect to (up to MAX_TCP_CLIENTS at once)."""

    def __init__(self, endpoint: Endpoint) -> None:
        self.name = endpoint.text
        self.server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self.server.bind((endpoint.host, endpoint.port))
        except OSError as err:
            self.server.close()
            raise IngestError(f"cannot open forwarding output {endpoint.text}: {err.strerror or err}") from err
        self.server.listen(MAX_TCP_CLIENTS)
        self.server.setblocking(False)
        self.clients: dict[socket.socket, MavlinkFramer] = {}
        self._lock = threading.Lock()
        self.sent = self.received = self.dropped = 0

    def sockets(self) -> list[socket.socket]:
        with self._lock:
            return [self.server, *self.clients]

    def send(self, packet: bytes) -> None:
        with self._lock:
            clients = list(self.clients)
        for client in clients:
            try:
                if client.send(packet) == len(packet):
                    self.sent += 1
                    continue
            except BlockingIOError:
                pass
            except OSError:
                self._drop(client)
                continue
            self.dropped += 1        # a slow client loses packets; the vehicle link never waits

    def readable(self, sock: socket.socket) -> list[bytes]:
        if sock is self.server:
            self._accept()
            return []
        try:
            data = sock.recv(65536)
        except BlockingIOError:
            return []
        except OSError:
            data = b""
        if not data:
            self._drop(sock)
            return []
        packets = self.clients.get(sock, MavlinkFramer()).feed(data)
        self.received += len(packets)
        return packets

    def _accept(self) -> None:
        try:
            client, _ = self.server.accept()
        except OSError:
            return
        with self._lock:
            if len(self.clients) >= MAX_TCP_CLIENTS:
                client.close()
                return
            client.setblocking(False)
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.clients[client] = MavlinkFramer()

    def _drop(self, client: socket.socket) -> None:
        with self._lock:
            self.clients.pop(client, None)
        client.close()

    def close(self) -> None:
        with self._lock:
            for client in self.clients:
                client.close()
            self.clients.clear()
        self.server.close()

    def snapshot(self) -> dict:
        return {"url": self.name, "clients": len(self.clients), "to_gcs": self.sent, "from_gcs": self.received,
                "dropped": self.dropped}


class Forwarder:
    """The forwarding outputs and their thread.

    Args:
        urls: forwarding outputs (checked with ``parse_forward_url``).
        listen_any: allow ``tcpin`` on non-loopback addresses (the operator's remote mode).
    Raises:
        IngestError: a refused string or an output that cannot open (port busy).
    """

    def __init__(self, urls, *, listen_any: bool = False) -> None:
        endpoints = [parse_forward_url(u, listen_any=listen_any) for u in urls]
        self.outputs: list = []
        try:
            for e in endpoints:
                self.outputs.append(_UdpOutput(e) if e.kind == "udpout" else _TcpInOutput(e))
        except BaseException:
            self.close()
            raise
        self._writer: Callable[[bytes], None] | None = None
        self.to_vehicle = self.to_vehicle_dropped = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def attach(self, writer: Callable[[bytes], None] | None) -> None:
        """Where packets from the outputs go (the live link's raw writer); None: dropped (no vehicle)."""
        self._writer = writer

    def start(self) -> "Forwarder":
        """Start the outputs' thread.  Also shortens the interpreter's thread switch interval
        (process-wide, ``sys.setswitchinterval``) to FORWARD_SWITCH_INTERVAL_S: every socket
        read releases the interpreter lock, and with the estimators' thread busy the reader would
        wait the default 5 ms to get it back, for each packet."""
        if self.outputs and sys.getswitchinterval() > FORWARD_SWITCH_INTERVAL_S:
            sys.setswitchinterval(FORWARD_SWITCH_INTERVAL_S)
        if self._thread is None and self.outputs:
            self._thread = threading.Thread(target=self._run, daemon=True, name="forwarder")
            self._thread.start()
        return self

    def to_outputs(self, packet: bytes) -> None:
        """A packet from the vehicle link to every output (called as it arrives)."""
        for out in self.outputs:
            out.send(packet)

    def _run(self) -> None:
        while not self._stop.is_set():
            owners = {s: out for out in self.outputs for s in out.sockets()}
            try:
                ready, _, _ = select.select(list(owners), [], [], 0.1)
            except (OSError, ValueError):       # a socket closed under us: look again
                self._stop.wait(0.01)
                continue
            for sock in ready:
                for packet in owners[sock].readable(sock):
                    self._to_vehicle(packet)

    def _to_vehicle(self, packet: bytes) -> None:
        writer = self._writer
        if writer is None:
            self.to_vehicle_dropped += 1
            return
        try:
            writer(packet)
            self.to_vehicle += 1
        except OSError:
            self.to_vehicle_dropped += 1

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
        for out in self.outputs:
            out.close()

    def snapshot(self) -> dict:
        return {"outputs": [o.snapshot() for o in self.outputs], "to_vehicle": self.to_vehicle,
                "to_vehicle_dropped": self.to_vehicle_dropped}
