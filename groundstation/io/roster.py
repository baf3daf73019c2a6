"""Every MAVLink system heard on a link: vehicles, other ground stations, link quality.

``SystemRoster.observe(msg, unix_s, packet)`` is called with every packet a live link receives
(before any filtering), so the station can list the vehicles sharing one radio or network,
follow one of them, and notice another ground station on the link.  Loss is counted from the
MAVLink sequence number of each (system, component) stream, as pymavlink's ``mavfile`` does.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

__all__ = ["SystemRoster", "HeardSystem", "MAV_TYPE_GCS", "MAV_AUTOPILOT_INVALID", "is_signed_packet"]

MAV_TYPE_GCS = 6
MAV_AUTOPILOT_INVALID = 8
RATE_WINDOW_S = 5.0
RADIO_IDS = (ord("3"), ord("D"))      # SiK radios' RADIO_STATUS: system '3', component 'D'

# MAV_TYPE / MAV_AUTOPILOT names the page shows (common.xml; the rest appear as numbers)
TYPE_NAMES = {0: "generic", 1: "fixed wing", 2: "quadrotor", 3: "coaxial", 4: "helicopter", 6: "ground station",
              10: "ground rover", 11: "surface boat", 12: "submarine", 13: "hexarotor", 14: "octorotor",
              15: "tricopter", 19: "VTOL", 20: "VTOL", 21: "VTOL", 22: "VTOL", 26: "gimbal", 27: "ADS-B",
              29: "dodecarotor", 35: "decarotor"}
AUTOPILOT_NAMES = {0: "generic", 3: "ardupilot", 8: "none", 12: "px4"}


def is_signed_packet(packet: bytes) -> bool:
    """A MAVLink 2 packet whose incompat flags say it carries a signature."""
    return len(packet) > 2 and packet[0] == 0xFD and bool(packet[2] & 0x01)


@dataclass
class HeardSystem:
    """One system id heard on the link (all its components together)."""
    sysid: int
    first_unix_s: float
    last_unix_s: float
    mav_type: int | None = None
    autopilot: int | None = None
    packets: int = 0
    lost: int = 0
    signed: int = 0
    components: set = field(default_factory=set)
    _last_seq: dict = field(default_factory=dict)
    _recent: deque = field(default_factory=lambda: deque(maxlen=4000))

    @property
    def is_gcs(self) -> bool:
        return self.mav_type == MAV_TYPE_GCS

    @property
    def is_vehicle(self) -> bool:
        """Sent a heartbeat of an autopilot (not a ground station, not a bare component)."""
        return self.autopilot is not None and self.autopilot != MAV_AUTOPILOT_INVALID and not self.is_gcs

    def rate_hz(self, now_unix_s: float) -> float:
        while self._recent and self._recent[0] < now_unix_s - RATE_WINDOW_S:
            self._recent.popleft()
        span = min(RATE_WINDOW_S, max(1e-3, now_unix_s - self.first_unix_s))
        return len(self._recent) / span

    def snapshot(self, now_unix_s: float) -> dict:
        total = self.packets + self.lost
        return {"sysid": self.sysid, "kind": "ground station" if self.is_gcs else
                ("vehicle" if self.is_vehicle else "component"),
                "type": None if self.mav_type is None else TYPE_NAMES.get(self.mav_type, f"type {self.mav_type}"),
                "autopilot": None if self.autopilot is None else
                AUTOPILOT_NAMES.get(self.autopilot, f"autopilot {self.autopilot}"),
                "components": sorted(self.components), "packets": self.packets, "lost": self.lost,
                "loss_pct": round(100.0 * self.lost / total, 2) if total else 0.0,
                "rate_hz": round(self.rate_hz(now_unix_s), 1),
                "last_seen_s": round(max(0.0, now_unix_s - self.last_unix_s), 2),
                "signed": self.signed > 0}


class SystemRoster:
    """The systems heard on one link; ``observe`` says what a packet revealed."""

    def __init__(self) -> None:
        self.systems: dict[int, HeardSystem] = {}

    def observe(self, msg, unix_s: float, packet: bytes = b"") -> str | None:
        """Count one received message.  Returns "vehicle" when it is the first autopilot
        heartbeat of a system, "gcs" for the first heartbeat of another ground station, else None."""
        sysid, compid = int(msg.get_srcSystem()), int(msg.get_srcComponent())
        if (sysid, compid) == RADIO_IDS:
            return None
        s = self.systems.get(sysid)
        if s is None:
            s = self.systems[sysid] = HeardSystem(sysid, unix_s, unix_s)
        s.last_unix_s = unix_s
        s.packets += 1
        s.components.add(compid)
        s._recent.append(unix_s)
        if packet and is_signed_packet(packet):
            s.signed += 1
        seq = int(msg.get_seq())
        last = s._last_seq.get(compid)
        if last is not None:
            s.lost += (seq - last - 1) % 256
        s._last_seq[compid] = seq
        if msg.get_type() != "HEARTBEAT":
            return None
        was = (s.is_vehicle, s.is_gcs)
        if msg.type == MAV_TYPE_GCS:
            s.mav_type = MAV_TYPE_GCS
        elif msg.autopilot != MAV_AUTOPILOT_INVALID or s.mav_type is None:
            s.mav_type, s.autopilot = int(msg.type), int(msg.autopilot)
        if s.is_gcs and not was[1]:
            return "gcs"
        if s.is_vehicle and not was[0]:
            return "vehicle"
        return None

    def vehicles(self) -> list[int]:
        return sorted(k for k, s in self.systems.items() if s.is_vehicle)

    def snapshot(self, now_unix_s: float) -> list[dict]:
        return [self.systems[k].snapshot(now_unix_s) for k in sorted(self.systems)]
