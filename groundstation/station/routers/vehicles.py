"""The systems heard on the live link and the vehicle the station follows."""
from __future__ import annotations

from fastapi import APIRouter
from pydantic import BaseModel, Field

from groundstation.station.deps import HubDep

router = APIRouter(prefix="/api", tags=["vehicles"])


class VehicleSelect(BaseModel):
    sysid: int = Field(ge=1, le=255, description="MAVLink system id of a vehicle heard on the link")


@router.get("/vehicles", summary="Every system heard on the live link; the followed vehicle; passive "
                                 "mode, signing counts and forwarding outputs")
def vehicles(hub: HubDep) -> dict:
    return hub.vehicles()


@router.post("/vehicles/select", summary="Follow another vehicle: estimation, alarms and the wizard start over")
def select_vehicle(req: VehicleSelect, hub: HubDep) -> dict:
    return hub.select_vehicle(req.sysid)
