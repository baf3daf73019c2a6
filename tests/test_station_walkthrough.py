"""A field user's session in one browser, start to end: the demo replay, a real log, seeking
back, the calibration page, a live vehicle (simulated, real MAVLink over UDP), the guided
calibration and accepting it (the parameters written to the vehicle and confirmed).

Screenshots at each step go to tests/artifacts/walkthrough_*.png; what must be visible in the
3-D view (route, vehicle, calibration cloud) is checked by counting coloured pixels."""
from __future__ import annotations

from browser_checks import (api, click, console_errors, has, inside, new_page, open_page,  # noqa: F401
                            set_value, shared_browser, shared_station, view_pixels_until, wait_js, wait_until)
from conftest import free_udp_port
from groundstation.sim.fake_vehicle import FakeVehicle
from groundstation.sim.scenarios import simulate


def _seek(page, t: float) -> None:
    page.evaluate("""t => { const s = document.getElementById('seek'); s.value = t;
                            s.dispatchEvent(new Event('input')); s.dispatchEvent(new Event('change')); }""", t)
    has(page, "#replay-time", f"{t:.1f} /")


def test_walkthrough(shared_station, new_page, artifacts):
    st = shared_station
    page = new_page(1280, 720, view=True)
    errors = console_errors(page)
    api(st, "POST", "/api/source/stop")
    open_page(page, st)

    # 1. the demo: replay, seek into the interference episode; route, line and vehicle in view
    click(page, "#recordings tr[data-name='demo.tlog']")
    set_value(page, "#speed", "4")
    click(page, "#replay")
    has(page, "#status", "demo.tlog")
    assert wait_until(lambda: not api(st, "GET", "/api/state")["analysing"], 60)
    click(page, "#pause")
    has(page, "#pause", "Resume")
    _seek(page, 175.0)
    has(page, "#alarm-banner.alarm")
    png, px = view_pixels_until(page, {"violet": 100, "red": 100, "cyan": 100, "orange": 100},
                                framed=("violet", "red", "cyan", "orange"))
    (artifacts / "walkthrough_1_demo.png").write_bytes(png)
    for name in ("violet", "red", "cyan", "orange"):
        assert px[name][0] >= 100 and inside(px[name][1], px["size"]), (name, px)

    # 2. a real log: nothing of the demo stays
    click(page, "#recordings tr[data-name='real.tlog']")
    click(page, "#replay")
    has(page, "#status", "real.tlog")
    assert wait_until(lambda: not api(st, "GET", "/api/state")["analysing"], 60)
    has(page, "#alarm-banner.ok")
    assert page.locator("#line-text").inner_text().startswith("none")
    has(page, "#tests tr[data-test='heading'] .state", "off")

    # 3. seek back: the state of that moment, at once
    click(page, "#pause")
    _seek(page, 200.0)
    _seek(page, 120.0)
    assert page.locator("#v-rp").inner_text() != "— / —"
    assert api(st, "GET", "/api/state")["t_s"] == 120.0
    # the real flight's route and the vehicle; in flight the vehicle is drawn at 0.4 of the
    # calibration model's size (issue 31: scaled to the route), 19-45 px here at 1280x720
    png, px = view_pixels_until(page, {"violet": 50, "orange": 10})
    (artifacts / "walkthrough_3_real_seek.png").write_bytes(png)
    assert px["violet"][0] >= 50 and px["orange"][0] >= 10, px

    # 4. the calibration page; back to the station: a connect while the replay runs waits for
    #    the vehicle's first packet; stopped, the station listens for the vehicle
    click(page, "header a[href='calibrate.html']")
    has(page, "#instruction", "press Start")
    page.go_back()
    has(page, "#recordings tr[data-name]")
    port = free_udp_port()
    set_value(page, "#connect", f"udpin:127.0.0.1:{port}")
    click(page, "#connect-btn")
    has(page, "#pending")
    click(page, "#stop")
    has(page, "#status", "no source")
    click(page, "#connect-btn")
    has(page, "#status", "live: udpin")
    assert page.locator("#replay-controls").is_hidden()

    # 5. the guided calibration on the live vehicle (simulated, sent as MAVLink at x6)
    open_page(page, st, "/calibrate.html")
    has(page, "#instruction", "press Start")
    click(page, "#start")
    has(page, "#steps li[data-step='x'].current")
    sim = simulate("calibration", 0)
    with FakeVehicle(sim.messages, port, speed=6.0) as fv:
        has(page, "#result-card", timeout_ms=120_000)                         # ~15 s on an idle machine
        assert page.locator("#result-status").inner_text() == "ok"
        has(page, "#live-fit", "fitted field")                               # the result's field, not a running fit's
        assert "WMM" not in page.locator("#warnings").inner_text()        # fitted field agrees with WMM
        png, px = view_pixels_until(page, {"orange": 100, "blue": 300, "green": 300, "amber": 300},
                                    framed=("orange", "blue", "green", "amber"))
        assert st.scene.cloud_points_shown > 500
        (artifacts / "walkthrough_5_calibration.png").write_bytes(png)
        for name, least in (("orange", 100), ("blue", 300), ("green", 300), ("amber", 300)):
            assert px[name][0] >= least and inside(px[name][1], px["size"]), (name, px)

        # 6. accept: the vehicle confirms every parameter
        click(page, "#accept")
        has(page, "#param-write .good")
        page.screenshot(path=str(artifacts / "walkthrough_6_accepted.png"), animations="disabled", timeout=120_000)
        result = api(st, "GET", "/api/calibration")["result"]
        for name, value in result["ardupilot_params"].items():
            assert abs(fv.params[name] - value) <= 1e-5 * max(1.0, abs(value)), name
    truth = sim.truth["mag"]["offsets_mG"]
    assert max(abs(a - b) for a, b in zip(result["offsets_mG"], truth)) < 5.0
    kind = lambda: api(st, "GET", "/api/state")["tests"]["field_correction"]["kind"]  # noqa: E731
    assert wait_until(lambda: kind() == "autopilot", 30), kind()     # written: on board once the echoes are in
    api(st, "POST", "/api/source/stop")
    assert errors == []
