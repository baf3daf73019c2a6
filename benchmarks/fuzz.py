"""Hostile-file fuzzing: mutated logs, missions and calibration files through the readers and the
CLI commands, in process, each run classified as

    clean      read / command finished, no warnings
    warnings   finished, damage reported as counted warnings (or a calibration status)
    error      refused with a one-line message (IngestError, `magstation: error: ...`)
    traceback  any other exception, or a command that printed a traceback
    hang       over the time budget
    leak       numpy RuntimeWarning or raw control characters reaching the output

    .venv/bin/python benchmarks/fuzz.py                  # 2,000 mutations
    .venv/bin/python benchmarks/fuzz.py --cases 300 --seed 1

Targets (issues 10, 26): 0 tracebacks, 0 hangs (and 0 leaks).  Seeds (``seeds``) are the small logs
in tests/data, the same .tlog/.bin with parameters set to NaN, +-inf and 3.4e38, a ULog written
here (clean and with such parameters), a calibration JSON, and the first 150 kB of a real PX4 ULog
from ../shared/data when present.  ``absurd_params`` reads the unmutated absurd-parameter seeds
and says whether the reader flags the values (a warning naming the parameter).
The smoke run is tests/test_fuzz.py.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import re
import signal
import struct
import sys
import tempfile
import time
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import groundstation  # noqa: E402,F401
from groundstation.cli import main as cli_main  # noqa: E402
from groundstation.io.errors import IngestError  # noqa: E402
from groundstation.io.logs import read_log  # noqa: E402
from groundstation.io.mission import read_mission  # noqa: E402
from groundstation.station.hub.recordings import compass_count, vehicle_type  # noqa: E402

DATA = ROOT / "tests" / "data"
SHARED_ULOG = ROOT.parent / "shared" / "data" / "px4-pyulog" / "sample_log_small.ulg"
OUTCOMES = ("clean", "warnings", "error", "traceback", "hang", "leak")
RAW_CONTROL = re.compile("[\x00-\x08\x0b-\x1f\x7f-\x9f]")
GOOD_CALIBRATION = {"results": [{"status": "ok", "offsets_mG": [12.0, -30.5, 4.0],
                                 "matrix": [[1.02, 0.01, 0.0], [0.01, 0.97, -0.02], [0.0, -0.02, 1.0]]}]}
# kind: (suffix, share of the cases)
KINDS = {"tlog": (".tlog", 0.26), "bin": (".bin", 0.22), "ulg": (".ulg", 0.12), "csv": (".csv", 0.12),
         "plan": (".plan", 0.08), "waypoints": (".waypoints", 0.06), "calibration": (".json", 0.14)}


class Hang(BaseException):
    pass


@dataclass
class Case:
    kind: str
    name: str          # what was done to the seed, for the report
    data: bytes


NON_FINITE = (float("nan"), float("inf"), float("-inf"), 3.4e38)      # 3.4e38: near float32's largest
ABSURD_PARAMS = ("COMPASS_OFS_X", "COMPASS_DIA_X", "COMPASS_DEV_ID", "MAV_TYPE")      # ArduPilot names
ABSURD_PX4_PARAMS = ("CAL_MAG0_XOFF", "CAL_MAG0_XSCALE", "CAL_MAG0_ID", "MAV_TYPE")


def seeds() -> dict[str, list[tuple[str, bytes]]]:
    """(name, bytes) seeds per kind: the small logs of tests/data, the same logs with parameters set
    to NaN, +-inf and 3.4e38, a ULog written here (clean and with such parameters), a calibration
    JSON, and the first 150 kB of a real PX4 ULog from ../shared/data when present."""
    tlog, dataflash = (DATA / "reference.tlog").read_bytes(), (DATA / "reference.bin").read_bytes()
    out = {"tlog": [("reference", tlog), ("absurd-params", _tlog_with_params(tlog))],
           "bin": [("reference", dataflash), ("absurd-params", _bin_with_params(dataflash))],
           "ulg": [("written", ulog_seed({"CAL_MAG0_ID": 396825, "CAL_MAG0_XOFF": 0.01, "MAV_TYPE": 2})),
                   ("absurd-params", ulog_seed(dict(zip(ABSURD_PX4_PARAMS, NON_FINITE))))],
           "csv": [("mag", (DATA / "mag.csv").read_bytes())],
           "plan": [("mission", (DATA / "mission.plan").read_bytes())],
           "waypoints": [("mission", (DATA / "mission.waypoints").read_bytes())],
           "calibration": [("good", json.dumps(GOOD_CALIBRATION).encode())]}
    if SHARED_ULOG.is_file():
        out["ulg"].append(("px4-pyulog", SHARED_ULOG.read_bytes()[:150_000]))
    return out


def _tlog_with_params(tlog: bytes) -> bytes:
    """The .tlog with PARAM_VALUE records (NaN, +-inf, 3.4e38 for each of ABSURD_PARAMS) before
    its first record, 1 ms earlier."""
    from groundstation.io.mavlink import mavlink2 as m

    mav = m.MAVLink(None, srcSystem=1, srcComponent=1)
    stamp = (int.from_bytes(tlog[:8], "big") - 1000).to_bytes(8, "big")
    names = [n for n in ABSURD_PARAMS for _ in NON_FINITE]
    records = [stamp + m.MAVLink_param_value_message(n.encode(), v, 9, len(names), i).pack(mav)
               for i, (n, v) in enumerate(zip(names, NON_FINITE * len(ABSURD_PARAMS)))]
    return b"".join(records) + tlog


def _bin_with_params(dataflash: bytes) -> bytes:
    """The DataFlash log with PARM records (NaN, +-inf, 3.4e38 for each of ABSURD_PARAMS) at its end."""
    sys.path.insert(0, str(DATA))
    from make_test_logs import df_record

    return dataflash + b"".join(df_record("PARM", 0, n, v) for n in ABSURD_PARAMS for v in NON_FINITE)


def _ulog_message(kind: bytes, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), kind[0]) + payload


def _ulog_keyed(kind: bytes, key: str, value: bytes) -> bytes:
    return _ulog_message(kind, bytes([len(key)]) + key.encode() + value)


def ulog_seed(params: dict[str, float], n: int = 400, rate_hz: float = 50.0) -> bytes:
    """A small PX4 ULog (format version 1): header, flag bits, the sensor_mag format, sys_name
    "PX4", the parameters (``*_ID`` as int32, the rest float32), and ``n`` sensor_mag samples at
    ``rate_hz`` turning once in the horizontal plane (0.2 G horizontal, 0.45 G down).  Message
    layout from the ULog file format spec (docs.px4.io, "ULog File Format")."""
    out = bytearray(b"ULog\x01\x12\x35\x01" + struct.pack("<Q", 0))
    out += _ulog_message(b"B", bytes(40))                 # no compat/incompat flags, no appended data
    out += _ulog_message(b"F", b"sensor_mag:uint64_t timestamp;uint32_t device_id;float x;float y;float z;"
                               b"float temperature")
    out += _ulog_keyed(b"I", "char[3] sys_name", b"PX4")
    for name, value in params.items():
        out += _ulog_keyed(b"P", f"int32_t {name}", struct.pack("<i", int(value))) if name.endswith("_ID") and \
            np.isfinite(value) else _ulog_keyed(b"P", f"float {name}", struct.pack("<f", value))
    out += _ulog_message(b"A", struct.pack("<BH", 0, 0) + b"sensor_mag")
    for i in range(n):
        turn = 2 * np.pi * i / n
        out += _ulog_message(b"D", struct.pack("<HQIffff", 0, 1_000_000 + int(i * 1e6 / rate_hz), 396825,
                                               0.2 * np.cos(turn), 0.2 * np.sin(turn), 0.45, 25.0))
    return bytes(out)


# ------------------------------------------------------------------------------ mutations

def _flip_bits(d: bytearray, rng) -> str:
    n = int(rng.integers(1, 24))
    for pos in rng.integers(0, len(d), n):
        d[pos] ^= 1 << int(rng.integers(0, 8))
    return f"flip{n}"


def _overwrite(d: bytearray, rng) -> str:
    at, n = int(rng.integers(0, len(d))), int(rng.integers(1, 400))
    fill = rng.choice([b"\x00", b"\xff", b"\xfd", b"\xfe", b"\xa3\x95", None])
    chunk = rng.bytes(n) if fill is None else (fill * n)[:n]
    d[at:at + n] = chunk
    return "overwrite"


def _truncate(d: bytearray, rng) -> str:
    del d[int(rng.integers(0, len(d))):]
    return "truncate"


def _insert(d: bytearray, rng) -> str:
    at = int(rng.integers(0, len(d) + 1))
    choice = int(rng.integers(0, 5))
    n = int(rng.integers(1, 20_000))
    chunk = [rng.bytes(n), b"\xfd" * n, b"\x00" * n, (b"\xa3\x95" + rng.bytes(1)) * (n // 3 + 1),
             bytes(d[:n])][choice]
    d[at:at] = chunk
    return "insert"


def _delete(d: bytearray, rng) -> str:
    at = int(rng.integers(0, len(d)))
    del d[at:at + int(rng.integers(1, 2000))]
    return "delete"


def _huge_length(d: bytearray, rng, kind: str) -> str:
    """Length/size fields set to their maximum (or zero) where the format has them."""
    if kind == "tlog":
        starts = np.flatnonzero(np.frombuffer(bytes(d), np.uint8) == 0xFD)
        for pos in rng.choice(starts, min(5, len(starts)), replace=False) if len(starts) else []:
            if pos + 1 < len(d):
                d[pos + 1] = int(rng.choice([0, 0xFF]))
    elif kind == "bin":
        fmts = [m.start() for m in re.finditer(b"\xa3\x95\x80", bytes(d))]
        for pos in rng.choice(fmts, min(3, len(fmts)), replace=False) if fmts else []:
            if pos + 4 < len(d):
                d[pos + 4] = int(rng.choice([0, 1, 0xFF]))
    elif kind == "ulg":
        arrays = [m.start(1) for m in re.finditer(rb"\[(\d+)\]", bytes(d))]
        if arrays:
            pos = int(rng.choice(arrays))
            d[pos:pos + 1] = str(int(rng.choice([0, 99999999, 2 ** 31]))).encode()
        else:
            at = int(rng.integers(16, max(17, len(d) - 2)))
            d[at:at + 2] = b"\xff\xff"
    else:
        _text_mutation(d, rng, kind)
    return "huge-length"


def _text_mutation(d: bytearray, rng, kind: str) -> str:
    text = d.decode("utf-8", "replace")
    numbers = list(re.finditer(r"-?\d+(\.\d+)?", text))
    replacement = str(rng.choice(["NaN", "Infinity", "-Infinity", "1e308", "-1e308", "null", "true", "\"x\"",
                                  "[]", "{}", "0", "1e999", "\x1b[2J", "\x00"]))
    choice = int(rng.integers(0, 5))
    if choice == 0 and numbers:
        m = numbers[int(rng.integers(0, len(numbers)))]
        text = text[:m.start()] + replacement + text[m.end():]
    elif choice == 1:
        depth = int(rng.integers(1000, 200_000))
        text = "[" * depth + text + "]" * depth if kind in ("plan", "calibration") else text + "x" * depth
    elif choice == 2:
        at = int(rng.integers(0, len(text) + 1))
        text = text[:at] + "\x1b]0;pwned\x07\x9b" + text[at:]
    elif choice == 3 and kind in ("plan", "calibration"):
        text = text.replace("{", "[", 1) if rng.random() < 0.5 else text.replace("\"status\"", "\"status\": 5, \"_\"")
    else:
        text = text.replace(",", ",,", int(rng.integers(1, 10)))
    d[:] = text.encode("utf-8", "surrogatepass")
    return "text"


def mutate(seed: bytes, kind: str, rng, seed_name: str = "") -> Case:
    d = bytearray(seed)
    ops = [_flip_bits, _overwrite, _truncate, _insert, _delete]
    names = []
    for _ in range(int(rng.integers(1, 4))):
        if not d:
            break
        r = rng.random()
        if r < 0.25:
            names.append(_huge_length(d, rng, kind))
        elif kind in ("csv", "plan", "waypoints", "calibration") and r < 0.6:
            names.append(_text_mutation(d, rng, kind))
        else:
            names.append(ops[int(rng.integers(0, len(ops)))](d, rng))
    return Case(kind, (f"{seed_name}:" if seed_name else "") + ("+".join(names) or "empty"), bytes(d))


def make_cases(n: int, seed: int = 0) -> list[Case]:
    """``n`` mutations spread over the kinds by their share (seeded)."""
    rng = np.random.default_rng(seed)
    src = seeds()
    kinds = [k for k in KINDS if k in src]
    shares = np.array([KINDS[k][1] for k in kinds])
    counts = np.floor(shares / shares.sum() * n).astype(int)
    counts[0] += n - counts.sum()
    cases = []
    for k, c in zip(kinds, counts):
        for _ in range(c):
            name, data = src[k][int(rng.integers(0, len(src[k])))]
            cases.append(mutate(data, k, rng, name))
    return cases


# ------------------------------------------------------------------------------ running

@contextlib.contextmanager
def time_budget(seconds: float):
    def alarm(*_):
        raise Hang()
    old = signal.signal(signal.SIGALRM, alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def _cli(args: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli_main(args)
    return rc, out.getvalue(), err.getvalue()


def _classify_cli(rc: int, out: str, err: str) -> str:
    if "Traceback" in err or "Traceback" in out:
        return "traceback"
    if RAW_CONTROL.search(out.replace("\n", "").replace("\t", "")) or RAW_CONTROL.search(err.replace("\n", "")):
        return "leak"
    errors = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("warning:")]
    if errors:
        return "error" if len(errors) == 1 and errors[0].startswith("magstation: error:") and rc != 0 else "traceback"
    return "warnings" if "warning:" in err or rc != 0 else "clean"


def commands_for(case: Case, path: Path, index: int) -> list[list[str]]:
    """The CLI commands a case goes through (analyze and calibrate on a share of the logs)."""
    small_log = str(DATA / "mag.csv")
    if case.kind == "calibration":
        return [["analyze", small_log, "--calibration", str(path)]]
    if case.kind in ("plan", "waypoints"):
        return [["analyze", small_log, "--mission", str(path)]]
    cmds = [["info", str(path)]]
    if index % 4 == 0:
        cmds.append(["analyze", str(path)])
    if index % 8 == 1 or case.kind == "csv":
        cmds.append(["calibrate", str(path)])
    return cmds


def run_case(case: Case, index: int, folder: Path, budget_s: float = 30.0) -> tuple[str, str]:
    """(outcome, detail) of one case: the direct reader call, then its CLI commands; the worst
    outcome counts (traceback > hang > leak > error > warnings > clean)."""
    path = folder / f"case{index}{KINDS[case.kind][0]}"
    path.write_bytes(case.data)
    results: list[tuple[str, str]] = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            with time_budget(budget_s):
                results.append(_direct(case, path))
                for args in commands_for(case, path, index):
                    results.append((_classify_cli(*_cli(args)), " ".join(args[:1])))
        except Hang:
            results.append(("hang", f"over {budget_s:g} s"))
        except Exception as err:       # escaped the CLI's own handling
            results.append(("traceback", f"{type(err).__name__}: {str(err)[:160]}"))
    numeric = [w for w in caught if issubclass(w.category, RuntimeWarning)]
    if numeric:
        results.append(("leak", f"{numeric[0].category.__name__}: {numeric[0].message}"))
    path.unlink(missing_ok=True)
    rank = {o: i for i, o in enumerate(("clean", "warnings", "error", "leak", "hang", "traceback"))}
    return max(results, key=lambda r: rank[r[0]])


def _direct(case: Case, path: Path) -> tuple[str, str]:
    """The reader called directly; anything it prints itself is a leak (readers count, not print)."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        outcome = _read(case, path)
    if out.getvalue().strip():
        return "leak", f"the reader printed {len(out.getvalue().splitlines())} lines: {out.getvalue()[:80]!r}"
    return outcome


def _read(case: Case, path: Path) -> tuple[str, str]:
    try:
        if case.kind in ("plan", "waypoints"):
            read_mission(path)
            return "clean", "read_mission"
        if case.kind == "calibration":
            return "clean", "json"
        log = read_log(path)
        vehicle_type(log), compass_count(log)          # what the station's recordings list shows
        return ("warnings" if log.warnings else "clean"), "read_log"
    except IngestError as err:
        return ("error" if "\n" not in str(err) else "traceback"), "read"
    except Hang:
        raise
    except Exception as err:
        return "traceback", f"{type(err).__name__}: {str(err)[:160]}"


def run(n: int, seed: int, budget_s: float, verbose: bool = False) -> tuple[Counter, list[str], float]:
    cases = make_cases(n, seed)
    counts: Counter = Counter()
    bad: list[str] = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for i, case in enumerate(cases):
            outcome, detail = run_case(case, i, Path(tmp), budget_s)
            counts[outcome] += 1
            counts[f"{case.kind}:{outcome}"] += 1
            if outcome in ("traceback", "hang", "leak"):
                bad.append(f"case {i} ({case.kind}, {case.name}, seed {seed}): {outcome}: {detail}")
            if verbose and i % 50 == 0:
                print(f"  {i}/{len(cases)} ...", file=sys.stderr)
    return counts, bad, time.perf_counter() - t0


def absurd_params() -> list[tuple[str, str, list[str]]]:
    """(kind, outcome, the absurd parameters a warning names) of each unmutated absurd-parameter seed."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for kind, entries in seeds().items():
            for name, data in entries:
                if name != "absurd-params":
                    continue
                outcome, _ = run_case(Case(kind, name, data), 0, Path(tmp))
                path = Path(tmp) / f"absurd{KINDS[kind][0]}"
                path.write_bytes(data)
                try:
                    text = " ".join(read_log(path).warnings)
                except IngestError as err:
                    text = str(err)
                rows.append((kind, outcome, [p for p in dict.fromkeys(ABSURD_PARAMS + ABSURD_PX4_PARAMS) if p in text]))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--budget", type=float, default=60.0, help="seconds per case before it counts as a hang")
    args = ap.parse_args()
    counts, bad, secs = run(args.cases, args.seed, args.budget, verbose=True)
    print(f"\n{args.cases} mutated files (seed {args.seed}) in {secs:.0f} s\n")
    kinds = [k for k in KINDS if any(counts[f"{k}:{o}"] for o in OUTCOMES)]
    print("| kind | " + " | ".join(OUTCOMES) + " |")
    print("|---|" + "---|" * len(OUTCOMES))
    for k in kinds + ["all"]:
        row = [counts[o] if k == "all" else counts[f"{k}:{o}"] for o in OUTCOMES]
        print(f"| {k} | " + " | ".join(str(v) for v in row) + " |")
    print()
    for name, target in (("traceback", 0), ("hang", 0), ("leak", 0)):
        verdict = "met" if counts[name] <= target else "MISSED"
        print(f"  {verdict:<6}  {name}s = {counts[name]} (target {target})")
    for line in bad[:30]:
        print("  " + line)
    print()
    for kind, outcome, flagged in absurd_params():
        print(f"  absurd parameters (NaN, +-inf, 3.4e38) in a {kind}: {outcome}; "
              + (f"flagged: {', '.join(flagged)}" if flagged else "NOT flagged (no warning names them)"))


if __name__ == "__main__":
    main()
