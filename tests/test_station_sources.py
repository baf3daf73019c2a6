"""Sources in the hub: a new source starts clean, a connect that reaches nothing stops nothing,
recordings start at the first packet, seeking rebuilds the state, downloads always answer.

The routers are exercised in process (FastAPI TestClient over a real hub)."""
from __future__ import annotations

import re
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from conftest import REAL_TLOG_PIECE, REAL_ULOG_PIECE, free_tcp_port, free_udp_port, wait_until
from groundstation.jobs.record import COL
from groundstation.sim.fake_vehicle import FakeVehicle
from groundstation.sim.scenarios import simulate
from groundstation.station.app import create_app
from groundstation.station.hub.session import Session, SessionError

ROOT = Path(__file__).resolve().parent.parent
DEMO = ROOT / "recordings" / "demo.tlog"


wait_for = wait_until


@pytest.fixture
def folder(tmp_path) -> Path:
    d = tmp_path / "recordings"
    d.mkdir()
    shutil.copy(DEMO, d / "demo.tlog")
    simulate("calibration", 0).write(d / "dance.tlog")          # no mission in it
    return d


@pytest.fixture
def hub(folder):
    session = Session(folder)
    yield session
    session.close()


def _replay(hub: Session, path: Path, speed: float = 50.0) -> None:
    hub.start_replay(path, speed)
    assert wait_for(lambda: not hub.snapshot()["analysing"])


def test_seek_rebuilds_route_alarms_and_plots(hub, folder):
    """Demo: interference from ~150 s.  Seek to 170 s, back to 60 s, forward to 220 s: every
    time the page gets the state of that moment (not blank, not the old plots)."""
    _replay(hub, folder / "demo.tlog")
    hub.replay_pause(True)
    for t, alarms, active in ((170.0, 1, True), (60.0, 0, False), (220.0, 1, False), (5.0, 0, False)):
        hub.replay_seek(t)
        s = hub.snapshot()
        assert s["t_s"] == pytest.approx(t) and s["alarm_count"] == alarms and s["alarm"]["active"] is active, t
        route = hub.scene_data()["route"]
        assert len(route) and t - 1.0 < route[-1, 0] <= t, t
        plots = hub.plot_data(60.0)
        assert t - 0.2 < plots["t_end_s"] <= t and plots["t_s"][0] >= t - 60.5, t
        assert s["vehicle"]["roll_deg"] is not None and s["line"] is not None, t
    hub.replay_seek(170.0)
    [alarm] = hub.alarm_list()
    assert alarm["end_s"] is None and 145 < alarm["start_s"] < 160
    assert "compass heading" in alarm["evidence_text"]
    hub.replay_seek(230.0)
    assert hub.alarm_list()[0]["end_s"] is not None


def test_seek_benchmark_smoke():
    out = subprocess.run([sys.executable, "benchmarks/seek.py", "--minutes", "5", "--seeks", "5", "--open-mb", "1"],
                         cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    worst = float(re.search(r"worst ([\d.]+) s", out.stdout).group(1))
    assert 0.0 < worst < 2.0, out.stdout
    assert float(re.search(r"^replayer made .*: ([\d.]+) s$", out.stdout, re.M).group(1)) < 2.0, out.stdout
    first, ready = map(float, re.search(r"^open -> playing .*: first sample pushed after ([\d.]+) s, the analysis "
                                        r"in after ([\d.]+) s$", out.stdout, re.M).groups())
    assert first < ready, out.stdout            # it plays while the log is analysed
    assert re.search(r"^open a [\d.]+ MB tlog by name -> playing: [\d.]+ s .*, target < 2 s: (met|MISSED)$",
                     out.stdout, re.M), out.stdout
    assert re.search(r"\| per-sample re-run .* \| [\d.]+ \| [\d.]+ \| extrapolated \|", out.stdout), out.stdout


def test_new_source_starts_clean(hub, folder):
    """After the demo (line, alarm, events, wizard running) a log without a mission replays
    with no line, no alarms, none of the demo's events; a live link starts with nothing."""
    _replay(hub, folder / "demo.tlog")
    hub.replay_pause(True)
    hub.replay_seek(170.0)
    assert hub.snapshot()["line"] is not None and hub.snapshot()["alarm"]["active"]
    hub.wizard_start()            # (on a replay it rewinds to the log's dance: issue 31)
    assert hub.snapshot()["wizard"]["state"] != "idle"
    _replay(hub, folder / "dance.tlog")
    s = hub.snapshot()
    assert s["line"] is None and s["alarm_count"] == 0 and not s["alarm"]["active"]
    assert s["wizard"]["state"] == "idle" and s["tests"]["path"]["state"] == "off"
    assert not any("demo" in e["text"] or "ALARM" in e["text"] for e in s["events"])
    report, _ = hub.analysis()
    assert report["mission"] is None and report["max_cross_track_m"] is None
    hub.stop()
    hub.connect(f"udpin:127.0.0.1:{free_udp_port()}")
    s = hub.snapshot()
    assert s["source"]["kind"] == "live" and s["rx_age_s"] is None and s["rx_count"] == 0
    assert s["vehicle"]["roll_deg"] is None and s["alarm_count"] == 0 and s["line"] is None
    assert hub.plot_data(60.0)["t_s"] == [] and len(hub.scene_data()["route"]) == 0


def test_clear_line_and_line_route(hub, folder):
    client = TestClient(create_app(hub), base_url="http://127.0.0.1")
    _replay(hub, folder / "demo.tlog")
    assert client.get("/api/line").json()["source"] == "mission"
    assert client.delete("/api/line").json()["ok"]
    s = client.get("/api/state").json()
    assert s["line"] is None and s["tests"]["path"] == {"state": "off", "why": "no preset line"}
    assert wait_for(lambda: not hub.flight.needs_review(), timeout=20)       # analysed again without it
    assert client.post("/api/line/from-mission").json()["source"] == "mission"


def test_connect_that_reaches_nothing_stops_nothing(hub, folder, capfd):
    """A refused TCP link fails in one line (no pymavlink retry spam); a UDP link that hears
    nothing keeps the replay running and writes no file; its first packet switches over."""
    _replay(hub, folder / "demo.tlog", speed=1.0)
    port = free_tcp_port()
    with pytest.raises(SessionError, match=f"cannot connect to 127.0.0.1:{port}: connection refused"):
        hub.connect(f"tcp:127.0.0.1:{port}")
    assert "Connection refused" not in capfd.readouterr().out
    udp = free_udp_port()
    hub.connect(f"udpin:127.0.0.1:{udp}")
    t0 = hub.snapshot()["replay"]["t_s"]
    time.sleep(0.6)
    s = hub.snapshot()
    assert s["source"]["kind"] == "replay" and s["source"]["pending"] == f"udpin:127.0.0.1:{udp}"
    assert s["replay"]["t_s"] > t0 and list(folder.glob("session-*")) == []
    sim = simulate("mission-clean", 0, duration_s=4.0)
    with FakeVehicle(sim.messages, udp, speed=2.0) as fv:
        assert wait_for(lambda: hub.snapshot()["source"]["kind"] == "live", timeout=10)
        assert fv.finished.wait(10)
    assert wait_for(lambda: hub.snapshot()["vehicle"]["roll_deg"] is not None, timeout=5)
    [rec] = folder.glob("session-*.tlog")
    assert rec.stat().st_size > 1000 and hub.snapshot()["source"]["recording"] == rec.name
    hub.stop()                         # a stopped connect attempt leaves nothing behind either
    hub.connect(f"udpin:127.0.0.1:{free_udp_port()}")
    hub.stop()
    assert len(list(folder.glob("session-*"))) == 1


def test_a_calibration_started_while_the_link_switches_over_stays_for_it(hub, folder, monkeypatch):
    """Start pressed after the connecting link heard its vehicle but before the station had
    switched to it (the old source stopping takes a moment on a busy machine) is meant for the
    new vehicle: the wizard keeps running on the new link, as it does when pressed earlier."""
    _replay(hub, folder / "demo.tlog", speed=1.0)
    udp = free_udp_port()
    hub.connect(f"udpin:127.0.0.1:{udp}")
    stop = hub.sources.stop
    in_switch = threading.Event()

    def slow_stop():
        in_switch.set()
        time.sleep(1.0)
        stop()
    monkeypatch.setattr(hub.sources, "stop", slow_stop)
    sim = simulate("mission-clean", 0, duration_s=4.0)
    with FakeVehicle(sim.messages, udp, speed=2.0) as fv:
        assert in_switch.wait(10)                       # first packet heard, the old source stopping
        assert hub.sources.pending is None and hub.snapshot()["source"]["kind"] == "replay"
        hub.wizard_start("onboard")                     # a replay has no calibrator: not refused, meant for the link
        assert hub.snapshot()["wizard"]["waiting_for"] == f"udpin:127.0.0.1:{udp}"
        assert wait_for(lambda: hub.snapshot()["source"]["kind"] == "live", timeout=10)
        w = hub.snapshot()["wizard"]
        assert (w["state"], w["mode"], w["waiting_for"]) == ("running", "onboard", None)
        assert wait_for(lambda: any(c[0] == 42424 for c in fv.commands), timeout=10)   # DO_START_MAG_CAL, to it
    assert hub.sources.switching is None
    hub.wizard_reset()


def test_a_calibration_started_while_a_link_connects_waits_for_its_vehicle(hub, folder):
    """Start pressed while a link connects and a replay still plays: the wizard waits for the new
    vehicle (the replay's samples do not fill its steps) and says so; Stop, and it is reset."""
    _replay(hub, folder / "dance.tlog", speed=4.0)
    udp = free_udp_port()
    hub.connect(f"udpin:127.0.0.1:{udp}")
    hub.wizard_start("guided")
    time.sleep(2.0)                                     # 8 s of the replayed dance
    w = hub.snapshot()["wizard"]
    assert w["state"] == "running" and w["waiting_for"] == f"udpin:127.0.0.1:{udp}"
    assert w["progress_deg"] == {"x": 0.0, "y": 0.0, "z": 0.0} and w["instruction"].startswith("Waiting for the vehicle")
    assert hub.snapshot()["replay"]["t_s"] > 4.0          # not rewound for the calibration
    hub.stop()
    assert hub.snapshot()["wizard"]["state"] == "idle"


def test_a_calibration_waiting_for_a_link_that_is_replaced_is_cancelled(hub, folder):
    """Start pressed while link A connects, then the operator connects B instead: A is given up,
    so the wizard no longer says it waits for A (it did until B's vehicle was heard, or forever);
    B's vehicle, when it comes, starts clean.  Connecting A again keeps the wait."""
    _replay(hub, folder / "dance.tlog", speed=4.0)
    a, b = f"udpin:127.0.0.1:{free_udp_port()}", free_udp_port()
    hub.connect(a)
    hub.wizard_start("guided")
    hub.connect(a)                                      # the same link again: still meant for it
    assert hub.snapshot()["wizard"]["waiting_for"] == a
    hub.connect(f"udpin:127.0.0.1:{b}")
    snap = hub.snapshot()
    assert (snap["wizard"]["state"], snap["wizard"]["waiting_for"]) == ("idle", None)
    assert any(f"waiting for the vehicle on {a} is cancelled" in e["text"] for e in snap["events"])
    with FakeVehicle(simulate("mission-clean", 0, duration_s=4.0).messages, b, speed=2.0):
        assert wait_for(lambda: hub.snapshot()["source"]["kind"] == "live", timeout=10)
    assert hub.snapshot()["wizard"]["state"] == "idle"


def test_downloads_of_a_ulog_replay(hub, folder):
    """A .ulg replay: the session log is the original file; the .tlog route says why it has none."""
    src = REAL_ULOG_PIECE
    shutil.copy(src, folder / "events.ulg")
    client = TestClient(create_app(hub), base_url="http://127.0.0.1")
    assert client.post("/api/replay/start", json={"recording": "events.ulg", "speed": 20}).status_code == 200
    assert wait_for(lambda: not hub.snapshot()["analysing"])
    r = client.get("/api/session/file")
    assert r.status_code == 200 and r.content == src.read_bytes()
    assert 'filename="events.ulg"' in r.headers["content-disposition"]
    r = client.get("/api/session.tlog")
    assert r.status_code == 404 and "not MAVLink" in r.json()["detail"]
    assert client.get("/api/analysis").json()["duration_s"] > 10
    assert client.get("/api/analysis.csv").text.startswith("t_s,")
    s = client.get("/api/state").json()
    assert s["downloads"] == {"log": "events.ulg", "tlog": False}
    tl = client.get("/api/replay/timeline").json()
    assert tl["ready"] and tl["duration_s"] > 10


def test_gps_outage_events_only_when_the_imu_streams(hub, folder):
    """The demo's 5 s gap between its parts is a gap in all the data, not a GPS outage; the
    timeline shows it as a data gap."""
    _replay(hub, folder / "demo.tlog", speed=100.0)
    assert wait_for(lambda: hub.snapshot()["replay"]["finished"], timeout=20)
    texts = [e["text"] for e in hub.events]
    assert not any("GPS fix lost" in t for t in texts), texts
    kinds = [(m["kind"], m["t_s"]) for m in hub.timeline()["markers"]]
    assert ("gap", pytest.approx(80.0, abs=1.0)) in kinds and not any(k == "gps" for k, _ in kinds)


def test_tests_state_and_field_correction_on_the_real_log(hub, folder):
    """The real ArduCopter telemetry log: heading and field tests off (2.8 Hz IMU: our attitude is
    not trusted, issue 30) and said so, the field autopilot-corrected (ArduPilot applies
    COMPASS_OFS), no path test without a line."""
    shutil.copy(REAL_TLOG_PIECE, folder / "real.tlog")      # its seconds 440-700
    _replay(hub, folder / "real.tlog")
    hub.replay_pause(True)
    hub.replay_seek(160.0)
    t = hub.snapshot()["tests"]
    assert t["heading"]["state"] == "off" and re.match(r"IMU rate 2\.\d Hz < 10 Hz", t["heading"]["why"])
    assert t["field"]["state"] == "off" and re.match(r"IMU rate 2\.\d Hz < 10 Hz", t["field"]["why"])
    assert t["path"]["state"] == "off"
    # no dance in the log: its in-flight fit (jobs.calibrate) is not used, ArduPilot's own stands
    assert hub.log_calibration is None
    assert t["field_correction"]["kind"] == "autopilot" and "ArduPilot" in t["field_correction"]["note"]
    rows = hub.flight.rows()
    assert not np.any(rows[:, COL["heading_on"]] > 0.5)


def _repeated(path: Path, minutes: float):
    """The log at ``path`` repeated end to end to ``minutes`` (a long flight without writing one)."""
    import copy

    from groundstation.io.logs import read_log
    base = read_log(path)
    period = base.duration_s + 0.02
    k = max(1, int(np.ceil(minutes * 60 / period)))
    out = copy.copy(base)
    for name in ("mag", "imu", "attitude", "gps", "battery"):
        a = getattr(base, name)
        if len(a):
            setattr(out, name, np.concatenate([a + np.r_[i * period, np.zeros(a.shape[1] - 1)] for i in range(k)]))
    return out


def test_a_long_replay_plays_while_it_is_analysed(tmp_path):
    """Issue 29: a replay starts playing once its file is read; the whole-log analysis runs beside
    it.  Meanwhile the page says "analysing" and shows the causal path's decisions (the live
    link's, which are analyze's: the same rows at the same times); then the analysis takes over
    from where the replay has got to, without a jump back."""
    log = _repeated(ROOT / "recordings" / "mission-clean.tlog", 6.0)
    hub = Session(tmp_path, record_live=False)
    seen: list = []           # (perf s, rx_count, analysing, rows shown) after each batch

    def listener():
        if hub.sources.kind == "replay":
            rows = hub.flight.rows()
            seen.append((time.perf_counter(), hub.sources.rx_count, hub.flight.review is None, rows[-50:].copy()))

    hub.add_listener(listener)
    try:
        t0 = time.perf_counter()
        hub.start_replay(tmp_path / "long.tlog", speed=20.0, flight_log=log)
        assert hub.snapshot()["analysing"]
        assert wait_for(lambda: not hub.snapshot()["analysing"], timeout=120)
        t_ready = time.perf_counter() - t0
        hub.replay_pause(True)
        review_rows = hub.flight.review.rows
        position = hub.snapshot()["t_s"]
    finally:
        hub.close()
    meanwhile = [s for s in seen if s[2] and s[1] > 0]
    assert meanwhile, "no sample was pushed before the analysis was in"
    t_first = meanwhile[0][0] - t0
    assert t_first < 0.3 * t_ready, (t_first, t_ready)          # well before the analysis ends
    shown = meanwhile[-1][3]
    assert len(shown) > 10 and shown[-1, COL["t_s"]] > 5.0         # it played seconds of the log meanwhile
    k = np.searchsorted(review_rows[:, COL["t_s"]], shown[:, COL["t_s"]])
    assert np.array_equal(review_rows[k, COL["t_s"]], shown[:, COL["t_s"]])
    for name in ("heading_on", "field_on", "steep", "alarm", "ev_heading", "ev_path", "ev_field", "cross_track_m",
                 "field_mG", "inclination_deg", "score"):
        np.testing.assert_allclose(shown[:, COL[name]], review_rows[k, COL[name]], atol=1e-6, equal_nan=True,
                                   err_msg=name)
    assert np.isfinite(shown[:, COL["field_mG"]]).all() and np.isfinite(shown[:, COL["cross_track_m"]]).any()
    assert position >= shown[-1, COL["t_s"]]                       # the analysis took over where it was


def test_a_large_log_plays_from_its_first_part_while_the_rest_is_read(tmp_path, monkeypatch):
    """Issue 29: a log over START_ABOVE_BYTES starts playing from its first START_BYTES (here the
    demo's 1.4 MB file with a 0.3 MB part); the page says it reads the rest; then the replay goes
    on with the whole file (its mission's preset line included) and the whole-log analysis is the
    one of the file read at once."""
    from groundstation.station.hub import sources

    path = tmp_path / "big.tlog"
    shutil.copy(DEMO, path)
    plain = Session(tmp_path / "plain", record_live=False)
    try:
        plain.start_replay(path, speed=1.0)
        assert wait_for(lambda: not plain.snapshot()["analysing"], 60)
        plain.replay_pause(True)
        whole_rows, whole_line = plain.flight.review.rows, plain.flight.line
        whole_duration = plain.snapshot()["replay"]["duration_s"]
    finally:
        plain.close()
    monkeypatch.setattr(sources, "START_BYTES", 300_000)
    monkeypatch.setattr(sources, "START_ABOVE_BYTES", 1_000_000)
    hub = Session(tmp_path / "parts", record_live=False)
    try:
        hub.start_replay(path, speed=1.0)
        first = hub.snapshot()["replay"]
        assert first["reading"] and first["duration_s"] < whole_duration - 100.0, first
        assert hub.flight.line is None                   # the demo's mission is after the first part
        assert wait_for(lambda: not hub.snapshot()["analysing"], 60)
        got = hub.snapshot()
        assert not got["replay"]["reading"] and got["replay"]["duration_s"] == whole_duration
        assert hub.flight.line == whole_line and whole_line["source"] == "mission"
        assert any("read to its end" in e["text"] for e in got["events"])
        np.testing.assert_array_equal(hub.flight.review.rows, whole_rows)
        assert hub.sources.rx_count > 0
    finally:
        hub.close()
