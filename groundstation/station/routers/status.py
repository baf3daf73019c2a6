"""Station health and the full state snapshot."""
from __future__ import annotations

import time

from fastapi import APIRouter, Request

from groundstation.station.deps import HubDep, PusherDep
from groundstation.station.schemas import Health, State

router = APIRouter(prefix="/api", tags=["station"])


@router.get("/health", response_model=Health)
def health(hub: HubDep, pusher: PusherDep, request: Request) -> Health:
    return Health(uptime_s=round(time.time() - request.app.state.started_unix_s, 1),
                  source=hub.snapshot()["source"]["kind"], viser_port=request.app.state.viser_port,
                  clients=len(pusher.clients))


@router.get("/state", response_model=State)
def state(hub: HubDep) -> dict:
    return hub.snapshot()
