"""Slow clients (slowloris) against the station in remote mode: header time and connections per
client are bounded, and the connections that have not sent a whole request yet are shed first,
so the operator's tokened request still answers at once.

The station runs in its own process with a small open-file limit (256, as on many systems), so
the test shows what a real machine would do when the descriptors run out; every socket is on
loopback."""
from __future__ import annotations

import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import httpx
import pytest

ROOT = Path(__file__).resolve().parents[1]
TOKEN = "slow-client-test-token-0123456789abcdef"
SLOW_SOCKETS = 250


def _station_process(recordings: Path, limits: str = "") -> tuple[subprocess.Popen, str]:
    """A remote-mode station (loopback) in a child process with RLIMIT_NOFILE 256; its base URL."""
    script = textwrap.dedent(f"""
        import resource, sys
        resource.setrlimit(resource.RLIMIT_NOFILE, (256, resource.getrlimit(resource.RLIMIT_NOFILE)[1]))
        from groundstation.station.app import Station
        from groundstation.station.settings import StationSettings
        {limits}
        settings = StationSettings(host="127.0.0.1", port=0, viser_port=None, allow_remote=True,
                                   access_token={TOKEN!r}, recordings_dir={str(recordings)!r}, **extra)
        st = Station(settings).start()
        print(st.port, flush=True)
        sys.stdin.read()
        st.close()
    """)
    if not limits:
        script = script.replace("**extra", "")
    proc = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    if not line.strip().isdigit():
        proc.kill()
        proc.wait(10)
        proc.stdout.close()
        pytest.fail(f"the station did not start: {line!r}")
    return proc, f"http://127.0.0.1:{int(line)}"


def _slow_sockets(port: int, n: int) -> list[socket.socket]:
    """n connections that each send a request line and one header, then wait (slowloris)."""
    out = []
    for i in range(n):
        s = socket.create_connection(("127.0.0.1", port), timeout=5)
        s.sendall(b"GET /api/health HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        out.append(s)
    return out


def _closed_by_server(sockets: list[socket.socket]) -> int:
    closed = 0
    for s in sockets:
        s.setblocking(False)
        try:
            if s.recv(1) == b"":
                closed += 1
        except BlockingIOError:
            pass
        except OSError:             # reset
            closed += 1
    return closed


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="sets RLIMIT_NOFILE in a child process")
def test_a_tokened_request_answers_while_250_slow_clients_hold_connections(recordings_dir):
    proc, base = _station_process(recordings_dir)
    port = int(base.rsplit(":", 1)[1])
    sockets: list[socket.socket] = []
    try:
        t0 = time.monotonic()
        sockets = _slow_sockets(port, SLOW_SOCKETS)
        time.sleep(1.0)                                          # the server accepts what it can
        for s in sockets[::5]:                                   # ... and they go on, slowly
            try:
                s.sendall(b"X-Slow: 1\r\n")
            except OSError:
                pass
        started = time.monotonic()
        r = httpx.get(base + "/api/health", headers={"Authorization": f"Bearer {TOKEN}"}, timeout=5)
        answered_s = time.monotonic() - started
        assert r.status_code == 200 and answered_s < 1.0, (r.status_code, answered_s)
        # the slow clients were shed, not held: at most the per-client bound stays open
        from groundstation.station.settings import ConnectionLimits
        held = SLOW_SOCKETS - _closed_by_server(sockets)
        assert held <= ConnectionLimits().max_per_client, held
        assert time.monotonic() - t0 < 20
    finally:
        for s in sockets:
            s.close()
        proc.stdin.close()
        proc.wait(10)
        proc.stdout.close()         # a pipe left to the garbage collector warns in a later test


def test_headers_must_arrive_within_the_header_timeout(recordings_dir):
    """A client that sends one header line every 0.3 s is closed after header_timeout_s (1 s
    here) although it never goes quiet; an idle connection and a slow body are not its business."""
    from groundstation.station.app import Station
    from groundstation.station.settings import ConnectionLimits, StationSettings

    settings = StationSettings(host="127.0.0.1", port=0, viser_port=None, allow_remote=True, access_token=TOKEN,
                               recordings_dir=recordings_dir,
                               connection_limits=ConnectionLimits(header_timeout_s=1.0, keep_alive_s=5))
    st = Station(settings).start()
    try:
        s = socket.create_connection(("127.0.0.1", st.port), timeout=5)
        s.sendall(b"GET /api/health HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        t0, closed_after = time.monotonic(), None
        s.settimeout(0.3)
        while time.monotonic() - t0 < 4.0:
            try:
                s.sendall(b"X-Slow: 1\r\n")
                if s.recv(1) == b"":
                    closed_after = time.monotonic() - t0
                    break
            except socket.timeout:
                continue
            except OSError:
                closed_after = time.monotonic() - t0
                break
        s.close()
        assert closed_after is not None and 0.8 <= closed_after <= 2.5, closed_after
        # a client that sends its headers at once is served, and its request may take longer
        slow_body = httpx.post(st.url + "/api/calibration/start", headers={"Authorization": f"Bearer {TOKEN}"},
                               content=_slowly([b"", b""], 0.7), timeout=10)
        assert slow_body.status_code == 200
    finally:
        st.close()


def _slowly(chunks: list[bytes], pause_s: float):
    for chunk in chunks:
        time.sleep(pause_s)
        yield chunk


def test_connection_limits_follow_the_open_file_limit():
    from groundstation.station.security import connection_cap
    from groundstation.station.settings import ConnectionLimits

    assert connection_cap(ConnectionLimits(), open_files=256) < 256 - 64
    assert connection_cap(ConnectionLimits(), open_files=1 << 20) == ConnectionLimits().max_connections_cap
    assert connection_cap(ConnectionLimits(max_connections=50), open_files=1 << 20) == 50


class _Conn:
    """A connection as ConnectionBook sees it."""

    def __init__(self, client: str, idle: bool = True, served: int = 0) -> None:
        self.client_key, self.idle, self.served = client, idle, served
        self.transport = self
        self.closed = False

    def close(self) -> None:
        self.closed = True


def test_room_is_made_by_closing_idle_connections_never_served_ones_first():
    from groundstation.station.security import ConnectionBook
    from groundstation.station.settings import ConnectionLimits

    book = ConnectionBook(ConnectionLimits(max_per_client=3), cap=5)
    served_idle, busy, slow = _Conn("a", served=1), _Conn("a", idle=False, served=1), _Conn("a")
    assert all(book.admit(c) for c in (served_idle, busy, slow))
    newcomer = _Conn("a")
    assert book.admit(newcomer) and slow.closed and not served_idle.closed      # never served: first
    assert book.admit(_Conn("a", idle=False)) and newcomer.closed
    assert book.admit(_Conn("a", idle=False)) and served_idle.closed            # then a served idle one
    assert not book.admit(_Conn("a")) and not busy.closed                       # all busy: refused
    others = [_Conn("b", idle=False), _Conn("c", idle=False)]
    assert all(book.admit(c) for c in others) and len(book.open) == 5
    assert not book.admit(_Conn("d"))                                           # the total cap
    assert (book.shed, book.refused) == (3, 2)
    for c in list(book.open):
        book.discard(c)
    assert book.open == {} and book.by_client == {}


def test_serve_refuses_limits_out_of_range_in_one_line(tmp_path):
    for args, needle in ((["--header-timeout", "0"], "header_timeout_s"),
                         (["--max-connections-per-client", "0"], "max_per_client")):
        r = subprocess.run([sys.executable, "-m", "groundstation.cli", "serve", "--port", "0", "--viser-port", "0",
                            *args], cwd=ROOT, capture_output=True, text=True, timeout=60)
        assert r.returncode == 1 and needle in r.stderr and r.stderr.count("\n") == 1, r.stderr
        assert "MagStation: web page" not in r.stdout


def test_a_client_whose_connections_are_all_inside_requests_gets_a_503(recordings_dir):
    from groundstation.station.app import Station
    from groundstation.station.settings import ConnectionLimits, StationSettings

    settings = StationSettings(port=0, viser_port=None, recordings_dir=recordings_dir,
                               connection_limits=ConnectionLimits(max_per_client=2))
    st = Station(settings).start()
    busy = []
    try:
        for _ in range(2):                 # uploads whose bodies are still coming: inside a request
            s = socket.create_connection(("127.0.0.1", st.port), timeout=5)
            s.sendall(b"POST /api/recordings/upload?filename=a.tlog HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                      b"Content-Type: application/octet-stream\r\nContent-Length: 100000\r\n\r\n" + b"\0" * 100)
            busy.append(s)
        time.sleep(0.5)
        r = httpx.get(st.url + "/api/health", timeout=5)
        assert r.status_code == 503 and r.text == "too many open connections: try again", (r.status_code, r.text)
        for s in busy:
            s.close()
        time.sleep(0.5)
        assert httpx.get(st.url + "/api/health", timeout=5).status_code == 200
    finally:
        for s in busy:
            s.close()
        st.close()
