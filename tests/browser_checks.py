"""Helpers of the browser tests: one shared station and chromium, page set-up, and what a
screenshot shows (coloured pixels of the 3-D view by class, label layout from the camera)."""
from __future__ import annotations

import io
import math
import shutil
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from conftest import (CHROMIUM, CHROMIUM_ARGS, REAL_TLOG_PIECE, REAL_ULOG_PIECE, SHARED_DATA,  # noqa: F401  (re-exported)
                      free_tcp_port, wait_until)

ROOT = Path(__file__).resolve().parent.parent
# shipped cuts of the real ArduCopter flight (its seconds 440-700: take-off at ~60 s) and of a PX4 ULog
REAL_LOG = REAL_TLOG_PIECE
ULOG = REAL_ULOG_PIECE

# colour classes of the 3-D view (hue ranges in degrees; saturated, not dark): see scene/view.py
HUES = {"red": (350, 10), "orange": (18, 38), "amber": (40, 55), "green": (95, 150), "cyan": (180, 200),
        "blue": (210, 245), "violet": (260, 290)}
VISER_PANEL = (270, 64)          # the minimised viser panel in the view's top-right corner (w, h px)


def make_recordings(directory: Path) -> Path:
    from groundstation.sim.scenarios import simulate
    directory.mkdir(parents=True, exist_ok=True)
    shutil.copy(ROOT / "recordings" / "demo.tlog", directory / "demo.tlog")
    simulate("calibration", 0).write(directory / "dance.tlog")
    simulate("demo", 1, mission="mission-anomaly").write(directory / "anomaly.tlog")
    shutil.copy(REAL_LOG, directory / "real.tlog")
    shutil.copy(ULOG, directory / "events.ulg")
    return directory


def start_station(directory: Path):
    from groundstation.station.app import Station
    return Station(port=0, viser_port=free_tcp_port(), recordings_dir=directory).start()


def launch_browser(playwright, viser_port: int):
    """Chromium with the viser origin isolated: the software-WebGL view renders in its own
    process and cannot starve the page's main thread."""
    args = CHROMIUM_ARGS + [f"--isolate-origins=http://127.0.0.1:{viser_port}"]
    return playwright.chromium.launch(executable_path=CHROMIUM, headless=True, args=args)


def console_errors(page) -> list[str]:
    errors: list[str] = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))
    return errors



def api(station, method: str, path: str, **kw):
    r = httpx.request(method, station.url + path, timeout=30, **kw)
    assert r.status_code < 400, (path, r.status_code, r.text)
    return r.json() if r.content else None


def replay(station, name: str, speed: float = 1.0, seek: float | None = None, paused: bool = True) -> None:
    """Start a replay (REST), wait for its analysis, optionally pause and seek."""
    api(station, "POST", "/api/replay/start", json={"recording": name, "speed": speed})
    assert wait_until(lambda: not api(station, "GET", "/api/state")["analysing"], 60)
    if paused:
        api(station, "POST", "/api/replay/pause", json={"paused": True})
    if seek is not None:
        api(station, "POST", "/api/replay/seek", json={"t_s": seek})


def dismiss_webgl_notice(page) -> None:
    """Headless chromium renders WebGL in software; the view then says so in a notice over the
    scene's top-left corner.  Hide it with a style (a real GPU never shows it)."""
    src = page.locator("#viewer").get_attribute("src") or ""
    origin = src.split("/?")[0].rstrip("/")
    assert wait_until(lambda: origin and any(f.url.startswith(origin) for f in page.frames), 30), src
    frame = next(f for f in page.frames if f.url.startswith(origin))
    frame.wait_for_load_state("domcontentloaded")
    frame.add_style_tag(content=".mantine-Notification-root { display: none !important; }")


def wait_js(page, expression: str, timeout_ms: int = 60_000) -> None:
    """Wait for a page expression to be truthy, polling every 200 ms.  (Playwright's selector
    waits poll on animation frames, which a software-rendered 3-D view beside the page can
    starve for seconds on a loaded machine.)"""
    page.wait_for_function(expression, polling=200, timeout=timeout_ms)


def has(page, selector: str, text: str | None = None, timeout_ms: int = 60_000) -> None:
    """Wait until ``selector`` matches an element (containing ``text``) that is displayed."""
    cond = (f"[...document.querySelectorAll({selector!r})].some(e => e.offsetParent !== null"
            + (f" && e.textContent.includes({text!r}))" if text is not None else ")"))
    wait_js(page, cond, timeout_ms)


def click(page, selector: str) -> None:
    """Click without waiting for animation frames (see ``wait_js``)."""
    has(page, selector)
    page.locator(selector).first.dispatch_event("click")


def set_value(page, selector: str, value: str) -> None:
    """Type ``value`` into an input as ``fill`` does (the value, then an input event), without
    Playwright's actionability waits: beside the software-rendered 3-D view they waited 18-32 s
    for animation frames on a loaded machine (see ``wait_js``)."""
    has(page, selector)
    page.locator(selector).first.evaluate(
        "(e, v) => { e.value = v; e.dispatchEvent(new Event('input', {bubbles: true})); }", value)


def open_page(page, station, path: str = "/index.html") -> None:
    page.goto(station.url + path)
    wait_js(page, "!document.getElementById('status').textContent.includes('connecting')")
    if getattr(page, "with_view", False):
        wait_js(page, "document.getElementById('viewer').getAttribute('src')")
        dismiss_webgl_notice(page)


def view_pixels(page, settle_ms: int = 1500) -> tuple[bytes, dict]:
    """Screenshot of the page, and the colour classes of the 3-D view in it: {class: (count,
    (x0, y0, x1, y1) bounding box in view pixels or None)}, the viser panel corner left out."""
    from PIL import Image
    time.sleep(settle_ms / 1000)
    png = page.screenshot(animations="disabled", timeout=120_000)
    box = page.locator("#viewer").bounding_box()
    x0, y0 = int(box["x"]), int(box["y"])
    w, h = int(box["width"]), int(box["height"])
    im = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=float)[y0:y0 + h, x0:x0 + w] / 255.0
    return png, {"size": (w, h), **classify(im, exclude=[(w - VISER_PANEL[0], 0, w, VISER_PANEL[1])])}


def view_pixels_until(page, least: dict[str, int], timeout_s: float = 90.0, framed=()) -> tuple[bytes, dict]:
    """``view_pixels`` again until every colour class has at least its count and the classes in
    ``framed`` lie inside the view (the view loads, draws and is framed for its final shape in
    its own time on a loaded machine); the last screenshot either way."""
    deadline = time.monotonic() + timeout_s
    while True:
        png, px = view_pixels(page, 1500)
        drawn = all(px[name][0] >= n for name, n in least.items())
        if (drawn and all(px[name][1] is not None and inside(px[name][1], px["size"]) for name in framed)) \
                or time.monotonic() > deadline:
            return png, px


def classify(im: np.ndarray, exclude=()) -> dict:
    r, g, b = im[..., 0], im[..., 1], im[..., 2]
    mx, mn = im.max(-1), im.min(-1)
    d = np.maximum(mx - mn, 1e-9)
    sat = np.where(mx > 0, (mx - mn) / np.maximum(mx, 1e-9), 0.0)
    hue = np.where(mx == r, (60 * (g - b) / d) % 360, np.where(mx == g, 60 * (b - r) / d + 120, 60 * (r - g) / d + 240))
    colourful = (sat > 0.5) & (mx > 0.35)
    for x0, y0, x1, y1 in exclude:
        colourful[y0:y1, x0:x1] = False
    out = {}
    for name, (lo, hi) in HUES.items():
        m = colourful & (((hue >= lo) & (hue <= hi)) if lo < hi else ((hue >= lo) | (hue <= hi)))
        ys, xs = np.nonzero(m)
        out[name] = (int(m.sum()), (int(xs.min()), int(ys.min()), int(xs.max()), int(ys.max())) if len(xs) else None)
    return out


def inside(bbox, size, margin: int = 4) -> bool:
    """A bounding box (x0, y0, x1, y1) lies inside a view of ``size`` (w, h), off its edges."""
    x0, y0, x1, y1 = bbox
    return x0 >= margin and y0 >= margin and x1 <= size[0] - margin and y1 <= size[1] - margin


def project(points, camera) -> np.ndarray:
    """World points -> view pixels (x right, y down) for a viser client camera."""
    pos, look = np.asarray(camera.position, float), np.asarray(camera.look_at, float)
    fwd = (look - pos) / np.linalg.norm(look - pos)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    w, h = camera.image_width, camera.image_height
    f = (h / 2) / math.tan(camera.fov / 2)
    out = []
    for p in np.asarray(points, float):
        v = p - pos
        z = v @ fwd
        out.append((w / 2 + f * (v @ right) / z, h / 2 - f * (v @ up) / z))
    return np.array(out)


def label_boxes(scene, camera, names_positions) -> list[tuple]:
    """Screen boxes of labels (text ~7 px per character, 16 px high) anchored bottom- or
    top-centre at their world positions."""
    boxes = []
    for text, world, anchor in names_positions:
        x, y = project([world], camera)[0]
        width = 7 * len(text)
        y0 = y - 16 if anchor == "bottom-center" else y
        boxes.append((text, x - width / 2, y0, x + width / 2, y0 + 16))
    return boxes


def overlaps(a, b) -> bool:
    return not (a[3] <= b[1] or b[3] <= a[1] or a[4] <= b[2] or b[4] <= a[2])


@pytest.fixture(scope="module")
def shared_station(tmp_path_factory):
    st = start_station(make_recordings(tmp_path_factory.mktemp("browser") / "recordings"))
    yield st
    st.close()


@pytest.fixture(scope="module")
def shared_browser(playwright_instance, shared_station):
    browser = launch_browser(playwright_instance, shared_station.viser_port)
    yield browser
    browser.close()


@pytest.fixture
def new_page(shared_browser, shared_station):
    """new_page(width, height, view=False) -> a page in a fresh context of that viewport; without
    ``view`` the 3-D view's server is not reached (software WebGL costs a core: tests that do
    not look at the view leave it out)."""
    contexts = []

    def make(width: int = 1280, height: int = 720, view: bool = False):
        ctx = shared_browser.new_context(viewport={"width": width, "height": height}, accept_downloads=True)
        if not view:
            ctx.route(f"http://127.0.0.1:{shared_station.viser_port}/**", lambda route: route.abort())
        contexts.append(ctx)
        page = ctx.new_page()
        page.with_view = view
        page.set_default_timeout(45_000)   # a shared 2-core machine under load
        return page

    yield make
    for ctx in contexts:
        ctx.close()
