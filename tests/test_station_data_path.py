"""One data path: a log gives the same alarms replayed, streamed live and analysed.

Replay shows the whole-log analysis (``analyze_flight``) up to the cursor; a live link goes
sample by sample through ``LiveAnalyzer``, whose inputs are built by the same functions; both list
alarms with ``AlarmTracker``.  Checked on the bundled demo (calibration dance + mission with an
interference episode) and on the real ArduCopter telemetry log (2.8 Hz IMU, corrupt packets,
ATTITUDE stamped seconds behind RAW_IMU).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import SHARED_DATA, shared_data
from live_path import live_alarms_and_rows
from groundstation.io.logs import read_log
from groundstation.jobs.analyze import analyze_flight, analyze_log
from groundstation.jobs.inputs import heading_deg
from groundstation.jobs.live import ReorderBuffer
from groundstation.jobs.record import COL, AlarmTracker
from groundstation.samples import AttitudeSample, ImuSample
from groundstation.station.hub.session import Session

ROOT = Path(__file__).resolve().parent.parent
DEMO = ROOT / "recordings" / "demo.tlog"
REAL = SHARED_DATA / "dronekit" / "flight_replay_flight.tlog"


def _replay_to_end(path: Path, tmp_path: Path) -> tuple[Session, list[dict]]:
    session = Session(tmp_path, record_live=False)
    session.start_replay(path, speed=100.0)
    deadline = time.monotonic() + 60
    while session.snapshot()["analysing"] and time.monotonic() < deadline:
        time.sleep(0.05)
    session.replay_pause(True)
    session.replay_seek(session.replay.duration_s)
    return session, session.alarm_list()


def _demo_interference_s() -> tuple[float, float]:
    """(onset, end) of the demo's simulated disturbance on the log's time axis [s]."""
    mission = json.loads(DEMO.with_suffix(".truth.json").read_text())["parts"][1]
    return (mission["log_offset_s"] + mission["interference"]["onset_s"],
            mission["log_offset_s"] + mission["interference"]["end_s"])


def _same_alarms(a: list[dict], b: list[dict], tol_s: float = 0.5) -> None:
    assert len(a) == len(b), (a, b)
    for x, y in zip(a, b):
        assert x["start_s"] == pytest.approx(y["start_s"], abs=tol_s), (x, y)
        assert sorted(x["evidence"]) == sorted(y["evidence"]), (x, y)


@pytest.mark.parametrize("path", [DEMO, REAL], ids=["demo", "real-arducopter"])
def test_replay_live_and_analyze_give_the_same_alarms(path, tmp_path):
    if not path.exists():
        shared_data(str(path.relative_to(SHARED_DATA)))
    session, replayed = _replay_to_end(path, tmp_path)
    calibration, line = session.flight.calibration, session.flight.line
    report, columns = session.analysis()               # GET /api/analysis: analyze_log, same settings
    review_rows = session.flight.review.rows
    session.close()
    analyzed = [a for a in report["alarms"] if a["kind"] == "combined"]
    live, live_rows = live_alarms_and_rows(path, tmp_path / "live", calibration, line)
    _same_alarms(replayed, analyzed)
    _same_alarms(live, analyzed)
    # row by row, the live record is the batch record (the declination of the true headings is
    # the WMM at the first fix live and at the median position in batch: compare the rest)
    batch = analyze_flight(read_log(path), calibration, [tuple(line["a"]), tuple(line["b"])] if line else None)
    batch_rows = batch.rows
    if path == DEMO:      # the field-vector test ran (its score is in "score", compared below)
        assert (batch.x["vector"].status == 0).mean() > 0.5
    assert live_rows.shape == batch_rows.shape
    decisions = ("t_s", "cross_track_m", "heading_on", "field_on", "steep", "alarm", "ev_heading", "ev_path",
                 "ev_field")
    estimates = ("roll_deg", "pitch_deg", "field_mG", "inclination_deg", "score")
    for name in decisions + estimates:
        np.testing.assert_allclose(live_rows[:, COL[name]], batch_rows[:, COL[name]], atol=1e-6, err_msg=name)
    # the live page shows the causal default AHRS; analyze's CSV, wherever the INS/GPS filter does
    # not run, the offline smoother of the same AHRS (issue 27) ...
    plain = columns["ins_mode"] == ""
    assert set(columns["attitude_source"][plain]) == {"offline"}
    # ... and the replay (the review of the finished log) shows analyze's CSV attitude, nothing else
    for name, csv in (("roll_deg", "roll_deg"), ("pitch_deg", "pitch_deg"), ("heading_deg", "heading_true_deg"),
                      ("v_forward_mps", "v_forward_mps"), ("v_lateral_mps", "v_lateral_mps")):
        np.testing.assert_allclose(review_rows[:, COL[name]], columns[csv], atol=1e-9, equal_nan=True, err_msg=name)
    for name in decisions:          # while every decision of the replay is the live link's and analyze's
        np.testing.assert_array_equal(review_rows[:, COL[name]], batch_rows[:, COL[name]], err_msg=name)
    d_roll = np.abs((live_rows[plain, COL["roll_deg"]] - columns["roll_deg"][plain] + 180.0) % 360.0 - 180.0)
    assert np.nanmedian(d_roll) < 1.5 and np.nanpercentile(d_roll, 90) < 6.0   # demo 0.13/0.46, real 0.88/5.3
    # one attitude (issue 30): the detector's reference is the attitude shown
    detector_roll = np.degrees(batch.x["chain"].roll_rad)
    shown = np.isfinite(live_rows[:, COL["roll_deg"]])
    assert shown.mean() > 0.9
    np.testing.assert_allclose(live_rows[shown, COL["roll_deg"]], detector_roll[shown], atol=1e-6)
    if path == DEMO:      # the interference episode of the demo and nothing before it; it ends with it
        onset_s, end_s = _demo_interference_s()
        assert len(analyzed) == 1 and onset_s < analyzed[0]["start_s"] < onset_s + 5.0
        assert end_s < analyzed[0]["end_s"] < end_s + 5.0, (analyzed[0], end_s)
        assert calibration is not None and line is not None
        # the explanation reaches the station: replayed and live alarms carry analyze's
        e = analyzed[0]["explanation"]
        assert e["kind"] == "rising with time" and e["disturbance_size_mG"] > 150.0
        assert "field_vector" in e["tests"] and analyzed[0]["explanation_text"].startswith("likely rising with time")
        for shown in (replayed[0], live[0]):
            assert shown["explanation"]["kind"] == e["kind"] and shown["explanation"]["tests"] == e["tests"]
            np.testing.assert_allclose(shown["explanation"]["disturbance_mG"], e["disturbance_mG"], atol=0.1)
            assert shown["explanation_text"] == analyzed[0]["explanation_text"]
    else:                 # a normal flight: analyze says no interference, and so do the page and the link
        assert analyzed == [] and report["heading_test"].startswith("off: IMU rate")


def test_reorder_buffer_puts_late_attitude_back_in_time_order():
    """ArduPilot stamps ATTITUDE on the boot clock, which runs behind RAW_IMU's arrival stamps:
    each attitude arrives after the IMU sample 0.25 s newer than it.  The buffer learns the
    lateness and gives the samples in time order (at one time, the IMU step last)."""
    imu = lambda t: ImuSample(t, (0, 0, 0), (0, 0, -9.8))  # noqa: E731
    buf = ReorderBuffer()
    out = []
    for k in range(10):
        t = 1.0 + 0.25 * k                      # exact in binary: ties are real ties
        out += buf.push([imu(t + 0.25)], wall_s=0.0) + buf.push([AttitudeSample(t, 0.0, 0.0, 0.0)], wall_s=0.0)
    out += buf.flush()
    order = [(s.t_s, type(s).__name__) for s in out]
    assert order == sorted(order, key=lambda x: (x[0], x[1] == "ImuSample"))   # time order, attitude first
    assert len(order) == 20
    assert buf.delay_s == pytest.approx(0.3125)                # the lateness seen (0.25 s) x 1.25


def test_alarm_tracker_in_chunks_equals_at_once():
    rng = np.random.default_rng(3)
    t = np.arange(2000) * 0.02
    flag = np.zeros(2000, bool)
    for start in (100, 180, 205, 900):                     # 205 is < 1 s after 180's run: merged
        flag[start:start + int(rng.integers(3, 20))] = True
    flag[1990:] = True                                     # on at the end: still active
    trig = rng.random((2000, 3)) > 0.7
    score = rng.random(2000) * 3
    whole = AlarmTracker()
    whole.update(t, flag, trig, score)
    parts = AlarmTracker()
    for a, b in ((0, 1), (1, 181), (181, 190), (190, 1000), (1000, 1995), (1995, 2000)):
        parts.update(t[a:b], flag[a:b], trig[a:b], score[a:b])
    assert parts.alarms == whole.alarms
    assert len(whole.alarms) == 4 and whole.alarms[-1]["end_s"] is None and whole.active


def test_headings_are_in_0_360_everywhere():
    """np.mod(-tiny, 360) is 360.0: every heading the station shows is folded into [0, 360)."""
    assert heading_deg(np.array([-1e-17, -1e-300, 2 * np.pi, 0.0]))[:2].tolist() == [0.0, 0.0]
    assert np.all(heading_deg(np.linspace(-20, 20, 100001)) < 360.0)
    log = read_log(DEMO)
    rows = analyze_flight(log, None).rows
    _, cols = analyze_log(log, None)
    for name in ("heading_deg", "mag_heading_deg", "ap_heading_deg", "course_deg"):
        v = rows[:, COL[name]]
        v = v[np.isfinite(v)]
        assert len(v) and v.min() >= 0.0 and v.max() < 360.0, name
    for name in ("yaw_deg", "mag_heading_deg", "heading_true_deg"):
        v = cols[name][np.isfinite(cols[name])]
        assert v.min() >= 0.0 and v.max() < 360.0, name


def test_rolling_imu_rate_live_chunks_equal_batch():
    """The heading test's IMU-rate gate: the live form (its last RATE_WINDOW + 1 times and a few
    new ones per call) gives every step the rate the batch form gives it."""
    from groundstation.jobs.inputs import RATE_WINDOW, imu_rate_hz
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.01, 0.4, 300))
    t[50:53] = t[49]                                           # repeated stamps: zero intervals
    batch = imu_rate_hz(t)
    d = np.diff(t)
    assert batch[0] == 0.0 and batch[10] == pytest.approx(1 / np.median(d[:10]), abs=0.005)   # to 0.01 Hz
    assert batch[200] == pytest.approx(1 / np.median(d[200 - RATE_WINDOW:200]), abs=0.005)
    k = np.arange(100)
    stamps = k * 0.1 + np.where(k % 3 == 0, 0.0, 1e-6)                         # .tlog microseconds
    assert 1 / np.median(np.diff(stamps)[:RATE_WINDOW]) < 10.0
    assert np.all(imu_rate_hz(stamps)[RATE_WINDOW:] == 10.0)                   # 10 Hz, not 9.9999
    live, hist = [], []
    for k in range(0, len(t), 7):
        h = np.asarray(hist[-(RATE_WINDOW + 1):])
        live += list(imu_rate_hz(np.r_[h, t[k:k + 7]], start=len(h)))
        hist += list(t[k:k + 7])
    np.testing.assert_array_equal(live, batch)


def test_rolling_imu_rate_in_blocks_is_np_median(monkeypatch):
    """The batch form takes each window's middle interval a block of windows at a time: every
    step's rate is 1 / np.median of its RATE_WINDOW intervals, across block edges too."""
    from groundstation.jobs import inputs
    t = np.cumsum(np.random.default_rng(1).uniform(0.01, 0.4, 3000))
    med = np.median(np.lib.stride_tricks.sliding_window_view(np.diff(t), inputs.RATE_WINDOW), axis=1)
    monkeypatch.setattr(inputs, "MEDIAN_ROWS", 97)
    np.testing.assert_array_equal(inputs.imu_rate_hz(t)[inputs.RATE_WINDOW + 1:], np.round(1.0 / med[1:], 2))
    t[1500] = np.nan                              # a NaN time: its windows' medians NaN, as np.median's
    with np.errstate(invalid="ignore"):
        med = np.median(np.lib.stride_tricks.sliding_window_view(np.diff(t), inputs.RATE_WINDOW), axis=1)
        expect = np.round(np.where(med > 0, 1.0 / med, np.inf), 2)
    np.testing.assert_array_equal(inputs.imu_rate_hz(t)[inputs.RATE_WINDOW + 1:], expect[1:])
