"""Log readers: every supported file becomes a FlightLog in internal units (groundstation/samples.py).

``read_log(path)`` picks the reader by suffix: MAVLink telemetry (.tlog), ArduPilot DataFlash
(.bin, TimeMS or TimeUS, MAG/MAG2/MAG3 or MAG with an instance column), PX4 ULog (.ulg, every
sensor_mag instance), CSV (.csv).  Every compass and IMU is kept (``FlightLog.compasses`` /
``imus``, the primary also as ``mag`` / ``imu``), with the parameter history, the onboard
calibration events, current and throttle.  Bad input never raises out of ``read_log`` except as an
``IngestError`` with a one-line message (nothing usable at all); damage inside a log (bad CRC,
garbage bytes, NaN fields, time going backwards, truncation) is skipped and counted in
``FlightLog.warnings``.

The binary logs are decoded column-wise with numpy (tlog.py, mavlink_bulk.py, dataflash.py):
pymavlink defines the messages (MAVLink payload layouts, DataFlash FMT records through DFReader's
index), every record of a type is one structured array, and the unit conversions are the numpy
functions the live decoder calls too (decode.py, dataflash_messages.py), so a log read here gives
the numbers the per-message path gives (tests/test_ingest_vectorised.py).  The .tlog reader
frames and decodes a window of the file at a time (the bytes it holds and its temporaries bounded),
but ``read_log`` returns the whole FlightLog: no consumer streams yet.
"""
from __future__ import annotations

import os
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
from typing import Callable, Iterable, Iterator

from ..errors import IngestError
from ...samples import FlightLog
from .builder import ABSURD_VALUE, LogBuilder, clean_table, iter_samples
from .csvlog import read_csv
from .dataflash import read_dataflash
from .tlog import read_tlog, tlog_records
from .ulog import read_ulog

__all__ = ["READERS", "read_log", "read_log_start", "START_SUFFIXES", "load_many", "summarize_rates", "iter_samples", "IngestError",
           "LogBuilder", "clean_table", "tlog_records"]

READERS: dict[str, Callable[[Path, Callable[[float], None] | None], FlightLog]] = {
    ".tlog": read_tlog, ".bin": read_dataflash, ".ulg": read_ulog, ".csv": read_csv,
}


def read_log(path: str | os.PathLike, progress: Callable[[float], None] | None = None) -> FlightLog:
    """Read any supported log into a FlightLog.  Raises IngestError with a one-line message
    when nothing usable can be read (missing file, unknown type, no readable messages).  A log
    without magnetometer samples is returned (``info`` still describes it); the commands that
    need the field say so."""
    path = Path(path)
    reader = READERS.get(path.suffix.lower())
    if path.suffix.lower() == ".px4log":
        raise IngestError(f"{path.name}: old PX4 .px4log (sdlog2) logs are not read; convert it with PX4's "
                          "sdlog2_dump.py to CSV, or log with PX4 v1.5 or later (.ulg)")
    if reader is None:
        raise IngestError(f"{path.name}: unknown log type '{path.suffix}' "
                          f"(supported: {', '.join(READERS)})")
    if not path.is_file():
        raise IngestError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise IngestError(f"{path.name}: file is empty")
    try:
        log = reader(path, progress)
    except IngestError:
        raise
    except Exception as err:  # a reader library failing on damage we did not foresee
        raise IngestError(f"{path.name}: could not be read ({type(err).__name__}: {err})") from err
    if progress is not None:
        progress(1.0)
    _rebase_corrupt_origin(log)
    _drop_absurd_params(log)
    if not (log.params or any(len(t) for t in (log.mag, log.imu, log.attitude, log.gps))):
        raise IngestError(f"{path.name}: no readable messages (is it really a {path.suffix} file?)")
    return log


START_SUFFIXES = (".tlog", ".bin")      # logs whose first part reads as a log of its own


def read_log_start(path: str | os.PathLike, nbytes: int) -> FlightLog:
    """The first ``nbytes`` of a .tlog or DataFlash .bin read as a log of their own (a replay
    plays them while the whole file is read): copied to a private temporary file and read by
    ``read_log``; the record cut at the end counts as a truncated tail.  Its times are the
    whole file's on that part (the boot clock's offset is a running minimum; a file re-based
    later in its length may differ).  Raises IngestError as read_log."""
    path = Path(path)
    if path.suffix.lower() not in START_SUFFIXES:
        raise IngestError(f"{path.name}: only {' and '.join(START_SUFFIXES)} logs are read in parts")
    with tempfile.TemporaryDirectory(prefix="magstation-start-") as tmp:
        part = Path(tmp) / ("start" + path.suffix.lower())
        try:
            with open(path, "rb") as src, open(part, "wb") as dst:
                dst.write(src.read(max(int(nbytes), 0)))
        except OSError as err:
            raise IngestError(f"{path.name}: cannot be read ({err.strerror or err})") from None
        log = read_log(part)
    log.source = str(path)
    return log


def _drop_absurd_params(log: FlightLog) -> None:
    """Parameter values that are NaN, infinite or beyond +-ABSURD_VALUE (as for samples) are
    dropped from ``params`` and ``param_history`` and counted in one warning naming them: nothing
    downstream has to guard an int() or a scale factor against them."""
    def sane(v: float) -> bool:
        return -ABSURD_VALUE < v < ABSURD_VALUE

    bad = sorted({k for k, v in log.params.items() if not sane(v)}
                 | {k for _, k, v in log.param_history if not sane(v)})
    if not bad:
        return
    log.params = {k: v for k, v in log.params.items() if sane(v)}
    log.param_history = [e for e in log.param_history if sane(e[2])]
    log.warnings[f"parameters with a NaN, infinite or absurd value (beyond {ABSURD_VALUE:g}) ignored: "
                 + ", ".join(bad[:6]) + (", ..." if len(bad) > 6 else "")] += len(bad)


TABLES = ("mag", "imu", "attitude", "gps", "battery")
EARLY_TOLERANCE_S = 60.0      # samples this much before the first timestamp: its stamp was corrupt
LATE_TOLERANCE_S = 86400.0    # no table starting within a day of it: same


def _rebase_corrupt_origin(log: FlightLog) -> None:
    """t_s counts from the log's first timestamp; when that one was corrupt (its row dropped as a
    time outlier), every table starts far from 0 (9e12 s): shift them back to start at 0 and say so.
    Every time-bearing part moves: the tables, each compass and IMU (shared arrays once), the
    parameter history, the onboard-calibration and status events."""
    starts = [float(getattr(log, n)[0, 0]) for n in TABLES if len(getattr(log, n))]
    if not starts or -EARLY_TOLERANCE_S <= min(starts) <= LATE_TOLERANCE_S:
        return
    shift = min(starts)
    moved: dict[int, np.ndarray] = {}

    def shifted(table: np.ndarray) -> np.ndarray:
        if id(table) not in moved:
            new = table.copy() if not table.flags.writeable else table
            if len(new):
                new[:, 0] -= shift
            moved[id(table)] = new
        return moved[id(table)]

    for name in TABLES + ("throttle",):
        setattr(log, name, shifted(getattr(log, name)))
    log.compasses = [replace(c, field=shifted(c.field)) for c in log.compasses]
    log.imus = {k: shifted(v) for k, v in log.imus.items()}
    log.param_history = [(t - shift, name, value) for t, name, value in log.param_history]
    for event in log.mag_cal:
        event.t_s -= shift
    for status in log.status:
        status.t_s -= shift
    if log.start_unix_s is not None:
        log.start_unix_s += shift
    log.warnings[f"the first timestamp was corrupt: times re-based by {-shift:.6g} s"] += 1


def summarize_rates(log: FlightLog) -> list[tuple[str, int, float]]:
    """(message type, count, mean rate Hz) sorted by count, for `magstation info`."""
    duration = max(log.duration_s, 1e-9)
    return [(k, v, v / duration) for k, v in log.message_counts.most_common()]


def load_many(paths: Iterable[str | os.PathLike]) -> Iterator[tuple[Path, FlightLog | IngestError]]:
    for p in paths:
        try:
            yield Path(p), read_log(p)
        except IngestError as err:
            yield Path(p), err
