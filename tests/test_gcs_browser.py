"""The page's source panel on a live link shared by two vehicles, in a passive station that forwards
the link to another ground station (chromium)."""
from __future__ import annotations

import time

import httpx
import pytest

from conftest import CHROMIUM, CHROMIUM_ARGS, free_udp_port, wait_until
from groundstation.sim.fake_vehicle import FakeVehicle
from groundstation.sim.scenarios import simulate


@pytest.fixture
def passive_station(tmp_path):
    from groundstation.station.app import Station
    st = Station(port=0, viser_port=None, recordings_dir=tmp_path, passive=True,
                 forward=(f"udpout:127.0.0.1:{free_udp_port()}",)).start()
    forwarding = st.session.sources.forwarder
    assert forwarding.running
    yield st
    st.close()
    assert wait_until(lambda: forwarding.proc.poll() is not None, 5.0, 0.05)     # stopped with the station


def test_page_lists_vehicles_follows_one_and_says_it_only_listens(playwright_instance, passive_station):
    st = passive_station
    port = free_udp_port()
    st.session.connect(f"udpin:127.0.0.1:{port}")
    sims = {k: simulate("mission-clean", k, duration_s=40.0) for k in (1, 2)}
    browser = playwright_instance.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
    vehicles = [FakeVehicle(sims[k].messages, port, speed=1.0, system_id=k).start() for k in (1, 2)]
    try:
        page = browser.new_context(viewport={"width": 1200, "height": 800}).new_page()
        page.goto(st.url + "/index.html")
        page.wait_for_function("document.querySelectorAll('#vehicles tbody tr').length === 2", timeout=20_000)
        note = page.locator("#passive-note")
        assert note.is_visible() and "sends nothing" in note.inner_text() and ".param" in note.inner_text()
        followed = httpx.get(st.url + "/api/vehicles").json()["selected"]
        cells = page.locator(f"#vehicles tr[data-sysid='{followed}'] td").all_inner_texts()
        assert cells[1:4] == ["vehicle", "quadrotor", "ardupilot"] and cells[6].endswith("s ago"), cells
        page.wait_for_selector("#link-extra:has-text('forwarding to udpout:127.0.0.1:')")
        other = 3 - followed
        page.wait_for_selector(f"#vehicles tr[data-sysid='{followed}'] td:has-text('●')")
        assert not page.locator(f"#vehicles tr[data-sysid='{followed}'] button").is_visible()
        page.locator(f"#vehicles tr[data-sysid='{other}'] button").click()
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and httpx.get(st.url + "/api/vehicles").json()["selected"] != other:
            time.sleep(0.1)
        assert httpx.get(st.url + "/api/vehicles").json()["selected"] == other
        page.wait_for_selector(f"#vehicles tr[data-sysid='{other}'] td:has-text('●')")
        page.wait_for_selector(f"#events:has-text('following vehicle {other}')")
        assert all(v.rx_datagrams == 0 for v in vehicles)         # passive: the Follow sent nothing either
    finally:
        for v in vehicles:
            v.stop()
        browser.close()
