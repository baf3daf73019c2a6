"""ArduPilot SITL (ArduCopter 4.7, ../shared/sitl) in the loop: start it by PID on loopback, set the
simulated compass truth, drive the calibration rig, stop it.

``Sitl`` runs ``arducopter`` in its own temporary folder (eeprom.bin, logs/) under ``timeout``
with ``-w`` (parameters back to the defaults files), ``-I N`` (every port + 10 N) and
``--serial0 udpclient:127.0.0.1:PORT`` (MAVLink pushed to the station's UDP listener on loopback,
so the link under test never leaves the machine).  The truth (``SIM_MAGn_OFS/DIA/ODI`` ...) goes in
a later defaults file at boot, or by PARAM_SET through the station's link (``set_params``); the rig
(``--model calibration``) turns as MAV_CMD_DO_SET_SERVO on outputs 5-8 says.  Used by the smoke
tests (tests/sitl/) and by benchmarks/sitl.py.  ``SITL_BINARY`` is None when the firmware is absent:
callers skip and say so (``MISSING``).

``Sitl()`` without an instance and port claims a free pair at ``start()`` (``claim``): a lock file
per instance and per port in the temporary folder (held until ``stop()``), so two pytest-xdist
workers or a benchmark beside the suite never start the same ``-I N``, and an instance whose ports
another SITL already holds (TCP 5762/5763 + 10 N, UDP 5501 + 10 N) is passed over.
"""
from __future__ import annotations

import fcntl
import math
import os
import socket
import shutil
import signal
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

SITL_DIR = Path(__file__).resolve().parents[3] / "shared" / "sitl"
SITL_BINARY = SITL_DIR / "arducopter" if (SITL_DIR / "arducopter").is_file() else None
MISSING = f"ArduPilot SITL firmware not found at {SITL_DIR / 'arducopter'} (../shared/sitl)"
HOME = (30.3, 120.1, 10.0, 0.0)           # lat, lon, alt m, yaw deg (the README's site)
PORTS = range(14610, 14640)               # this harness's UDP ports
INSTANCES = range(10, 20)                 # -I 10..19 (every SITL port + 10 N); other users take 1..9
# benchmarks flown beside the suite: -I 20..29 with UDP ports 14640-14649, taken only when named
# (never claimed for a caller that names none), so a benchmark never waits for the suite nor it for one
BENCH_INSTANCES = range(20, 30)
BENCH_PORTS = range(14640, 14650)
MAV_CMD_DO_SET_SERVO = 183
MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN = 246

# three compasses with known offsets and soft iron (the truth a calibration must find); the field
# the sensor reads is inv(M) B - OFS, so a correct calibration gives COMPASS_OFSn = SIM_MAGn_OFS and
# COMPASS_DIAn/ODIn = SIM_MAGn_DIA/ODI (the README of ../shared/sitl)
RIG_TRUTH = {
    1: {"OFS": (120.0, -80.0, 45.0), "DIA": (1.03, 0.97, 1.01), "ODI": (0.02, -0.015, 0.01)},
    2: {"OFS": (-60.0, 95.0, -140.0), "DIA": (0.98, 1.04, 0.99), "ODI": (-0.01, 0.02, 0.015)},
    3: {"OFS": (35.0, 150.0, -70.0), "DIA": (1.02, 1.01, 0.96), "ODI": (0.015, 0.01, -0.02)},
}


def truth_params(truth: dict = RIG_TRUTH) -> dict[str, float]:
    """SIM_MAGn_OFS/DIA/ODI_X/Y/Z of ``truth``."""
    out = {}
    for n, t in truth.items():
        for key in ("OFS", "DIA", "ODI"):
            for axis, v in zip("XYZ", t[key]):
                out[f"SIM_MAG{n}_{key}_{axis}"] = float(v)
    return out


def uncalibrated_params(n_compasses: int = 3) -> dict[str, float]:
    """COMPASS_OFS*/DIA*/ODI* as an uncalibrated compass has them.  An offset of exactly 0 is
    replaced at boot by SIM_MAGn_OFS (SITL starts "calibrated"), so the defaults use 0.001 mG."""
    out = {}
    for n in range(1, n_compasses + 1):
        sfx = "" if n == 1 else str(n)
        for axis in "XYZ":
            out[f"COMPASS_OFS{sfx}_{axis}"] = 0.001
            out[f"COMPASS_DIA{sfx}_{axis}"] = 1.0
            out[f"COMPASS_ODI{sfx}_{axis}"] = 0.0
    return out


def rig_pwm(angle_rad: float) -> int:
    """Output 6/7/8 PWM holding ``angle_rad`` (angle = -pi + 2 pi (pwm - 1000) / 1000)."""
    return int(round(1000 + (angle_rad + math.pi) * 1000 / (2 * math.pi)))


def _lock(name: str):
    """An exclusive lock on <tmp>/magstation-sitl-<name>.lock (the open file, held until closed), or None."""
    f = open(Path(tempfile.gettempdir()) / f"magstation-sitl-{name}.lock", "w")
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        f.close()
        return None
    return f


def _bindable(kind: int, port: int) -> bool:
    with socket.socket(socket.AF_INET, kind) as s:
        try:
            s.bind(("0.0.0.0" if kind == socket.SOCK_STREAM else "127.0.0.1", port))
        except OSError:
            return False
    return True


def _instance_free(n: int) -> bool:
    """No process holds the ports SITL -I n binds (TCP 5762/5763 + 10 n on every address, UDP 5501 + 10 n)."""
    return (_bindable(socket.SOCK_STREAM, 5762 + 10 * n) and _bindable(socket.SOCK_STREAM, 5763 + 10 * n)
            and _bindable(socket.SOCK_DGRAM, 5501 + 10 * n))


def claim(instance: int | None = None, port: int | None = None, timeout_s: float = 120.0) -> tuple[int, int, list]:
    """A free (instance, UDP port) of INSTANCES x PORTS and the locks holding them (see the module
    docstring); a given ``instance`` or ``port`` is waited for while another holder has it.
    Raises TimeoutError when none comes free within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        for n in ([instance] if instance is not None else INSTANCES):
            held = _lock(f"I{n}")
            if held is None:
                continue
            if not _instance_free(n):
                held.close()
                continue
            for p in ([port] if port is not None else PORTS):
                held_port = _lock(f"udp{p}")
                if held_port is None:
                    continue
                if _bindable(socket.SOCK_DGRAM, p):
                    return n, p, [held, held_port]
                held_port.close()
            held.close()
        if time.monotonic() > deadline:
            raise TimeoutError(f"no free SITL instance of -I {INSTANCES.start}..{INSTANCES.stop - 1} / UDP port "
                               f"of {PORTS.start}-{PORTS.stop - 1} within {timeout_s:.0f} s")
        time.sleep(0.5)


@dataclass
class Sitl:
    """One ArduCopter SITL process (see module docstring).  ``extra``: parameters written to a
    last defaults file (SIM truth, stream rates ...).  ``instance``/``port`` None: claimed at start."""
    instance: int | None = None
    port: int | None = None
    model: str = "quad"
    speedup: float = 1.0
    extra: dict[str, float] = field(default_factory=dict)
    limit_s: float = 300.0
    home: tuple = HOME
    run_dir: Path | None = None
    proc: subprocess.Popen | None = None
    locks: list = field(default_factory=list)

    def __post_init__(self) -> None:
        if SITL_BINARY is None:
            raise FileNotFoundError(MISSING)
        if (self.instance not in (None, *INSTANCES, *BENCH_INSTANCES)
                or self.port not in (None, *PORTS, *BENCH_PORTS)):
            raise ValueError(f"the SITL harness uses -I {INSTANCES.start}..{INSTANCES.stop - 1} and UDP ports "
                             f"{PORTS.start}-{PORTS.stop - 1} (benchmarks, named: -I {BENCH_INSTANCES.start}.."
                             f"{BENCH_INSTANCES.stop - 1}, {BENCH_PORTS.start}-{BENCH_PORTS.stop - 1})")

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None else None

    @property
    def log_dir(self) -> Path:
        return self.run_dir / "logs"

    def start(self) -> "Sitl":
        self.instance, self.port, self.locks = claim(self.instance, self.port)
        self.run_dir = Path(tempfile.mkdtemp(prefix=f"sitl{self.instance}-"))
        defaults = [SITL_DIR / "copter.parm"]
        if self.model == "calibration":
            defaults.append(SITL_DIR / "calibration-rig.parm")
        if self.extra:
            mine = self.run_dir / "extra.parm"
            mine.write_text("".join(f"{k} {v:.9g}\n" for k, v in self.extra.items()))
            defaults.append(mine)
        cmd = ["timeout", "-s", "TERM", f"{self.limit_s:.0f}", str(SITL_BINARY), "--model", self.model,
               "--speedup", f"{self.speedup:g}", "-w", "-I", str(self.instance),
               "--defaults", ",".join(str(p) for p in defaults),
               "--home", ",".join(f"{v:g}" for v in self.home),
               "--serial0", f"udpclient:127.0.0.1:{self.port}"]
        self.proc = subprocess.Popen(cmd, cwd=self.run_dir, stdout=open(self.run_dir / "sitl.out", "wb"),
                                     stderr=subprocess.STDOUT, start_new_session=True)
        return self

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def output(self) -> str:
        try:
            return (self.run_dir / "sitl.out").read_text(errors="replace")[-2000:]
        except OSError:
            return ""

    def stop(self, keep: bool = False) -> None:
        """SIGTERM to our own process group (timeout and its arducopter child), by PID."""
        if self.proc is not None and self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(timeout=5)
        for held in self.locks:
            held.close()
        self.locks = []
        if not keep and self.run_dir is not None:
            shutil.rmtree(self.run_dir, ignore_errors=True)

    def bin_logs(self) -> list[Path]:
        return sorted(self.log_dir.glob("*.BIN")) if self.run_dir is not None else []


# ------------------------------------------------------------------ through the station's link

def station_link(session, timeout_s: float = 30.0):
    """The session's live link once it follows the vehicle (raises TimeoutError)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        link = session.sources.link
        if link is not None and link.sysid is not None and link.connected:
            return link
        time.sleep(0.1)
    raise TimeoutError("the station never heard the SITL vehicle")


def station_for(sitl: Sitl, recordings: Path, timeout_s: float = 40.0):
    """A station session listening on the SITL's UDP port (udpin on loopback), following it
    (raises RuntimeError with the end of the SITL's output when it is never heard)."""
    from groundstation.station.hub.session import Session

    session = Session(recordings)
    session.connect(f"udpin:127.0.0.1:{sitl.port}")
    try:
        station_link(session, timeout_s=timeout_s)
    except TimeoutError:
        session.close()
        raise RuntimeError(f"the station never heard SITL (pid {sitl.pid}): {sitl.output()[-500:]}") from None
    return session


def command(session, cmd: int, *params: float) -> None:
    """COMMAND_LONG through the station (as its pages send them)."""
    link = station_link(session)
    session.vehicle.send_command(link, cmd, *params)


def set_servo(session, output: int, pwm: int) -> None:
    command(session, MAV_CMD_DO_SET_SERVO, output, pwm)


def rig_hold(session, roll_rad: float, pitch_rad: float, yaw_rad: float) -> None:
    """Hold an attitude on the rig (output 5 at 1150)."""
    for out, angle in ((6, roll_rad), (7, pitch_rad), (8, yaw_rad)):
        set_servo(session, out, rig_pwm(angle))
    set_servo(session, 5, 1150)


def rig_spin(session, axis: tuple[int, int, int], rate_rad_s: float) -> None:
    """Spin about ``axis`` (outputs 6/7/8 - 1500) at ``rate_rad_s`` (output 5 = 1300 + 700 rate / 2 pi)."""
    for out, a in zip((6, 7, 8), axis):
        set_servo(session, out, 1500 + int(a))
    set_servo(session, 5, int(round(1300 + 700 * rate_rad_s / (2 * math.pi))))


def rig_tour(session) -> None:
    """The rig's 18 built-in poses, 6 s (simulated) each."""
    set_servo(session, 5, 1250)


def rig_stop(session) -> None:
    set_servo(session, 5, 1000)


def set_params(session, params: dict[str, float], timeout_s: float = 1.0) -> list[str]:
    """PARAM_SET through the station, each confirmed by its echo; returns the names that failed."""
    link = station_link(session)
    _, failed, _ = session.vehicle.write_params(link, params, lambda done: None, tries=4, timeout_s=timeout_s)
    return failed


def wait_for(predicate, timeout_s: float, step_s: float = 0.1):
    """Poll ``predicate`` until it returns something true (returned) or ``timeout_s`` passes (None)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        got = predicate()
        if got:
            return got
        time.sleep(step_s)
    return None


# ------------------------------------------------------------------ flying (GUIDED)
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_DO_REPOSITION = 192
COPTER_GUIDED, COPTER_LAND = 4, 9


class Watch:
    """HEARTBEAT armed flag, COMMAND_ACKs and the position of the vehicle, from a pymavlink hook
    on the station's link (read only)."""

    def __init__(self, link) -> None:
        self.armed = False
        self.acks: list[tuple[int, int]] = []
        self.position: tuple[float, float, float] | None = None   # lat, lon deg, relative alt m
        link.mav.message_hooks.append(self._hook)

    def _hook(self, _conn, msg) -> None:
        if msg.get_srcSystem() != 1:
            return
        kind = msg.get_type()
        if kind == "HEARTBEAT" and msg.type != 6:
            self.armed = bool(msg.base_mode & 128)
        elif kind == "COMMAND_ACK":
            self.acks.append((int(msg.command), int(msg.result)))
        elif kind == "GLOBAL_POSITION_INT":
            self.position = (msg.lat * 1e-7, msg.lon * 1e-7, msg.relative_alt * 1e-3)


def set_mode(session, custom_mode: int) -> None:
    command(session, MAV_CMD_DO_SET_MODE, 1, custom_mode)


def arm(session, watch: Watch, timeout_s: float = 120.0) -> bool:
    """GUIDED, then arm until the vehicle says armed (its pre-arm checks pass once the EKF has GPS)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not watch.armed:
        set_mode(session, COPTER_GUIDED)
        command(session, MAV_CMD_COMPONENT_ARM_DISARM, 1)
        wait_for(lambda: watch.armed, 2.0, 0.1)
    return watch.armed


def goto(session, lat_deg: float, lon_deg: float, alt_m: float) -> None:
    """MAV_CMD_DO_REPOSITION as COMMAND_INT (ArduPilot takes positions only in COMMAND_INT)."""
    link = station_link(session)
    link.mav.mav.command_int_send(link.sysid, 1, 6, MAV_CMD_DO_REPOSITION, 0, 0, -1, 1, 0, math.nan,
                                  int(lat_deg * 1e7), int(lon_deg * 1e7), float(alt_m))


# ------------------------------------------------------------------ one clock for .BIN and .tlog
def boot_offset_s(path, log) -> float:
    """b [s] such that ``t_s + b`` is the vehicle's boot time for ``log`` (read from ``path``).

    The .BIN's t_s is its boot clock (TimeUS) from its first record; the session .tlog's is the
    station's receive time from its first packet, with ATTITUDE placed by its ``time_boot_ms``
    (groundstation.io.decode.BootClock).  Both logs' UNIX starts differ (the .BIN's from GPS time,
    the .tlog's from the station's clock: 0.75 s apart on this firmware), so alarms are compared on
    the boot clock: b is the median of (ATT TimeUS or ATTITUDE time_boot_ms) - the attitude rows'
    t_s, row by row (the readers keep every attitude in order), over the first boot only (up to
    the first boot time going back: a reboot)."""
    import numpy as np
    from pymavlink import mavutil

    boots = []
    conn = mavutil.mavlink_connection(str(path))
    try:
        while True:
            m = conn.recv_match(type=["ATT", "ATTITUDE"])
            if m is None:
                break
            if m.get_type() == "ATT":
                boots.append(m.TimeUS * 1e-6)
            elif m.get_srcSystem() == 1:
                boots.append(m.time_boot_ms * 1e-3)
    finally:
        conn.close()
    t = np.asarray(log.attitude, dtype=float).reshape(-1, 4)[:, 0]
    back = np.flatnonzero(np.diff(boots) < -1.0) if len(boots) > 1 else []
    n = min(len(boots), len(t), int(back[0]) + 1 if len(back) else len(boots))
    if n == 0:
        raise ValueError(f"{path}: no attitude with a boot time to align on")
    return float(np.median(np.asarray(boots[:n]) - t[:n]))
