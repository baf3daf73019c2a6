"""The source: a live connection string or a recording from recordings/."""
from __future__ import annotations

from fastapi import APIRouter, HTTPException, Request

from groundstation.io.errors import IngestError
from groundstation.io.link import validate_connection_string
from groundstation.station.deps import HubDep
from groundstation.station.schemas import Ok, SourceInfo, SourceRequest

router = APIRouter(prefix="/api", tags=["source"])


@router.get("/recordings", response_model=list[str])
def recordings(hub: HubDep) -> list[str]:
    return hub.recording_names()


@router.post("/source", response_model=SourceInfo,
             summary="Choose the source: a live connection string or a recording name")
def choose_source(req: SourceRequest, hub: HubDep, request: Request) -> dict:
    if (req.connect is None) == (req.recording is None):
        raise HTTPException(400, detail="give exactly one of 'connect' or 'recording'")
    if req.connect is not None:
        try:   # a request may open listeners on loopback only, unless the station is in remote mode
            url = validate_connection_string(req.connect, listen_any=request.app.state.access.remote)
        except IngestError as err:
            raise HTTPException(400, detail=str(err)) from err
        hub.connect(url)
    else:
        hub.start_replay(hub.resolve_recording(req.recording), req.speed, req.loop)
    return hub.snapshot()["source"]


@router.post("/source/stop", response_model=Ok)
def stop_source(hub: HubDep) -> Ok:
    hub.stop()
    return Ok(message="stopped")
