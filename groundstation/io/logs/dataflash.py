"""ArduPilot DataFlash logs (.bin) through pymavlink's DFReader."""
from __future__ import annotations

from pathlib import Path
from typing import Callable

from ..errors import IngestError
from .builder import LogBuilder
from .dataflash_messages import WANTED, DataFlashDecoder
from ...samples import FlightLog

__all__ = ["read_dataflash"]


def _open_reader(path: Path):
    from pymavlink import DFReader

    try:
        return DFReader.DFReader_binary(str(path), zero_time_base=False)
    except Exception as err:  # pymavlink raises bare exceptions on unreadable headers
        raise IngestError(f"{path.name}: not a readable DataFlash log ({type(err).__name__})") from err


def read_dataflash(path: Path, progress: Callable[[float], None] | None) -> FlightLog:
    """ArduPilot DataFlash .bin of any generation (TimeMS or TimeUS, MAG/MAG2/MAG3 or MAG with an
    instance column): every compass and IMU, ATT, GPS, current (CURR/BAT/BATT), throttle
    (CTUN/CURR/RCOU), PARM history, CMD, MSG.  See dataflash_messages.py for units and timing.

    Args:
        path: the .bin file; progress: called with the fraction read (0..1), or None.
    Returns:
        FlightLog (``compasses`` with the logged motor compensation, ``param_history`` with the
        MAG Ofs* changes as COMPASS_OFS{n}_*); damage is counted in ``warnings``.
    Raises:
        IngestError: the header cannot be read at all.
    """
    reader = _open_reader(path)
    return _read_messages(path, progress, reader)


def _read_messages(path: Path, progress: Callable[[float], None] | None, reader) -> FlightLog:
    builder = LogBuilder(str(path))
    log = builder.log
    log.autopilot = "ardupilot"
    decoder = DataFlashDecoder()
    while True:
        try:
            m = reader.recv_match(type=WANTED)
        except Exception as err:  # truncated/corrupt tail inside pymavlink's parser
            log.warnings[f"log truncated or corrupt ({type(err).__name__})"] += 1
            break
        if m is None:
            break
        mtype = m.get_type()
        log.message_counts[mtype] += 1
        try:
            for s in decoder.decode(m, mtype):
                builder.add(s)
            if decoder.history:       # logged offsets, in file order with the PARM records
                for entry in decoder.history:
                    builder.add_history(*entry)
                decoder.history.clear()
        except (AttributeError, TypeError, ValueError, OverflowError) as err:
            log.warnings[f"undecodable {mtype}: {type(err).__name__}"] += 1
        if progress is not None and sum(log.message_counts.values()) % 20000 == 0:
            progress(min(reader.offset / max(reader.data_len, 1), 1.0))
    if reader.data_len - reader.offset > 0:
        log.warnings[f"log truncated: last {reader.data_len - reader.offset} bytes unreadable"] += 1
    throttle_source, throttle = decoder.throttle_samples()
    for s in throttle:
        builder.add(s)
    builder.source_names.update(decoder.source_names)
    log.mag_calibration_applied = True  # ArduPilot logs the corrected field (offsets in OfsX..)
    log = builder.finish()
    if throttle_source:
        log.message_counts[f"throttle from {throttle_source}"] = len(throttle)
    if decoder.gps_week_ms is not None:
        week, ms, t = decoder.gps_week_ms
        log.start_unix_s = 315964800 + week * 604800 + ms * 1e-3 - 18 - t  # GPS epoch, leap s
    return log
