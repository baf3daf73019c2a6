"""Request and response models of the station API (the OpenAPI schema at /docs)."""
from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, Field, StringConstraints


def _no_control_characters(value: str) -> str:
    if any(ord(c) < 0x20 or 0x7F <= ord(c) < 0xA0 for c in value):
        raise ValueError("control characters (a null byte, escape ...) are not allowed")
    return value


RecordingName = Annotated[str, StringConstraints(min_length=1, max_length=255),
                          AfterValidator(_no_control_characters)]
ConnectionString = Annotated[str, StringConstraints(min_length=1, max_length=512),
                             AfterValidator(_no_control_characters)]


class Health(BaseModel):
    status: Literal["ok"] = "ok"
    uptime_s: float
    source: str
    viser_port: int | None
    clients: int


class SourceInfo(BaseModel):
    kind: Literal["none", "live", "replay"]
    name: str
    link: str
    autopilot: str | None
    recording: str | None


class ReplayInfo(BaseModel):
    t_s: float
    duration_s: float
    paused: bool
    speed: float
    finished: bool
    loop: bool


class Vehicle(BaseModel):
    roll_deg: float | None
    pitch_deg: float | None
    yaw_deg: float | None
    ap_roll_deg: float | None = Field(description="the autopilot's own attitude estimate")
    ap_pitch_deg: float | None
    ap_yaw_deg: float | None
    heading_mag_deg: float | None = Field(description="tilt-compensated magnetic heading (true)")
    heading_att_deg: float | None = Field(description="attitude-filter heading (true)")
    v_forward_mps: float | None
    v_lateral_mps: float | None
    cross_track_m: float | None
    field_mG: float | None
    lat_deg: float | None
    lon_deg: float | None
    fix_type: int


class AlarmNow(BaseModel):
    active: bool
    evidence: list[str]
    since_s: float | None


class Line(BaseModel):
    a: list[float] = Field(min_length=2, max_length=2, description="[lat_deg, lon_deg]")
    b: list[float] = Field(min_length=2, max_length=2, description="[lat_deg, lon_deg]")
    source: str = "user"


class ParamWrite(BaseModel):
    state: str
    autopilot: str | None = None
    total: int = 0
    confirmed: list[str] = []
    failed: list[str] = []
    message: str = ""


class Wizard(BaseModel):
    state: str
    step: str | None
    step_index: int
    instruction: str
    progress_deg: dict[str, float]
    turn_target_deg: float
    coverage: float
    coverage_target: float
    samples: int
    rls_offsets_mG: list[float] | None
    rls_field_mG: float | None
    expected_field_mG: float | None
    warnings: list[str]
    result: dict[str, Any] | None = Field(description="calibration result object (issue 3) "
                                                      "+ heading_error_deg")
    param_write: ParamWrite | None


class Event(BaseModel):
    t_s: float
    unix_s: float
    level: str
    text: str


class State(BaseModel):
    version: int
    wall_unix_s: float
    t_s: float
    rx_count: int
    rx_age_s: float | None
    source: SourceInfo
    replay: ReplayInfo | None
    vehicle: Vehicle
    alarm: AlarmNow
    alarm_count: int
    line: Line | None
    calibration_in_use: bool
    wizard: Wizard
    events: list[Event]


class Alarm(BaseModel):
    kind: str
    evidence: list[str]
    start_s: float
    end_s: float | None
    peak: float | None


class SourceRequest(BaseModel):
    connect: ConnectionString | None = Field(None, description="pymavlink connection string, e.g. udpin:127.0.0.1:14550")
    recording: RecordingName | None = Field(None, description="a file name from GET /api/recordings")
    speed: float = 1.0
    loop: bool = False


class ReplayStart(BaseModel):
    recording: RecordingName
    speed: float = 1.0
    loop: bool = False


class Seek(BaseModel):
    t_s: float


class Speed(BaseModel):
    speed: float


class Pause(BaseModel):
    paused: bool = True


class Ok(BaseModel):
    ok: bool = True
    message: str = ""
