"""Plain CSV dumps (.csv) of the magnetometer, with optional time and attitude columns."""
from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import IngestError
from .builder import clean_table
from ...samples import FlightLog

__all__ = ["read_csv"]


def read_csv(path: Path, progress: Callable[[float], None] | None) -> FlightLog:
    """CSV with columns mx,my,mz (mG) and optional t_s, roll_deg, pitch_deg, yaw_deg."""
    log = FlightLog(source=str(path), mag_calibration_applied=False)
    with open(path, newline="", encoding="utf-8", errors="replace") as f:
        reader = csv.DictReader(f)
        fields = {c.strip().lower(): c for c in (reader.fieldnames or [])}
        if not {"mx", "my", "mz"} <= fields.keys():
            raise IngestError(f"{path.name}: CSV needs columns mx,my,mz (milligauss); found "
                              f"{', '.join(fields) or 'none'}")
        has_att = {"roll_deg", "pitch_deg", "yaw_deg"} <= fields.keys()
        mag, att = [], []
        for i, row in enumerate(reader):
            try:
                t = float(row[fields["t_s"]]) if "t_s" in fields else float(i)
                mag.append((t, float(row[fields["mx"]]), float(row[fields["my"]]), float(row[fields["mz"]])))
                if has_att:
                    att.append((t, *(math.radians(float(row[fields[k]]))
                                     for k in ("roll_deg", "pitch_deg", "yaw_deg"))))
            except (TypeError, ValueError):
                log.warnings["CSV rows that are not numbers skipped"] += 1
    log.message_counts["csv rows"] = len(mag)
    log.mag = clean_table(np.asarray(mag, dtype=float).reshape(-1, 4), "mag", log.warnings)
    log.attitude = clean_table(np.asarray(att, dtype=float).reshape(-1, 4), "attitude", log.warnings)
    if len(log.mag):
        t0 = log.mag[0, 0]
        log.mag[:, 0] -= t0
        if len(log.attitude):
            log.attitude[:, 0] -= t0
    return log
