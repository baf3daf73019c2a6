"""Seek benchmark: how long the station takes to show the state at any point of a long replay.

A replay is analysed once when it starts (``groundstation.station.hub.review``: the whole-log
detection of ``magstation analyze``); a seek then moves a cursor and rebuilds the alarms so far
from the flight record.  This builds an N-minute 50 Hz log (the bundled mission-clean flight
repeated end to end), starts its replay in a session and seeks to random points, timing what
the page needs after a seek: the seek itself, the state snapshot (JSON), the plots, the alarm
list and the 3-D scene's arrays.  The peer is the per-sample path a seek would otherwise need:
feeding the log up to the seek point through ``LiveAnalyzer`` (timed on the first minute,
extrapolated).

    .venv/bin/python benchmarks/seek.py              # 60-minute log, 20 seeks
    .venv/bin/python benchmarks/seek.py --minutes 5 --seeks 5   # smoke run

Targets (issue 29): every seek in a 1-hour 50 Hz log under 0.5 s (worst of the seeks); a 100 MB
log starts playing within 2 s of opening it.  A replay plays as soon as its file is read (the
samples take the causal path) while the whole-log analysis runs beside it; printed: the time to
the first sample pushed and to the analysis being in.  ``--open-mb N`` also writes an N-MB
ArduPilot-style 50 Hz tlog (``benchmarks/ingest.py``'s stream) and times opening it by name, the
reading included, as the page's "play" does.

    .venv/bin/python benchmarks/seek.py --minutes 60 --open-mb 100
"""
from __future__ import annotations

import argparse
import copy
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from groundstation.io.logs import iter_samples, read_log  # noqa: E402
from groundstation.jobs.live import LiveAnalyzer  # noqa: E402
from groundstation.station.hub.session import Session  # noqa: E402

TARGET_SEEK_S = 0.5
TARGET_PLAY_S = 2.0
TABLES = ("mag", "imu", "attitude", "gps", "battery")


def long_log(minutes: float):
    """The mission-clean recording repeated end to end to ``minutes`` (50 Hz IMU and mag)."""
    base = read_log(ROOT / "recordings" / "mission-clean.tlog")
    period = base.duration_s + 0.02
    k = max(1, int(np.ceil(minutes * 60 / period)))
    out = copy.copy(base)
    for name in TABLES:
        a = getattr(base, name)
        parts = []
        for i in range(k):
            b = a.copy()
            b[:, 0] += i * period
            parts.append(b)
        setattr(out, name, np.concatenate(parts) if len(a) else a)
    return out


def per_sample_rate(log, seconds: float = 60.0) -> float:
    """Log seconds per wall second of the per-sample path (LiveAnalyzer) on the first minute."""
    live = LiveAnalyzer(None, [p[:2] for p in log.mission] or None, log.start_unix_s)
    t0 = time.perf_counter()
    last = 0.0
    for s in iter_samples(log):
        if s.t_s > seconds:
            break
        if live.accepts(s):
            live.on_sample(s)
        last = s.t_s
    return last / (time.perf_counter() - t0)


def until_playing(session: Session, t0: float, timeout_s: float = 1800.0,
                  analysis: bool = True) -> tuple[float, float | None]:
    """(s from t0 to the first sample the replay pushed, s to the whole-log analysis in; None
    unless ``analysis``: then it returns at the first sample)."""
    first = None
    while time.perf_counter() - t0 < timeout_s:
        if first is None and session.sources.rx_count > 0:
            first = time.perf_counter() - t0
            if not analysis:
                return first, None
        if not session.snapshot()["analysing"]:
            return (first if first is not None else time.perf_counter() - t0), time.perf_counter() - t0
        time.sleep(0.005)
    raise TimeoutError("the replay did not start or its analysis did not finish")


def open_file(mb: float) -> dict:
    """Open an ``mb``-MB tlog by name (read, replayer, play) and time it to the first sample."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from ingest import write_tlog

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "big.tlog"
        write_tlog(path, mb / 40.6 * 120.0)          # 40.6 MB per 2 hours of this stream
        session = Session(tmp, record_live=False)
        try:
            t0 = time.perf_counter()
            session.start_replay(path, speed=1.0)
            opened = time.perf_counter() - t0
            first_s, _ = until_playing(session, t0, analysis=False)
            analysing = session.snapshot()["analysing"]
        finally:
            session.close()
        return {"mb": path.stat().st_size / 2**20, "opened_s": opened, "first_s": first_s, "analysing": analysing}


def run(minutes: float, seeks: int, seed: int = 0) -> dict:
    log = long_log(minutes)
    rng = np.random.default_rng(seed)
    with tempfile.TemporaryDirectory() as tmp:
        session = Session(tmp, record_live=False)
        try:
            from groundstation.io.replay import Replayer
            r0 = time.perf_counter()
            Replayer(log)
            replayer_s = time.perf_counter() - r0
            t0 = time.perf_counter()
            session.start_replay(Path(tmp) / "long.tlog", speed=1.0, flight_log=log)
            first_s, ready_s = until_playing(session, t0)
            session.replay_pause(True)
            times = []
            points = np.r_[log.duration_s * 0.999, 1.0, rng.uniform(0, log.duration_s, max(0, seeks - 2))]
            for t in points:
                s0 = time.perf_counter()
                session.replay_seek(float(t))
                session.snapshot_json()
                session.plot_data(60.0)
                session.alarm_list()
                session.scene_data()
                times.append(time.perf_counter() - s0)
            snap = session.snapshot()
        finally:
            session.close()
    return {"duration_s": log.duration_s, "imu_rows": len(log.imu), "ready_s": ready_s, "first_s": first_s,
            "seek_s": times,
            "replayer_s": replayer_s,
            "per_sample_rate": per_sample_rate(log), "t_after": snap["t_s"]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--seeks", type=int, default=20)
    ap.add_argument("--open-mb", type=float, default=0.0,
                    help="also write a tlog of this size and time opening it by name (0: not)")
    args = ap.parse_args(argv)
    r = run(args.minutes, args.seeks)
    seek = np.asarray(r["seek_s"])
    peer_end = r["duration_s"] / r["per_sample_rate"]
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"log: {r['duration_s'] / 60:.1f} min, {r['imu_rows']} IMU rows at 50 Hz; load average {load:.1f} "
          f"on {os.cpu_count()} cores")
    print(f"whole-log analysis in (beside the playing replay): {r['ready_s']:.2f} s after the start (once per "
          f"replay, and after a calibration or line change)")
    print(f"replayer made (every sample of the log, ready to play and seek): {r['replayer_s']:.3f} s")
    print(f"open -> playing (the log already read): first sample pushed after {r['first_s']:.3f} s, the "
          f"analysis in after {r['ready_s']:.2f} s")
    if args.open_mb > 0:
        o = open_file(args.open_mb)
        print(f"open a {o['mb']:.1f} MB tlog by name -> playing: {o['first_s']:.2f} s (read + replayer "
              f"{o['opened_s']:.2f} s; {'still analysing then' if o['analysing'] else 'analysed by then'}), "
              f"target < {TARGET_PLAY_S:g} s: {'met' if o['first_s'] < TARGET_PLAY_S else 'MISSED'}")
    print("| path | seek median s | seek max s | seeks |")
    print("|---|---|---|---|")
    print(f"| station (whole-log analysis + cursor) | {np.median(seek):.3f} | {seek.max():.3f} | {len(seek)} |")
    print(f"| per-sample re-run up to the seek point (LiveAnalyzer, {r['per_sample_rate']:.0f}x real time) | "
          f"{peer_end / 2:.1f} | {peer_end:.1f} | extrapolated |")
    ok = seek.max() < TARGET_SEEK_S
    print(f"target: every seek < {TARGET_SEEK_S:g} s in a 1-hour 50 Hz log: "
          f"{'met' if ok else 'MISSED'} (worst {seek.max():.3f} s over {args.minutes:g} min)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
