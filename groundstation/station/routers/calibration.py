"""The guided calibration: start, reset, finish, accept (writes the vehicle), .param export."""
from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, Query
from fastapi.responses import PlainTextResponse, Response

from groundstation.io.params import format_param_file
from groundstation.station.deps import HubDep
from groundstation.station.hub.session import NotFoundError
from groundstation.station.schemas import ParamWrite, Wizard

router = APIRouter(prefix="/api/calibration", tags=["calibration"])


@router.get("", response_model=Wizard)
def calibration(hub: HubDep) -> dict:
    return hub.snapshot()["wizard"]


@router.post("/start", response_model=Wizard)
def calibration_start(hub: HubDep) -> dict:
    hub.wizard_start()
    return hub.snapshot()["wizard"]


@router.post("/reset", response_model=Wizard)
def calibration_reset(hub: HubDep) -> dict:
    hub.wizard_reset()
    return hub.snapshot()["wizard"]


@router.post("/finish", response_model=Wizard, summary="Fit now with what was collected (skip the remaining steps)")
def calibration_finish(hub: HubDep) -> dict:
    hub.wizard_finish_now()
    return hub.snapshot()["wizard"]


@router.post("/accept", response_model=ParamWrite,
             summary="Use the result; on a live link write it to the vehicle (confirmed by echo)")
def calibration_accept(hub: HubDep) -> dict:
    return hub.wizard_accept()


@router.get("/params", response_class=PlainTextResponse, summary="The result as an autopilot .param file")
def calibration_params(hub: HubDep, autopilot: Literal["ardupilot", "px4"] | None = Query(None)) -> Response:
    snap = hub.snapshot()
    result = snap["wizard"]["result"]
    if not result or result.get("status") != "ok":
        raise NotFoundError("no successful calibration result yet")
    ap = autopilot or snap["source"]["autopilot"] or "ardupilot"
    params = result.get(f"{ap}_params") or {}
    if not params:
        raise NotFoundError(f"the result has no {ap} parameters")
    return PlainTextResponse(format_param_file(params), headers={
        "Content-Disposition": f'attachment; filename="magstation-{ap}.param"'})
