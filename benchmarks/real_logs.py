"""Real and simulated autopilot logs through `magstation calibrate`, next to the vehicle, the truth and
pymavlink's magfit_WMM.py.

    .venv/bin/python benchmarks/real_logs.py                 # real logs + simulated seed 1 (--seeds N for more),
                                                             # magfit_WMM on every 4th record of each .bin
                                                             # (--magfit-reduce 1: all; ~15-40 min on 2 cores)
    .venv/bin/python benchmarks/real_logs.py --quick         # real logs + seed 1, magfit on every 10th record
    .venv/bin/python benchmarks/real_logs.py --smoke         # one short simulated flight, no real logs, no magfit
                                                             # (the test; < 20 s)
magfit_WMM needs the "bench" extra (scipy, matplotlib).

Every log is read with groundstation.io.logs.read_log and calibrated with
groundstation.jobs.calibrate.calibrate_compasses (every compass); one row per log and compass:
status, method, our COMPASS_OFS (ArduPilot convention, −offsets), the reference, the largest
per-axis difference and the target:
* real logs in ../shared/data: the dronekit ArduCopter tlog (2015, 2.7 Hz) against the offsets the
  vehicle had in force at the end (target 20 mG, the issue's "well-calibrated vehicle" figure);
  the PX4 ULogs against their CAL_MAGn offsets (too short to fit: the status must name why);
* simulated ArduPilot flights (groundstation.sim.ardupilot, known truth): a 1.5 Hz telemetry log
  with an onboard calibration dance, against the vehicle's MAG_CAL_REPORT (target 20 mG); a flight
  without a dance (2 Hz tlog, and its DataFlash log in the three layouts: TimeMS MAG/MAG2/MAG3,
  TimeUS MAG/MAG2/MAG3, TimeUS MAG with an instance column), in-flight WMM fit against the truth
  (target 5 mG), motor field per ampere against the truth (target 10 %);
* magfit_WMM.py (--elliptical --cmot, compass 1) on the same .bin files: its offsets against the
  truth and its runtime over ours (ours: reading the log + calibrating all three compasses).
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import re  # noqa: E402
import struct  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
SHARED = ROOT.parent / "shared" / "data"

from groundstation.io.logs import read_log  # noqa: E402
from groundstation.jobs.calibrate import calibrate_compasses  # noqa: E402
from groundstation.jobs.compass_raw import compass_fields  # noqa: E402
from groundstation.samples import FlightLog  # noqa: E402

LAYOUTS = ("timems", "timeus_split", "timeus_instance")
REAL_LOGS = ("dronekit/flight_replay_flight.tlog", "px4-pyulog/sample_log_small.ulg",
             "px4-pyulog/sample_px4_events.ulg", "px4-pyulog/sample.ulg")


@dataclass
class Row:
    log: str
    compass: int | None
    status: str
    method: str
    ours: np.ndarray | None          # COMPASS_OFS convention (−b), mG
    ref_name: str
    ref: np.ndarray | None
    target_mG: float | None
    seconds: float
    named: bool = True               # the status names its reason (targets: ok, or a reason; never no_data with data)
    sd: np.ndarray | None = None     # our stated 1σ per axis (mG)
    versus: tuple[float, float] | None = None   # peer rows: (our error mG on the same file, our seconds)

    @property
    def err_mG(self) -> float | None:
        if self.ours is None or self.ref is None:
            return None
        return float(np.max(np.abs(self.ours - self.ref)))

    @property
    def verdict(self) -> str:
        if self.versus is not None:          # a peer: ours must be at least as accurate and faster
            if self.err_mG is None:
                return "peer failed"
            ok = self.versus[0] <= self.err_mG + 0.5 and self.versus[1] < self.seconds
            return f"ours {self.versus[0]:.1f} mG in {self.versus[1]:.1f} s: {'PASS' if ok else 'FAIL'}"
        if not self.named:
            return "FAIL"
        if self.target_mG is None or self.status not in ("ok", "weak"):
            return "named" if self.status != "ok" else "-"
        return "PASS" if self.err_mG is not None and self.err_mG <= self.target_mG else "FAIL"


# ------------------------------------------------------------------------------------ helpers

def calibrate_file(path: Path) -> tuple[FlightLog, list[dict], float]:
    """(log, results, seconds for reading + calibrating)."""
    t0 = time.perf_counter()
    log = read_log(path)
    results = calibrate_compasses(log)
    return log, results, time.perf_counter() - t0


def ours_ofs(r: dict) -> np.ndarray | None:
    return None if r.get("offsets_mG") is None else -np.asarray(r["offsets_mG"], float)


def named(r: dict) -> bool:
    """A status that names its reason; no_data only for a compass without thousands of samples."""
    return r["status"] != "error" and not (r["status"] == "no_data" and r.get("samples", 0) >= 1000)


def truth_ofs(sim, k: int) -> np.ndarray:
    return -np.asarray(sim.truth["compasses"][k]["offsets_rot_mG"], float)


def window_offsets(log: FlightLog, k: int):
    """(COMPASS_OFS of compass k's chosen calibration window, the search) — the window step alone."""
    from groundstation.jobs.calibrate.context import log_context
    from groundstation.jobs.calibrate.settings import DEFAULT_SETTINGS
    from groundstation.jobs.calibrate.windows import window_step
    cf = [f for f in compass_fields(log) if f.compass == k][0]
    step = window_step(log, cf, log_context(log), DEFAULT_SETTINGS)
    w = step.search.chosen_window
    return (None if w is None else -w.fit.offsets_mG), step.search


def inflight_fits(log: FlightLog, k: int):
    """(WmmFit, MotorFieldFit) of compass k on the whole log (the in-flight steps alone)."""
    from groundstation.jobs.calibrate.context import log_context
    from groundstation.jobs.calibrate.inflight import flight_inputs, inflight_step, motor_step
    from groundstation.jobs.calibrate.settings import DEFAULT_SETTINGS
    cf = [f for f in compass_fields(log) if f.compass == k][0]
    ctx = log_context(log)
    x = flight_inputs(log, cf, DEFAULT_SETTINGS.inflight_max_samples)
    return inflight_step(cf, x, ctx, DEFAULT_SETTINGS), motor_step(cf, x, ctx)


# ------------------------------------------------------------------------------------ peers

MAGFIT = Path(__import__("pymavlink").__file__).parent / "tools" / "magfit_WMM.py"


def run_magfit(path: Path, mag: int = 1, reduce: int = 1, timeout_s: float = 1800.0) -> dict:
    """pymavlink's magfit_WMM.py on a DataFlash log (same model as ours: --elliptical --cmot).
    Returns {"ofs": COMPASS_OFS (3,), "cmot": (3,), "runtime_s"} or {"error": ...}."""
    try:
        import scipy  # noqa: F401  (magfit_WMM needs scipy and matplotlib: the "bench" extra)
        import matplotlib  # noqa: F401
    except ImportError as err:
        return {"error": f"magfit_WMM needs {err.name}"}
    cmd = [sys.executable, str(MAGFIT), "--att-source", "ATT", "--mag", str(mag), "--elliptical", "--cmot",
           "--reduce", str(reduce), str(path)]
    t0 = time.perf_counter()
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, env=dict(os.environ, MPLBACKEND="Agg"))
    except subprocess.TimeoutExpired:
        return {"error": f"timeout after {timeout_s:.0f} s", "runtime_s": timeout_s}
    dt = time.perf_counter() - t0
    m = re.search(r"New: Vector3\(([-\d.]+), ([-\d.]+), ([-\d.]+)\).*cmot: Vector3\(([-\d.]+), ([-\d.]+), ([-\d.]+)\)",
                  out.stdout)
    if not m:
        failed = re.search(r"Fit failed: (.*)", out.stdout)
        why = failed.group(1) if failed else (out.stderr.strip().splitlines() or ["no result"])[-1]
        return {"error": why[:120], "runtime_s": dt}
    v = np.array([float(x) for x in m.groups()])
    return {"ofs": v[:3], "cmot": v[3:], "runtime_s": dt}


# ------------------------------------------------------------------------------------ rows

def real_log_names() -> list[str]:
    """The known real logs and every other log file under ../shared/data (any a later crawl adds)."""
    names = list(REAL_LOGS)
    if SHARED.is_dir():
        for p in sorted(SHARED.rglob("*")):
            rel = str(p.relative_to(SHARED))
            if p.is_file() and p.suffix.lower() in (".bin", ".tlog", ".ulg", ".log", ".px4log") and rel not in names:
                names.append(rel)
    return names


def _att(r: dict) -> str:
    """The attitude source the in-flight fit used, for the method column."""
    return f" ({r['attitude_source']})" if r.get("method") == "wmm_inflight" and r.get("attitude_source") else ""


def _sd(r: dict) -> np.ndarray | None:
    sd = r.get("offsets_sd_mG")
    return None if not sd or None in sd else np.asarray(sd, float)


def real_rows(magfit_reduce: int | None = 1) -> list[Row]:
    """Ours on every real log, against the offsets the vehicle had in force at the end; magfit_WMM on
    every ArduPilot log beside it (it reads DataFlash MAG/ATT/BAT; on a telemetry log it says why not)."""
    rows = []
    for name in real_log_names():
        path = SHARED / name
        if not path.is_file():
            rows.append(Row(name, None, "missing", "", None, "", None, None, 0.0))
            continue
        try:
            log, results, dt = calibrate_file(path)
        except Exception as e:  # an unreadable log is a row, not a crash
            rows.append(Row(name, None, f"unreadable: {e}", "", None, "", None, None, 0.0))
            continue
        first = None
        for r in results:
            corr = r.get("corrections") or {}
            end = corr.get("offsets_in_force_end_mG")
            ref = -np.asarray(end, float) if end and None not in end else None
            target = 20.0 if name.startswith("dronekit") else None
            rows.append(Row(name, r["compass"], r["status"], (r.get("method") or "-") + _att(r), ours_ofs(r),
                            "vehicle's offsets in force", ref, target, dt, named(r), _sd(r)))
            first = rows[-1] if first is None else first
        if magfit_reduce is not None and log.autopilot == "ardupilot" and first is not None:
            mf = run_magfit(path, 1, magfit_reduce)
            versus = (first.err_mG if first.err_mG is not None else float("inf"), first.seconds)
            if "error" in mf:
                rows.append(Row(name, 0, f"error: {mf['error']}", f"magfit_WMM --reduce {magfit_reduce}", None,
                                first.ref_name, None, None, mf.get("runtime_s", 0.0), versus=versus))
            else:
                rows.append(Row(name, 0, "ok", f"magfit_WMM --reduce {magfit_reduce}", mf["ofs"], first.ref_name,
                                first.ref, None, mf["runtime_s"], versus=versus))
    return rows


def dance_rows(seed: int, tmp: Path, imu_rate_hz: float = 1.5) -> list[Row]:
    """An onboard calibration in a low-rate telemetry log: ours vs the vehicle's MAG_CAL_REPORT."""
    from groundstation.sim.ardupilot import ArduSimConfig, simulate_ardupilot
    sim = simulate_ardupilot(ArduSimConfig(seed=seed, imu_rate_hz=imu_rate_hz))
    log, results, dt = calibrate_file(sim.write_tlog(tmp / f"dance-{seed}.tlog"))
    rows = []
    for r in results:
        rep = r.get("onboard_report") or {}
        ref = np.asarray(rep["COMPASS_OFS"], float) if rep.get("COMPASS_OFS") else None
        rows.append(Row(f"sim {seed} dance {imu_rate_hz:g} Hz tlog", r["compass"], r["status"], r.get("method") or "-",
                        ours_ofs(r), "MAG_CAL_REPORT", ref, 20.0, dt, named(r)))
    return rows


def flight_rows(seed: int, tmp: Path, layouts, magfit_reduce: int | None, log_rate_hz: float = 10.0
                ) -> tuple[list[Row], list[str]]:
    """A flight without a dance: tlog and DataFlash layouts vs truth (offsets 5 mG, motor 10 %), magfit side by side."""
    from groundstation.sim.ardupilot import ArduSimConfig, simulate_ardupilot
    from groundstation.sim.ardupilot_flight import FlightPlan
    sim = simulate_ardupilot(ArduSimConfig(seed=seed, imu_rate_hz=2.0,
                                           plan=FlightPlan(dance=False, legs=6, log_rate_hz=log_rate_hz)))
    rows, motor = [], []
    files = [("tlog", sim.write_tlog(tmp / f"flight-{seed}.tlog"))]
    files += [(f"bin {lay}", sim.write_bin(tmp / f"flight-{seed}-{lay}.bin", lay)) for lay in layouts]
    for kind, path in files:
        log, results, dt = calibrate_file(path)
        for r in results:
            k = r["compass"]
            rows.append(Row(f"sim {seed} flight {kind}", k, r["status"], r.get("method") or "-", ours_ofs(r),
                            "truth", truth_ofs(sim, k), 5.0, dt, named(r), _sd(r)))
            mot = r.get("motor") or {}
            if kind == "tlog" and mot.get("status") == "ok":
                f = np.asarray(sim.truth["compasses"][k]["motor_mG_per_A"], float)
                rel = 100 * float(np.linalg.norm(np.asarray(mot["motor_mG_per_unit"], float) - f) / np.linalg.norm(f))
                motor.append(f"| sim {seed} flight tlog | {k} | {np.linalg.norm(f):.2f} | {rel:.1f} | 10 | "
                             f"{'PASS' if rel <= 10 else 'FAIL'} |")
            elif kind == "tlog":
                motor.append(f"| sim {seed} flight tlog | {k} | - | {mot.get('status', 'no fit')} | 10 | named |")
        if kind.startswith("bin") and magfit_reduce is not None:
            rows.append(_magfit_row(sim, seed, kind, path, magfit_reduce, rows[-len(results)]))
    return rows, motor


def _magfit_row(sim, seed: int, kind: str, path: Path, reduce: int, ours: Row) -> Row:
    """magfit_WMM on compass 0 of the same file, against the truth and our row (error, seconds:
    ours read the log and calibrate all three compasses)."""
    mf = run_magfit(path, 1, reduce)
    label = f"sim {seed} flight {kind}"
    versus = (ours.err_mG if ours.err_mG is not None else float("inf"), ours.seconds)
    if "error" in mf:
        return Row(label, 0, f"error: {mf['error']}", f"magfit_WMM --reduce {reduce}", None, "truth", None, None,
                   mf.get("runtime_s", 0.0), versus=versus)
    return Row(label, 0, "ok", f"magfit_WMM --reduce {reduce} ({mf['runtime_s'] / ours.seconds:.0f}x our time)",
               mf["ofs"], "truth", truth_ofs(sim, 0), None, mf["runtime_s"], versus=versus)


# ------------------------------------------------------------------------------------ SITL

SITL = ROOT.parent / "shared" / "sitl"
SITL_TRUTH_OFS = {0: np.array([120.0, -80.0, 60.0]), 1: np.array([5.0, 13.0, -18.0]), 2: np.array([5.0, 13.0, -18.0])}


SITL_INSTANCE = 5          # -I 5: SITL's own ports + 50; our MAVLink listener on loopback UDP below
SITL_PORT = 14655


def record_sitl(tmp: Path, circle_s: float = 150.0, speedup: int = 5, port: int = SITL_PORT,
                timeout_s: float = 600.0) -> tuple[Path | None, str, Path | None]:
    """Fly ArduPilot SITL (../shared/sitl, instance -I ``SITL_INSTANCE``, MAVLink to udp
    127.0.0.1:``port``): take off to 30 m, circle (every heading) for ``circle_s`` s of vehicle
    time, land.  Compass 1 has SIM_MAG1_OFS = (120, −80, 60) mG and COMPASS_OFS = (1, 1, 1) in force
    (uncalibrated; COMPASS_USE = 0, the EKF takes compass 2), compasses 2 and 3 the defaults (5, 13, −18) both ways;
    the truth is COMPASS_OFSn = SIM_MAGn_OFS.  The telemetry received (4 Hz streams and the parameter list) is kept as a .tlog.
    Returns (the DataFlash .BIN, note, the .tlog)."""
    from pymavlink import mavutil
    binary = SITL / "arducopter"
    if not binary.is_file():
        return None, "no ../shared/sitl/arducopter", None
    run = tmp / "sitl"
    run.mkdir(exist_ok=True)
    t = SITL_TRUTH_OFS[0]
    (run / "truth.parm").write_text(f"SIM_MAG1_OFS_X {t[0]}\nSIM_MAG1_OFS_Y {t[1]}\nSIM_MAG1_OFS_Z {t[2]}\n"
                                    "COMPASS_OFS_X 1\nCOMPASS_OFS_Y 1\nCOMPASS_OFS_Z 1\nARMING_CHECK 0\n"
                                    "COMPASS_USE 0\n"
                                    "CIRCLE_RADIUS 3000\nCIRCLE_RATE 15\n")
    cmd = [str(binary), "--model", "quad", "--speedup", str(speedup), "-w", "-I", str(SITL_INSTANCE),
           "--defaults", f"{SITL / 'copter.parm'},{run / 'truth.parm'}", "--home", "-35.3632,149.1652,584,0",
           "--serial0", f"udpclient:127.0.0.1:{port}"]
    proc = subprocess.Popen(cmd, cwd=run, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + timeout_s
    try:
        m = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}")
        # pymavlink's UDP link does not write its logfile: each message is kept here, stamped with the
        # vehicle's clock (time_boot_ms / time_usec since boot, else the last seen): at --speedup N the
        # wall clock runs N times slower than the flight, and a real ground station sees real time
        tlog_file = open(run / "telemetry.tlog", "wb")
        t0_us, boot_us = int(time.time() * 1e6), [0]

        def keep(msg) -> None:
            if msg.get_type() == "BAD_DATA":
                return
            ms, us = getattr(msg, "time_boot_ms", None), getattr(msg, "time_usec", None)
            if ms is not None:
                boot_us[0] = max(boot_us[0], int(ms) * 1000)
            elif us is not None and 0 < us < 10 ** 11:        # µs since boot, not a UNIX time
                boot_us[0] = max(boot_us[0], int(us))
            tlog_file.write(struct.pack(">Q", t0_us + boot_us[0]) + msg.get_msgbuf())

        m.mav.set_callback(keep)
        if m.wait_heartbeat(timeout=60) is None:
            return None, "SITL sent no heartbeat", None
        m.mav.request_data_stream_send(m.target_system, m.target_component, mavutil.mavlink.MAV_DATA_STREAM_ALL, 4, 1)
        m.param_fetch_all()

        def boot_s() -> float:
            msg = m.recv_match(type="ATTITUDE", blocking=True, timeout=5)
            return -1.0 if msg is None else msg.time_boot_ms / 1000.0

        last_rc = [0.0]

        def hold_throttle() -> None:
            """Throttle stick at mid (RC_CHANNELS_OVERRIDE, 2 Hz): CIRCLE takes the climb rate from it,
            and SITL's idle stick (1000) made the vehicle descend into the ground (measured)."""
            if time.monotonic() - last_rc[0] > 0.5:
                last_rc[0] = time.monotonic()
                m.mav.rc_channels_override_send(m.target_system, m.target_component, 0, 0, 1500, 0, 0, 0, 0, 0)

        def wait_until(cond, limit_s: float) -> bool:
            t0 = boot_s()
            while time.monotonic() < deadline:
                hold_throttle()
                if cond():
                    return True
                if boot_s() - t0 > limit_s:
                    return False
            return False

        def armed() -> bool:
            hb = m.recv_match(type="HEARTBEAT", blocking=True, timeout=5)
            return hb is not None and bool(hb.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

        def try_arm() -> bool:
            m.set_mode("GUIDED")
            m.arducopter_arm()
            return armed() or armed()

        if not wait_until(try_arm, 180):
            return None, "SITL would not arm in GUIDED within 180 s", None
        m.mav.command_long_send(m.target_system, m.target_component, mavutil.mavlink.MAV_CMD_NAV_TAKEOFF,
                                0, 0, 0, 0, 0, 0, 0, 30)

        def high() -> bool:
            g = m.recv_match(type="GLOBAL_POSITION_INT", blocking=True, timeout=5)
            return g is not None and g.relative_alt > 25_000

        if not wait_until(high, 90):
            return None, "SITL did not climb to 25 m", None
        m.set_mode("CIRCLE")
        wait_until(lambda: False, circle_s)
        m.set_mode("LAND")
        wait_until(lambda: not armed(), 120)
        m.param_fetch_all()          # the parameters once more at the end, as a ground station would
        wait_until(lambda: False, 5)
    finally:
        if "tlog_file" in locals():
            tlog_file.close()
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
    logs = sorted((run / "logs").glob("*.BIN"))
    tlog = run / "telemetry.tlog"
    return (logs[-1], "", tlog if tlog.is_file() else None) if logs else (None, "SITL wrote no .BIN", None)


def sitl_rows(tmp: Path, magfit_reduce: int | None) -> list[Row]:
    path, note, tlog = record_sitl(tmp)
    if path is None:
        return [Row("SITL circle flight .BIN", None, f"not recorded: {note}", "", None, "", None, None, 0.0)]
    rows = []
    for label, p in (("SITL circle flight .BIN", path), ("SITL circle flight telemetry .tlog", tlog)):
        if p is None:
            continue
        log, results, dt = calibrate_file(p)
        rows += [Row(label, r["compass"], r["status"], (r.get("method") or "-") + _att(r), ours_ofs(r),
                     "SIM_MAG_OFS", SITL_TRUTH_OFS.get(r["compass"]), 5.0, dt, named(r), _sd(r)) for r in results]
    if magfit_reduce is not None and rows:
        mf = run_magfit(path, 1, magfit_reduce)
        versus = (rows[0].err_mG if rows[0].err_mG is not None else float("inf"), rows[0].seconds)
        rows.append(Row("SITL circle flight .BIN", 0, "ok" if "ofs" in mf else f"error: {mf.get('error')}",
                        f"magfit_WMM --reduce {magfit_reduce}", mf.get("ofs"), "SIM_MAG_OFS", SITL_TRUTH_OFS[0], None,
                        mf.get("runtime_s", 0.0), versus=versus))
    return rows


# ------------------------------------------------------------------------------------ table

def _vec(v) -> str:
    return "-" if v is None else "[" + ", ".join(f"{x:.0f}" for x in v) + "]"


def format_rows(rows: list[Row]) -> str:
    head = ("| log | compass | status | method | COMPASS_OFS ours | our 1σ mG | reference | reference COMPASS_OFS | "
            "max Δ mG | Δ within 1σ | target mG | verdict | s |")
    lines = [head, "|" + "---|" * 13]
    for r in rows:
        err = "-" if r.err_mG is None else f"{r.err_mG:.1f}"
        sd = "-" if r.sd is None else "[" + ", ".join(f"{x:.1f}" for x in r.sd) + "]"
        within = "-" if r.sd is None or r.ours is None or r.ref is None else \
            f"{int(np.sum(np.abs(r.ours - r.ref) <= r.sd))}/3"
        lines.append(f"| {r.log} | {'-' if r.compass is None else r.compass} | {r.status} | {r.method} | {_vec(r.ours)} | "
                     f"{sd} | {r.ref_name} | {_vec(r.ref)} | {err} | {within} | "
                     f"{'-' if r.target_mG is None else f'{r.target_mG:g}'} | {r.verdict} | {r.seconds:.1f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="seed 1 only; magfit_WMM on every 10th record")
    ap.add_argument("--smoke", action="store_true", help="one short simulated flight, no real logs, no magfit")
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument("--magfit-reduce", type=int, default=4, help="magfit_WMM --reduce (1: every record)")
    ap.add_argument("--no-magfit", action="store_true")
    ap.add_argument("--sitl", action="store_true", help="also record and fit an ArduPilot SITL circle flight")
    ap.add_argument("--no-sim", action="store_true", help="real logs (and --sitl) only")
    a = ap.parse_args(argv)
    seeds = [1] if (a.quick or a.smoke) else list(range(1, a.seeds + 1))
    reduce = None if (a.no_magfit or a.smoke) else (10 if a.quick else a.magfit_reduce)
    rows, motor = ([] if a.smoke else real_rows(None if a.no_magfit else (10 if a.quick else 1))), []
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        if a.sitl:
            rows += sitl_rows(tmp, reduce if reduce is not None else None)
        for s in ([] if a.no_sim else seeds):
            rows += dance_rows(s, tmp)
            fr, mr = flight_rows(s, tmp, ("timeus_instance",) if a.smoke else LAYOUTS, reduce,
                                 log_rate_hz=4.0 if a.smoke else 10.0)
            rows += fr
            motor += mr
    print(format_rows(rows))
    print("\nMotor field per ampere (in-flight fit on the telemetry log) against the truth")
    print("| log | compass | truth mG/A | error % | target % | verdict |\n|---|---|---|---|---|---|")
    print("\n".join(motor))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
