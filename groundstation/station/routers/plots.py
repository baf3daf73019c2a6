"""The page's plots: the last part of the flight record (headings with their references, field
against the WMM, velocity, cross-track) and the alarms in it."""
from __future__ import annotations

from fastapi import APIRouter, Query

from groundstation.station.deps import HubDep
from groundstation.station.schemas import Plots

router = APIRouter(prefix="/api", tags=["plots"])


@router.get("/plots", response_model=Plots)
def plots(hub: HubDep, window_s: float = Query(60.0, ge=5.0, le=3600.0)) -> dict:
    return hub.plot_data(window_s)
