"""Real and simulated autopilot logs through `magstation calibrate`, next to the vehicle, the truth and
pymavlink's magfit_WMM.py.

    .venv/bin/python benchmarks/real_logs.py                 # real logs + simulated seed 1 (--seeds N for more),
                                                             # magfit_WMM on every 4th record of each .bin
                                                             # (--magfit-reduce 1: all; ~15-40 min on 2 cores)
    .venv/bin/python benchmarks/real_logs.py --quick         # real logs + seed 1, magfit on every 10th record
    .venv/bin/python benchmarks/real_logs.py --smoke         # one short simulated flight, no real logs, no magfit
                                                             # (the test; < 20 s)
    .venv/bin/python benchmarks/real_logs.py --sitl 10 --sitl-recorded DIR --no-sim --magfit-reduce 10
                                                             # + ten ArduPilot SITL route flights at 1x (-I 15..19,
                                                             # five at once, ~5 min each), kept in DIR and re-used;
                                                             # one table per compass: truth, ours .BIN/.tlog, 1σ,
                                                             # magfit_WMM, the motor field
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
  truth and its runtime over ours (ours: reading the log + calibrating all three compasses);
* ArduPilot SITL route flights (SitlFlight, record_sitl): against SIM_MAGn_OFS and SIM_MAG_MOT, from
  the .BIN and the telemetry .tlog, magfit_WMM on every compass of the .BIN (dataflash_for_compass).
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import re  # noqa: E402
import shutil  # noqa: E402
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
    wmm = inflight_step(cf, x, ctx, DEFAULT_SETTINGS)
    return wmm, motor_step(cf, x, ctx, wmm)


# ------------------------------------------------------------------------------------ peers

MAGFIT = Path(__import__("pymavlink").__file__).parent / "tools" / "magfit_WMM.py"


def copy_dataflash(path: Path, out: Path, edit) -> Path:
    """Copy the DataFlash log ``path`` record by record to ``out``; ``edit(name, fields, record)`` returns
    the record (bytes) to write, or None to drop it (``fields``: column -> (byte offset, struct code);
    FMT records are passed as name "FMT" with the format's name, columns and record)."""
    from pymavlink.DFReader import FORMAT_TO_STRUCT
    data = path.read_bytes()
    fmts: dict[int, tuple[str, int, dict]] = {}
    parts, i = [], 0
    while i + 3 <= len(data):
        if data[i] != 0xA3 or data[i + 1] != 0x95:
            i += 1                                   # resynchronise on a damaged stretch, as DFReader does
            continue
        mtype = data[i + 2]
        if mtype == 128 and i + 89 <= len(data):
            ftype, flen = data[i + 3], data[i + 4]
            name = data[i + 5:i + 9].rstrip(b"\0").decode(errors="replace")
            fmt = data[i + 9:i + 25].rstrip(b"\0").decode(errors="replace")
            cols = data[i + 25:i + 89].rstrip(b"\0").decode(errors="replace").split(",")
            fields, ofs = {}, 3
            for c, code in zip(cols, fmt):
                st = FORMAT_TO_STRUCT.get(code, ("B",))[0]
                fields[c] = (ofs, st)
                ofs += struct.calcsize("<" + st)
            fmts[ftype] = (name, flen, fields)
            rec = edit("FMT", {"Name": name, "Columns": cols}, data[i:i + 89])
            if rec is not None:
                parts.append(rec)
            i += 89
            continue
        if mtype not in fmts:
            i += 1
            continue
        name, flen, fields = fmts[mtype]
        rec = edit(name, fields, data[i:i + flen])
        if rec is not None:
            parts.append(rec)
        i += flen
    out.write_bytes(b"".join(parts))
    return out


def _field(rec: bytes, fields: dict, col: str):
    ofs, st = fields[col]
    return struct.unpack_from("<" + st, rec, ofs)[0]


def dataflash_for_compass(path: Path, k: int, out: Path) -> Path:
    """A copy of the DataFlash log ``path`` in which magfit_WMM.py's ``--mag 1`` means compass
    index ``k`` (0-based).  magfit_WMM reads ``MAG`` for its first compass and ``MAG<n>`` for the
    others, and takes every ``MAG`` record: on ArduPilot 4.x, whose one ``MAG`` message carries all
    compasses with an instance column ``I``, it fitted the three compasses' samples as one (the
    "iteration limit" failure on the SITL .BIN).  The copy keeps the ``MAG`` records of instance
    ``k`` only (older logs: ``MAG<k+1>`` renamed ``MAG``), and swaps compass k's PARM names
    (COMPASS_OFSn/DIAn/ODIn/MOTn/SCALEn) with compass 1's, so magfit strips compass k's corrections."""
    n = k + 1
    swap: dict[str, str] = {}
    if k > 0:
        for key in ("OFS", "DIA", "ODI", "MOT"):
            for axis in "XYZ":
                swap[f"COMPASS_{key}_{axis}"], swap[f"COMPASS_{key}{n}_{axis}"] = \
                    f"COMPASS_{key}{n}_{axis}", f"COMPASS_{key}_{axis}"
        swap["COMPASS_SCALE"], swap[f"COMPASS_SCALE{n}"] = f"COMPASS_SCALE{n}", "COMPASS_SCALE"

    def edit(name: str, fields: dict, rec: bytes):
        if name == "FMT":
            if k > 0 and fields["Name"] == f"MAG{n}":
                return rec[:5] + b"MAG\0" + rec[9:]
            if k > 0 and fields["Name"] == "MAG" and "I" not in fields["Columns"]:
                return rec[:5] + b"MAGx" + rec[9:]      # the first compass's own MAG: out of magfit's way
            return rec
        if name == "MAG" and "I" in fields:
            return rec if _field(rec, fields, "I") == k else None
        if name == "PARM" and "Name" in fields:
            ofs = fields["Name"][0]
            pname = rec[ofs:ofs + 16].rstrip(b"\0").decode(errors="replace")
            if pname in swap:
                return rec[:ofs] + swap[pname].encode().ljust(16, b"\0") + rec[ofs + 16:]
        return rec
    return copy_dataflash(path, out, edit)


CUT_BIN_KEEP = {"FMT": 1, "FMTU": 1, "UNIT": 1, "MULT": 1, "PARM": 1, "MSG": 1, "MODE": 1, "ORGN": 1,
                "MAG": 2, "ATT": 2, "GPS": 1, "BAT": 5}      # name: keep every n-th record
CUT_TLOG_KEEP = {"HEARTBEAT": 4, "PARAM_VALUE": 1, "RAW_IMU": 1, "SCALED_IMU2": 1, "SCALED_IMU3": 1,
                 "ATTITUDE": 1, "GPS_RAW_INT": 2, "GLOBAL_POSITION_INT": 4, "SYS_STATUS": 2,
                 "BATTERY_STATUS": 8, "SENSOR_OFFSETS": 8, "STATUSTEXT": 1, "SYSTEM_TIME": 8}


def cut_sitl_flight(run: Path, out: Path) -> list[Path]:
    """A small copy of a recorded SITL flight (``record_sitl``) for tests/data: the .BIN with the
    records the in-flight fit reads (MAG and ATT every 2nd record: 5 Hz; BAT 2 Hz; GPS, PARM, ...),
    the .tlog with its compass, attitude, position, battery and parameter messages, and truth.json."""
    from pymavlink import mavutil
    out.mkdir(parents=True, exist_ok=True)
    seen: dict[tuple, int] = {}

    def edit(name: str, fields: dict, rec: bytes):
        if name == "FMT":
            return rec
        every = CUT_BIN_KEEP.get(name)
        if every is None:
            return None
        key = (name, _field(rec, fields, "I") if "I" in fields and name == "MAG" else 0)
        seen[key] = seen.get(key, -1) + 1
        return rec if seen[key] % every == 0 else None
    copy_dataflash(run / "flight.BIN", out / "flight.BIN", edit)
    conn = mavutil.mavlink_connection(str(run / "telemetry.tlog"))
    kept: dict[str, int] = {}
    with open(out / "telemetry.tlog", "wb") as f:
        while True:
            m = conn.recv_match()
            if m is None:
                break
            every = CUT_TLOG_KEEP.get(m.get_type())
            if every is None:
                continue
            kept[m.get_type()] = kept.get(m.get_type(), -1) + 1
            if kept[m.get_type()] % every == 0:
                f.write(struct.pack(">Q", int(m._timestamp * 1e6)) + m.get_msgbuf())
    conn.close()
    shutil.copy(run / "truth.json", out / "truth.json")
    return [out / "flight.BIN", out / "telemetry.tlog", out / "truth.json"]


def run_magfit(path: Path, mag: int = 1, reduce: int = 1, timeout_s: float = 1800.0, iterations: int = 1000) -> dict:
    """pymavlink's magfit_WMM.py on compass index ``mag - 1`` of a DataFlash log (the same model as
    ours: --elliptical --cmot; attitude ATT; ``--iter`` raised from its 100 to ``iterations``: SLSQP on
    its 13 parameters ends "Iteration limit reached" at 100 on a 3-minute flight), through
    ``dataflash_for_compass``.  Returns {"ofs": COMPASS_OFS (3,), "cmot": (3,), "runtime_s"} or {"error": ...}."""
    if path.suffix.lower() != ".bin":
        return {"error": "magfit_WMM reads DataFlash logs only (PARM, MAG, ATT, BAT, GPS records)"}
    try:
        import scipy  # noqa: F401  (magfit_WMM needs scipy and matplotlib: the "bench" extra)
        import matplotlib  # noqa: F401
    except ImportError as err:
        return {"error": f"magfit_WMM needs {err.name}"}
    with tempfile.TemporaryDirectory() as d:
        one = dataflash_for_compass(path, mag - 1, Path(d) / "compass.bin")
        cmd = [sys.executable, str(MAGFIT), "--att-source", "ATT", "--mag", "1", "--elliptical", "--cmot",
               "--reduce", str(reduce), "--iter", str(iterations), "--save-plot", str(one)]
        t0 = time.perf_counter()
        try:
            out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s,
                                 env=dict(os.environ, MPLBACKEND="Agg"))
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
sys.path.insert(0, str(ROOT / "tests" / "sitl"))      # harness.Sitl: the one way this project starts SITL
SITL_INSTANCES = range(15, 20)                         # -I 15..19 (benchmarks/sitl.py and its tests take 10..14)
SITL_PORTS = range(14635, 14640)                       # our MAVLink listener (loopback UDP), one per instance
SITL_SITES = (("Canberra", (-35.3632, 149.1652, 584.0)), ("Hangzhou", (30.3, 120.1, 10.0)),
              ("Tromsø", (69.68, 18.94, 20.0)), ("Boulder", (40.015, -105.27, 1655.0)),
              ("Cape Town", (-33.92, 18.42, 30.0)))


@dataclass(frozen=True)
class SitlFlight:
    """One recorded ArduCopter SITL flight and its truth: per compass n (1..3) SIM_MAGn_OFS (mG),
    DIA, ODI; SIM_MAG_MOT (mG/A, body frame, all compasses); no calibration dance.  The corrections
    in force are an uncalibrated vehicle's for compasses 2 and 3 (COMPASS_OFSn 0.001, DIA 1, ODI 0,
    COMPASS_MOTn 0: COMPASS_USE2/3 = 0) and the truth for compass 1, which the EKF uses (offsets,
    soft iron and, from ``compensated_motor`` on, COMPASS_MOT: seeds 1–3 were flown with it 0, and
    the EKF's yaw then followed the motor field: 33 mG of x error from the .tlog's ATTITUDE on seed 3).
    Every correction in force is stripped before the fit.  Truth: COMPASS_OFSn = SIM_MAGn_OFS,
    the field per ampere = SIM_MAG_MOT (COMPASS_MOT = −SIM_MAG_MOT)."""
    seed: int
    site: str
    home: tuple[float, float, float, float]          # lat, lon deg, alt m, initial yaw deg
    ofs_mG: tuple[tuple[float, float, float], ...]
    dia: tuple[tuple[float, float, float], ...]
    odi: tuple[tuple[float, float, float], ...]
    mot_mG_per_A: tuple[float, float, float]
    compensated_motor: bool = True
    vertices: int = 10
    radius_m: tuple[float, float] = (40.0, 90.0)     # the route's vertices from home (the first three flights: 50–110)

    @staticmethod
    def of_seed(seed: int) -> "SitlFlight":
        """Distinct truth, site and heading per seed (SIM_MAG_MOT of 2–5 mG/A per axis, mixed signs)."""
        rng = np.random.default_rng(1000 + seed)
        site, (lat, lon, alt) = SITL_SITES[seed % len(SITL_SITES)]
        ofs = tuple(tuple(float(round(v)) for v in rng.uniform(-150, 150, 3)) for _ in range(3))
        dia = tuple(tuple(float(round(v, 3)) for v in rng.uniform(0.95, 1.05, 3)) for _ in range(3))
        odi = tuple(tuple(float(round(v, 3)) for v in rng.uniform(-0.03, 0.03, 3)) for _ in range(3))
        mot = tuple(float(round(v, 1)) for v in rng.uniform(2, 5, 3) * rng.choice([-1, 1], 3))
        old = seed <= 3                        # the first three flights: compass 1's motor field uncompensated, 7 vertices
        return SitlFlight(seed, site, (lat, lon, alt, float(rng.integers(0, 360))), ofs, dia, odi, mot,
                          compensated_motor=not old, vertices=7 if old else 10)

    def params(self) -> dict[str, float]:
        out = {"ARMING_CHECK": 0, "COMPASS_USE2": 0, "COMPASS_USE3": 0, "COMPASS_MOTCT": 2, "LOG_DISARMED": 0}
        for n in (1, 2, 3):
            sfx = "" if n == 1 else str(n)
            for key, vals in (("OFS", self.ofs_mG), ("DIA", self.dia), ("ODI", self.odi)):
                for axis, v in zip("XYZ", vals[n - 1]):
                    out[f"SIM_MAG{n}_{key}_{axis}"] = v
                    inforce = v if n == 1 else {"OFS": 0.001, "DIA": 1.0, "ODI": 0.0}[key]
                    out[f"COMPASS_{key}{sfx}_{axis}"] = inforce
            for axis, v in zip("XYZ", self.mot_mG_per_A):
                out[f"COMPASS_MOT{sfx}_{axis}"] = -v if (n == 1 and self.compensated_motor) else 0.0
        for axis, v in zip("XYZ", self.mot_mG_per_A):
            out[f"SIM_MAG_MOT_{axis}"] = v
        return out

    def truth_ofs(self, k: int) -> np.ndarray:
        """COMPASS_OFS of compass index k (0-based)."""
        return np.asarray(self.ofs_mG[k], float)

    def truth_mot(self) -> np.ndarray:
        """COMPASS_MOT (ArduPilot adds COMPASS_MOT × current to the field: −SIM_MAG_MOT)."""
        return -np.asarray(self.mot_mG_per_A, float)

    def route(self) -> list[tuple[float, float, float, float]]:
        """(north m, east m, alt m, ground speed m/s) targets: a hexagon-ish loop of legs at random
        bearings (every heading), each at its own speed (3–11 m/s) and height (15–60 m), with a
        vertical climb and a descent in place between some legs, so that the current (climb: high,
        descent: low, speed changes) varies independently of the attitude."""
        rng = np.random.default_rng(2000 + self.seed)
        bearings = np.sort(rng.uniform(0, 2 * np.pi, self.vertices)) + rng.uniform(0, 2 * np.pi)
        pts = []
        for i, b in enumerate(bearings):
            r = rng.uniform(50, 110) if self.vertices == 7 else rng.uniform(*self.radius_m)
            alt = float(rng.uniform(15, 60))
            pts.append((r * np.cos(b), r * np.sin(b), alt, float(rng.uniform(3, 11))))
            if i in (1, 4) or (self.vertices > 7 and i == 7):   # climb / descend in place: current without tilt
                pts.append((r * np.cos(b), r * np.sin(b), 70.0 if alt < 40 else 12.0, 5.0))
        pts.append((0.0, 0.0, 20.0, 6.0))
        return pts


def record_sitl(tmp: Path, flight: SitlFlight, instance: int | None = 15, port: int | None = 14635,
                timeout_s: float = 600.0, speedup: float = 1.0, land: bool = True
                ) -> tuple[Path | None, str, Path | None]:
    """Fly ArduPilot SITL (../shared/sitl, harness.Sitl, ``-I instance``, MAVLink to udp
    127.0.0.1:``port``, at ``speedup`` (1 for the benchmark: a station's .tlog is stamped by the wall
    clock; the .tlog kept here is stamped by the vehicle's) through
    ``flight.route()`` in GUIDED (take off to 20 m, MAV_CMD_DO_CHANGE_SPEED + DO_REPOSITION per
    target, land unless ``land`` is False), the throttle stick held at mid by RC override.  The telemetry received (4 Hz
    streams, the parameter list at the start and the end) is kept as a .tlog stamped with the
    vehicle's clock.  Returns (the DataFlash .BIN, note, the .tlog); the truth goes to truth.json."""
    import json
    from harness import SITL_BINARY, Sitl
    from pymavlink import mavutil
    if SITL_BINARY is None:
        return None, "no ../shared/sitl/arducopter", None
    if (instance is not None and instance not in SITL_INSTANCES) or (port is not None and port not in SITL_PORTS):
        return None, f"SITL instance {instance}/port {port} outside -I {SITL_INSTANCES.start}..{SITL_INSTANCES.stop - 1}", None
    sitl = Sitl(instance, port, speedup=speedup, extra=flight.params(), limit_s=timeout_s + 30, home=flight.home)
    run = tmp
    run.mkdir(parents=True, exist_ok=True)
    deadline = time.monotonic() + timeout_s
    tlog_file = open(run / "telemetry.tlog", "wb")
    m = None
    try:
        sitl.start()                      # claims the instance and our UDP port (None: the harness picks free ones)
        instance, port = sitl.instance, sitl.port
        (run / "truth.json").write_text(json.dumps({"recorded": f"benchmarks/real_logs.py record_sitl, -I {instance}, 1x, "
                                                                f"{time.strftime('%Y-%m-%d', time.gmtime())}",
                                                    "flight": flight.__dict__, "params": flight.params()}, indent=1))
        m = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}")
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
        last_rc = [0.0]
        pos = {"n": 0.0, "e": 0.0, "alt": 0.0}

        def pump(limit_s: float, cond=lambda: False) -> bool:
            """Read the link (keeping every message) until ``cond()`` or ``limit_s`` s pass."""
            end = min(time.monotonic() + limit_s, deadline)
            while time.monotonic() < end:
                if time.monotonic() - last_rc[0] > 0.5:
                    last_rc[0] = time.monotonic()
                    m.mav.rc_channels_override_send(m.target_system, m.target_component, 0, 0, 1500, 0, 0, 0, 0, 0)
                msg = m.recv_match(blocking=True, timeout=0.5)
                if msg is not None and msg.get_type() == "GLOBAL_POSITION_INT":
                    # from home, in the frame of the targets (LOCAL_POSITION_NED is from the EKF origin,
                    # whose height differed from home's by more than the 2 m arrival gate at Canberra)
                    pos.update(n=(msg.lat * 1e-7 - flight.home[0]) * 111_320.0,
                               e=(msg.lon * 1e-7 - flight.home[1]) * 111_320.0 * np.cos(np.radians(flight.home[0])),
                               alt=msg.relative_alt * 1e-3)
                if cond():
                    return True
            return False

        def armed() -> bool:
            return bool(m.motors_armed())

        arm_end = time.monotonic() + 180
        while not armed() and time.monotonic() < arm_end:
            m.set_mode("GUIDED")
            m.arducopter_arm()
            pump(3.0, armed)
        if not armed():
            return None, "SITL would not arm in GUIDED within 180 s", None
        m.mav.command_long_send(m.target_system, m.target_component, mavutil.mavlink.MAV_CMD_NAV_TAKEOFF,
                                0, 0, 0, 0, 0, 0, 0, 20)
        if not pump(60, lambda: pos["alt"] > 18):
            return None, "SITL did not climb to 18 m", None
        lat0, lon0 = flight.home[0], flight.home[1]
        for n, e, alt, speed in flight.route():
            m.mav.command_long_send(m.target_system, m.target_component, mavutil.mavlink.MAV_CMD_DO_CHANGE_SPEED,
                                    0, 1, speed, -1, 0, 0, 0, 0)
            lat = lat0 + n / 111_320.0
            lon = lon0 + e / (111_320.0 * np.cos(np.radians(lat0)))
            m.mav.set_position_target_global_int_send(0, m.target_system, m.target_component, 6, 0b110111111000,
                                                      int(lat * 1e7), int(lon * 1e7), alt, 0, 0, 0, 0, 0, 0, 0, 0)
            pump(60, lambda: np.hypot(pos["n"] - n, pos["e"] - e) < 4 and abs(pos["alt"] - alt) < 2)
        if land:                     # (a test stops in the air: the .BIN is readable up to its last record)
            m.set_mode("LAND")
            pump(90, lambda: not armed())
        m.param_fetch_all()          # the parameters once more at the end, as a ground station would
        pump(5 / speedup)
    finally:
        tlog_file.close()
        sitl.stop(keep=True)
        logs = sitl.bin_logs()
        if logs:
            shutil.copy(logs[-1], run / "flight.BIN")
        if sitl.run_dir is not None:
            shutil.rmtree(sitl.run_dir, ignore_errors=True)
        if m is not None:
            m.close()
    tlog = run / "telemetry.tlog"
    if not logs:
        return None, "SITL wrote no .BIN", None
    return run / "flight.BIN", "", tlog if tlog.is_file() else None


def _motor_ours(r: dict) -> tuple[np.ndarray | None, str]:
    """Our field per ampere (mG/A, the field the current adds: SIM_MAG_MOT's sense) and where from:
    the WMM fit's motor term when it was fitted, else the separate interference fit."""
    w = r.get("inflight") or {}
    if "f_x" in (w.get("fitted") or []) and w.get("motor_mG_per_unit") and None not in w["motor_mG_per_unit"]:
        return np.asarray(w["motor_mG_per_unit"], float), "wmm"
    mot = r.get("motor") or {}
    if mot.get("status") == "ok" and mot.get("motor_mG_per_unit"):
        return np.asarray(mot["motor_mG_per_unit"], float), "motor fit"
    return None, (mot.get("status") or "not fitted")


def load_sitl_flight(run: Path):
    """(SitlFlight, .BIN, .tlog) of a flight recorded by ``record_sitl`` into ``run`` (truth.json)."""
    import json
    d = json.loads((run / "truth.json").read_text())["flight"]
    f = SitlFlight(**{k: (tuple(tuple(x) if isinstance(x, list) else x for x in v) if isinstance(v, list) else v)
                      for k, v in d.items()})
    return f, run / "flight.BIN", run / "telemetry.tlog"


def sitl_rows(tmp: Path, magfit_reduce: int | None, seeds: list[int], recorded: Path | None = None
              ) -> tuple[list[Row], list[str]]:
    """Record (or, with ``recorded``, re-read from recorded/seed<N>/) one SITL route flight per seed,
    up to five at once on -I 15..19, and fit both its logs.  Returns the rows of the main table and
    the per-compass SITL table (truth, ours .BIN, ours .tlog, 1σ, magfit_WMM; motor field)."""
    from concurrent.futures import ThreadPoolExecutor
    runs: dict[int, tuple] = {}
    if recorded is not None:
        for s in seeds:
            if (recorded / f"seed{s}" / "truth.json").is_file():
                runs[s] = load_sitl_flight(recorded / f"seed{s}")
    todo = [s for s in seeds if s not in runs]

    def fly(i_s):
        i, s = i_s
        f = SitlFlight.of_seed(s)
        path, note, tlog = record_sitl((recorded or tmp) / f"seed{s}", f, SITL_INSTANCES[i], SITL_PORTS[i])
        return s, f, path, note, tlog
    for start in range(0, len(todo), len(SITL_INSTANCES)):
        with ThreadPoolExecutor(len(SITL_INSTANCES)) as ex:
            for s, f, path, note, tlog in ex.map(fly, enumerate(todo[start:start + len(SITL_INSTANCES)])):
                runs[s] = (f, path, tlog) if path is not None else (f, None, note)
    def magfit(job):
        """magfit_WMM on compass k of seed s's .BIN, kept beside it (magfit_c<k>_r<reduce>.json: 0.5–3 min each)."""
        import json
        s, k = job
        cache = Path(runs[s][1]).parent / f"magfit_c{k}_r{magfit_reduce}.json"
        if cache.is_file():
            d = json.loads(cache.read_text())
        else:
            d = run_magfit(Path(runs[s][1]), k + 1, magfit_reduce)
            d = {key: (v.tolist() if isinstance(v, np.ndarray) else v) for key, v in d.items()}
            if "ofs" in d:
                cache.write_text(json.dumps(d))
        return job, {key: (np.asarray(v, float) if key in ("ofs", "cmot") else v) for key, v in d.items()}
    jobs = [(s, k) for s in seeds if runs[s][1] is not None for k in range(3)] if magfit_reduce is not None else []
    with ThreadPoolExecutor(2) as ex:
        peers = dict(ex.map(magfit, jobs))
    rows, table = [], []
    for s in seeds:
        f, path, tlog = runs[s]
        label = f"SITL route {s} ({f.site})"
        if path is None:
            rows.append(Row(label, None, f"not recorded: {tlog}", "", None, "", None, None, 0.0))
            continue
        got = {}
        for kind, p in (("bin", path), ("tlog", tlog)):
            if p is None or not Path(p).is_file():
                continue
            log, results, dt = calibrate_file(Path(p))
            for r in results:
                k = r["compass"]
                got[(kind, k)] = r
                rows.append(Row(f"{label} .{'BIN' if kind == 'bin' else 'tlog'}", k, r["status"],
                                (r.get("method") or "-") + _att(r), ours_ofs(r), "SIM_MAG_OFS", f.truth_ofs(k), 5.0,
                                dt, named(r), _sd(r)))
        for k in range(3):
            mf = peers.get((s, k), {"error": "not run"})
            if "ofs" in mf:
                rows.append(Row(f"{label} .BIN", k, "ok", f"magfit_WMM --reduce {magfit_reduce}", mf["ofs"], "SIM_MAG_OFS",
                                f.truth_ofs(k), None, mf["runtime_s"]))
            cells = [label, str(k), _vec(f.truth_ofs(k))]
            for kind in ("bin", "tlog"):
                r = got.get((kind, k))
                o = None if r is None else ours_ofs(r)
                sd = None if r is None else _sd(r)
                err = None if o is None else float(np.max(np.abs(o - f.truth_ofs(k))))
                cells.append("-" if r is None else f"{r['status']} {_vec(o)} Δ {'-' if err is None else f'{err:.1f}'}")
                cells.append("-" if sd is None else "[" + ", ".join(f"{x:.1f}" for x in sd) + "]")
            if "ofs" in mf:
                cells.append(f"{_vec(mf['ofs'])} Δ {float(np.max(np.abs(mf['ofs'] - f.truth_ofs(k)))):.1f}")
            else:
                cells.append(f"no result ({mf['error']})")
            mot_truth = np.asarray(f.mot_mG_per_A, float)
            cells.append(_vec1(mot_truth))
            for kind in ("bin", "tlog"):
                r = got.get((kind, k))
                mv, src = (None, "-") if r is None else _motor_ours(r)
                cells.append(f"{src}" if mv is None else
                             f"{_vec1(mv)} {100 * np.linalg.norm(mv - mot_truth) / np.linalg.norm(mot_truth):.0f} %")
            cells.append("-" if "cmot" not in mf else
                         f"{_vec1(-mf['cmot'])} {100 * np.linalg.norm(-mf['cmot'] - mot_truth) / np.linalg.norm(mot_truth):.0f} %")
            table.append("| " + " | ".join(cells) + " |")
    return rows, table


SITL_HEAD = ("| flight | compass | truth COMPASS_OFS | ours .BIN (Δ max mG) | 1σ .BIN | ours .tlog (Δ max mG) | 1σ .tlog | "
             "magfit_WMM .BIN (Δ max mG) | SIM_MAG_MOT mG/A | ours .BIN (error) | ours .tlog (error) | magfit_WMM −cmot |\n"
             + "|" + "---|" * 12)


def _vec1(v) -> str:
    return "[" + ", ".join(f"{x:.2f}" for x in v) + "]"


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
    ap.add_argument("--sitl", type=int, nargs="?", default=0, const=5, metavar="N",
                    help="also record and fit N (default 5) ArduPilot SITL route flights (seeds 1..N, 1x, up to 5 at once)")
    ap.add_argument("--sitl-recorded", type=Path, default=None, metavar="DIR",
                    help="keep the SITL flights in DIR/seed<N>/ and re-use those already there")
    ap.add_argument("--sitl-first", type=int, default=1, metavar="S",
                    help="the first SITL seed (seeds S..S+N-1; seeds not looked at while developing)")
    ap.add_argument("--no-sim", action="store_true", help="real logs (and --sitl) only")
    ap.add_argument("--no-real", action="store_true", help="without the logs under ../shared/data")
    a = ap.parse_args(argv)
    seeds = [1] if (a.quick or a.smoke) else list(range(1, a.seeds + 1))
    reduce = None if (a.no_magfit or a.smoke) else (10 if a.quick else a.magfit_reduce)
    rows, motor, sitl_table = ([] if a.smoke or a.no_real else real_rows(None if a.no_magfit else (10 if a.quick else 1))), [], []
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        if a.sitl:
            sr, sitl_table = sitl_rows(tmp, reduce, list(range(a.sitl_first, a.sitl_first + a.sitl)), a.sitl_recorded)
            rows += sr
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
    if sitl_table:
        print("\nArduPilot SITL route flights: offsets (COMPASS_OFS, mG) and the motor field per ampere against SIM truth")
        print(SITL_HEAD)
        print("\n".join(sitl_table))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
