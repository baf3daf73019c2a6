"""`magstation simulate SCENARIO --live udpout:HOST:PORT`: a simulated vehicle one command away.
Both commands of the README's tour as processes on loopback: `magstation serve --connect udpin:...`
and the live calibration dance, the wizard driven in chromium; the station's wizard fits it, the
accepted parameters are written to the simulated vehicle and read back (its PARAM_VALUE echoes),
and the station says the field is corrected on board.  Truth: the scenario's own (groundstation.sim.scenarios)."""
from __future__ import annotations

import os
import sqlite3
import subprocess
from pathlib import Path
import sys
import time

import httpx
import pytest

from conftest import CHROMIUM, CHROMIUM_ARGS, free_tcp_port, free_udp_port
from groundstation.sim.scenarios import simulate

CLI = [sys.executable, "-m", "groundstation.cli"]


def _wait(predicate, timeout_s: float, what: str, procs=()):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for p in procs:
            assert p.poll() is None, f"{p.args[3]} exited {p.returncode}: {p.stdout.read() if p.stdout else ''}"
        try:
            value = predicate()
            if value:
                return value
        except httpx.HTTPError:
            pass
        time.sleep(0.25)
    raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}")


def _start(args: list[str], fleet_db: Path | None = None) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    if fleet_db is not None:      # the wizard's written result goes to a history of the test's own
        env["MAGSTATION_FLEET_DB"] = str(fleet_db)
    return subprocess.Popen(CLI + args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)


def _stop(p: subprocess.Popen) -> str:
    if p.poll() is None:
        p.terminate()
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(5)
    if p.stdout is None:
        return ""
    with p.stdout:                 # closed here: a pipe left to the garbage collector warns in a later test
        return p.stdout.read()


def test_live_errors_are_one_line():
    for args, words in ((["calibration", "--live", "udpin:127.0.0.1:14550"], "expected udpout:HOST:PORT"),
                        (["calibration", "--live", "udpout:127.0.0.1:99999"], "expected udpout:HOST:PORT"),
                        (["calibration"], "give --out FILE.tlog"),
                        (["nowhere", "--live", "udpout:127.0.0.1:14550"], "unknown scenario 'nowhere'"),
                        (["calibration", "--live", "udpout:127.0.0.1:14550", "--speed", "0"], "--speed must be")):
        r = subprocess.run(CLI + ["simulate", *args], capture_output=True, text=True, timeout=60)
        assert r.returncode == 1 and words in r.stderr and r.stderr.count("\n") == 1, (args, r.stderr)


def test_serve_recordings_must_be_a_folder(tmp_path):
    not_a_folder = tmp_path / "a-file"
    not_a_folder.write_text("x")
    r = subprocess.run(CLI + ["serve", "--recordings", str(not_a_folder), "--port", str(free_tcp_port())],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and "--recordings" in r.stderr and "cannot use it as a folder" in r.stderr, r.stderr
    assert r.stderr.count("\n") == 1, r.stderr


def test_simulate_live_drives_the_station_and_the_wizard(tmp_path, playwright_instance, artifacts):
    """The README's tour in chromium: the station page of `magstation serve` shows the simulated
    vehicle; on the calibration page Start, the dance streamed by `simulate --live` fills the
    steps, the result card shows 'ok', Accept writes the parameters and the vehicle confirms them."""
    udp, port, viser_port = free_udp_port(), free_tcp_port(), free_tcp_port()
    url = f"http://127.0.0.1:{port}"
    recordings = tmp_path / "recordings"          # made by serve; the checkout's recordings/ stays as it was
    station = _start(["serve", "--connect", f"udpin:127.0.0.1:{udp}", "--port", str(port),
                      "--viser-port", str(viser_port), "--recordings", str(recordings)],
                     fleet_db=tmp_path / "fleet.sqlite")
    vehicle = None
    browser = playwright_instance.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
    try:
        _wait(lambda: httpx.get(url + "/api/state", timeout=5).json()["source"]["kind"] == "live", 60,
              "the station", [station])
        ctx = browser.new_context(viewport={"width": 1280, "height": 720})
        # the 3-D view is not looked at here: its software WebGL would take most of a core
        ctx.route(f"http://127.0.0.1:{viser_port}/**", lambda route: route.abort())
        page = ctx.new_page()
        page.set_default_timeout(60_000)
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(url + "/calibrate.html")
        page.wait_for_selector("#instruction:has-text('press Start')")
        page.click("#start")
        assert _wait(lambda: httpx.get(url + "/api/calibration", timeout=5).json()["state"] == "running", 30,
                     "the wizard to start", [station])
        vehicle = _start(["simulate", "calibration", "--live", f"udpout:127.0.0.1:{udp}", "--speed", "6"])
        first = _wait(lambda: vehicle.stdout.readline(), 60, "the vehicle's first line", [vehicle])
        assert first.startswith("streaming 'calibration' (") and f"udpin:127.0.0.1:{udp}" in first
        page.wait_for_selector("#status:has-text('ardupilot')")
        page.wait_for_selector("#result-card:not([hidden])", timeout=180_000)
        assert page.locator("#result-status").inner_text() == "ok"
        result = httpx.get(url + "/api/calibration", timeout=5).json()["result"]
        truth = simulate("calibration", 0).truth["mag"]["offsets_mG"]
        assert max(abs(a - b) for a, b in zip(result["offsets_mG"], truth)) < 5.0
        page.click("#accept")
        page.wait_for_selector("#param-write .good", timeout=90_000)   # every parameter echoed by the vehicle
        page.screenshot(path=str(artifacts / "simulate_live_written.png"))
        # written and confirmed by the vehicle's PARAM_VALUE echoes: the field is corrected on board now
        _wait(lambda: httpx.get(url + "/api/state", timeout=5).json()["tests"]["field_correction"]["kind"]
              == "autopilot", 90, "the vehicle to confirm the parameters", [station, vehicle])
        # the written result is in the history it was pointed at (not in the repository's recordings/)
        with sqlite3.connect(tmp_path / "fleet.sqlite") as db:
            rows = db.execute("SELECT ofs_x_mG, ofs_y_mG, ofs_z_mG FROM calibrations WHERE compass = 0").fetchall()
        assert rows and max(abs(a - b) for a, b in zip(rows[-1], result["offsets_mG"])) < 0.01, rows
        assert errors == [], errors
    finally:
        browser.close()
        out_v = _stop(vehicle) if vehicle is not None else ""
        out_s = _stop(station)
    assert "Traceback" not in out_v + out_s, out_v + out_s
    assert len(list(recordings.glob("session-*.tlog"))) == 1      # the live link recorded where it was told
