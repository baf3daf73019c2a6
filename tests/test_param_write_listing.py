"""A parameter write while the vehicle still sends a parameter list (seen on ArduPilot SITL at 8x
on a loaded machine): its PARAM_SET echoes queue behind the list's values and come seconds late.
The write waits while other PARAM_VALUEs keep coming, and still gives up on a silent vehicle."""
from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import pytest

from groundstation.samples import ParamSample
from groundstation.station.hub.vehicle import VehicleLink

pytestmark = pytest.mark.serial     # the stub vehicle's answers are paced by wall-clock sleeps


class ListingVehicle:
    """A stub link: each PARAM_SET is echoed ``echo_after_s`` later; meanwhile, if ``listing``,
    other parameters arrive every 0.05 s (a PARAM_REQUEST_LIST being answered)."""

    def __init__(self, state: VehicleLink, echo_after_s: float, listing: bool) -> None:
        self.state, self.echo_after_s, self.listing = state, echo_after_s, listing
        self.passive = False
        self.decoder = SimpleNamespace(vehicle_sysid=1)
        self.mav = SimpleNamespace(mav=SimpleNamespace(param_set_send=self.param_set_send))
        self.threads: list[threading.Thread] = []

    def param_set_send(self, _sysid, _comp, name: bytes, value: float, _type) -> None:
        t = threading.Thread(target=self._answer, args=(name.decode(), value), daemon=True)
        self.threads.append(t)
        t.start()

    def _answer(self, name: str, value: float) -> None:
        end = time.monotonic() + self.echo_after_s
        i = 0
        while time.monotonic() < end:
            if self.listing:
                with self.state._lock:
                    self.state.on_param(ParamSample(0.0, f"LIST_PARAM_{i}", float(i)))
                i += 1
            time.sleep(0.05)
        with self.state._lock:
            self.state.on_param(ParamSample(0.0, name, value))


def write(echo_after_s: float, listing: bool):
    state = VehicleLink(threading.RLock())
    link = ListingVehicle(state, echo_after_s, listing)
    t0 = time.monotonic()
    confirmed, failed, _ = state.write_params(link, {"COMPASS_OFS_X": 120.0}, lambda done: None,
                                              tries=1, timeout_s=0.5)
    return confirmed, failed, time.monotonic() - t0


def test_echo_late_behind_a_parameter_list_is_waited_for():
    confirmed, failed, took = write(1.5, listing=True)
    assert confirmed == ["COMPASS_OFS_X"] and failed == [], (confirmed, failed)
    assert 1.4 < took < 3.0


def test_a_late_echo_with_nothing_else_coming_is_a_failure_after_the_timeout():
    confirmed, failed, took = write(1.5, listing=False)
    assert confirmed == [] and failed == ["COMPASS_OFS_X"]
    assert took < 1.0
