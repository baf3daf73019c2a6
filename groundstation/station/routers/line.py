"""The preset line the route is judged against."""
from __future__ import annotations

from fastapi import APIRouter

from groundstation.station.deps import HubDep
from groundstation.station.schemas import Line, Ok

router = APIRouter(prefix="/api/line", tags=["line"])


@router.get("", response_model=Line | None)
def get_line(hub: HubDep) -> dict | None:
    return hub.snapshot()["line"]


@router.put("", response_model=Line, summary="Set the preset line by coordinates")
def put_line(line: Line, hub: HubDep) -> dict:
    return hub.set_line(line.a, line.b, "user")


@router.delete("", response_model=Ok, summary="Clear the preset line (no path-deviation test)")
def delete_line(hub: HubDep) -> Ok:
    hub.clear_line()
    return Ok(message="preset line cleared")


@router.post("/from-mission", response_model=Line, summary="Set the preset line from the first and last mission waypoints")
def line_from_mission(hub: HubDep) -> dict:
    return hub.line_from_mission()
