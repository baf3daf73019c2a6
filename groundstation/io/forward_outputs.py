"""The forwarding outputs the forwarding process (``groundstation.io.relay``) serves: a ground
station listening on UDP (``udpout:HOST:PORT``) or ground stations connecting over TCP
(``tcpin:HOST:PORT``).  Both pass whole packets (``MavlinkFramer``) and count them; a slow
receiver loses packets, the vehicle link never waits for it.
"""
from __future__ import annotations

import socket

from .endpoints import Endpoint
from .errors import IngestError
from .forward import MavlinkFramer

__all__ = ["UdpOutput", "TcpInOutput", "open_output", "MAX_TCP_CLIENTS"]

MAX_TCP_CLIENTS = 8


class UdpOutput:
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


class TcpInOutput:
    """A TCP port ground stations connect to (up to MAX_TCP_CLIENTS at once).

    Raises:
        IngestError: the port cannot be opened (in use, not an address of this machine).
    """

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
        self.sent = self.received = self.dropped = 0

    def sockets(self) -> list[socket.socket]:
        return [self.server, *self.clients]

    def send(self, packet: bytes) -> None:
        for client in list(self.clients):
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
        packets = self.clients[sock].feed(data)
        self.received += len(packets)
        return packets

    def _accept(self) -> None:
        try:
            client, _ = self.server.accept()
        except OSError:
            return
        if len(self.clients) >= MAX_TCP_CLIENTS:
            client.close()
            return
        client.setblocking(False)
        client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.clients[client] = MavlinkFramer()

    def _drop(self, client: socket.socket) -> None:
        self.clients.pop(client, None)
        client.close()

    def close(self) -> None:
        for client in self.clients:
            client.close()
        self.clients.clear()
        self.server.close()

    def snapshot(self) -> dict:
        return {"url": self.name, "clients": len(self.clients), "to_gcs": self.sent, "from_gcs": self.received,
                "dropped": self.dropped}


def open_output(endpoint: Endpoint):
    return UdpOutput(endpoint) if endpoint.kind == "udpout" else TcpInOutput(endpoint)
