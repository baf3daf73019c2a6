"""Numbers and names as a person reads them in terminal and report text: one place for "n/a"
instead of ``None mG``, no ``-0.0``, time spans, coordinates, test and GPS fix names."""
from __future__ import annotations

import math

__all__ = ["FIX_NAMES", "TEST_NAMES", "fix_name", "lat_lon", "num", "score_name", "span_s", "without_status"]

# MAVLink GPS_FIX_TYPE (common.xml)
FIX_NAMES = {0: "no GPS", 1: "no fix", 2: "2D fix", 3: "3D fix", 4: "DGPS", 5: "RTK float", 6: "RTK fixed",
             7: "static", 8: "PPP"}
# the detection's tests (groundstation.jobs.alarm_explain.SCORE_NAMES) and single-test alarm kinds
TEST_NAMES = {"heading_difference": "heading difference", "path_deviation": "path deviation",
              "field_strength_inclination": "field strength / inclination", "field_vector": "field vector",
              "field_anomaly": "field anomaly", "combined": "combined"}


def num(value, fmt: str = "{:.1f}", unit: str = "") -> str:
    """``value`` formatted with ``fmt`` and `` unit``; "n/a" (no unit) when missing or not finite;
    a value that rounds to zero is shown without a minus sign."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    text = fmt.format(value)
    if text.startswith("-") and text.strip("-0.%") == "":
        text = text[1:]
    return f"{text} {unit}" if unit else text


def span_s(start_s, end_s, fmt: str = "{:.0f}") -> str:
    """A time span in seconds, ``12–80 s``; an open end reads ``12 s–end``."""
    if end_s is None:
        return f"{num(start_s, fmt)} s–end"
    return f"{num(start_s, fmt)}–{num(end_s, fmt)} s"


def lat_lon(lat_deg: float, lon_deg: float, digits: int = 6) -> str:
    """``30.260000 N, 120.120000 E`` (6 digits: 0.1 m)."""
    return (f"{abs(lat_deg):.{digits}f} {'N' if lat_deg >= 0 else 'S'}, "
            f"{abs(lon_deg):.{digits}f} {'E' if lon_deg >= 0 else 'W'}")


def score_name(kind: str) -> str:
    return TEST_NAMES.get(kind, kind.replace("_", " "))


def fix_name(fix_type) -> str:
    try:
        return FIX_NAMES.get(int(fix_type), f"fix type {int(fix_type)}")
    except (TypeError, ValueError):
        return "n/a"


def without_status(status: str, message: str) -> str:
    """``message`` without a leading ``status:`` (``ambiguous: ambiguous: ...`` reads once)."""
    text = str(message or "")
    head = f"{status}:"
    return text[len(head):].lstrip() if text.startswith(head) else text
