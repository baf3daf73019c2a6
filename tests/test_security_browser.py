"""Cross-site attacks in chromium: a page on another origin (a second small HTTP server on another
loopback port, and the same server reached as `localhost`) auto-submits forms and fires fetch and
WebSocket requests at the station while a fake vehicle does the calibration dance.  It must not
change the source, drive the wizard, get parameters written or read /ws or the 3-D view; the
station's own page, opened afterwards in the same browser, still drives the wizard."""
from __future__ import annotations

import http.server
import threading
import time

import httpx
import pytest

from conftest import CHROMIUM, CHROMIUM_ARGS, free_udp_port
from groundstation.sim.fake_vehicle import FakeVehicle
from groundstation.sim.scenarios import simulate

HOSTILE_PAGE = """<!doctype html><html><body>
<iframe name="sink" style="display:none"></iframe>
<form id="f1" method="POST" target="sink" action="{station}/api/calibration/start"></form>
<form id="f2" method="POST" target="sink" action="{station}/api/source/stop"></form>
<form id="f3" method="POST" target="sink" action="{station}/api/calibration/finish"></form>
<form id="f4" method="POST" target="sink" action="{station}/api/calibration/accept"></form>
<form id="f5" method="POST" target="sink" enctype="text/plain" action="{station}/api/source">
  <input name='{{"recording": "x.tlog", "pad": "' value='"}}'></form>
<script>
window.results = {{ws: 0, wsOpen: false, viser: 0, viserOpen: false, viserClose: null, token: "unread", fetches: []}};
const S = "{station}";
const pause = (ms) => new Promise((r) => setTimeout(r, ms));
async function attack() {{
  for (const id of ["f1", "f2", "f5"]) {{ document.getElementById(id).submit(); await pause(150); }}
  for (const p of ["/api/calibration/start", "/api/source/stop", "/api/replay/stop", "/api/line/from-mission"]) {{
    try {{ await fetch(S + p, {{method: "POST", mode: "no-cors", credentials: "include"}}); results.fetches.push(p + " sent"); }}
    catch (e) {{ results.fetches.push(p + " " + e); }}
  }}
  try {{ await fetch(S + "/api/calibration/start", {{method: "POST", headers: {{"X-MagStation-Token": "guess"}}}}); }}
  catch (e) {{ results.fetches.push("preflighted post blocked"); }}
  try {{ const r = await fetch(S + "/api/page-token"); results.token = await r.text(); }}
  catch (e) {{ results.token = "blocked"; }}
  const ws = new WebSocket(S.replace("http", "ws") + "/ws");
  ws.onopen = () => {{ results.wsOpen = true; }};
  ws.onmessage = () => {{ results.ws += 1; ws.send("ack"); }};
  const vs = new WebSocket("{viser}", ["viser-v{viser_version}"]);
  vs.onopen = () => {{ results.viserOpen = true; }};
  vs.onmessage = () => {{ results.viser += 1; }};
  vs.onclose = (e) => {{ results.viserClose = e.code; }};
  await pause(2500);                                      // the dance goes on ...
  for (const id of ["f3", "f4", "f1", "f3", "f4"]) {{ document.getElementById(id).submit(); await pause(300); }}
  results.done = true;
}}
attack();
</script></body></html>"""


class _HostileServer:
    """Serves HOSTILE_PAGE from its own loopback port (another origin than the station)."""

    def __init__(self, page: str) -> None:
        body = page.encode()

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self):  # noqa: N802
                self.send_response(200)
                self.send_header("Content-Type", "text/html")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args):
                pass

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.port = self.httpd.server_address[1]
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture
def browser(playwright_instance, station):
    args = CHROMIUM_ARGS + [f"--isolate-origins=http://127.0.0.1:{station.viser_port}"]
    b = playwright_instance.chromium.launch(executable_path=CHROMIUM, headless=True, args=args)
    yield b
    b.close()


@pytest.mark.parametrize("attacker_host", ["127.0.0.1", "localhost"])
def test_a_foreign_page_cannot_drive_the_station(station, browser, artifacts, attacker_host):
    import viser

    sim = simulate("calibration", 0)
    port = free_udp_port()
    with httpx.Client(base_url=station.url) as c:
        assert c.post("/api/source", json={"connect": f"udpin:127.0.0.1:{port}"}).status_code == 200
    page = HOSTILE_PAGE.format(station=station.url, viser=f"ws://127.0.0.1:{station.viser_port}/",
                               viser_version=viser.__version__)
    hostile = _HostileServer(page)
    ctx = browser.new_context()
    try:
        with FakeVehicle(sim.messages, port, speed=6.0) as fv:
            evil = ctx.new_page()
            evil.goto(f"http://{attacker_host}:{hostile.port}/")
            evil.wait_for_function("window.results && window.results.done === true", timeout=30_000)
            time.sleep(1.0)
            results = evil.evaluate("window.results")
            state = httpx.get(station.url + "/api/state").json()
            assert state["source"]["kind"] == "live", state["source"]
            assert state["wizard"]["state"] == "idle", state["wizard"]["state"]
            assert fv.param_sets == []
            assert results["ws"] == 0 and not results["wsOpen"], results          # refused (403)
            # viser has no handshake hook: the guard closes the socket (1008) before any message
            assert results["viser"] == 0 and results.get("viserClose") in (1006, 1008), results
            assert "token" not in results["token"] or results["token"] in ("blocked", "unread"), results
            evil.screenshot(path=str(artifacts / f"hostile_page_{attacker_host}.png"))

            # the station's own page, same browser: the wizard starts and its state streams in
            own = ctx.new_page()
            logs = []
            own.on("console", lambda m: logs.append(f"{m.type}: {m.text}"))
            own.on("response", lambda r: logs.append(f"{r.request.method} {r.url} {r.status}"))
            own.goto(station.url + "/calibrate.html")
            own.click("#start")
            try:
                own.wait_for_selector("#steps li[data-step='x'].current", timeout=30_000)
            except Exception:
                print("\n".join(logs), httpx.get(station.url + "/api/calibration").json()["state"])
                raise
            assert httpx.get(station.url + "/api/calibration").json()["state"] == "running"
    finally:
        ctx.close()
        hostile.close()


def test_dns_rebinding_is_refused_in_the_browser(playwright_instance, station):
    """The browser resolves an attacker's name to the station's address (what DNS rebinding
    achieves): the page, the API and /ws all refuse the foreign Host."""
    b = playwright_instance.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS + [
        "--host-resolver-rules=MAP rebind.example 127.0.0.1"])
    try:
        pg = b.new_page()
        base = f"http://rebind.example:{station.port}"
        assert pg.goto(base + "/index.html").status == 400
        status = pg.evaluate("""async (base) => {
            const r = await fetch(base + "/api/calibration/start", {method: "POST"});
            const ws = await new Promise((done) => {
                const s = new WebSocket(base.replace("http", "ws") + "/ws");
                s.onopen = () => done("open"); s.onerror = () => done("refused"); });
            return [r.status, ws]; }""", base)
        assert status == [400, "refused"], status
        assert httpx.get(station.url + "/api/calibration").json()["state"] == "idle"
    finally:
        b.close()


def test_a_backslash_in_the_first_visits_path_does_not_take_chromium_off_site(playwright_instance, recordings_dir):
    """``/%5Clocalhost:PORT/x?token=T``: the redirect that sets the cookie used to say
    ``Location: /\\localhost:PORT/x``, which chromium reads as ``//localhost:PORT/x`` (another
    origin, here a second local server).  It must stay on the station."""
    from groundstation.station.app import Station

    other = _HostileServer("<!doctype html><title>elsewhere</title>")
    st = Station(host="127.0.0.1", allow_remote=True, port=0, viser_port=None, recordings_dir=recordings_dir).start()
    browser = playwright_instance.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
    try:
        pg = browser.new_context().new_page()
        token = st.settings.access_token
        for path in (f"/%5Clocalhost:{other.port}/index.html", f"/%5C%5Clocalhost:{other.port}/index.html",
                     f"/%09/localhost:{other.port}/index.html"):
            pg.goto(f"{st.url}{path}?token={token}")
            assert pg.url.startswith(f"{st.url}/"), (path, pg.url)
            assert "elsewhere" not in pg.content()
    finally:
        browser.close()
        st.close()
        other.close()
