"""Preset lines (missions) from Mission Planner `.waypoints`, QGroundControl `.plan` and logs.

A mission is a list of (lat_deg, lon_deg, alt_m) navigation waypoints in order; the preset
line of the interference test is the leg between consecutive waypoints.
"""
from __future__ import annotations

import json
from pathlib import Path

from .decode import MAV_CMD_NAV_WAYPOINT
from .errors import IngestError
from .logs import read_log

Waypoint = tuple[float, float, float]


def _valid(lat: float, lon: float) -> bool:
    return -90 <= lat <= 90 and -180 <= lon <= 180 and not (lat == 0 and lon == 0)


def read_waypoints_file(path: Path) -> list[Waypoint]:
    """Mission Planner `QGC WPL 110`: tab-separated INDEX CURRENT FRAME COMMAND P1-P4 LAT LON ALT
    AUTOCONTINUE.  Item 0 is home and is not part of the route."""
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
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
        if index != 0 and command == MAV_CMD_NAV_WAYPOINT and _valid(lat, lon):
            route.append((lat, lon, alt))
    return route


def read_plan_file(path: Path) -> list[Waypoint]:
    """QGroundControl `.plan` JSON: mission.items[] of SimpleItem with params[4:7] = lat, lon, alt."""
    try:
        plan = json.loads(path.read_text(encoding="utf-8"))
        items = plan["mission"]["items"]
    except (json.JSONDecodeError, KeyError, TypeError) as err:
        raise IngestError(f"{path.name}: not a QGroundControl .plan file ({err})") from err
    route: list[Waypoint] = []
    for item in items:
        if item.get("type") != "SimpleItem" or item.get("command") != MAV_CMD_NAV_WAYPOINT:
            continue
        params = item.get("params") or []
        if len(params) >= 7 and all(isinstance(p, (int, float)) for p in params[4:7]):
            lat, lon, alt = (float(p) for p in params[4:7])
            if _valid(lat, lon):
                route.append((lat, lon, alt))
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
