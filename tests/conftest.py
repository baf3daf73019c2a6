"""Shared fixtures: a running station (FastAPI + viser) on free loopback ports, a fake vehicle,
a headless Debian chromium through Playwright, and a small synthetic rotation dance with
known calibration truth."""
from __future__ import annotations

import math
import os
import socket
import time
from pathlib import Path

import numpy as np
import pytest

from groundstation.io.mavlink import mavlink2

ARTIFACTS = Path(__file__).resolve().parent / "artifacts"
# the real public logs: ../shared/data beside the checkout (tests that need them skip without)
SHARED = Path(__file__).resolve().parents[2] / "shared"
SHARED_DATA = SHARED / "data"
# small cuts of two of them shipped with the tests (tests/data/real/README.md: source, cut, licence)
REAL_TLOG_PIECE = Path(__file__).resolve().parent / "data" / "real" / "dronekit-flight-440-700s.tlog"
REAL_ULOG_PIECE = Path(__file__).resolve().parent / "data" / "real" / "px4-events-cut.ulg"
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--use-gl=swiftshader", "--enable-unsafe-swiftshader",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--no-first-run", "--disable-dev-shm-usage"]


def _shared_missing(rel: str) -> str | None:
    """The skip reason when ../shared/<rel> (a file, a folder, or a glob) is absent, else None."""
    present = any(SHARED.glob(rel)) if any(c in rel for c in "*?[") else (SHARED / rel).exists()
    return None if present else f"needs ../shared/{rel} (beside the checkout; not shipped)"


def shared_path(rel: str) -> Path:
    """The path of ../shared/<rel> (``data/...`` real logs, ``sitl/...``, ``px4sitl/...`` SITL binaries);
    the calling test skips with the reason when it is absent.  The one way a test asks for what
    the repository does not ship (``shared_data`` and ``needs_shared`` for the logs in ../shared/data)."""
    reason = _shared_missing(rel)
    if reason:
        pytest.skip(reason)
    return SHARED / rel


def shared_data(rel: str) -> Path:
    """The path of ../shared/data/<rel>; the calling test skips with the reason when it is absent."""
    return shared_path("data/" + rel)


def needs_shared(rel: str):
    """Mark: the test (or module, as `pytestmark`) skips with the reason without ../shared/data/<rel>."""
    reason = _shared_missing("data/" + rel)
    return pytest.mark.skipif(reason is not None, reason=reason or "")


def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ------------------------------------------------------------------------------ parallel runs

# ./test's parallel phase (pytest-xdist --dist loadfile --no-loadscope-reorder) hands out whole
# modules in this order, the longest first (measured with --durations; an order only: a module
# left out runs after these), so that no long module starts last and runs alone at the end
LONGEST_FIRST = ("test_fleet_cluster.py", "test_browser.py", "test_browser_calibration.py", "test_browser_pages.py",
                 "test_station_walkthrough.py", "test_benchmarks.py", "test_ingest_vectorised.py",
                 "test_inflight_quality.py", "test_browser_calibration_in_use.py", "test_calibration_in_use.py",
                 "test_gcs_vehicles.py", "test_analysis.py", "test_cautions.py", "test_station_sources.py",
                 "test_calibrate_real_logs.py", "test_fuzz.py", "test_security.py", "test_fleet.py")


def pytest_collection_modifyitems(config, items):
    if os.environ.get("PYTEST_XDIST_WORKER"):      # every worker sorts its collection alike
        rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
        items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


# ------------------------------------------------------------------------------ synthetic truth

DANCE_TRUTH = {
    "field_ned_mG": np.array([220.0, 15.0, 420.0]),
    "offsets_mG": np.array([120.0, -80.0, 45.0]),
    "A": np.array([[1.08, 0.03, 0.0], [0.03, 0.95, -0.02], [0.0, -0.02, 1.02]]),
    "lat_lon": (47.397, 8.546),
}


def _axis_rot(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def rotation_dance_messages(rate_hz: float = 50.0, turn_s: float = 6.0, tumble_s: float = 24.0,
                            start_unix: float = 1.8e9, seed: int = 0) -> list:
    """HEARTBEAT-free MAVLink stream of a handheld dance: full turns about body X, Y, Z, then a
    tumble.  SCALED_IMU carries gyro (mrad/s), accel (mG) and raw mag = A m_body + b (mG);
    ATTITUDE the true attitude; GPS_RAW_INT a fixed position."""
    rng = np.random.default_rng(seed)
    truth = DANCE_TRUTH
    dt = 1.0 / rate_hz
    R = np.eye(3)  # body -> NED
    segments = [(np.array([1.0, 0, 0]), turn_s), (np.array([0, 1.0, 0]), turn_s), (np.array([0, 0, 1.0]), turn_s)]
    rates = []
    for axis, dur in segments:
        w = 2 * math.pi * 1.08 / dur
        rates += [axis * w] * int(dur * rate_hz)
    axis = np.array([1.0, 0.4, 0.2])
    for i in range(int(tumble_s * rate_hz)):
        if i % int(rate_hz) == 0:
            axis = rng.normal(size=3)
        rates.append(axis / np.linalg.norm(axis) * 1.6)
    msgs = []
    g_ned = np.array([0, 0, -9.80665])   # specific force of a vehicle at rest, NED
    for i, w in enumerate(rates):
        t = i * dt
        R = R @ _axis_rot(w, np.linalg.norm(w) * dt) if np.linalg.norm(w) > 0 else R
        m_body = R.T @ truth["field_ned_mG"]
        raw = truth["A"] @ m_body + truth["offsets_mG"] + rng.normal(0, 1.0, 3)
        acc_mg = (R.T @ g_ned) / 9.80665 * 1000
        boot_ms = int(t * 1000)
        gyro = w * 1000
        msgs.append((start_unix + t, mavlink2.MAVLink_scaled_imu_message(
            boot_ms, int(acc_mg[0]), int(acc_mg[1]), int(acc_mg[2]), int(gyro[0]), int(gyro[1]), int(gyro[2]),
            int(round(raw[0])), int(round(raw[1])), int(round(raw[2])))))
        roll = math.atan2(R[2, 1], R[2, 2])
        pitch = -math.asin(max(-1, min(1, R[2, 0])))
        yaw = math.atan2(R[1, 0], R[0, 0])
        msgs.append((start_unix + t, mavlink2.MAVLink_attitude_message(boot_ms, roll, pitch, yaw, *w)))
        if i % int(rate_hz / 5) == 0:
            lat, lon = truth["lat_lon"]
            msgs.append((start_unix + t, mavlink2.MAVLink_gps_raw_int_message(
                int(t * 1e6), 6, int(lat * 1e7), int(lon * 1e7), 500000, 80, 80, 0, 0, 14)))
    return msgs


# ------------------------------------------------------------------------------ station

@pytest.fixture
def recordings_dir(tmp_path) -> Path:
    d = tmp_path / "recordings"
    d.mkdir()
    return d


@pytest.fixture
def station(recordings_dir):
    from groundstation.station.app import Station
    st = Station(port=0, viser_port=free_tcp_port(), recordings_dir=recordings_dir).start()
    yield st
    st.close()


@pytest.fixture
def station_no_viser(recordings_dir):
    from groundstation.station.app import Station
    st = Station(port=0, viser_port=None, recordings_dir=recordings_dir).start()
    yield st
    st.close()


# ------------------------------------------------------------------------------ browser

@pytest.fixture(scope="session")
def playwright_instance():
    if not Path(CHROMIUM).exists():
        pytest.skip("Debian chromium not installed (/usr/bin/chromium)")
    from playwright.sync_api import sync_playwright
    with sync_playwright() as p:
        yield p


@pytest.fixture
def page(playwright_instance, station):
    """A page in a fresh chromium whose viser origin is isolated: the software-WebGL 3-D view
    then renders in its own process and cannot starve the page's main thread."""
    args = CHROMIUM_ARGS + [f"--isolate-origins=http://127.0.0.1:{station.viser_port}"]
    browser = playwright_instance.chromium.launch(executable_path=CHROMIUM, headless=True, args=args)
    ctx = browser.new_context(viewport={"width": 1200, "height": 700})
    pg = ctx.new_page()
    yield pg
    ctx.close()
    browser.close()


@pytest.fixture(scope="session")
def artifacts() -> Path:
    ARTIFACTS.mkdir(exist_ok=True)
    return ARTIFACTS


def wait_until(cond, timeout: float = 20.0, step: float = 0.05) -> bool:
    """Poll ``cond`` every ``step`` s until it is true (True) or ``timeout`` s pass (False)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(step)
    return False
