"""REST API and WebSocket of the station (FastAPI in a thread on a free loopback port)."""
from __future__ import annotations

import json
import time

import httpx
import pytest
import websockets.sync.client as ws_client

from conftest import free_udp_port
from groundstation.sim.scenarios import simulate


@pytest.fixture
def mission_recording(recordings_dir):
    sim = simulate("mission-clean", 0, duration_s=40.0)
    sim.write(recordings_dir / "mission.tlog")
    return "mission.tlog"


@pytest.fixture
def client(station_no_viser):
    with httpx.Client(base_url=station_no_viser.url, timeout=10) as c:
        yield c


def test_health_state_docs_and_pages(client):
    h = client.get("/api/health").json()
    assert h["status"] == "ok" and h["source"] == "none"
    s = client.get("/api/state").json()
    assert s["source"]["kind"] == "none" and s["wizard"]["state"] == "idle"
    assert client.get("/docs").status_code == 200
    paths = client.get("/openapi.json").json()["paths"]
    for p in ("/api/health", "/api/state", "/api/source", "/api/replay/seek", "/api/calibration/accept",
              "/api/line", "/api/alarms", "/api/session.tlog", "/api/analysis", "/api/analysis.csv"):
        assert p in paths
    for page in ("/index.html", "/calibrate.html", "/calibrate.js", "/app.js", "/style.css"):
        assert client.get(page).status_code == 200


def test_binds_loopback_only_unless_allowed(recordings_dir):
    from groundstation.station.app import Station
    with pytest.raises(ValueError):
        Station(host="0.0.0.0", port=0, viser_port=None, recordings_dir=recordings_dir)


def test_errors_are_4xx_with_detail(client, mission_recording):
    cases = [
        ("post", "/api/source", {"recording": "../../etc/passwd"}),
        ("post", "/api/source", {"recording": "/etc/passwd"}),
        ("post", "/api/source", {"recording": "nope.tlog"}),
        ("post", "/api/source", {"connect": "http://example.com"}),
        ("post", "/api/source", {}),
        ("post", "/api/replay/start", {"recording": "x/../mission.tlog"}),
        ("post", "/api/replay/seek", {"t_s": 1.0}),        # no replay running
        ("post", "/api/replay/stop", None),
        ("post", "/api/calibration/accept", None),
        ("post", "/api/calibration/finish", None),
        ("get", "/api/calibration/params", None),
        ("put", "/api/line", {"a": [95.0, 0.0], "b": [1.0, 1.0]}),
        ("put", "/api/line", {"a": [1.0], "b": [1.0, 1.0]}),
        ("post", "/api/line/from-mission", None),
        ("get", "/api/session.tlog", None),
        ("get", "/api/analysis", None),
    ]
    for method, path, body in cases:
        r = client.request(method.upper(), path, json=body)
        assert 400 <= r.status_code < 500, (path, body, r.status_code)
        assert "detail" in r.json(), (path, r.text)


def test_replay_controls_line_and_downloads(client, mission_recording):
    assert client.get("/api/recordings").json() == [mission_recording]
    info = client.get("/api/recordings/info").json()
    assert [i["name"] for i in info] == [mission_recording] and info[0]["duration_s"] == pytest.approx(40, abs=1)
    r = client.post("/api/replay/start", json={"recording": mission_recording, "speed": 10})
    assert r.status_code == 200, r.text
    assert r.json()["duration_s"] > 30
    # the mission in the log sets the preset line
    line = client.get("/api/line").json()
    assert line is not None and line["source"] == "mission"
    time.sleep(0.5)
    r = client.post("/api/replay/pause", json={"paused": True}).json()
    assert r["paused"]
    r = client.post("/api/replay/seek", json={"t_s": 20.0}).json()
    assert abs(r["t_s"] - 20.0) < 0.1
    r = client.post("/api/replay/speed", json={"speed": 30}).json()
    assert r["speed"] == 30
    client.post("/api/replay/pause", json={"paused": False})
    deadline = time.monotonic() + 5
    while not client.get("/api/state").json()["replay"]["finished"] and time.monotonic() < deadline:
        time.sleep(0.1)
    s = client.get("/api/state").json()
    assert s["replay"]["finished"]
    assert s["vehicle"]["lat_deg"] is not None and s["vehicle"]["cross_track_m"] is not None
    assert abs(s["vehicle"]["cross_track_m"]) < 20
    # line by coordinates
    new = client.put("/api/line", json={"a": [30.26, 120.12], "b": [30.27, 120.12]}).json()
    assert new["source"] == "user" and client.get("/api/state").json()["line"]["b"] == [30.27, 120.12]
    assert client.post("/api/line/from-mission").json()["source"] == "mission"
    assert isinstance(client.get("/api/alarms").json(), list)
    tlog = client.get("/api/session.tlog")
    assert tlog.status_code == 200 and len(tlog.content) > 10_000
    report = client.get("/api/analysis").json()
    assert report["duration_s"] > 30 and report["rtk"] is True and report["alarms"] == []
    csv = client.get("/api/analysis.csv")
    assert csv.status_code == 200 and csv.text.startswith("t_s,roll_deg")
    assert len(csv.text.splitlines()) > 1000
    assert client.post("/api/replay/stop").json()["ok"]
    assert client.get("/api/state").json()["source"]["kind"] == "none"


@pytest.mark.serial     # counts pushes per wall-clock second
def test_websocket_pushes_at_least_10hz_and_survives_disconnects(station_no_viser, client, mission_recording):
    url = station_no_viser.url.replace("http://", "ws://") + "/ws"
    client.post("/api/replay/start", json={"recording": mission_recording, "speed": 2})
    # a client that goes away mid-stream, twice, abruptly
    for _ in range(2):
        c = ws_client.connect(url)
        c.recv()
        c.socket.close()
    with ws_client.connect(url) as ws:
        t0 = time.monotonic()
        msgs = []
        while time.monotonic() - t0 < 1.0:
            msgs.append(json.loads(ws.recv(timeout=2)))
            ws.send("ack")
    assert len(msgs) >= 10
    versions = [m["version"] for m in msgs]
    assert versions == sorted(versions) and versions[-1] > versions[0]
    # a client that never acknowledges is throttled (no backlog), not cut off
    with ws_client.connect(url) as ws:
        t0 = time.monotonic()
        n = 0
        while time.monotonic() - t0 < 2.0:
            ws.recv(timeout=2)
            n += 1
    assert 2 <= n <= 6
    assert client.get("/api/health").json()["status"] == "ok"


def test_live_source_via_rest(client, recordings_dir):
    """A live link records from its first packet: listening alone leaves no (0-byte) file."""
    from groundstation.sim.fake_vehicle import FakeVehicle
    port = free_udp_port()
    r = client.post("/api/source", json={"connect": f"udpin:127.0.0.1:{port}"})
    assert r.status_code == 200 and r.json()["kind"] == "live"
    assert r.json()["recording"] is None and list(recordings_dir.glob("session-*")) == []
    assert client.get("/api/session.tlog").status_code == 404
    sim = simulate("mission-clean", 0, duration_s=3.0)
    with FakeVehicle(sim.messages, port, speed=4.0) as fv:
        assert fv.finished.wait(10)
    deadline = time.monotonic() + 5
    while client.get("/api/state").json()["source"]["recording"] is None and time.monotonic() < deadline:
        time.sleep(0.1)
    rec = client.get("/api/state").json()["source"]["recording"]
    assert rec.endswith(".tlog") and (recordings_dir / rec).stat().st_size > 0
    assert rec in client.get("/api/recordings").json()
    assert client.get("/api/session/file").status_code == 200


def test_scene_decimates_50k_points_and_orients_vehicle(recordings_dir):
    import math

    import numpy as np

    from conftest import free_tcp_port
    from groundstation.station.scene import CLOUD_DISPLAY_POINTS, S_FLIP, Scene, attitude_wxyz
    from groundstation.station.hub.session import Session

    # attitude: yaw 90 deg (nose east) puts the model's nose on viser -y (east); roll 90 puts
    # its right wing (viser -y) down (-z)
    def rotate(q, v):
        w, x, y, z = q
        r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        return r @ v
    np.testing.assert_allclose(rotate(attitude_wxyz(0, 0, math.pi / 2), [1, 0, 0]), [0, -1, 0], atol=1e-9)
    np.testing.assert_allclose(rotate(attitude_wxyz(math.pi / 2, 0, 0), [0, -1, 0]), [0, 0, -1], atol=1e-9)

    session = Session(recordings_dir)
    scene = Scene(session, port=free_tcp_port())
    try:
        rng = np.random.default_rng(0)
        u = rng.normal(size=(50_000, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        C = np.diag([1.1, 0.9, 1.0])
        offsets = np.array([100.0, -50.0, 20.0])
        raw = (u * 500.0) @ np.linalg.inv(C).T + offsets           # C (raw - b) = 500 u
        fit = {"offsets_mG": offsets.tolist(), "matrix": C.tolist(), "field_mG": 500.0}
        scene._update_cloud(raw, fit, calibrating=True)
        assert 0 < scene.cloud_points_shown <= CLOUD_DISPLAY_POINTS
        corrected = np.asarray(scene.corrected.points, dtype=float) @ S_FLIP
        np.testing.assert_allclose(np.linalg.norm(corrected, axis=1), 1.0, atol=2e-3)   # float16
    finally:
        scene.close()


def test_a_connection_to_the_3d_view_that_sends_nothing_prints_no_traceback(recordings_dir, caplog):
    """A port probe or a browser's preconnect to the 3-D view's port, closed before its request:
    the station's console stays clean (the websockets server printed a traceback for it), and the
    view still serves its page afterwards."""
    import socket

    from conftest import free_tcp_port
    from groundstation.station.hub.session import Session
    from groundstation.station.scene import Scene

    scene = Scene(Session(recordings_dir), port=free_tcp_port())
    try:
        for request in (b"", b"", b"GARBAGE\r\n\r\n"):
            with socket.create_connection(("127.0.0.1", scene.port), timeout=5) as probe:
                probe.sendall(request)
                time.sleep(0.3)
        time.sleep(1.0)
        assert httpx.get(f"http://127.0.0.1:{scene.port}/", timeout=10).status_code == 200
    finally:
        scene.close()
    told = [r.getMessage() for r in caplog.records if r.exc_info or "handshake" in r.getMessage()]
    assert told == [], told


def test_a_framing_the_browser_lost_is_sent_again_but_a_later_drag_is_kept(monkeypatch):
    """The 3-D view's camera rule: a pose other than the one sent, reported in the first seconds
    after sending (the viewer's own start-up camera landing after ours on a loaded machine), is
    framed again; the same report later is the user's drag and kept."""
    from types import SimpleNamespace

    import numpy as np

    from groundstation.station.scene import view

    pos, look = np.array([-20.0, 0.0, 8.0]), np.array([0.0, 0.0, 0.0])
    now = [100.0]
    monkeypatch.setattr(view.time, "monotonic", lambda: now[0])
    kept = SimpleNamespace(position=tuple(pos + [0.1, 0.0, 0.0]), look_at=tuple(look))   # 0.5 % off: ours
    other = SimpleNamespace(position=(30.0, 5.0, 9.0), look_at=(1.0, 2.0, 0.0))          # somebody else's
    lo, hi = view.REFRAME_CHECK_S
    for age_s, cam, lost in ((0.5 * lo, other, False),      # its report may predate ours
                             (0.5 * (lo + hi), kept, False),
                             (0.5 * (lo + hi), other, True),
                             (hi + 1.0, other, False)):      # a drag
        now[0] = 100.0 + age_s
        assert view.Scene._pose_lost(cam, pos, look, 100.0) is lost, (age_s, cam)


def test_alarm_list_carries_the_explanation(client, recordings_dir):
    """GET /api/alarms on the demo after its interference episode: the alarm's explanation (the
    disturbance vector in the body frame, growth, tests, likely kind) in numbers and in words."""
    import shutil
    from pathlib import Path
    shutil.copy(Path(__file__).resolve().parent.parent / "recordings" / "demo.tlog", recordings_dir / "demo.tlog")
    assert client.post("/api/replay/start", json={"recording": "demo.tlog", "speed": 1}).status_code == 200
    deadline = time.monotonic() + 60
    while client.get("/api/state").json()["analysing"] and time.monotonic() < deadline:
        time.sleep(0.1)
    client.post("/api/replay/pause", json={"paused": True})
    client.post("/api/replay/seek", json={"t_s": 230.0})
    [alarm] = client.get("/api/alarms").json()
    e = alarm["explanation"]
    assert alarm["end_s"] is not None and e["kind"] == "rising with time" and len(e["disturbance_mG"]) == 3
    assert e["disturbance_size_mG"] > 150.0 and "field_vector" in e["tests"]
    assert alarm["explanation_text"].startswith("likely rising with time; disturbance ")
