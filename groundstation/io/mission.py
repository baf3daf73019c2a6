"""Preset lines (missions) from Mission Planner `.waypoints`, QGroundControl `.plan` and logs.

A mission is a list of (lat_deg, lon_deg, alt_m) navigation waypoints in order; the preset
line of the interference test is the leg between consecutive waypoints.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

from .decode import MAV_CMD_NAV_WAYPOINT
from .errors import IngestError
from .logs import read_log

Waypoint = tuple[float, float, float]
MAX_MISSION_BYTES = 20 << 20      # a mission file is kilobytes; refuse to parse anything huge


def _read_text(path: Path) -> str:
    if path.stat().st_size > MAX_MISSION_BYTES:
        raise IngestError(f"{path.name}: {path.stat().st_size} bytes is too large for a mission file")
    return path.read_text(encoding="utf-8", errors="replace")


def _number(value: object) -> float | None:
    """A finite JSON number (not a bool), else None."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def _valid(lat: float, lon: float) -> bool:
    return -90 <= lat <= 90 and -180 <= lon <= 180 and not (lat == 0 and lon == 0)


def read_waypoints_file(path: Path) -> list[Waypoint]:
    """Mission Planner `QGC WPL 110`: tab-separated INDEX CURRENT FRAME COMMAND P1-P4 LAT LON ALT
    AUTOCONTINUE.  Item 0 is home and is not part of the route."""
    lines = _read_text(path).splitlines()
    if not lines or not lines[0].startswith("QGC WPL"):
        raise IngestError(f"{path.name}: not a QGC WPL waypoint file (first line must be 'QGC WPL 110')")
    route: list[Waypoint] = []
    for line in lines[1:]:
        cols = line.split()
        if len(cols) < 12:
            continue
        try:
            index, command = int(cols[0]), int(cols[3])
            lat, lon, alt = float(cols[8]), float(cols[9]), float(cols[10])
        except ValueError:
            continue
        if index != 0 and command == MAV_CMD_NAV_WAYPOINT and _valid(lat, lon) and math.isfinite(alt):
            route.append((lat, lon, alt))
    return route


def read_plan_file(path: Path) -> list[Waypoint]:
    """QGroundControl `.plan` JSON: mission.items[] of SimpleItem with params[4:7] = lat, lon, alt.
    Items that are not objects, or whose coordinates are not finite numbers, are skipped.

    Raises:
        IngestError: not JSON (or nested too deeply), no ``mission.items`` list, too few waypoints.
    """
    try:
        plan = json.loads(_read_text(path))
    except (ValueError, RecursionError) as err:        # JSONDecodeError is a ValueError
        raise IngestError(f"{path.name}: not a QGroundControl .plan file ({str(err)[:120]})") from err
    mission = plan.get("mission") if isinstance(plan, dict) else None
    items = mission.get("items") if isinstance(mission, dict) else None
    if not isinstance(items, list):
        raise IngestError(f"{path.name}: not a QGroundControl .plan file (no mission.items list)")
    route: list[Waypoint] = []
    skipped = 0
    for item in items:
        if not isinstance(item, dict):
            skipped += 1
            continue
        if item.get("type") != "SimpleItem" or item.get("command") != MAV_CMD_NAV_WAYPOINT:
            continue
        params = item.get("params")
        coords = [_number(p) for p in params[4:7]] if isinstance(params, list) and len(params) >= 7 else [None]
        if None in coords or not _valid(coords[0], coords[1]):
            skipped += 1
            continue
        route.append((coords[0], coords[1], coords[2]))
    if len(route) < 2 and skipped:
        raise IngestError(f"{path.name}: needs at least two waypoints to define a preset line (found "
                          f"{len(route)}; {skipped} items were not valid mission items)")
    return route


def read_mission(path: str | Path) -> list[Waypoint]:
    """Waypoints of a `.waypoints`/`.txt` (QGC WPL), `.plan`, or a log's uploaded mission."""
    path = Path(path)
    if not path.is_file():
        raise IngestError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix in (".waypoints", ".txt", ".mission"):
        route = read_waypoints_file(path)
    elif suffix == ".plan":
        route = read_plan_file(path)
    else:
        route = read_log(path).mission
    if len(route) < 2:
        raise IngestError(f"{path.name}: needs at least two waypoints to define a preset line "
                          f"(found {len(route)})")
    return route
