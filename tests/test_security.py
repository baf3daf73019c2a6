"""Security of the station's network surface: connection strings, cross-site requests, WebSocket
origins (ours and viser's), Host allow-list, remote mode (token, cookie, TLS) and request limits.

Each test drives a real station (uvicorn on a free loopback port) the way an attacker or a script
would, and asserts the exact refusal and that nothing changed."""
from __future__ import annotations

import json
import os
import socket
import stat
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
import websockets.sync.client as ws_client
from websockets.exceptions import ConnectionClosed, InvalidStatus

from conftest import free_tcp_port, free_udp_port
from groundstation.io.errors import IngestError
from groundstation.io.link import LiveLink, validate_connection_string
from groundstation.io.mavlink import mavlink2 as m

EVIL = "http://evil.example"
TOKEN_HEADER = "X-MagStation-Token"


# ------------------------------------------------------------------------------ connection strings

@pytest.fixture
def planted(tmp_path):
    """A program under a bin/ folder that leaves a marker when run, a .elf, a tlog, a folder."""
    bindir = tmp_path / "evil" / "bin"
    bindir.mkdir(parents=True)
    marker = tmp_path / "ran"
    prog = bindir / "prog"
    prog.write_text(f"#!/bin/sh\ntouch {marker}\nsleep 1\n")
    prog.chmod(0o755)
    elf = tmp_path / "x.elf"
    elf.write_bytes(prog.read_bytes())
    elf.chmod(0o755)
    tlog = tmp_path / "old.tlog"
    tlog.write_bytes(Path(__file__).with_name("data").joinpath("reference.tlog").read_bytes())
    return {"prog": prog, "elf": elf, "tlog": tlog, "dir": tmp_path, "marker": marker}


def _hostile_strings(p: dict) -> list[str]:
    up = "/dev/" + "../" * 12
    shm = Path("/dev/shm")
    strings = [
        up + str(p["prog"]).lstrip("/"), str(p["prog"]), str(p["prog"]) + ",57600",
        up + str(p["elf"]).lstrip("/"), str(p["elf"]), up + str(p["tlog"]).lstrip("/"), str(p["tlog"]),
        up + str(p["dir"]).lstrip("/"), str(p["dir"]), "/dev", "/dev/", "/dev/.", "/dev/null/../../etc/passwd",
        "/dev/ttyUSB0/../../" + str(p["tlog"]).lstrip("/"), "/dev/nonexistent-port", "/etc/passwd",
        "old.tlog", "log.bin", "x.px4log", "csv:/etc/passwd", "uds:/tmp/sock", "unix:/tmp/sock",
        "mcast:", "udpbcast:255.255.255.255:14550", "wsserver:0.0.0.0:1", "ws://evil:1", "wss://evil:1",
        "127.0.0.1:14550", "udpin:127.0.0.1:14550:1", "tcp:evil.example", "udp:host:0", "tcp:a b:1",
        "udpin:127.0.0.1:14550\n/bin/sh", "tcp:127.0.0.1:5760,57600", "/dev/ttyS0,fast", "COM3x",
        "\x00/dev/tty", "udpin:[::1]:14550", "",
    ]
    if shm.is_dir():
        f = shm / f"magstation-test-{os.getpid()}"
        f.write_bytes(b"x")
        strings.append(str(f))
    if os.name != "nt":
        strings.append("COM3")
    return strings


def test_connection_strings_naming_files_programs_or_folders_are_refused(planted):
    for url in _hostile_strings(planted):
        with pytest.raises(IngestError) as err:
            validate_connection_string(url)
        message = str(err.value)
        assert "\n" not in message and message, url
    assert not planted["marker"].exists()
    for f in Path("/dev/shm").glob(f"magstation-test-{os.getpid()}"):
        f.unlink()


def test_connection_strings_that_are_accepted():
    assert validate_connection_string("udpin:127.0.0.1:14550") == "udpin:127.0.0.1:14550"
    assert validate_connection_string(" tcp:localhost:5760 ") == "tcp:localhost:5760"
    assert validate_connection_string("udpout:10.0.0.2:14550") == "udpout:10.0.0.2:14550"
    # the operator (CLI) may listen on every interface; a request over HTTP may not (below)
    assert validate_connection_string("udpin:0.0.0.0:14550") == "udpin:0.0.0.0:14550"
    with pytest.raises(IngestError, match="loopback"):
        validate_connection_string("udpin:0.0.0.0:14550", listen_any=False)
    with pytest.raises(IngestError, match="loopback"):
        validate_connection_string("tcpin:192.168.1.2:5760", listen_any=False)
    assert validate_connection_string("tcpin:127.0.0.1:5760", listen_any=False)


def test_api_refuses_program_file_and_wildcard_listener(station_no_viser, planted, recordings_dir):
    url = station_no_viser.url
    up = "/dev/" + "../" * 12
    for connect in (up + str(planted["prog"]).lstrip("/"), up + str(planted["tlog"]).lstrip("/"),
                    f"udpin:0.0.0.0:{free_udp_port()}", f"tcpin:0.0.0.0:{free_tcp_port()}",
                    f"udp:0.0.0.0:{free_udp_port()}"):
        r = httpx.post(url + "/api/source", json={"connect": connect})
        assert r.status_code == 400, (connect, r.status_code, r.text)
        assert "\n" not in r.json()["detail"]
    time.sleep(0.2)
    assert not planted["marker"].exists()
    assert httpx.get(url + "/api/state").json()["source"]["kind"] == "none"
    assert list(recordings_dir.iterdir()) == []          # no half-made recording either


def _pty_pair():
    master, slave = os.openpty()
    path = os.ttyname(slave)
    return master, slave, path


def test_serial_link_on_a_real_device_node():
    """A pseudo-terminal is a character device under /dev: the serial path (pyserial) carries
    MAVLink both ways."""
    master, slave, path = _pty_pair()
    assert stat.S_ISCHR(os.stat(path).st_mode)
    assert validate_connection_string(f"{path},115200") == f"{path},115200"
    link = LiveLink(f"{path},115200")
    try:
        enc = m.MAVLink(None, srcSystem=1, srcComponent=1)
        os.write(master, bytes(m.MAVLink_heartbeat_message(2, 3, 81, 0, 4, 3).pack(enc)))
        deadline = time.time() + 5
        got = []
        while time.time() < deadline and not link.connected:
            got += link.poll()
            time.sleep(0.02)
        assert link.connected and link.decoder.autopilot == "ardupilot"
        link.poll()                                   # housekeeping: our GCS heartbeat goes out
        os.set_blocking(master, False)
        time.sleep(0.1)
        out = b""
        try:
            out = os.read(master, 4096)
        except BlockingIOError:
            pass
        assert b"\xfd" in out or b"\xfe" in out
    finally:
        link.close()
        os.close(master)
        os.close(slave)


def test_serial_errors_are_one_line(monkeypatch):
    with pytest.raises(IngestError, match="no such device"):
        validate_connection_string("/dev/ttyMAGSTATION9,57600")
    master, slave, path = _pty_pair()
    try:
        import serial
        real = serial.Serial

        def busy(*args, **kwargs):
            raise serial.SerialException(16, f"could not open port {path}: [Errno 16] Device or resource busy")
        monkeypatch.setattr(serial, "Serial", busy)
        with pytest.raises(IngestError) as err:
            LiveLink(path)
        assert "busy" in str(err.value) and "\n" not in str(err.value)
        monkeypatch.setattr(serial, "Serial", real)
        monkeypatch.setitem(sys.modules, "serial", None)         # pyserial not installed
        with pytest.raises(IngestError, match="pyserial"):
            LiveLink(path)
    finally:
        os.close(master)
        os.close(slave)


def test_serial_on_a_non_tty_device_is_a_clear_error():
    with pytest.raises(IngestError) as err:
        LiveLink("/dev/null")
    assert "\n" not in str(err.value) and "/dev/null" in str(err.value)


# ------------------------------------------------------------------------------ cross-site requests

WRITES = [
    ("POST", "/api/calibration/start", None), ("POST", "/api/calibration/reset", None),
    ("POST", "/api/calibration/finish", None), ("POST", "/api/calibration/accept", None),
    ("POST", "/api/source/stop", None), ("POST", "/api/replay/stop", None),
    ("POST", "/api/line/from-mission", None), ("PUT", "/api/line", {"a": [1.0, 1.0], "b": [1.1, 1.0]}),
    ("POST", "/api/source", {"recording": "mission.tlog"}),
    ("POST", "/api/replay/start", {"recording": "mission.tlog"}),
    ("POST", "/api/replay/pause", {"paused": True}), ("POST", "/api/replay/seek", {"t_s": 1.0}),
    ("POST", "/api/replay/speed", {"speed": 2.0}),
]


@pytest.fixture
def mission_recording(recordings_dir):
    from groundstation.sim.scenarios import simulate
    simulate("mission-clean", 0, duration_s=20.0).write(recordings_dir / "mission.tlog")
    return "mission.tlog"


def _page_token(base: str) -> str:
    r = httpx.get(base + "/api/page-token", headers={"Origin": base})
    assert r.status_code == 200, r.text
    return r.json()["token"]


def test_cross_site_writes_are_refused(station_no_viser, mission_recording):
    base = station_no_viser.url
    state0 = httpx.get(base + "/api/state").json()
    token = _page_token(base)
    forged = [
        {"Origin": EVIL},
        {"Origin": "null"},
        {"Origin": EVIL, TOKEN_HEADER: token},                        # a stolen token is not enough
        {"Referer": EVIL + "/page.html"},
        {"Origin": base},                                              # our origin but no token
        {"Origin": base, TOKEN_HEADER: "guess"},
        {"Origin": base.replace("127.0.0.1", "localhost"), TOKEN_HEADER: token},   # another origin
        {"Sec-Fetch-Site": "cross-site"},
    ]
    for method, path, body in WRITES:
        for headers in forged:
            r = httpx.request(method, base + path, json=body, headers=headers)
            assert r.status_code == 403, (method, path, headers, r.status_code, r.text)
            assert "access-control-allow-origin" not in r.headers
        # what a cross-site <form> sends: urlencoded, with the attacker's Origin
        r = httpx.request(method, base + path, content=b"x=1", headers={
            "Origin": EVIL, "Content-Type": "application/x-www-form-urlencoded"})
        assert r.status_code == 403
    state1 = httpx.get(base + "/api/state").json()
    assert state1["wizard"]["state"] == state0["wizard"]["state"] == "idle"
    assert state1["source"]["kind"] == "none" and state1["line"] is None


def test_own_page_and_scripts_still_write(station_no_viser, mission_recording):
    base = station_no_viser.url
    token = _page_token(base)
    ours = {"Origin": base, TOKEN_HEADER: token, "Referer": base + "/index.html"}
    r = httpx.post(base + "/api/source", json={"recording": mission_recording}, headers=ours)
    assert r.status_code == 200, r.text
    assert httpx.post(base + "/api/replay/pause", json={"paused": True}, headers=ours).status_code == 200
    # a script on the station machine: no Origin, no token (curl, Python, tests)
    assert httpx.post(base + "/api/source/stop").status_code == 200
    assert httpx.post(base + "/api/calibration/start").status_code == 200
    # the page token is never served to another site; nor is any other /api answer
    for headers in ({"Origin": EVIL}, {"Sec-Fetch-Site": "cross-site"}, {"Sec-Fetch-Site": "same-site"}):
        for path in ("/api/page-token", "/api/state", "/api/analysis", "/api/session.tlog"):
            r = httpx.get(base + path, headers=headers)
            assert r.status_code == 403 and "access-control-allow-origin" not in r.headers, (path, headers)
    assert httpx.get(base + "/api/state", headers={"Sec-Fetch-Site": "same-origin"}).status_code == 200
    # /docs documents the header on the writing routes
    spec = httpx.get(base + "/openapi.json").json()
    params = spec["paths"]["/api/calibration/accept"]["post"].get("parameters", [])
    assert any(p["name"] == TOKEN_HEADER and p["in"] == "header" for p in params)


def test_preflight_grants_nothing(station_no_viser):
    base = station_no_viser.url
    for path in ("/api/source", "/api/calibration/accept", "/api/page-token", "/api/state"):
        r = httpx.options(base + path, headers={"Origin": EVIL, "Access-Control-Request-Method": "POST",
                                                "Access-Control-Request-Headers": TOKEN_HEADER})
        assert r.status_code >= 400
        assert not any(h.startswith("access-control-") for h in r.headers), r.headers


def _ws_url(base: str) -> str:
    return base.replace("http://", "ws://") + "/ws"


def test_ws_refuses_foreign_and_null_origins(station_no_viser):
    base = station_no_viser.url
    for origin in (EVIL, "null", "http://127.0.0.1:1", base.replace("127.0.0.1", "localhost")):
        with pytest.raises(InvalidStatus) as err:
            ws_client.connect(_ws_url(base), origin=origin, open_timeout=5)
        assert err.value.response.status_code == 403, origin
    for origin in (None, base):                      # scripts (no Origin) and our own page
        with ws_client.connect(_ws_url(base), origin=origin, open_timeout=5) as ws:
            assert json.loads(ws.recv(timeout=5))["source"]["kind"] == "none"


def test_host_header_allow_list(station_no_viser):
    base = station_no_viser.url
    port = station_no_viser.port
    for host in ("evil.example", f"evil.example:{port}", f"127.0.0.1.evil.example:{port}", "", "[::2]"):
        r = httpx.get(base + "/api/health", headers={"Host": host})
        assert r.status_code == 400, (host, r.status_code)
    for host in (f"127.0.0.1:{port}", f"localhost:{port}", "localhost", f"[::1]:{port}"):
        assert httpx.get(base + "/api/health", headers={"Host": host}).status_code == 200, host
    with pytest.raises(InvalidStatus):
        ws_client.connect(_ws_url(base), additional_headers={"Host": "evil.example"}, open_timeout=5)


def test_viser_websocket_refuses_foreign_origins(station):
    import viser

    url = f"ws://127.0.0.1:{station.viser_port}/"
    proto = [f"viser-v{viser.__version__}"]
    for origin in (EVIL, "null"):
        try:
            with ws_client.connect(url, origin=origin, subprotocols=proto, open_timeout=5) as ws:
                with pytest.raises(ConnectionClosed):
                    msg = ws.recv(timeout=3)
                    pytest.fail(f"viser sent {len(msg)} bytes to origin {origin}")
        except InvalidStatus:
            pass
    with ws_client.connect(url, origin=f"http://127.0.0.1:{station.viser_port}", subprotocols=proto,
                           open_timeout=5) as ws:
        assert len(ws.recv(timeout=5)) > 0                 # the scene, for the 3-D view itself


# ------------------------------------------------------------------------------ remote mode

@pytest.fixture
def remote_station(recordings_dir):
    """Remote mode (token required), bound to loopback so the test opens nothing to the network."""
    from groundstation.station.app import Station
    st = Station(host="127.0.0.1", allow_remote=True, port=0, viser_port=None,
                 recordings_dir=recordings_dir).start()
    yield st
    st.close()


def test_remote_mode_needs_the_token(remote_station):
    base = remote_station.url
    token = remote_station.settings.access_token
    assert token and len(token) >= 32
    for path in ("/api/health", "/api/state", "/index.html", "/docs", "/openapi.json"):
        r = httpx.get(base + path)
        assert r.status_code == 401, (path, r.status_code)
    assert httpx.get(base + "/api/state", headers={"Authorization": "Bearer wrong"}).status_code == 401
    bearer = {"Authorization": f"Bearer {token}"}
    assert httpx.get(base + "/api/state", headers=bearer).status_code == 200
    assert httpx.post(base + "/api/calibration/start", headers=bearer).status_code == 200
    with pytest.raises(InvalidStatus):
        ws_client.connect(_ws_url(base), open_timeout=5)
    with ws_client.connect(_ws_url(base), additional_headers=bearer, open_timeout=5) as ws:
        assert json.loads(ws.recv(timeout=5))["wizard"]["state"] != "idle"


def test_remote_mode_first_visit_sets_a_strict_cookie(remote_station):
    base = remote_station.url
    token = remote_station.settings.access_token
    with httpx.Client(base_url=base) as c:
        r = c.get(f"/index.html?token={token}")
        assert r.status_code in (302, 303, 307) and "token" not in r.headers["location"]
        cookie = r.headers["set-cookie"].lower()
        assert "httponly" in cookie and "samesite=strict" in cookie and token.lower() in cookie
        assert c.get("/index.html").status_code == 200
        assert c.get("/api/state").status_code == 200
        # the cookie does not make a cross-site write possible
        assert c.post("/api/calibration/start", headers={"Origin": EVIL}).status_code == 403
        page = _page_token_with(c, base)
        assert c.post("/api/calibration/start", headers={"Origin": base, TOKEN_HEADER: page}).status_code == 200
    assert httpx.get(base + "/index.html?token=wrong").status_code == 401


def _page_token_with(client: httpx.Client, base: str) -> str:
    r = client.get("/api/page-token", headers={"Origin": base})
    assert r.status_code == 200
    return r.json()["token"]


def test_remote_mode_with_tls(recordings_dir, tmp_path):
    from groundstation.station.app import Station
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1", "-subj",
                    "/CN=localhost", "-keyout", str(key), "-out", str(cert)], check=True, capture_output=True)
    st = Station(host="127.0.0.1", allow_remote=True, port=0, viser_port=None, recordings_dir=recordings_dir,
                 tls_cert=cert, tls_key=key).start()
    try:
        assert st.url.startswith("https://")
        token = st.settings.access_token
        r = httpx.get(st.url + "/api/health", headers={"Authorization": f"Bearer {token}"}, verify=False)
        assert r.status_code == 200
        r = httpx.get(st.url + f"/index.html?token={token}", verify=False)
        assert "secure" in r.headers["set-cookie"].lower()
        with pytest.raises(httpx.HTTPError):
            httpx.get(st.url.replace("https://", "http://") + "/api/health", timeout=3)
        from groundstation.station.settings import StationSettings
        wide = StationSettings(host="0.0.0.0", allow_remote=True, tls_cert=cert, tls_key=key)
        assert wide.viser_host == "127.0.0.1" and wide.scheme == "https"   # viser has no TLS
    finally:
        st.close()


def test_remote_mode_guards_the_3d_view(recordings_dir):
    import viser
    from groundstation.station.app import Station
    st = Station(host="127.0.0.1", allow_remote=True, port=0, viser_port=free_tcp_port(),
                 recordings_dir=recordings_dir)
    try:
        url = f"ws://127.0.0.1:{st.viser_port}/"
        own = f"http://127.0.0.1:{st.viser_port}"
        proto = [f"viser-v{viser.__version__}"]
        with ws_client.connect(url, origin=own, subprotocols=proto, open_timeout=5) as ws:
            with pytest.raises(ConnectionClosed):
                ws.recv(timeout=3)
        cookie = {"Cookie": f"magstation_token={st.settings.access_token}"}
        with ws_client.connect(url, origin=own, subprotocols=proto, additional_headers=cookie,
                               open_timeout=5) as ws:
            assert len(ws.recv(timeout=5)) > 0
    finally:
        st.close()


def test_tls_settings_are_checked(tmp_path):
    from groundstation.station.settings import StationSettings
    with pytest.raises(ValueError, match="both"):
        StationSettings(tls_cert=tmp_path / "c.pem")
    with pytest.raises(ValueError, match="not a file"):
        StationSettings(tls_cert=tmp_path / "c.pem", tls_key=tmp_path / "k.pem")


# ------------------------------------------------------------------------------ limits

def test_request_bodies_are_bounded(station_no_viser):
    base = station_no_viser.url
    big = b'{"recording": "' + b"a" * (2 << 20) + b'"}'
    r = httpx.post(base + "/api/source", content=big, headers={"Content-Type": "application/json"})
    assert r.status_code == 413 and "1 MiB" in r.json()["detail"]

    def chunks():                                    # no Content-Length: counted while streaming
        yield b'{"recording": "'
        for _ in range(64):
            yield b"a" * 65536
        yield b'"}'
    r = httpx.post(base + "/api/source", content=chunks(), headers={"Content-Type": "application/json"})
    assert r.status_code == 413
    assert httpx.get(base + "/api/health").status_code == 200


def test_body_limits_are_a_setting_per_prefix():
    from groundstation.station.settings import StationSettings
    s = StationSettings(body_limits=(("/", 1 << 20), ("/api/uploads/", 200 << 20)))
    assert s.body_limit_for("/api/uploads/x") == 200 << 20 and s.body_limit_for("/api/source") == 1 << 20


def test_hostile_names_give_4xx_not_500(station_no_viser, mission_recording):
    base = station_no_viser.url
    for body in ({"recording": "a\x00.tlog"}, {"recording": "a" * 5000 + ".tlog"},
                 {"recording": "\x1b[2J.tlog"}, {"connect": "udpin:127.0.0.1:1\x00"},
                 {"connect": "/dev/" + "a" * 5000}):
        for path in ("/api/source", "/api/replay/start"):
            if path == "/api/replay/start" and "connect" in body:
                continue
            r = httpx.post(base + path, json=body)
            assert r.status_code in (400, 404, 422), (path, body.keys(), r.status_code, r.text[:200])
            detail = json.dumps(r.json()["detail"])
            assert len(detail) < 2000, detail[:200]


# ------------------------------------------------------------------------------ serve on the CLI

def _serve(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    root = Path(__file__).resolve().parents[1]
    return subprocess.run([sys.executable, "-m", "groundstation.cli", "serve", *args], cwd=root,
                          capture_output=True, text=True, timeout=timeout)


def test_serve_errors_are_one_line_and_no_address_is_printed(tmp_path):
    empty = tmp_path / "empty.tlog"
    empty.write_bytes(b"")
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen(1)
    port = busy.getsockname()[1]
    try:
        cases = [("--connect", "bogus:1", "--port", "0"), ("--replay", str(empty), "--port", "0"),
                 ("--port", str(port), "--viser-port", str(free_tcp_port())),
                 ("--connect", "/dev/" + "../" * 10 + "bin/true", "--port", "0")]
        for args in cases:
            out = _serve(*args)
            assert out.returncode != 0, (args, out.stdout, out.stderr)
            assert "Traceback" not in out.stderr, out.stderr
            lines = [ln for ln in out.stderr.splitlines() if ln.strip()]
            assert len(lines) == 1 and lines[0].startswith("magstation: error:"), (args, out.stderr)
            assert "web page" not in out.stdout, (args, out.stdout)
    finally:
        busy.close()
