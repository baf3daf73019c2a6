"""The recordings folder: metadata (cached by file version) and uploads (size limit, type by
suffix and content, generated names inside the folder), through the routers in process; and
./run then ./test install stamps (scripts/bootstrap.sh)."""
from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from conftest import REAL_ULOG_PIECE
from groundstation.io.logs import read_log
from groundstation.jobs.analyze import analyze_flight
from groundstation.jobs.record import COL
from groundstation.sim.scenarios import simulate
from groundstation.station.app import create_app
from groundstation.station.hub import recordings as rec_module
from groundstation.station.hub.session import Session

ROOT = Path(__file__).resolve().parent.parent
DEMO = ROOT / "recordings" / "demo.tlog"
ULOG = REAL_ULOG_PIECE


@pytest.fixture
def folder(tmp_path) -> Path:
    d = tmp_path / "recordings"
    d.mkdir()
    return d


@pytest.fixture
def client(folder):
    session = Session(folder, max_upload_bytes=3_000_000)
    with TestClient(create_app(session), base_url="http://127.0.0.1") as c:
        yield c
    session.close()


def _upload(client, name: str, data: bytes):
    return client.post("/api/recordings/upload", params={"filename": name}, content=data,
                       headers={"Content-Type": "application/octet-stream"})


def test_upload_stores_a_checked_log_under_its_own_name(client, folder):
    r = _upload(client, "../../My flight (1).tlog", DEMO.read_bytes())
    assert r.status_code == 201, r.text
    info = r.json()
    name = info["name"]
    assert name.startswith("upload-") and name.endswith("-My_flight_1.tlog") and "/" not in name
    assert (folder / name).read_bytes() == DEMO.read_bytes()
    assert sorted(p.name for p in folder.iterdir()) == [name]           # nothing else, nothing outside
    assert info["duration_s"] == pytest.approx(235.0, abs=1) and info["autopilot"] == "ardupilot"
    assert info["vehicle"] == "quadrotor" and info["compasses"] == 1 and info["start_unix_s"] > 1.7e9
    assert client.get("/api/recordings").json() == [name]
    assert client.post("/api/replay/start", json={"recording": name, "speed": 20}).status_code == 200


def test_upload_refuses_wrong_type_mismatch_garbage_and_size(client, folder):
    tlog = DEMO.read_bytes()
    r = _upload(client, "notes.txt", b"hello")
    assert r.status_code == 422 and "not a log type" in r.json()["detail"]
    r = _upload(client, "flight.ulg", tlog[:100_000])                       # a .tlog named .ulg
    assert r.status_code == 422 and "does not look like a .ulg file (its content is a .tlog log)" in r.json()["detail"]
    r = _upload(client, "flight.tlog", b"")
    assert r.status_code == 422 and "empty" in r.json()["detail"]
    garbage = tlog[:10] + os.urandom(50_000)                                  # right magic, nothing readable
    r = _upload(client, "broken.tlog", garbage)
    assert r.status_code == 422 and "broken.tlog" in r.json()["detail"]
    r = _upload(client, "big.tlog", tlog + tlog + tlog)                        # 4.2 MB > 3 MB
    assert r.status_code == 413 and "3 MB" in r.json()["detail"]
    assert list(folder.iterdir()) == []                                       # no leftovers, no .part


def test_upload_ulog_and_info_of_every_recording(client, folder):
    r = _upload(client, ULOG.name, ULOG.read_bytes())
    assert r.status_code == 201, r.text
    assert r.json()["autopilot"] == "px4" and r.json()["compasses"] >= 1
    shutil.copy(DEMO, folder / "demo.tlog")
    (folder / "bad.csv").write_text("not,a,log\n")
    info = {i["name"]: i for i in client.get("/api/recordings/info").json()}
    assert info["demo.tlog"]["duration_s"] == pytest.approx(235.0, abs=1)
    assert info["demo.tlog"]["size_bytes"] == DEMO.stat().st_size
    assert info["bad.csv"]["error"] and info["bad.csv"]["duration_s"] is None


def test_info_is_read_once_per_file_version(client, folder, monkeypatch):
    shutil.copy(DEMO, folder / "demo.tlog")
    calls = []
    real = rec_module.RecordingsFolder.describe
    monkeypatch.setattr(rec_module.RecordingsFolder, "describe", staticmethod(lambda p: calls.append(p) or real(p)))
    client.get("/api/recordings/info")
    client.get("/api/recordings/info")
    assert len(calls) == 1
    os.utime(folder / "demo.tlog", (1e9, 1e9))                              # a new version of the file
    client.get("/api/recordings/info")
    assert len(calls) == 2


def test_run_then_test_install_the_test_extras(tmp_path):
    """./run (no extras) then ./test (extras "test"): each has its own install stamp, so the
    test extras get installed after a plain install (scripts/bootstrap.sh, in a temp copy with
    a stand-in python that records what pip was asked)."""
    shutil.copy(ROOT / "scripts" / "bootstrap.sh", tmp_path / "bootstrap.sh")
    (tmp_path / "pyproject.toml").write_text("[project]\nname = 'x'\n")
    bin_dir = tmp_path / ".venv" / "bin"
    bin_dir.mkdir(parents=True)
    fake = bin_dir / "python"
    fake.write_text('#!/bin/sh\necho "$@" >> "$(dirname "$0")/../pip.log"\n')
    fake.chmod(0o755)
    script = "source ./bootstrap.sh && bootstrap_venv && bootstrap_venv test && bootstrap_venv test"
    subprocess.run(["bash", "-c", script], cwd=tmp_path, check=True, timeout=30)
    installs = [line for line in (tmp_path / ".venv" / "pip.log").read_text().splitlines() if "-e" in line]
    assert installs == ["-m pip install -q -e .", "-m pip install -q -e .[test]"]      # the third call: up to date
    assert (tmp_path / ".venv" / ".installed").exists() and (tmp_path / ".venv" / ".installed-test").exists()


def _rms_deg(err_deg: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square((np.asarray(err_deg) + 180.0) % 360.0 - 180.0))))


def test_review_of_an_uploaded_finished_flight_shows_the_smoothed_attitude(client, folder, tmp_path):
    """A simulated finished flight (closed-loop mission, vehicle calibrated on board, gyro bias
    0.3 °/s per axis), uploaded and opened for review: the attitude the station's state API shows
    is the offline smoother's and says so, it is closer to the simulation's truth than the causal
    AHRS's (which the live link would show), and the alarms and every decision are analyze's."""
    sim = simulate("mission-clean", 3, onboard_calibration=True, duration_s=150.0,
                   gyro_bias_rad_s=np.radians([0.3, -0.3, 0.3]))
    path = sim.write(tmp_path / "finished.tlog")
    r = _upload(client, "finished.tlog", path.read_bytes())
    assert r.status_code == 201, r.text
    name = r.json()["name"]
    assert client.post("/api/replay/start", json={"recording": name, "speed": 1}).status_code == 200
    deadline = time.monotonic() + 120
    while client.get("/api/state").json()["analysing"] and time.monotonic() < deadline:
        time.sleep(0.1)
    client.post("/api/replay/pause", json={"paused": True})
    truth = sim.result
    log = read_log(path)
    causal = analyze_flight(log, None)            # the causal AHRS: what analyze decides on and live shows
    t_rows = causal.rows[:, COL["t_s"]]
    shown, causal_shown, truth_deg = [], [], []
    for t_s in np.linspace(20.0, 148.0, 97):      # after the first 20 s (start-up) to the end
        assert client.post("/api/replay/seek", json={"t_s": t_s}).status_code == 200
        v = client.get("/api/state").json()["vehicle"]
        assert v["attitude_source"] == "offline", v
        k = int(np.searchsorted(t_rows, t_s, side="right")) - 1          # the row the cursor shows
        j = int(np.argmin(np.abs(truth.t_s - t_rows[k])))
        assert abs(truth.t_s[j] - t_rows[k]) < 1e-3
        shown.append([v["roll_deg"], v["pitch_deg"], v["yaw_deg"]])
        causal_shown.append(causal.rows[k, [COL["roll_deg"], COL["pitch_deg"], COL["heading_deg"]]])
        truth_deg.append(np.degrees([truth.roll_rad[j], truth.pitch_rad[j], truth.yaw_rad[j]]))
    shown, causal_shown, truth_deg = (np.array(a, dtype=float) for a in (shown, causal_shown, truth_deg))
    err_s = [_rms_deg(shown[:, i] - truth_deg[:, i]) for i in range(3)]
    err_c = [_rms_deg(causal_shown[:, i] - truth_deg[:, i]) for i in range(3)]
    tilt_s, tilt_c = np.hypot(err_s[0], err_s[1]), np.hypot(err_c[0], err_c[1])
    # measured: roll 0.15 vs 0.48 deg, pitch 1.18 vs 1.60, tilt 1.18 vs 1.67, heading 1.80 vs 4.81
    assert tilt_s < 0.85 * tilt_c and err_s[2] < 0.8 * err_c[2], (err_s, err_c)
    # the decisions are analyze's: the same alarms, and row by row the same decision columns
    report = client.get("/api/analysis").json()
    analyzed = [(a["start_s"], a["end_s"]) for a in report["alarms"] if a["kind"] == "combined"]
    client.post("/api/replay/seek", json={"t_s": 150.0})
    assert [(a["start_s"], a["end_s"]) for a in client.get("/api/alarms").json()] == analyzed
    review = client.app.state.hub.flight.review
    assert review.rows.shape == causal.rows.shape
    for col in ("t_s", "alarm", "ev_heading", "ev_path", "ev_field", "score", "heading_on", "field_on", "path_on",
                "steep", "mag_heading_deg", "field_mG", "inclination_deg", "cross_track_m"):
        np.testing.assert_array_equal(review.rows[:, COL[col]], causal.rows[:, COL[col]], err_msg=col)


def test_a_replay_stopped_as_it_starts_is_a_conflict_not_a_server_error(client, monkeypatch):
    """A stop that lands between the replay's start and its answer (the page's stop button racing
    an API start, seen in CI): 409 with a one-line reason, never a 500 from the response model."""
    name = _upload(client, "race.tlog", DEMO.read_bytes()).json()["name"]
    real = Session.start_replay

    def start_then_stopped(self, *a, **kw):
        real(self, *a, **kw)
        self.stop()
    monkeypatch.setattr(Session, "start_replay", start_then_stopped)
    r = client.post("/api/replay/start", json={"recording": name, "speed": 1})
    assert r.status_code == 409 and "stopped as it started" in r.text, (r.status_code, r.text)
