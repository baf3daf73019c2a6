"""The station's pages without internet (a field laptop): chromium with every request that is not
to the loopback station aborted.  /docs (Swagger UI) renders from the files the station
serves; no page asks for a third-party origin; no page loads a foreign script without integrity."""
from __future__ import annotations

from urllib.parse import urlsplit

import pytest

from conftest import CHROMIUM, CHROMIUM_ARGS

LOOPBACK = {"127.0.0.1", "localhost", "::1", "[::1]"}


@pytest.fixture
def offline_page(playwright_instance):
    browser = playwright_instance.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
    ctx = browser.new_context(viewport={"width": 1280, "height": 720})
    foreign: list[str] = []

    def route(r):
        if urlsplit(r.request.url).hostname in LOOPBACK:
            r.continue_()
        else:                                   # the network is down: nothing leaves the machine
            foreign.append(r.request.url)
            r.abort("internetdisconnected")

    ctx.route("**/*", route)
    page = ctx.new_page()
    page.set_default_timeout(30_000)
    yield page, foreign
    ctx.close()
    browser.close()


def test_api_docs_render_offline(station_no_viser, offline_page, artifacts):
    st = station_no_viser
    page, foreign = offline_page
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(st.url + "/docs")
    page.wait_for_selector(".swagger-ui .info .title:has-text('MagStation')")
    page.wait_for_function("document.querySelectorAll('.swagger-ui .opblock').length >= 10")
    assert page.locator(".swagger-ui .opblock-summary-path[data-path='/api/state']").count() >= 1
    for w, h in ((1280, 720), (1920, 1080)):
        page.set_viewport_size({"width": w, "height": h})
        page.screenshot(path=str(artifacts / f"docs_offline_{w}.png"))
    assert page.request.get(st.url + "/redoc").status == 404      # its page would fetch a CDN logo
    assert errors == [] and foreign == []


def test_pages_load_nothing_foreign(station_no_viser, offline_page):
    st = station_no_viser
    page, foreign = offline_page
    for path in ("/index.html", "/calibrate.html", "/fleet.html", "/docs"):
        page.goto(st.url + path)
        page.wait_for_load_state("load")
        unchecked = page.evaluate("""() => [...document.scripts]
            .filter(s => s.src && new URL(s.src).origin !== location.origin && !s.integrity).map(s => s.src)""")
        assert unchecked == [], (path, unchecked)
    assert foreign == []
