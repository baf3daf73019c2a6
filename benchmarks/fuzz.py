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

Targets (issue 10): 0 tracebacks, 0 hangs (and 0 leaks).  Seeds are the small logs in tests/data,
a calibration JSON, and the first 150 kB of a real PX4 ULog from ../shared/data when present.
The smoke run is tests/test_fuzz.py.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import re
import signal
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


def seeds() -> dict[str, bytes]:
    out = {"tlog": (DATA / "reference.tlog").read_bytes(), "bin": (DATA / "reference.bin").read_bytes(),
           "csv": (DATA / "mag.csv").read_bytes(), "plan": (DATA / "mission.plan").read_bytes(),
           "waypoints": (DATA / "mission.waypoints").read_bytes(),
           "calibration": json.dumps(GOOD_CALIBRATION).encode()}
    if SHARED_ULOG.is_file():
        out["ulg"] = SHARED_ULOG.read_bytes()[:150_000]
    return out


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


def mutate(seed: bytes, kind: str, rng) -> Case:
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
    return Case(kind, "+".join(names) or "empty", bytes(d))


def make_cases(n: int, seed: int = 0) -> list[Case]:
    """``n`` mutations spread over the kinds by their share (seeded)."""
    rng = np.random.default_rng(seed)
    src = seeds()
    kinds = [k for k in KINDS if k in src]
    shares = np.array([KINDS[k][1] for k in kinds])
    counts = np.floor(shares / shares.sum() * n).astype(int)
    counts[0] += n - counts.sum()
    return [mutate(src[k], k, rng) for k, c in zip(kinds, counts) for _ in range(c)]


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


if __name__ == "__main__":
    main()
