"""The station's "calibration in use" in headless chromium: replay mission-fast.tlog (a vehicle
that never calibrated on board: the heading test is off), choose the demo's dance calibration on
the page (and, in a second test, upload the vehicle's .param file), and the alarm appears with the
same start as `analyze --calibration` (±0.5 s); the choice survives a restart of the station, and
`review` of the folder afterwards finds the alarms with the airframe's calibration."""
from __future__ import annotations

import shutil
from pathlib import Path

import httpx
import pytest

from browser_checks import api, launch_browser, open_page, wait_js, wait_until
from groundstation.io.logs import read_log
from groundstation.io.params import format_param_file
from groundstation.jobs.analyze import analyze_log
from groundstation.jobs.calibrate import calibrate_log
from groundstation.station.app import Station
from conftest import free_tcp_port

ROOT = Path(__file__).resolve().parents[1]
WAIT_S = 90.0        # 2 shared cores: the whole-log analysis runs again after each choice


def _station(directory: Path) -> Station:
    return Station(port=0, viser_port=free_tcp_port(), recordings_dir=directory, record_live=False).start()


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("in_use") / "recordings"
    d.mkdir()
    for name in ("demo.tlog", "mission-fast.tlog"):
        shutil.copy(ROOT / "recordings" / name, d / name)
    return d


@pytest.fixture(scope="module")
def expected(folder) -> dict:
    """What `analyze mission-fast.tlog --calibration` (the demo's dance) finds, computed here."""
    demo = calibrate_log(read_log(folder / "demo.tlog"))
    assert demo["status"] == "ok" and demo["method"] == "window"
    report, _ = analyze_log(read_log(folder / "mission-fast.tlog"), calibration=demo)
    first = report["first_alarm_s"]
    assert first is not None
    bare, _ = analyze_log(read_log(folder / "mission-fast.tlog"))
    assert not bare["interference_detected"] and bare["heading_test"].startswith("off")   # the defect
    return {"calibration": demo, "first_alarm_s": first}


@pytest.fixture
def browser_page(playwright_instance):
    stations, browsers = [], []

    def make(st):
        b = launch_browser(playwright_instance, st.viser_port)
        browsers.append(b)
        ctx = b.new_context(viewport={"width": 1280, "height": 900})
        ctx.route(f"http://127.0.0.1:{st.viser_port}/**", lambda route: route.abort())   # no 3-D view
        page = ctx.new_page()
        open_page(page, st)
        return page
    yield make
    for b in browsers:
        b.close()


def _replay_to_end(st, page) -> None:
    api(st, "POST", "/api/replay/start", json={"recording": "mission-fast.tlog", "speed": 20.0})
    assert wait_until(lambda: not api(st, "GET", "/api/state")["analysing"], WAIT_S)
    api(st, "POST", "/api/replay/pause", json={"paused": True})
    page.wait_for_selector("#status:has-text('mission-fast.tlog')")


def _page_alarm_start(st, page) -> float:
    api(st, "POST", "/api/replay/seek", json={"t_s": api(st, "GET", "/api/state")["replay"]["duration_s"]})
    wait_js(page, "document.querySelectorAll('#alarms tr[data-t]').length >= 1", WAIT_S * 1000)
    return float(page.locator("#alarms tr[data-t]").first.get_attribute("data-t"))


def _analysed_again(st, n_before: int) -> bool:
    events = api(st, "GET", "/api/state")["events"]
    return sum("analysed again" in e["text"] for e in events) > n_before


def test_choose_the_demo_dance_then_the_alarm_and_the_choice_persists(folder, expected, browser_page):
    st = _station(folder)
    try:
        page = browser_page(st)
        _replay_to_end(st, page)
        assert api(st, "GET", "/api/state")["tests"]["heading"]["state"] == "off"
        wait_js(page, "[...document.querySelectorAll('#cal-choice option')].some(o => o.value === 'recording:demo.tlog')",
                WAIT_S * 1000)
        page.select_option("#cal-choice", "recording:demo.tlog")
        page.locator("#cal-use").dispatch_event("click")
        page.wait_for_selector("#cal-in-use:has-text('the dance in demo.tlog')", timeout=WAIT_S * 1000)
        assert "absolute" in page.locator("#cal-in-use").text_content()
        assert wait_until(lambda: _analysed_again(st, 0), WAIT_S)
        assert api(st, "GET", "/api/state")["tests"]["heading"]["state"] != "off"
        start = _page_alarm_start(st, page)
        assert start == pytest.approx(expected["first_alarm_s"], abs=0.5)
    finally:
        st.close()
    st = _station(folder)                          # a restart: the airframe's choice comes back
    try:
        page = browser_page(st)                    # open before the replay: its chooser follows the choice
        api(st, "POST", "/api/replay/start", json={"recording": "mission-fast.tlog", "speed": 20.0})
        assert wait_until(lambda: not api(st, "GET", "/api/state")["analysing"], WAIT_S)
        choice = api(st, "GET", "/api/state")["calibration_choice"]
        assert choice["source"] == "recording" and "demo.tlog" in choice["label"], choice
        wait_js(page, "document.getElementById('cal-choice').value === 'recording:demo.tlog'", WAIT_S * 1000)
        api(st, "POST", "/api/replay/seek", json={"t_s": api(st, "GET", "/api/state")["replay"]["duration_s"]})
        combined = [a for a in api(st, "GET", "/api/analysis")["alarms"] if a["kind"] == "combined"]
        assert combined and combined[0]["start_s"] == pytest.approx(expected["first_alarm_s"], abs=0.5)
    finally:
        st.close()


def test_upload_the_vehicle_param_file_then_the_alarm(folder, expected, browser_page, tmp_path):
    pfile = tmp_path / "vehicle.param"
    pfile.write_text("# Mission Planner export of the calibrated vehicle\n"
                     + format_param_file(expected["calibration"]["ardupilot_params"])
                     + "SYSID_THISMAV,1\nNOT A PARAMETER LINE\n")
    bad = tmp_path / "evil.param"
    bad.write_bytes(b"\x7fELF\x00\x00binary")
    st = _station(folder)
    try:
        page = browser_page(st)
        _replay_to_end(st, page)
        api(st, "POST", "/api/calibration/in-use", json={"source": "none"})
        page.set_input_files("#cal-upload", str(bad))
        page.wait_for_selector("#cal-error:has-text('binary data')", timeout=WAIT_S * 1000)
        n = sum("analysed again" in e["text"] for e in api(st, "GET", "/api/state")["events"])
        page.set_input_files("#cal-upload", str(pfile))
        page.wait_for_selector("#cal-in-use:has-text('uploaded vehicle.param')", timeout=WAIT_S * 1000)
        assert "1 bad line(s) skipped" in page.locator("#cal-in-use").text_content()
        assert wait_until(lambda: _analysed_again(st, n), WAIT_S)
        start = _page_alarm_start(st, page)
        assert start == pytest.approx(expected["first_alarm_s"], abs=0.5)
        stored = [p.name for p in folder.iterdir() if p.name.startswith("calibration-")]
        assert any(n.endswith("-vehicle.param") for n in stored), stored
        # the security pattern: a write from another origin is refused, nothing changes
        r = httpx.post(st.url + "/api/calibration/in-use", json={"source": "none"},
                       headers={"Origin": "http://evil.example"}, timeout=10)
        assert r.status_code == 403
        assert api(st, "GET", "/api/state")["calibration_choice"]["source"] == "upload"
    finally:
        st.close()


def test_review_after_a_calibration_was_chosen_finds_the_alarms(folder, expected, tmp_path):
    """The chosen dance is in the airframe's history: `review` analyses mission-fast.tlog (no dance
    of its own) with it, and demo.tlog with its own dance (its alarm at ~149.3 s)."""
    pytest.importorskip("dask.distributed")
    from groundstation.cli import main
    from groundstation.io import fleet_db

    st = _station(folder)
    try:
        api(st, "POST", "/api/replay/start", json={"recording": "mission-fast.tlog", "speed": 20.0})
        assert wait_until(lambda: not api(st, "GET", "/api/state")["analysing"], WAIT_S)
        api(st, "POST", "/api/calibration/in-use", json={"source": "recording", "name": "demo.tlog"})
    finally:
        st.close()
    db = folder / fleet_db.DB_NAME
    assert main(["review", str(folder), "--db", str(db), "--out", str(tmp_path / "out"), "--workers", "1"]) == 0
    with fleet_db.connect(db, read_only=True) as con:
        rows = {r["file_name"]: r for r in fleet_db.flight_rows(con) if (r["compass"] or 0) == 0}
    fast, demo = rows["mission-fast.tlog"], rows["demo.tlog"]
    assert fast["calibration_used"].startswith("history:") and fast["alarm_count"] >= 1
    assert fast["first_alarm_s"] == pytest.approx(expected["first_alarm_s"], abs=0.5)
    assert demo["calibration_used"].startswith("own dance") and demo["first_alarm_s"] == pytest.approx(149.3, abs=1.0)
