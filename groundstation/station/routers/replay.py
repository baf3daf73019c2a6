"""Replay controls: start, stop, pause, seek, speed, and the timeline of the replayed log."""
from __future__ import annotations

from fastapi import APIRouter

from groundstation.station.deps import HubDep
from groundstation.station.hub.session import ConflictError
from groundstation.station.schemas import Ok, Pause, ReplayInfo, ReplayStart, Seek, Speed, Timeline

router = APIRouter(prefix="/api/replay", tags=["replay"])


@router.post("/start", response_model=ReplayInfo)
def replay_start(req: ReplayStart, hub: HubDep) -> dict:
    hub.start_replay(hub.resolve_recording(req.recording), req.speed, req.loop)
    info = hub.snapshot()["replay"]
    if info is None:        # a stop (or another source) came in between: say so, not a 500
        raise ConflictError("the replay was stopped as it started (another request changed the source)")
    return info


@router.post("/stop", response_model=Ok)
def replay_stop(hub: HubDep) -> Ok:
    if hub.replay is None:
        raise ConflictError("no replay running")
    hub.stop()
    return Ok(message="replay stopped")


@router.post("/pause", response_model=ReplayInfo)
def replay_pause(req: Pause, hub: HubDep) -> dict:
    hub.replay_pause(req.paused)
    return hub.snapshot()["replay"]


@router.post("/seek", response_model=ReplayInfo)
def replay_seek(req: Seek, hub: HubDep) -> dict:
    hub.replay_seek(req.t_s)
    return hub.snapshot()["replay"]


@router.post("/speed", response_model=ReplayInfo)
def replay_speed(req: Speed, hub: HubDep) -> dict:
    hub.replay_speed(req.speed)
    return hub.snapshot()["replay"]


@router.get("/timeline", response_model=Timeline,
            summary="Markers of the replayed log: alarms, GPS outages, data gaps, vehicle messages")
def replay_timeline(hub: HubDep) -> dict:
    return hub.timeline()
