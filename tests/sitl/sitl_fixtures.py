"""Fixtures of the ArduPilot SITL tests (see harness.py): ``start_sitl`` starts
``../shared/sitl/arducopter`` by PID on loopback and stops it; ``station_for`` is a station session
listening for it.  Every test skips, saying why, when the firmware is absent.  (Not a conftest.py:
a second module named ``conftest`` would shadow tests/conftest.py for every ``from conftest import``.)"""
from __future__ import annotations

from pathlib import Path

import pytest

from harness import MISSING, SITL_BINARY, Sitl, station_link

__all__ = ["start_sitl", "station_for"]


@pytest.fixture
def start_sitl():
    """start_sitl(instance, port, **options) -> a running Sitl, stopped (by its PID) after the test."""
    if SITL_BINARY is None:
        pytest.skip(MISSING)
    started: list[Sitl] = []

    def start(instance: int, port: int, **options) -> Sitl:
        sitl = Sitl(instance, port, **options).start()
        started.append(sitl)
        return sitl

    yield start
    for sitl in started:
        sitl.stop()


def station_for(sitl: Sitl, recordings: Path):
    """A station session listening on the SITL's UDP port (udpin on loopback), following it."""
    from groundstation.station.hub.session import Session

    session = Session(recordings)
    session.connect(f"udpin:127.0.0.1:{sitl.port}")
    try:
        station_link(session, timeout_s=40)
    except TimeoutError:
        session.close()
        raise AssertionError(f"the station never heard SITL (pid {sitl.pid}): {sitl.output()[-500:]}") from None
    return session
