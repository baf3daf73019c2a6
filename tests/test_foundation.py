"""Mission readers, replay pacing, CLI behaviour and the estimators' purity rule."""
from __future__ import annotations

import ast
from collections import Counter
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import groundstation  # noqa: F401
from groundstation.cli import main
from groundstation.io.errors import IngestError
from groundstation.io.logs import read_log
from groundstation.io.mission import read_mission
from groundstation.io.replay import Replayer

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"
ROUTE = [pytest.approx((30.26, 120.12, 20.0)), pytest.approx((30.261, 120.121, 20.0))]


@pytest.mark.parametrize("name", ["mission.waypoints", "mission.plan", "reference.tlog", "reference.bin"])
def test_mission_from_every_source(name):
    assert read_mission(DATA / name) == ROUTE


def test_mission_errors(tmp_path):
    bad = tmp_path / "x.waypoints"
    bad.write_text("not a mission\n")
    with pytest.raises(IngestError, match="QGC WPL"):
        read_mission(bad)
    with pytest.raises(IngestError, match="at least two waypoints"):
        read_mission(DATA / "mag.csv")


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_replay_paces_pauses_seeks_and_changes_speed():
    clock = FakeClock()
    rep = Replayer(read_log(DATA / "reference.tlog"), speed=2.0, clock=clock)
    first = rep.due()
    assert all(s.t_s <= 0.0 for s in first)
    clock.now += 1.0  # 2 s of log at speed 2
    got = rep.due()
    assert got and max(s.t_s for s in got) <= 2.0 and rep.samples[rep.index].t_s > 2.0
    rep.pause()
    clock.now += 10
    assert rep.due() == [] and rep.position_s == pytest.approx(2.0)
    rep.resume()
    rep.set_speed(1.0)
    clock.now += 0.5
    assert max(s.t_s for s in rep.due()) <= 2.5
    rep.seek(8.0)
    assert rep.samples[rep.index].t_s >= 8.0
    clock.now += 100
    rest = rep.due()
    assert rest and rep.finished and min(s.t_s for s in rest) >= 8.0


def test_replay_loops_and_unpaced_iteration():
    clock = FakeClock()
    log = read_log(DATA / "reference.tlog")
    rep = Replayer(log, speed=1000.0, loop=True, clock=clock)
    clock.now += 1.0
    rep.due()
    assert rep.loops == 1 and rep.index == 0
    assert len(list(Replayer(log))) == len(rep.samples)


def test_a_replay_of_the_first_part_holds_at_its_end_and_goes_on_with_the_whole_file(tmp_path):
    """Issue 29: a large log plays from its first part (``read_log_start``) while the rest is
    read; that replay holds at the part's end (not finished, not looped), and the whole file's
    replayer goes on from there: every sample of the whole log given once, in order."""
    from groundstation.io.logs import read_log_start

    path = tmp_path / "whole.tlog"
    shutil.copy(ROOT / "recordings" / "demo.tlog", path)
    whole = read_log(path)
    part = read_log_start(path, 300_000)
    assert part.source == str(path) and 20.0 < part.imu[-1, 0] < whole.imu[-1, 0] - 100.0
    n = len(part.imu)                                       # the part's times are the whole file's
    np.testing.assert_array_equal(part.imu[:n - 1], whole.imu[:n - 1])
    clock = FakeClock()
    rep = Replayer(part, speed=1.0, loop=True, clock=clock)
    rep.more_to_come = True
    given = rep.due()
    clock.now += 60.0
    given += rep.due()
    clock.now += 1000.0                                       # far past the part's end
    given += rep.due()
    assert rep.index == len(rep.samples) and not rep.finished and rep.loops == 0
    nxt = rep.continued(whole)
    assert nxt.position_s == pytest.approx(rep.position_s) and not nxt.more_to_come
    clock.now += 1000.0
    given += nxt.due()
    times = [s.t_s for s in given]
    assert times == sorted(times)
    # every sample of the whole log once, but for its mission (read after the part: at t 0, the
    # station takes it from the whole log, Session.whole_replay_read)
    key = lambda s: (type(s).__name__, s.t_s)  # noqa: E731
    expected = [key(s) for s in Replayer(whole).samples[0:len(Replayer(whole).samples)]]
    assert Counter(map(key, given)) == Counter(k for k in expected if k[0] != "MissionSample")
    assert len(part.mission) == 0 and len(whole.mission) == 2
    bin_whole, bin_part = read_log(DATA / "reference.bin"), read_log_start(DATA / "reference.bin", 40_000)
    n = len(bin_part.mag)                                    # a DataFlash .bin alike
    assert 100 < n < len(bin_whole.mag) and np.array_equal(bin_part.mag[:n - 1], bin_whole.mag[:n - 1])
    assert nxt.loops == 1                                         # the whole one loops, as asked


def test_cli_info(capsys):
    assert main(["info", str(DATA / "reference.tlog")]) == 0
    out = capsys.readouterr().out
    assert "ardupilot" in out and "RTK             yes" in out and "2 waypoints" in out
    assert "SCALED_IMU" in out


def test_cli_errors_are_one_line_without_traceback():
    proc = subprocess.run([sys.executable, "-m", "groundstation.cli", "info", str(DATA / "garbage.tlog")],
                          capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 1
    assert proc.stderr.strip().startswith("magstation: error:") and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_cli_warns_about_damage_and_goes_on(capsys):
    assert main(["info", str(DATA / "corrupt.tlog")]) == 0
    assert "corrupt packets skipped" in capsys.readouterr().err


def test_serve_refuses_non_loopback_without_flag(capsys):
    assert main(["serve", "--host", "0.0.0.0", "--replay", str(DATA / "reference.tlog")]) == 1
    assert "--allow-remote" in capsys.readouterr().err


def test_estimators_are_pure():
    """estimators/ never imports I/O or server code."""
    forbidden = {"groundstation", "fastapi", "viser", "pymavlink", "uvicorn", "pyulog", "socket",
                 "requests", "httpx"}
    for path in (ROOT / "estimators").glob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            for name in names:
                assert name.split(".")[0] not in forbidden, f"{path.name} imports {name}"
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "open":
                pytest.fail(f"{path.name} opens files")


def test_sample_timeline_is_every_row_once_in_time_order():
    """The replay's samples (``SampleTimeline``, made when asked for): head first, then every IMU,
    magnetometer, attitude and GPS row and status event once, times non-decreasing, equal times in
    table order; a slice, an index and iteration give the same samples."""
    from groundstation.io.logs.builder import SampleTimeline
    from groundstation.samples import AttitudeSample, GpsSample, ImuSample, MagSample, StatusSample

    log = read_log(DATA / "reference.tlog")
    tl = SampleTimeline(log)
    every = list(tl)
    head = len(log.params) + len(log.mission) + (1 if log.autopilot else 0)
    assert len(every) == len(tl) == head + len(log.imu) + len(log.mag) + len(log.attitude) + len(log.gps) + len(log.status)
    body = every[head:]
    t = np.array([s.t_s for s in body])
    assert np.all(np.diff(t) >= 0) and np.array_equal(tl.t_s[head:], t)
    kinds = (ImuSample, MagSample, AttitudeSample, GpsSample)
    for kind, table in zip(kinds, (log.imu, log.mag, log.attitude, log.gps)):
        got = [s for s in body if isinstance(s, kind)]
        assert len(got) == len(table) and [s.t_s for s in got] == table[:, 0].tolist()
        assert all(type(s.t_s) is float for s in got[:5])
    assert [s for s in body if isinstance(s, StatusSample)] == sorted(log.status, key=lambda s: s.t_s)
    rank = {k: i for i, k in enumerate(kinds)}
    for a, b in zip(body, body[1:]):                      # a tie: IMU, magnetometer, attitude, GPS
        if a.t_s == b.t_s and type(a) in rank and type(b) in rank:
            assert rank[type(a)] <= rank[type(b)]
    assert [repr(s) for s in tl[head - 2:head + 40]] == [repr(s) for s in every[head - 2:head + 40]]
    assert repr(tl[-1]) == repr(every[-1]) and repr(tl[head + 7]) == repr(every[head + 7])
