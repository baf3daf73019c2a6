"""ArduPilot DataFlash logs (.bin): pymavlink's DFReader indexes the records, numpy decodes them.

DFReader (its C indexer) finds every record and learns the FMT layouts; the records
``recv_match(type=WANTED)`` would return are then decoded type by type, each type's records one
numpy structured array built from its FMT format characters (``_FMT_DTYPE``), with DFReader's
value rules (c/C/e/E / 100, L / 1e7, text decoded UTF-8 else Latin-1 up to the first NUL), and
turned into samples with ``DataFlashDecoder``'s rules on whole columns (``_BulkDecoder``).

Falls back to the per-record path (``_read_messages_per_record``, DFReader's ``recv_match`` and
``DataFlashDecoder`` message by message) for the rare structures whose per-record behaviour is
not reproduced column-wise: a FMT whose Length does not match its format or whose column and
format counts differ, a message type named twice, a wanted record missing a column its handler
needs, a non-finite float where an integer is read.  DFReader's own side effects of reading
(``_add_msg`` complaining about a record) are not reproduced.
"""
from __future__ import annotations

import os
import re
import sys
import threading
from collections import Counter
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

from .quiet import counting, quiet, record
from ..errors import IngestError
from .builder import LogBuilder
from .dataflash_columns import build_log as _build_bulk_log, decode_records, take_records
from .dataflash_messages import WANTED, DataFlashDecoder
from ...samples import FlightLog

__all__ = ["read_dataflash"]


# pymavlink's DataFlash reader prints a line per skipped byte ("bad header ... at N"): a megabyte of
# garbage is a million lines.  We count instead: its Python prints through ``quiet`` (quiet.py); its
# C indexer (dfindexer) writes to fd 2 itself while holding the GIL (a pipe would deadlock), so fd 2
# points at /dev/null while it runs (milliseconds) and the skipped bytes are counted from its index.
BAD_HEADER = "bad DataFlash header bytes skipped"
_READER_LINES = ((re.compile(r"^bad header"), BAD_HEADER, None),
                 (re.compile(r"^Skipped (\d+) bad bytes"), "DataFlash bytes skipped between messages", 1),
                 (re.compile(r"^unknown msg type"), "DataFlash: unknown message type (rest of the log not indexed)", None),
                 (re.compile(r"^Failed to parse"), "DataFlash: unparseable messages skipped", None))


def _classify(line: str) -> tuple[str, int]:
    for pattern, key, group in _READER_LINES:
        found = pattern.match(line)
        if found:
            return key, int(found.group(group)) if group else 1
    return "DataFlash reader complaints", 1


_fd2_lock = threading.Lock()


@contextmanager
def _fd2_to_devnull() -> Iterator[None]:
    """fd 2 -> /dev/null for the duration (process-wide: held briefly, one reader at a time)."""
    with _fd2_lock:
        sys.stderr.flush()
        saved = os.dup(2)
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, 2)
        os.close(null)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)


def _close_reader(reader) -> None:
    """Close a DFReader's map and file; its file even when the map cannot close yet (a view of it is
    still alive: the garbage collector frees the map, and an mmap outlives its file descriptor)."""
    data_map, handle = getattr(reader, "data_map", None), getattr(reader, "filehandle", None)
    if data_map is not None:
        try:
            data_map.close()
        except (BufferError, OSError, ValueError):
            pass
    if handle is not None:
        handle.close()


def _open_reader(path: Path):
    from pymavlink import DFReader

    class QuietReader(DFReader.DFReader_binary):
        def __init__(self, *args, **kwargs):
            try:
                super().__init__(*args, **kwargs)
            except BaseException:     # pymavlink leaves its file open when the header cannot be read
                _close_reader(self)
                raise

        def init_arrays_fast(self, progress_callback=None):
            with _fd2_to_devnull():
                super().init_arrays_fast(progress_callback=progress_callback)
            covered = sum(self.counts[t] * fmt.len for t, fmt in self.formats.items() if 0 <= t < 256)
            if self.data_len > covered:
                record(BAD_HEADER, self.data_len - covered)

    quiet(DFReader, _classify)
    try:
        return QuietReader(str(path), zero_time_base=False)
    except Exception as err:  # pymavlink raises bare exceptions on unreadable headers
        raise IngestError(f"{path.name}: not a readable DataFlash log ({type(err).__name__})") from err


def read_dataflash(path: Path, progress: Callable[[float], None] | None) -> FlightLog:
    """ArduPilot DataFlash .bin of any generation (TimeMS or TimeUS, MAG/MAG2/MAG3 or MAG with an
    instance column): every compass and IMU, ATT, GPS, current (CURR/BAT/BATT), throttle
    (CTUN/CURR/RCOU), PARM history, CMD, MSG.  See dataflash_messages.py for units and timing.
    pymavlink's per-byte complaints about damage become counted warnings.

    Args:
        path: the .bin file; progress: called with the fraction read (0..1), or None.
    Returns:
        FlightLog (``compasses`` with the logged motor compensation, ``param_history`` with the
        MAG Ofs* changes as COMPASS_OFS{n}_*); damage is counted in ``warnings``.
    Raises:
        IngestError: the header cannot be read at all.
    """
    counts: Counter = Counter()
    with counting(counts):
        reader = _open_reader(path)
        try:
            taken = take_records(reader)
        finally:
            _close_reader(reader)
        del reader              # its index (a list of offsets a message type) and map, before decoding
        decoded = decode_records(taken) if taken is not None else None
        del taken               # the records' columns: freed once decoded
        if decoded is None:     # a structure read record by record: indexed again, its complaints once
            counts.clear()
            reader = _open_reader(path)
            try:
                log = _read_messages_per_record(path, progress, reader)
            finally:
                _close_reader(reader)
        else:
            log = _build_bulk_log(path, progress, decoded)
    log.warnings.update(counts)
    return log


def _read_messages_per_record(path: Path, progress: Callable[[float], None] | None, reader) -> FlightLog:
    """The fallback: DFReader's recv_match and DataFlashDecoder, one record at a time."""
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
