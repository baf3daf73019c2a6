"""Request and response models of the station API (the OpenAPI schema at /docs)."""
from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field


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
    recording: str | None = Field(description="the session's .tlog (a live link's, from its first packet, "
                                              "or the replayed .tlog)")
    log_file: str | None = Field(None, description="the session's log in its own format (GET /api/session/file)")
    pending: str | None = Field(None, description="a link armed while another source runs: it takes over at "
                                                  "its first packet")


class ReplayInfo(BaseModel):
    t_s: float
    duration_s: float
    paused: bool
    speed: float
    finished: bool
    loop: bool


class Vehicle(BaseModel):
    """The vehicle at the last IMU step shown (headings true, in [0, 360))."""
    roll_deg: float | None
    pitch_deg: float | None
    yaw_deg: float | None
    ap_roll_deg: float | None = Field(description="the autopilot's own attitude estimate")
    ap_pitch_deg: float | None
    ap_yaw_deg: float | None = Field(description="the autopilot's heading, in [0, 360)")
    heading_mag_deg: float | None = Field(description="tilt-compensated magnetic heading (true)")
    heading_att_deg: float | None = Field(description="attitude-filter heading (true)")
    course_deg: float | None = Field(None, description="GPS course over ground (when moving)")
    speed_mps: float | None = None
    v_forward_mps: float | None
    v_lateral_mps: float | None
    cross_track_m: float | None = Field(description="signed: + right of the preset line's A->B")
    field_mG: float | None
    inclination_deg: float | None = None
    lat_deg: float | None
    lon_deg: float | None
    fix_type: int


class InterferenceTest(BaseModel):
    state: Literal["on", "off", "paused", "untrusted", "waiting"]
    why: str


class FieldCorrection(BaseModel):
    kind: Literal["station", "autopilot", "raw", "unknown", "none"] = Field(
        description="station-corrected (our calibration), autopilot-corrected, raw sensor output")
    note: str


class InterferenceTests(BaseModel):
    """Which interference tests run at this step, and why not."""
    heading: InterferenceTest
    field: InterferenceTest
    path: InterferenceTest
    field_correction: FieldCorrection


class Downloads(BaseModel):
    log: str | None = Field(description="file name GET /api/session/file returns, None before there is one")
    tlog: bool = Field(description="GET /api/session.tlog has a file")


class AlarmNow(BaseModel):
    active: bool
    evidence: list[str]
    evidence_text: str = Field("", description="the evidence in words")
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
    analysing: bool = Field(description="a replay's log is being analysed before it plays")
    reorder_delay_s: float = Field(description="how long live samples wait to be put in time order")
    alarm: AlarmNow
    alarm_count: int
    line: Line | None
    calibration_in_use: bool
    tests: InterferenceTests
    downloads: Downloads
    wizard: Wizard
    events: list[Event]


class Alarm(BaseModel):
    kind: str
    evidence: list[str] = Field(description="every test that fired during the alarm")
    evidence_at_start: list[str] = []
    evidence_text: str = Field("", description="the evidence in words")
    start_s: float
    end_s: float | None = Field(description="None while the alarm is on")
    peak: float | None
    unit: str = ""


class RecordingInfo(BaseModel):
    name: str
    size_bytes: int
    modified_unix_s: float
    recording: bool = Field(description="the live session being written now (not read)")
    duration_s: float | None
    start_unix_s: float | None = Field(description="when the log starts (UTC), if it says")
    autopilot: str | None
    vehicle: str | None
    compasses: int | None
    error: str | None = Field(description="why the log cannot be read, if it cannot")


class Marker(BaseModel):
    t_s: float
    end_s: float | None
    kind: Literal["alarm", "gps", "gap", "message"]
    label: str


class Timeline(BaseModel):
    duration_s: float
    ready: bool = Field(description="False while the log is being analysed")
    markers: list[Marker]


class PlotWmm(BaseModel):
    field_mG: float | None
    inclination_deg: float | None
    declination_deg: float | None


class PlotAlarm(BaseModel):
    start_s: float
    end_s: float | None


class Plots(BaseModel):
    """The last ``window_s`` of the flight record, decimated; None where a value is unknown."""
    t_s: list[float | None]
    t_end_s: float
    window_s: float
    series: dict[str, list[float | None]]
    wmm: PlotWmm
    alarms: list[PlotAlarm]


class SourceRequest(BaseModel):
    connect: str | None = Field(None, description="pymavlink connection string, e.g. udpin:127.0.0.1:14550")
    recording: str | None = Field(None, description="a file name from GET /api/recordings")
    speed: float = 1.0
    loop: bool = False


class ReplayStart(BaseModel):
    recording: str
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
