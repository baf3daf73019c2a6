"""A tlog through the live path, packet by packet, as a link delivers it (for tests).

``live_alarms_and_rows(path, folder, calibration, line)``: the tlog's packets in file order go
through ``MavlinkDecoder`` and ``Session.process_batch`` (the link worker's call) with the given
calibration and preset line; returns the session's alarms and its flight record rows.
"""
from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np

from groundstation.io.decode import MavlinkDecoder
from groundstation.io.logs import tlog_records
from groundstation.station.hub.session import Session


def live_alarms_and_rows(path: Path, folder: Path, calibration: dict | None,
                         line: dict | None) -> tuple[list[dict], np.ndarray]:
    session = Session(folder, record_live=False)
    with session._lock:
        session.flight.new_source(None)
        session.flight.set_calibration(calibration)
        session.flight.set_line(line)
    dec = MavlinkDecoder()
    t0 = None
    batch = []
    for unix, msg in tlog_records(path.read_bytes(), Counter()):
        t0 = unix if t0 is None else t0
        batch += dec.decode(msg, unix - t0)
        if len(batch) > 200:
            with session._lock:
                session.process_batch(batch)     # the worker's call: samples wait in time order
            batch = []
    session.feed(batch)
    alarms, rows = session.alarm_list(), session.flight.rows().copy()
    session.close()
    return alarms, rows
