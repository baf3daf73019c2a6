"""The compass calibration: guided dance, onboard and large-vehicle modes, accept/write, reboot, heading
check, .param export."""
from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import PlainTextResponse, Response

from groundstation.io.magcal import section_centres
from groundstation.io.params import format_param_file
from groundstation.station.deps import HubDep
from groundstation.station.hub.session import NotFoundError
from groundstation.station.hub.in_use import MAX_CALIBRATION_UPLOAD_BYTES, InUseError
from groundstation.station.schemas import (AcceptRequest, CalibrationStart, CompassInclude, FixedYawRequest, Fitness,
                                           HeadingCheckRequest, ParamWrite, RebootRequest, Wizard)

router = APIRouter(prefix="/api/calibration", tags=["calibration"])


def _wizard(hub) -> dict:
    return hub.snapshot()["wizard"]


@router.get("", response_model=Wizard)
def calibration(hub: HubDep) -> dict:
    return _wizard(hub)


@router.post("/start", response_model=Wizard,
             summary="Start: guided dance, the vehicle's onboard calibrator, or large-vehicle (fixed yaw)")
def calibration_start(hub: HubDep, body: CalibrationStart | None = None) -> dict:
    hub.wizard_start((body or CalibrationStart()).mode)
    return _wizard(hub)


@router.post("/reset", response_model=Wizard)
def calibration_reset(hub: HubDep) -> dict:
    hub.wizard_reset()
    return _wizard(hub)


@router.post("/finish", response_model=Wizard, summary="Fit now with what was collected (skip the remaining steps)")
def calibration_finish(hub: HubDep) -> dict:
    hub.wizard_finish_now()
    return _wizard(hub)


@router.put("/compasses/{index}", response_model=Wizard, summary="Include a compass or leave it out")
def calibration_compass(hub: HubDep, index: int, body: CompassInclude) -> dict:
    hub.calibration.set_included(index, body.included)
    return _wizard(hub)


@router.put("/fitness", response_model=Wizard, summary="Fitness threshold (ArduPilot COMPASS_CAL_FIT levels)")
def calibration_fitness(hub: HubDep, body: Fitness) -> dict:
    hub.calibration.set_fitness(body.level)
    return _wizard(hub)


@router.post("/accept", response_model=ParamWrite,
             summary="Use the result; on a live link write it (confirmed by echo), or accept the vehicle's own fit")
def calibration_accept(hub: HubDep, body: AcceptRequest | None = None) -> dict:
    return hub.calibration.accept((body or AcceptRequest()).which)


@router.post("/onboard/cancel", response_model=Wizard, summary="Cancel the vehicle's calibrator")
def calibration_onboard_cancel(hub: HubDep) -> dict:
    hub.calibration.cancel_onboard()
    return _wizard(hub)


@router.post("/fixed-yaw", response_model=Wizard,
             summary="Large vehicle: MAV_CMD_FIXED_MAG_CAL_YAW with the entered heading or the walk's GPS course")
def calibration_fixed_yaw(hub: HubDep, body: FixedYawRequest) -> dict:
    hub.calibration.fixed_yaw(body.yaw_deg, body.source)
    return _wizard(hub)


@router.post("/reboot", response_model=Wizard, summary="Reboot the vehicle (needs confirm: true)")
def calibration_reboot(hub: HubDep, body: RebootRequest) -> dict:
    hub.calibration.reboot(body.confirm)
    return _wizard(hub)


@router.post("/heading-check", response_model=Wizard,
             summary="Heading check: held at a known bearing, or a straight walk (GPS course)")
def calibration_heading_check(hub: HubDep, body: HeadingCheckRequest) -> dict:
    hub.calibration.heading_check(body.kind, body.bearing_deg)
    return _wizard(hub)


@router.post("/heading-check/stop", response_model=Wizard, summary="End the walk and compare with its GPS course")
def calibration_heading_check_stop(hub: HubDep) -> dict:
    hub.calibration.stop_walk()
    return _wizard(hub)


@router.get("/sections", summary="Unit vectors of the 80 sections of MAG_CAL_PROGRESS's completion mask")
def calibration_sections() -> list[list[float]]:
    return [[round(float(v), 4) for v in c] for c in section_centres()]


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


# ---------------------------------------------------------------------------- the calibration in use
@router.get("/in-use", summary="The calibration in use, where it came from, and the sources to choose from")
def calibration_in_use(hub: HubDep) -> dict:
    with hub._lock:
        return hub.in_use.options()


@router.post("/in-use", summary="Choose the calibration in use: {source: log|recording|wizard|history|vehicle|none, "
                                "name: recording}")
def calibration_in_use_choose(hub: HubDep, body: dict) -> dict:
    source, name = body.get("source"), body.get("name")
    if not isinstance(source, str) or (name is not None and not isinstance(name, str)):
        raise InUseError("give {\"source\": ..., \"name\": recording} as strings")
    return hub.in_use.choose(source[:40], None if name is None else name[:255])


@router.post("/in-use/upload", summary="Upload a calibrate JSON or a vehicle .param file (raw body) and use it")
async def calibration_in_use_upload(request: Request, hub: HubDep,
                                    filename: str = Query(..., min_length=1, max_length=255)) -> dict:
    data = bytearray()
    async for chunk in request.stream():
        data += chunk
        if len(data) > MAX_CALIBRATION_UPLOAD_BYTES:
            raise InUseError(f"'{filename[:60]}': larger than {MAX_CALIBRATION_UPLOAD_BYTES >> 20} MiB")
    return await run_in_threadpool(hub.in_use.upload, filename, bytes(data))
