"""Fixtures of the ArduPilot SITL tests (see harness.py): ``start_sitl`` starts
``../shared/sitl/arducopter`` by PID on loopback and stops it; ``station_for`` (harness.py, re-exported)
is a station session listening for it.  Every test skips, saying why, when the firmware is absent.
(Not a conftest.py: a second module named ``conftest`` would shadow tests/conftest.py for every
``from conftest import``.)"""
from __future__ import annotations

import pytest

from harness import MISSING, SITL_BINARY, Sitl, station_for

__all__ = ["start_sitl", "station_for"]


@pytest.fixture
def start_sitl():
    """start_sitl(instance=None, port=None, **options) -> a running Sitl (a free instance and port
    claimed when not given), stopped (by its PID) after the test."""
    if SITL_BINARY is None:
        pytest.skip(MISSING)
    started: list[Sitl] = []

    def start(instance: int | None = None, port: int | None = None, **options) -> Sitl:
        sitl = Sitl(instance, port, **options).start()
        started.append(sitl)
        return sitl

    yield start
    for sitl in started:
        sitl.stop()

