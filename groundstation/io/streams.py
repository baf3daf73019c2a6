"""The messages the station asks a live vehicle for, whether each arrives, and why not.

A stock ArduCopter streams nothing but HEARTBEAT (every ``MAVn_*`` stream rate is 0), so the
station asks for each message it decodes with MAV_CMD_SET_MESSAGE_INTERVAL at its own rate
(``STREAMS``), matches the COMMAND_ACKs to the requests (the vehicle answers in order), counts
what arrives and says, per message, "arriving", or why it is missing: refused (the ACK's result),
accepted but not sent (the vehicle lacks that sensor), no answer (older firmware: asked again with
REQUEST_DATA_STREAM), only sent while the vehicle calibrates (MAG_CAL_*), or, on a passive link,
not streamed by the other ground station.  ``StreamTracker`` is pure bookkeeping (times in UNIX
seconds passed in); ``groundstation.io.link.LiveLink`` sends and feeds it.
"""
from __future__ import annotations

from dataclasses import dataclass

__all__ = ["StreamSpec", "STREAMS", "StreamTracker", "IMU_MESSAGES", "ACK_RESULT_TEXT"]


@dataclass(frozen=True)
class StreamSpec:
    """One message the station consumes: its name, the rate asked for [Hz] (per autopilot:
    ``rate_ardupilot_hz`` where it differs) and what the station uses it for.  ``on_demand``:
    the vehicle sends it only while something runs (the onboard calibrator)."""
    name: str
    rate_hz: float
    use: str
    rate_ardupilot_hz: float | None = None
    on_demand: bool = False
    optional: bool = False      # refused by some firmware, the station does without it (not "missing")

    def rate_for(self, autopilot: str | None) -> float:
        """The rate to ask for [Hz]; 0: not asked of this autopilot."""
        if autopilot == "ardupilot" and self.rate_ardupilot_hz is not None:
            return self.rate_ardupilot_hz
        return self.rate_hz


# Every message groundstation.io.decode.MavlinkDecoder turns into samples that is sent as a stream
# (PARAM_VALUE, MISSION_ITEM, COMMAND_ACK and STATUSTEXT come as answers or events, not streams).
# ArduPilot sends compass 1 and IMU 1 in RAW_IMU; its SCALED_IMU and HIGHRES_IMU repeat them (HIGHRES
# in mG x 1000, not the gauss its definition says), so they are not asked of ArduPilot (rate 0).
STREAMS: tuple[StreamSpec, ...] = (
    StreamSpec("ATTITUDE", 50, "attitude, the autopilot's heading"),
    StreamSpec("RAW_IMU", 50, "compass 1 and IMU 1 (ArduPilot)"),
    StreamSpec("SCALED_IMU", 50, "compass 1 and IMU 1", rate_ardupilot_hz=0),
    StreamSpec("SCALED_IMU2", 50, "compass 2 and IMU 2"),
    StreamSpec("SCALED_IMU3", 50, "compass 3 and IMU 3"),
    StreamSpec("HIGHRES_IMU", 50, "IMU and compass (PX4)", rate_ardupilot_hz=0),
    StreamSpec("GPS_RAW_INT", 10, "position, course and the WMM field"),
    StreamSpec("GLOBAL_POSITION_INT", 10, "position when GPS_RAW_INT is missing"),
    StreamSpec("SYS_STATUS", 5, "battery current (motor interference)"),
    StreamSpec("VFR_HUD", 10, "throttle"),
    StreamSpec("SYSTEM_TIME", 1, "the date (WMM) and the vehicle's boot time (reboots)"),
    StreamSpec("SENSOR_OFFSETS", 1, "compass 1 offsets in force (older ArduPilot; else from the parameters)",
               optional=True),
    StreamSpec("MAG_CAL_PROGRESS", 10, "onboard calibration progress", on_demand=True),
    StreamSpec("MAG_CAL_REPORT", 1, "onboard calibration report", on_demand=True),
)
IMU_MESSAGES = frozenset({"RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3", "HIGHRES_IMU"})
ACK_RESULT_TEXT = {0: "accepted", 1: "temporarily rejected", 2: "denied", 3: "unsupported", 4: "failed",
                   5: "in progress", 6: "cancelled"}
ARRIVING_WITHIN_S = 3.0     # a message heard this recently is arriving (at >= 1/3 Hz)
ACK_WAIT_S = 2.0            # no COMMAND_ACK this long after a request: no answer
RETRY_AFTER_S = 3.0         # accepted yet nothing arrived this long: asked again (lost datagram) ...
MAX_TRIES = 3               # ... up to this many requests per message


@dataclass
class _Stream:
    spec: StreamSpec
    requested_unix: float | None = None
    tries: int = 0
    ack: int | None = None            # MAV_RESULT of the last answered request
    not_asked: bool = False           # rate 0 for this autopilot (StreamSpec.rate_for)
    count: int = 0                    # arrived since the link (re)started
    first_unix: float | None = None
    last_unix: float | None = None


class StreamTracker:
    """Per-message request, acknowledgement and arrival state of one followed vehicle.

    ``requested(names, unix)`` when SET_MESSAGE_INTERVAL went out for ``names``;
    ``ack(result)`` for each COMMAND_ACK of MAV_CMD_SET_MESSAGE_INTERVAL (matched to the oldest
    unanswered request); ``seen(name, unix)`` for each message of the vehicle;
    ``retry_due(unix)`` the accepted messages not arriving that should be asked again;
    ``snapshot(unix, passive)`` for /api/state.
    """

    def __init__(self) -> None:
        self.streams: dict[str, _Stream] = {s.name: _Stream(s) for s in STREAMS}
        self._unanswered: list[str] = []
        self.fallback_sent_unix: float | None = None
        self.any_ack = False
        # optional messages this vehicle refused (name -> MAV_RESULT): asked once, never again (each
        # request of SENSOR_OFFSETS makes ArduPilot 4.7 post "No ap_message for mavlink id (150)")
        self.unavailable: dict[str, int] = {}

    def restart(self) -> None:
        """Forget requests and arrivals (a reboot: the vehicle's stream rates are back to its
        defaults); the optional messages it refused stay refused."""
        unavailable, old = self.unavailable, self.streams
        self.__init__()
        self.unavailable = unavailable
        for name in unavailable:
            st = self.streams[name]
            st.requested_unix, st.tries, st.ack = old[name].requested_unix, old[name].tries, old[name].ack

    def to_ask(self, names) -> list[str]:
        """``names`` less the optional messages this vehicle already refused."""
        return [n for n in names if n not in self.unavailable]

    def requested(self, names, unix: float) -> None:
        for name in names:
            st = self.streams[name]
            st.requested_unix, st.tries = unix, st.tries + 1
            self._unanswered.append(name)

    def ack(self, result: int) -> str | None:
        """The name a SET_MESSAGE_INTERVAL ACK answers (None when none was waiting)."""
        self.any_ack = True
        if not self._unanswered:
            return None
        name = self._unanswered.pop(0)
        st = self.streams[name]
        st.ack = int(result)
        if st.spec.optional and st.ack != 0:
            self.unavailable[name] = st.ack
        return name

    def seen(self, name: str, unix: float) -> None:
        st = self.streams.get(name)
        if st is None:
            return
        st.count += 1
        st.last_unix = unix
        if st.first_unix is None:
            st.first_unix = unix

    def arriving(self, name: str, unix: float) -> bool:
        st = self.streams[name]
        return st.last_unix is not None and unix - st.last_unix <= ARRIVING_WITHIN_S

    def last_imu_unix(self) -> float | None:
        times = [self.streams[n].last_unix for n in IMU_MESSAGES if self.streams[n].last_unix is not None]
        return max(times) if times else None

    def unanswered_since(self, unix: float) -> bool:
        """Requests went out more than ACK_WAIT_S ago and none was accepted (no answer, or every
        answer a refusal: older firmware, which still honours REQUEST_DATA_STREAM)."""
        sent = [st.requested_unix for st in self.streams.values() if st.requested_unix is not None]
        accepted = any(st.ack == 0 for st in self.streams.values())
        return bool(sent) and not accepted and unix - min(sent) > ACK_WAIT_S

    def skipped(self, names) -> None:
        """Not asked of this autopilot (its rate there is 0)."""
        for name in names:
            self.streams[name].not_asked = True

    def retry_due(self, unix: float) -> list[str]:
        """Accepted (or unanswered) continuous streams that have not arrived RETRY_AFTER_S after
        their request, with tries left."""
        out = []
        for name, st in self.streams.items():
            if st.spec.on_demand or st.requested_unix is None or st.tries >= MAX_TRIES:
                continue
            if st.ack not in (None, 0) or self.arriving(name, unix):
                continue
            if st.last_unix is not None and st.last_unix >= st.requested_unix:
                continue    # it came after the request, and stopped: the stale rule deals with that
            if unix - st.requested_unix > RETRY_AFTER_S:
                out.append(name)
        return out

    def _rate_hz(self, st: _Stream, unix: float) -> float | None:
        if st.first_unix is None or st.last_unix is None or st.count < 2 or st.last_unix <= st.first_unix:
            return None
        return round((st.count - 1) / (st.last_unix - st.first_unix), 1)

    def _why_missing(self, st: _Stream, passive: bool) -> str:
        if st.not_asked:
            return "not asked of this autopilot (" + (
                "ArduPilot sends compass 1 and IMU 1 in RAW_IMU)" if st.spec.name in ("SCALED_IMU", "HIGHRES_IMU")
                else "the station does without it)")
        if passive:
            return ("MagStation only listens here (asks for nothing) and the other ground station does not "
                    "have it streamed")
        if st.spec.on_demand:
            return "requested; the vehicle sends it only while its onboard calibration runs"
        if st.requested_unix is None:
            return "not requested yet"
        if st.ack is not None and st.ack != 0:
            return f"the vehicle refused SET_MESSAGE_INTERVAL ({ACK_RESULT_TEXT.get(st.ack, st.ack)})" + (
                "; asked again with REQUEST_DATA_STREAM" if self.fallback_sent_unix is not None else "")
        if st.ack == 0:
            return ("accepted by the vehicle but not sent (it may not have this sensor"
                    + (", e.g. no third compass)" if st.spec.name == "SCALED_IMU3" else ")"))
        if self.fallback_sent_unix is not None:
            return "no answer to SET_MESSAGE_INTERVAL; asked again with REQUEST_DATA_STREAM (older firmware)"
        return "asked; waiting for the vehicle"

    def snapshot(self, unix: float, passive: bool) -> dict:
        """{"messages": [{name, use, state, rate_hz, why, acked}], "missing": [...]}; state is
        "arriving", "on demand" (MAG_CAL_* while no calibration runs), "not asked" (of this
        autopilot), "not available" (an optional message the vehicle refused) or "missing"."""
        rows, missing = [], []
        for name, st in self.streams.items():
            if self.arriving(name, unix):
                state, why = "arriving", ("provided by the other ground station" if passive else
                                          "requested by MagStation" if st.requested_unix is not None else
                                          "streamed by the vehicle's own settings")
            else:
                why = self._why_missing(st, passive)
                state = "on demand" if st.spec.on_demand and not passive and st.requested_unix is not None \
                    else "not asked" if st.not_asked and not passive \
                    else "not available" if st.spec.optional and st.ack not in (None, 0) else "missing"
                if state == "missing":
                    missing.append(name)
            rows.append({"name": name, "use": st.spec.use, "state": state, "rate_hz": self._rate_hz(st, unix)
                         if state == "arriving" else None, "why": why,
                         "acked": None if st.ack is None else ACK_RESULT_TEXT.get(st.ack, str(st.ack))})
        return {"messages": rows, "missing": missing}
