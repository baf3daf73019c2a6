"""Interference alarms of this session."""
from __future__ import annotations

from fastapi import APIRouter

from groundstation.station.deps import HubDep
from groundstation.station.schemas import Alarm

router = APIRouter(prefix="/api", tags=["alarms"])


@router.get("/alarms", response_model=list[Alarm])
def alarms(hub: HubDep) -> list[dict]:
    return hub.alarm_list()
