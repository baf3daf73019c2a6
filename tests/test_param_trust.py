"""Parameters the station can trust (issue 24 found-item 5): a spoofed PARAM_VALUE during a guided
dance writes nothing wrong and the page says why; NaN, infinities, 3.4e38 and values beyond the
autopilot's range are refused and counted (live cache, logs, `info`); a real change of the
vehicle's compass corrections during the dance stops the step and re-reads."""
from __future__ import annotations

import socket
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from conftest import free_udp_port, wait_until
from groundstation.io.logs import read_log
from groundstation.io.mavlink import TlogWriter, mavlink2, new_encoder
from groundstation.io.params import param_value_problem, trusted_params
from groundstation.samples import ParamSample
from groundstation.sim.fake_autopilot import default_params
from groundstation.sim.fake_vehicle import FakeVehicle
from groundstation.sim.vehicle_streams import guided_dance_attitude, make_hardware, pack_stream, three_compasses
from groundstation.station.hub.session import Session
from groundstation.station.hub.vehicle import VehicleLink
from groundstation.station.wizard.param_check import CompassParamCheck, is_correction_param

ROOT = Path(__file__).resolve().parents[1]
ABSURD = [float("nan"), float("inf"), -float("inf"), 3.4e38]


# ------------------------------------------------------------------ the one range check
@pytest.mark.parametrize("value", ABSURD)
def test_non_finite_and_float32_garbage_refused_for_any_parameter(value):
    assert param_value_problem("COMPASS_OFS_X", value) is not None
    assert param_value_problem("SOME_OTHER_PARAM", value) is not None


def test_documented_ranges():
    ok = {"COMPASS_OFS_X": -119.9, "COMPASS_OFS3_Z": 1700.0, "COMPASS_DIA_X": 0.0, "COMPASS_DIA2_Y": 1.05,
          "COMPASS_ODI3_Z": -0.2, "COMPASS_SCALE": 0.0, "COMPASS_SCALE2": 1.1, "COMPASS_ORIENT": 101,
          "COMPASS_DEC": -0.1, "CAL_MAG0_XOFF": 0.4, "CAL_MAG1_ROT": -1, "SERVO5_FUNCTION": 0}
    bad = {"COMPASS_OFS_Y": 3500.0, "COMPASS_DIA_X": 0.1, "COMPASS_ODI_Y": 1.5, "COMPASS_SCALE3": 2.0,
           "COMPASS_ORIENT2": 60, "COMPASS_DEC": 4.0, "COMPASS_MOT_X": -2000.0, "CAL_MAG2_XSCALE": 9.0,
           "CAL_MAG0_ZOFF": 5.0}
    assert all(param_value_problem(k, v) is None for k, v in ok.items())
    for k, v in bad.items():
        assert param_value_problem(k, v) is not None, k
        assert k in param_value_problem(k, v)          # the message names the parameter
    kept, refused = trusted_params({"COMPASS_OFS_X": 5.0, "COMPASS_OFS_Y": float("nan"), "COMPASS_ODI_Y": 1.5})
    assert kept == {"COMPASS_OFS_X": 5.0} and len(refused) == 2


@pytest.mark.parametrize("value", ABSURD + [3000.5])
def test_live_cache_refuses_and_counts(value):
    v = VehicleLink(threading.RLock())
    v.reset("ardupilot", {"COMPASS_OFS_X": -119.9})
    assert v.on_param(ParamSample(1.0, "COMPASS_OFS_X", value)) is False
    assert v.params["COMPASS_OFS_X"] == -119.9 and v.refused_count == 1
    assert "COMPASS_OFS_X" in v.refused_values["COMPASS_OFS_X"]


def _tlog_with(path: Path, values: dict[str, float]) -> None:
    enc = new_encoder(1, 1)
    with TlogWriter(path) as w:
        t = 1_700_000_000.0
        w.write_packet(bytes(mavlink2.MAVLink_heartbeat_message(2, 3, 0, 0, 3, 3).pack(enc)), t)
        for i, (name, value) in enumerate(values.items()):
            w.write_packet(bytes(mavlink2.MAVLink_param_value_message(name.encode(), value, 9, len(values), i)
                                 .pack(enc)), t + 0.1 * (i + 1))


def test_log_parameters_refused_and_info_flags_them(tmp_path):
    path = tmp_path / "absurd.tlog"
    _tlog_with(path, {"COMPASS_OFS_X": 3.4e38, "COMPASS_OFS_Y": float("nan"), "COMPASS_OFS_Z": -18.0,
                      "COMPASS_DIA_X": 7.0})
    log = read_log(path)
    assert log.params == {"COMPASS_OFS_Z": -18.0}
    assert sum(n for w, n in log.warnings.items() if w.startswith("parameter value refused")) == 3
    out = subprocess.run([sys.executable, "-m", "groundstation.cli", "info", str(path)], capture_output=True,
                         text=True, cwd=ROOT, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "ABSURD VALUES   3 parameter value(s) refused" in out.stdout
    assert "COMPASS_OFS_X: 3.4e+38 is absurd" in out.stdout and "COMPASS_DIA_X: 7 is outside" in out.stdout


# ------------------------------------------------------------------ the wizard's reference values
def test_param_check_reference_changes_and_reread():
    chk = CompassParamCheck()
    chk.begin({"COMPASS_OFS_X": -119.9, "COMPASS_DEC": 0.0, "SERVO1_MIN": 1000})
    assert chk.reference == {"COMPASS_OFS_X": -119.9}        # only what corrects the field
    assert not is_correction_param("COMPASS_DEC") and is_correction_param("CAL_MAG2_ZODIAG")
    assert chk.on_value("COMPASS_OFS_X", np.float32(-119.9)) is None      # the float32 echo is the same value
    assert chk.on_value("COMPASS_OFS_X", 300.0) == "COMPASS_OFS_X -119.9 -> 300"
    names = chk.start("fit", 0.0)
    assert names == ["COMPASS_OFS_X"] and not chk.done(1.0)
    chk.on_value("COMPASS_OFS_X", -119.9)
    assert chk.done(1.0) and chk.finish() == ([], [])
    chk.start("write", 10.0)
    assert chk.done(10.0 + 5.0)                               # unanswered: gives up after the timeout
    assert chk.finish() == ([], ["COMPASS_OFS_X"])


# ------------------------------------------------------------------ over UDP, with the fake vehicle
OFS_IN_FORCE = (-119.9, 80.3, -45.2)


def _vehicle_params() -> dict[str, float]:
    p = default_params("ardupilot", 3)
    p.update({f"COMPASS_OFS_{a}": v for a, v in zip("XYZ", OFS_IN_FORCE)})
    return p


def _spoof(port: int, name: str, value: float, count: int = 5) -> None:
    """PARAM_VALUE in the vehicle's name (system 1, component 1) from another UDP port."""
    enc = new_encoder(1, 1)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for _ in range(count):
            s.sendto(bytes(mavlink2.MAVLink_param_value_message(name.encode(), value, 9, 1, 0).pack(enc)),
                     ("127.0.0.1", port))
            time.sleep(0.05)


def _dance(hw):
    return pack_stream(guided_dance_attitude(rate_hz=12.5), hw, seed=2)


@contextmanager
def _dancing(tmp_path, hw, speed: float):
    """(session, vehicle, port): a station listening on loopback, a fake vehicle whose stream
    waits until the station knows its parameters, the guided wizard started and fed > 100
    samples of the dance; both stopped afterwards."""
    session = Session(tmp_path, record_live=False)
    port = free_udp_port()
    session.connect(f"udpin:127.0.0.1:{port}")
    fv = FakeVehicle(_dance(hw), port, speed=speed, params=_vehicle_params())
    fv.hold_before = 40
    fv.start()
    try:
        assert wait_until(lambda: session.params.get("COMPASS_OFS_X") == pytest.approx(-119.9, abs=1e-3), 10)
        session.wizard_start()
        fv.release()
        assert wait_until(lambda: session.snapshot()["wizard"]["samples"] > 100, 20)
        yield session, fv, port
    finally:
        fv.stop()
        session.close()


def test_spoofed_param_value_during_a_guided_dance_writes_nothing_wrong(tmp_path):
    hw = make_hardware(three_compasses())
    with _dancing(tmp_path, hw, 8.0) as (session, fv, port):
        _spoof(port, "COMPASS_OFS_X", 300.0)
        for bad in ABSURD:                        # from the vehicle's own address: refused for their value
            fv._sock.sendto(bytes(mavlink2.MAVLink_param_value_message(b"COMPASS_OFS_Y", bad, 9, 1, 0)
                                  .pack(fv._enc)), fv.target)
        assert wait_until(lambda: session.snapshot()["wizard"]["state"] == "result", 90)
        w = session.snapshot()["wizard"]
        r = w["result"]
        assert r["status"] == "ok", r
        ap = r["ardupilot_params"]
        # the truth: the sensor reads A m + o, so COMPASS_OFS = −o, whatever the vehicle had in force
        np.testing.assert_allclose([ap[f"COMPASS_OFS_{a}"] for a in "XYZ"], -hw.compasses[0].offsets_mG, atol=3.0)
        trust = w["param_trust"]
        assert trust["refused"] >= 1 and "127.0.0.1" in trust["last"] and "COMPASS_OFS_X" in trust["last"]
        assert trust["values_refused"] == len(ABSURD)
        assert any("parameter value(s) refused" in t for t in w["warnings"])          # on the page
        events = [e["text"] for e in session.events]
        assert any("PARAM_VALUE COMPASS_OFS_X = 300 refused" in e for e in events), events
        assert session.params["COMPASS_OFS_X"] == pytest.approx(-119.9, abs=1e-3)
        assert session.vehicles()["param_trust"]["refused"] >= 1                      # the API
        pw = session.wizard_accept()
        assert pw["state"] == "checking"
        assert wait_until(lambda: session.snapshot()["wizard"]["param_write"]["state"] not in ("checking", "writing"),
                          20)
        pw = session.snapshot()["wizard"]["param_write"]
    assert pw["state"] == "written", pw
    np.testing.assert_allclose([fv.params[f"COMPASS_OFS_{a}"] for a in "XYZ"], -hw.compasses[0].offsets_mG, atol=3.0)


def test_real_change_during_the_dance_stops_the_step_and_rereads(tmp_path):
    hw = make_hardware(three_compasses())
    with _dancing(tmp_path, hw, 4.0) as (session, fv, _):
        other = new_encoder(254, 190)            # another ground station writes to the vehicle
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.sendto(bytes(mavlink2.MAVLink_param_set_message(1, 1, b"COMPASS_OFS_X", 250.0, 9).pack(other)),
                     fv._sock.getsockname())
        assert wait_until(lambda: any("calibration restarted" in e["text"] for e in session.events), 15)
        events = [e["text"] for e in session.events]
        w = session.snapshot()["wizard"]
    assert any("compass parameter changed during the dance: COMPASS_OFS_X -119.9 -> 250" in e for e in events), events
    assert w["state"] == "running" and w["step"] == "x"                      # the dance starts again
    assert "COMPASS_OFS_X -119.9 -> 250" in w["banner"]["text"]
    assert w["param_check"]["checked"] >= 3
