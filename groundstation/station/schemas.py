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
    fix_name: str = "no GPS"     # MAVLink GPS_FIX_TYPE by name (groundstation.jobs.words.fix_name)
    attitude_source: Literal["offline", "causal"] | None = Field(
        None, description="roll, pitch and attitude heading: 'offline' = the offline smoother over the whole "
                          "replayed log (forward and backward AHRS), 'causal' = the causal AHRS (live; the "
                          "INS/GPS filter around a replay's GPS outages). Alarms always use the causal AHRS")


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
    state: str = Field(description="writing | written | failed | not_connected")
    autopilot: str | None = None
    total: int = 0
    confirmed: list[str] = []
    failed: list[str] = []
    failures: list[dict[str, Any]] = Field([], description="per failed name: sent, echoed (None: no answer), text")
    message: str = ""


class CompassState(BaseModel):
    index: int = Field(description="0 = first compass (RAW_IMU), 1 = SCALED_IMU2, 2 = SCALED_IMU3")
    name: str
    instance: int
    included: bool
    samples: int
    coverage: float | None = Field(description="fraction of direction cells its live fit covers")
    cells: str = Field(description="100 chars '0'/'1': the equal-area direction cells covered")
    live_offsets_mG: list[float] | None
    live_field_mG: float | None
    trusted: bool = Field(description="the live fit is good enough to judge the field strength")
    disturbances: int
    result: dict[str, Any] | None = Field(description="calibration result of this compass: fit, orientation, "
                                                      "fitness_mG, pass, reasons, cautions, parameters")


class Wizard(BaseModel):
    state: str = Field(description="idle | running | result | accepted")
    mode: str = Field(description="guided | onboard | fixed_yaw")
    paused: bool = Field(description="link lost during the dance")
    waiting_for: str | None = Field(None, description="started while this link was connecting: it starts on "
                                                      "that link's vehicle when its first packet arrives")
    banner: dict[str, Any] | None
    step: str | None
    step_index: int
    instruction: str
    hint: str | None = Field(description="e.g. no motion")
    progress_deg: dict[str, float] = Field(description="net turn about each body axis while its step was current")
    turn_target_deg: float
    coverage: float = Field(description="fraction of field directions (body frame) seen, floored to 1 %")
    coverage_target: float
    coverage_cells: str
    next_pose: dict[str, Any] | None
    current_direction: list[float] | None = Field(description="unit field direction in the body frame now")
    samples: int
    live_offsets_mG: list[float] | None
    live_field_mG: float | None
    expected_field_mG: float | None
    declination_deg: float | None
    warnings: list[str]
    compasses: list[CompassState]
    consistency: dict[str, Any] | None
    deviation: dict[str, Any] | None
    fitness_level: str
    result: dict[str, Any] | None = Field(description="combined result of the included compasses")
    param_write: ParamWrite | None
    onboard: dict[str, Any] | None
    fixed_yaw: dict[str, Any] | None
    reboot: dict[str, Any] | None
    heading_check: dict[str, Any] | None
    in_use: str | None = Field(description="whose calibration corrects the heading: station | vehicle")
    settings: dict[str, Any]


class CalibrationStart(BaseModel):
    mode: Literal["guided", "onboard", "fixed_yaw"] = "guided"


class CompassInclude(BaseModel):
    included: bool


class Fitness(BaseModel):
    level: Literal["very_strict", "strict", "default", "relaxed"]


class AcceptRequest(BaseModel):
    which: Literal["ours", "vehicle"] = "ours"


class FixedYawRequest(BaseModel):
    yaw_deg: float | None = Field(None, description="true heading of the vehicle, deg")
    source: Literal["entered", "gps"] = "entered"


class RebootRequest(BaseModel):
    confirm: bool = False


class HeadingCheckRequest(BaseModel):
    kind: Literal["bearing", "walk"] = "bearing"
    bearing_deg: float | None = Field(None, description="known true bearing the vehicle points at, deg")


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
    calibration_choice: dict | None = Field(None, description="the calibration in use: source (log, recording, "
                                            "wizard, history, vehicle, upload, none), label, relative_to, frame, "
                                            "note, airframe (as GET /api/calibration/in-use 'current')")
    tests: InterferenceTests
    downloads: Downloads
    wizard: Wizard
    events: list[Event]
    vehicles: dict | None = Field(None, description="live links: every system heard, the one followed, passive "
                                  "mode, signing counts and forwarding (as GET /api/vehicles)")


class AlarmExplanation(BaseModel):
    """What an alarm looks like (groundstation.jobs.alarm_explain / estimators.detection_explain)."""
    disturbance_mG: list[float] | None = Field(None, description="estimated disturbance, body frame FRD [mG], "
                                                                  "where it was largest")
    disturbance_size_mG: float | None = None
    growth_mG_s: float | None = Field(None, description="growth of its size before the alarm [mG/s]")
    tests: list[str] = Field([], description="tests whose score reached their threshold")
    kind: str = Field(description="moving with current | fixed in place | rising with time")
    position: dict[str, float] | None = Field(None, description="{lat, lon} [deg] of an anomaly fixed in place")
    current_correlation: float | None = Field(None, description="Pearson r of its size with the motor signal")


class Alarm(BaseModel):
    kind: str
    evidence: list[str] = Field(description="every test that fired during the alarm")
    evidence_at_start: list[str] = []
    evidence_text: str = Field("", description="the evidence in words")
    start_s: float
    end_s: float | None = Field(description="None while the alarm is on")
    peak: float | None
    unit: str = ""
    explanation: AlarmExplanation | None = None
    explanation_text: str = Field("", description="the explanation in words")


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
