"""Vehicle parameter files (.param) in and the parameters in force of a log from them.

Formats read (one parameter a line; ``#`` comments and blank lines allowed):

* Mission Planner / ArduPilot ``NAME,VALUE``
* MAVProxy / QGroundControl ``NAME VALUE`` (spaces or tabs)
* QGroundControl's parameter export, tab-separated ``VEHICLE COMPONENT NAME VALUE TYPE``

Every other line (a name that is not an ArduPilot/PX4 identifier, a value that is not a finite
number, too many fields) is counted and skipped; the caller prints one warning with the count and
the first such line.  Files are read as bytes with a size limit (``MAX_PARAM_FILE_BYTES``), decoded
as UTF-8 with replacement: a hostile file gives skipped lines, never an exception other than
``ParamFileError`` (one line).

``apply_to_log(log, values, source)`` makes the values the log's parameters in force where the log
has none of its own; ``UNCALIBRATED_ARDUPILOT`` / ``uncalibrated_px4()`` are the autopilots' defaults
for a vehicle that was never calibrated (``--assume-uncalibrated``).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

from estimators.compass_corrections import ardupilot_param_names

__all__ = ["ParamFile", "ParamFileError", "read_param_file", "parse_param_text", "apply_to_log",
           "uncalibrated_params", "MAX_PARAM_FILE_BYTES", "MAX_PARAMS"]

MAX_PARAM_FILE_BYTES = 4 << 20      # a full ArduPilot parameter file is ~40 kB
MAX_PARAMS = 20000                  # ArduPilot has ~1500 parameters; PX4 ~1200
_NAME = re.compile(r"^[A-Z][A-Z0-9_]{0,31}$")   # MAVLink param_id: 16 chars; headroom for other tools


class ParamFileError(ValueError):
    """The file cannot be read as a parameter file at all (one line)."""


@dataclass(frozen=True)
class ParamFile:
    """values: {NAME: value}; skipped: bad lines; first_bad: the first of them (quoted, cut to 60)."""
    values: dict
    skipped: int
    first_bad: str | None
    source: str

    def warning(self) -> str | None:
        if not self.skipped:
            return None
        return f"{self.source}: {self.skipped} line(s) not a parameter, skipped (first: {self.first_bad})"


def _value(text: str) -> float | None:
    try:
        v = float(text)
    except ValueError:
        return None
    return v if math.isfinite(v) and abs(v) < 1e30 else None


def _parse_line(line: str) -> tuple[str, float] | None:
    if "," in line and "\t" not in line:
        parts = [p.strip() for p in line.split(",")]
    else:
        parts = line.split()
    if len(parts) == 2:
        name, value = parts
    elif len(parts) == 5 and parts[0].isdigit() and parts[1].isdigit() and parts[4].isdigit():
        name, value = parts[2], parts[3]          # QGC: vehicle component name value type
    else:
        return None
    v = _value(value)
    if not _NAME.match(name) or v is None:
        return None
    return name, v


def parse_param_text(text: str, source: str = "parameters") -> ParamFile:
    """Parameters of a .param text (see the module docstring); a name given twice keeps the last."""
    values: dict[str, float] = {}
    skipped, first_bad = 0, None
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        got = _parse_line(line)
        if got is None or (got[0] not in values and len(values) >= MAX_PARAMS):
            skipped += 1
            if first_bad is None:
                first_bad = repr(raw.strip()[:60])
            continue
        values[got[0]] = got[1]
    return ParamFile(values, skipped, first_bad, source)


def read_param_file(path: str | Path) -> ParamFile:
    """Read a .param file.  Raises ParamFileError: unreadable, too large, or no parameter in it."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            data = f.read(MAX_PARAM_FILE_BYTES + 1)
    except OSError as err:
        raise ParamFileError(f"{path.name}: cannot read ({err.strerror or err})") from None
    if len(data) > MAX_PARAM_FILE_BYTES:
        raise ParamFileError(f"{path.name}: larger than {MAX_PARAM_FILE_BYTES >> 20} MiB, not a parameter file")
    if b"\x00" in data:
        raise ParamFileError(f"{path.name}: binary data, not a parameter file")
    out = parse_param_text(data.decode("utf-8", errors="replace"), path.name)
    if not out.values:
        raise ParamFileError(f"{path.name}: no NAME,VALUE / NAME VALUE parameter lines"
                             + (f" ({out.skipped} other lines)" if out.skipped else ""))
    return out


def uncalibrated_params(autopilot: str | None, compasses: int = 3) -> dict[str, float]:
    """The compass parameters of a never-calibrated vehicle (the autopilot's defaults): ArduPilot
    COMPASS_OFS* 0, DIA* 0 (identity), ODI* 0, SCALE* 0 (unused), MOT* 0, MOTCT 0; PX4 CAL_MAGn
    offsets 0, scales 1, off-diagonals 0 (rotation left as the log says)."""
    if autopilot == "px4":
        out = {}
        for n in range(compasses):
            for a in "XYZ":
                out.update({f"CAL_MAG{n}_{a}OFF": 0.0, f"CAL_MAG{n}_{a}SCALE": 1.0, f"CAL_MAG{n}_{a}ODIAG": 0.0})
        return out
    out = {"COMPASS_MOTCT": 0.0}
    for k in range(compasses):
        names = ardupilot_param_names(k)
        for group in ("offsets", "diag", "offdiag", "scale", "motor"):
            out.update({n: 0.0 for n in names[group]})
    return out


def _calibration_names(name: str) -> bool:
    return name.startswith(("COMPASS_", "CAL_MAG", "SENS_BOARD_"))


def apply_to_log(log, values: dict[str, float], source: str) -> str:
    """The values become ``log.params`` where the log has no value of its own (a value the log
    reported — PARAM_VALUE, PARM, SENSOR_OFFSETS, DataFlash MAG offsets — wins); returns one line
    saying how many were used.  The log's autopilot is taken from the file when the log has none."""
    from groundstation.io.params import detect_autopilot

    have = set(log.params) | {h[1] for h in log.param_history}
    if any(n.startswith("COMPASS_OFS") for n in have):
        have |= {n for n in values if n.startswith("COMPASS_")}    # the log's own corrections stand
    if any(n.startswith("CAL_MAG") for n in have):
        have |= {n for n in values if n.startswith("CAL_MAG")}
    used = {k: float(v) for k, v in values.items() if k not in have}
    log.params.update(used)
    if log.autopilot is None:
        log.autopilot = detect_autopilot(values)
    n_cal = sum(_calibration_names(k) for k in used)
    if not used:
        return f"{source}: not used (the log has its own parameters)"
    return f"{source}: {len(used)} parameter(s) taken as in force ({n_cal} compass calibration)"
