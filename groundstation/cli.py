"""`magstation` command line: serve, calibrate, analyze, simulate, review, info.

Errors are one line on stderr and a non-zero exit code, never a traceback (set
MAGSTATION_DEBUG=1 to see one).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

from groundstation.io.params import ardupilot_never_calibrated
from groundstation.io.errors import IngestError
from groundstation.io.logs import read_log
from groundstation.samples import FlightLog
from groundstation.cli_common import CliError, printable
from groundstation.cli_fleet import add_params_options, add_review_parser
from groundstation.cli_simulate import add_simulate_parser

from groundstation.paths import RECORDINGS_DIR
DEMO_RECORDING = RECORDINGS_DIR / "demo.tlog"


MAX_CALIBRATION_BYTES = 10 << 20


@contextmanager
def progress_bar(label: str) -> Iterator[Callable[[float], None] | None]:
    """A tqdm bar on a terminal (fraction 0..1 in), nothing when output is piped."""
    if not sys.stderr.isatty():
        yield None
        return
    from tqdm import tqdm

    with tqdm(total=1000, desc=label, unit="‰", leave=False, file=sys.stderr) as bar:
        def update(fraction: float) -> None:
            bar.update(max(0, int(fraction * 1000) - bar.n))
        yield update


def load_log(path: str | Path) -> FlightLog:
    with progress_bar(f"reading {printable(Path(path).name)}") as progress:
        log = read_log(path, progress)
    for warning, count in log.warnings.items():
        print(f"warning: {printable(Path(path).name)}: {printable(warning)} ({count})", file=sys.stderr)
    return log


def in_force_params(args: argparse.Namespace) -> tuple[dict | None, str | None]:
    """(values, label) of --params FILE or --assume-uncalibrated (never both); (None, None) without.
    A bad line of the file is counted and skipped with one warning."""
    from groundstation.io.param_file import ParamFileError, read_param_file

    path, assume = getattr(args, "params", None), getattr(args, "assume_uncalibrated", False)
    if path and assume:
        raise CliError("give --params FILE or --assume-uncalibrated, not both")
    if assume:
        return {}, "--assume-uncalibrated"
    if not path:
        return None, None
    try:
        pf = read_param_file(path)
    except ParamFileError as err:
        raise CliError(str(err)) from None
    if pf.warning():
        print(f"warning: {printable(pf.warning())}", file=sys.stderr)
    return pf.values, printable(Path(path).name)


def with_params(log: FlightLog, values: dict | None, label: str | None) -> FlightLog:
    """The log with --params / --assume-uncalibrated as its parameters in force where it has none (one line)."""
    if values is None:
        return log
    from groundstation.io.param_file import apply_to_log, uncalibrated_params

    if label == "--assume-uncalibrated":
        values = uncalibrated_params(log.autopilot)
    print(f"parameters: {printable(apply_to_log(log, values, label))}", file=sys.stderr)
    return log


def _write_json(path: str, obj: object) -> None:
    Path(path).write_text(json.dumps(obj, indent=2, allow_nan=False) + "\n", encoding="utf-8")


def _file_name(record: dict) -> dict:
    """``record`` with its "file" as the file's name: a report to share carries no local path."""
    return {**record, "file": Path(str(record["file"])).name} if record.get("file") else record


# ------------------------------------------------------------------------------------ commands

def cmd_info(args: argparse.Namespace) -> int:
    from groundstation.io.logs import summarize_rates
    from groundstation.jobs.log_summary import compass_lines, refused_parameter_lines

    log = load_log(args.file)
    tables = {"magnetometer": log.mag, "IMU": log.imu, "attitude": log.attitude, "GPS": log.gps,
              "battery current": log.battery}
    print(printable(args.file))
    print(f"  duration        {log.duration_s:.1f} s")
    print(f"  autopilot       {printable(log.autopilot or 'unknown')}")
    for name, table in tables.items():
        if len(table) > 1:
            span = table[-1, 0] - table[0, 0]
            rate = (len(table) - 1) / span if span > 0 else 0.0
            print(f"  {name:<15} {len(table)} samples, {rate:.1f} Hz")
        else:
            print(f"  {name:<15} none")
    if len(log.mag) and log.mag_calibration_applied is not None:
        if not log.mag_calibration_applied:
            state = "raw sensor output"
        elif ardupilot_never_calibrated(log.params):
            state = "corrected by the autopilot, but COMPASS_OFS_* are 0 (never calibrated)"
        else:
            state = "already calibrated by the autopilot"
        print(f"  mag field       {state}")
    print(printable("\n".join(compass_lines(log)), lines=True))
    rtk = bool(len(log.gps) and (log.gps[:, 7] >= 5).any())
    print(f"  RTK             {'yes' if rtk else 'no'}")
    if len(log.gps):
        import numpy as np

        from groundstation.jobs.words import fix_name
        kinds, counts = np.unique(log.gps[:, 7][np.isfinite(log.gps[:, 7])].astype(int), return_counts=True)
        print("  GPS fixes       " + ", ".join(f"{fix_name(k)} {n}" for k, n in zip(kinds[::-1], counts[::-1])))
    print(f"  mission         {len(log.mission)} waypoints" if log.mission else "  mission         none")
    print(f"  parameters      {len(log.params)}")
    for line in refused_parameter_lines(log):
        print(printable(line))
    print("  messages:")
    for mtype, count, rate in summarize_rates(log)[: args.top]:
        print(f"    {printable(mtype):<28} {count:>8}  {rate:8.2f} Hz")
    for warning, count in log.warnings.items():
        print(f"  warning: {printable(warning)} ({count})")
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from groundstation.jobs.calibrate import (DEFAULT_SETTINGS, calibrate_compasses, error_result, format_consistency,
                                              format_summary)

    values, label = in_force_params(args)
    settings = replace(DEFAULT_SETTINGS, attitude_source=args.attitude)
    results = []
    for file in args.files:
        try:
            found = calibrate_compasses(with_params(load_log(file), values, label), settings)    # one result per compass
        except IngestError as err:
            found = [error_result(file, str(err))]
        results += found
        text = "\n".join([format_summary(r) for r in found] + [format_consistency(found[0].get("consistency"))])
        print(printable(text.rstrip(), lines=True))
    if args.json:
        _write_json(args.json, {"results": [_file_name(r) for r in results]})
    if args.param_out:
        _write_params(args.param_out, results, args.accept_weak)
    return 0 if all(r["status"] == "ok" for r in results) else 1


def _write_params(path: str, results: list[dict], accept_weak: bool = False) -> None:
    """Every absolute result's parameters in one .param file (a relative result has none to write).
    A weak (not recommended) answer is refused in one line unless ``accept_weak``."""
    weak = [r for r in results if r.get("relative_to") == "raw" and (r.get("status") == "weak" or (
        r.get("status") == "ok" and r.get("recommended") is False))]
    if weak and not accept_weak:
        r = weak[0]
        why = (r.get("recommendation") or r.get("status") or "").split(";")[0].removeprefix("not recommended: ")
        raise CliError(f"not writing {path}: compass {r.get('compass')} of {r.get('file')} is not recommended "
                       f"({why}); give --accept-weak to write it with its stated 1σ")
    values: dict[str, float] = {}
    for r in results:
        ap = r.get("autopilot") or "ardupilot"
        if r.get("status") in (("ok", "weak") if accept_weak else ("ok",)) and r.get("relative_to") == "raw":
            values.update(r.get("px4_params" if ap == "px4" else "ardupilot_params") or {})
    if not values:
        raise CliError("no absolute calibration to write as parameters: the fit is relative to corrections in "
                       "force that the log does not hold (give --params FILE or --assume-uncalibrated)")
    from groundstation.io.params import format_param_file
    Path(path).write_text(format_param_file(values), encoding="utf-8")
    print(f"wrote {printable(path)} ({len(values)} parameters)")


def _load_calibration(path: str) -> dict:
    """The first calibration with status 'ok' in a `calibrate --json` file (or a bare result),
    checked (``check_calibration``).  Raises CliError (one line) otherwise."""
    from groundstation.jobs.calibration_check import check_calibration

    try:
        if Path(path).stat().st_size > MAX_CALIBRATION_BYTES:
            raise CliError(f"{path}: too large for a calibration JSON")
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError) as err:   # JSONDecodeError, bad UTF-8, deep nesting
        raise CliError(f"{path}: not a readable calibration JSON ({str(err)[:120]})") from err
    candidates = data.get("results", [data]) if isinstance(data, dict) else []
    if not isinstance(candidates, list):
        raise CliError(f"{path}: 'results' must be a list of calibration objects")
    for result in candidates:     # "no_parameters": an older calibrate's relative fit
        if not isinstance(result, dict) or result.get("status") not in ("ok", "no_parameters"):
            continue
        if result.get("offsets_mG") is None:
            if result.get("status") == "ok":
                raise CliError(f"{path}: unusable calibration: offsets_mG missing")
            continue
        try:
            check_calibration(result)
        except ValueError as err:
            raise CliError(f"{path}: unusable calibration: {err}") from err
        return result
    raise CliError(f"{path}: holds no calibration with status 'ok'")


def cmd_analyze(args: argparse.Namespace) -> int:
    from groundstation.jobs.analyze import analyze_log
    from groundstation.jobs.report import format_report, write_csv
    from groundstation.io.mission import read_mission

    if args.plot:
        from groundstation.jobs.flight_plot import PlotUnavailable, check_plotting
        try:
            check_plotting()                # before the work, not after it
        except PlotUnavailable as e:
            raise CliError(str(e)) from None
    calibration = _load_calibration(args.calibration) if args.calibration else None
    mission = read_mission(args.mission) if args.mission else None
    values, label = in_force_params(args)
    log = with_params(load_log(args.file), values, label)
    with progress_bar("analyzing"):
        report, columns = analyze_log(log, calibration=calibration, mission=mission, columns=bool(args.csv))
    print(printable(format_report(report), lines=True))
    if args.json:
        _write_json(args.json, _file_name(report))
    if args.csv:
        write_csv(args.csv, columns)
    if args.plot:
        _plot(args.plot, log, calibration, mission, report)
    return 0


def _plot(path: str, log, calibration, mission, report: dict) -> None:
    from groundstation.jobs.analyze import analyze_flight
    from groundstation.jobs.flight_plot import PlotUnavailable, plot_flight
    try:
        plot_flight(analyze_flight(log, calibration, mission), [a for a in report["alarms"] if a["kind"] == "combined"],
                    path, title=str(report.get("file") or ""))
    except PlotUnavailable as e:
        raise CliError(str(e)) from None
    except OSError as e:
        raise CliError(f"cannot write {path}: {e.strerror or e}") from None
    print(f"wrote {path}")


def cmd_serve(args: argparse.Namespace) -> int:
    replay = Path(args.replay) if args.replay else None
    if args.connect is None and replay is None:
        if not DEMO_RECORDING.is_file():
            raise CliError(f"no source given and the demo recording {DEMO_RECORDING} is missing")
        replay = DEMO_RECORDING
    if replay is not None and not replay.is_file():
        raise CliError(f"{replay}: no such file")
    if args.connect is not None:
        from groundstation.io.link import validate_connection_string
        args.connect = validate_connection_string(args.connect)     # the operator may listen on 0.0.0.0
    from groundstation.station.settings import ConnectionLimits, StationSettings   # light: no server import yet

    settings = StationSettings(host=args.host, port=args.port, viser_port=args.viser_port,
                               allow_remote=args.allow_remote, allowed_hosts=tuple(args.allowed_host),
                               tls_cert=args.tls_cert, tls_key=args.tls_key, sysid=args.sysid,
                               passive=args.passive, forward=tuple(args.forward), signing_key=_signing_key(args),
                               connection_limits=ConnectionLimits(header_timeout_s=args.header_timeout,
                                                                  max_per_client=args.max_connections_per_client),
                               **_serve_params(args), **_serve_recordings(args))
    from groundstation.station.app import StationStartError, serve

    try:
        serve(settings, connect=args.connect, replay=replay, speed=args.speed)
    except StationStartError as err:
        raise CliError(str(err)) from err
    return 0


def _serve_recordings(args: argparse.Namespace) -> dict:
    """serve --recordings DIR as a StationSettings field (the folder made if missing)."""
    if args.recordings is None:
        return {}
    folder = Path(args.recordings)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise CliError(f"--recordings {folder}: cannot use it as a folder ({e.strerror or e})") from None
    return {"recordings_dir": folder}


def _serve_params(args: argparse.Namespace) -> dict:
    """serve --params / --assume-uncalibrated as StationSettings fields."""
    values, label = in_force_params(args)
    return {} if values is None else {"params_in_force": tuple(sorted(values.items())), "params_label": label}


def _signing_key(args: argparse.Namespace) -> bytes | None:
    """The MAVLink 2 signing key of --signing-key-file or --signing-passphrase-env (never printed)."""
    from groundstation.io.signing import passphrase_from_env, read_key_file

    if args.signing_key_file and args.signing_passphrase_env:
        raise CliError("give --signing-key-file or --signing-passphrase-env, not both")
    if args.signing_key_file:
        return read_key_file(args.signing_key_file)
    if args.signing_passphrase_env:
        return passphrase_from_env(args.signing_passphrase_env)
    return None


def _add_link_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("beside another ground station")
    g.add_argument("--sysid", type=int, metavar="N", help="follow vehicle N (MAVLink system id, 1-255) when several "
                                                          "share the link (default: the first heard)")
    g.add_argument("--passive", action="store_true",
                   help="listen only: no heartbeat, stream-rate or parameter requests, no writes (default: off)")
    g.add_argument("--forward", action="append", default=[], metavar="URL",
                   help="pass the vehicle link on to another ground station: udpout:HOST:PORT or "
                        "tcpin:127.0.0.1:PORT (repeatable; default: none); their packets go back to the vehicle")
    g.add_argument("--signing-key-file", metavar="FILE",
                   help="MAVLink 2 signing key: 32 bytes, 64 hex digits, or a passphrase (SHA-256, as MAVProxy); "
                        "default: no signing")
    g.add_argument("--signing-passphrase-env", metavar="VAR",
                   help="MAVLink 2 signing with the passphrase in environment variable VAR (default: no signing)")


def _add_serve_parser(sub) -> None:
    from groundstation.station.settings import ConnectionLimits   # light: settings only

    p = sub.add_parser("serve", help="run the ground station (web page + 3-D view)",
                       description="Run the ground station: the web page, the 3-D view and the API (/docs). "
                                   "Without --connect or --replay it replays the bundled demo in a loop.")
    source = p.add_mutually_exclusive_group()
    source.add_argument("--connect", metavar="URL",
                        help="live link: udpin:0.0.0.0:14550, tcp:HOST:PORT or /dev/ttyUSB0,57600 "
                             "(default: replay the demo)")
    source.add_argument("--replay", metavar="FILE", help="replay a log (.tlog .bin .ulg .csv)")
    p.add_argument("--speed", type=float, default=1.0, help="replay speed, times real time (default 1)")
    p.add_argument("--recordings", metavar="DIR",
                   help=f"folder of the live recordings, the uploads and the logs the page offers to replay "
                        f"(made if missing; default {RECORDINGS_DIR})")
    p.add_argument("--host", default="127.0.0.1",
                   help="address the web page listens on (default 127.0.0.1; others need --allow-remote)")
    p.add_argument("--port", type=int, default=8000, help="TCP port of the web page and API (default 8000)")
    p.add_argument("--viser-port", type=int, default=8080, help="TCP port of the 3-D view (default 8080)")
    p.add_argument("--allow-remote", action="store_true",
                   help="remote mode: allow a non-loopback --host; every request then needs the token printed "
                        "at start (default: off)")
    p.add_argument("--allowed-host", action="append", default=[], metavar="NAME",
                   help="a host name or address the station is reached by (Host header), repeatable "
                        "(default: the loopback names and --host)")
    p.add_argument("--tls-cert", metavar="CERT.pem", help="serve HTTPS with this certificate (with --tls-key; "
                                                         "default: HTTP)")
    p.add_argument("--tls-key", metavar="KEY.pem", help="the certificate's private key (PEM)")
    limits = ConnectionLimits()
    p.add_argument("--header-timeout", type=float, default=limits.header_timeout_s, metavar="S",
                   help="close a connection whose request line and headers take longer "
                        f"(default {limits.header_timeout_s:g} s)")
    p.add_argument("--max-connections-per-client", type=int, default=limits.max_per_client, metavar="N",
                   help=f"open connections per client address (default {limits.max_per_client}; more behind a proxy)")
    _add_link_options(p)
    add_params_options(p)
    p.set_defaults(func=cmd_serve)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="magstation", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    _add_serve_parser(sub)

    p = sub.add_parser("calibrate", help="magnetometer calibration from one or more logs",
                       description="Fit every compass of each log (hard and soft iron, mG) and check them "
                                   "against each other and the WMM; exit 1 unless every fit is ok.")
    p.add_argument("files", nargs="+", metavar="FILE", help="logs (.tlog .bin .ulg .csv) with a rotation dance")
    p.add_argument("--json", metavar="OUT", help="write the results (offsets mG, matrix, parameters) as JSON "
                                                 "(default: none)")
    p.add_argument("--param-out", metavar="FILE.param", help="write the absolute COMPASS_*/CAL_MAG* parameters "
                                                             "as a .param file (default: none)")
    p.add_argument("--attitude", metavar="SOURCE", default="auto",
                   help="attitude for the in-flight fit: ATT, AHR2 (DCM), XKF1 (EKF3), NKF1 (EKF2), ATTITUDE, "
                        "vehicle_attitude or ahrs (ours, from the IMU) (default: auto, the one that fits best)")
    p.add_argument("--accept-weak", action="store_true", help="with --param-out: also write answers marked "
                                                               "`recommended: no` (weak, with their 1σ); default: refuse")
    add_params_options(p)
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser("analyze", help="heading, velocity split and interference detection",
                       description="Heading check, velocity split and interference detection over one log.")
    p.add_argument("file", metavar="FILE", help="the log (.tlog .bin .ulg .csv)")
    p.add_argument("--calibration", metavar="CAL.json",
                   help="a `calibrate --json` file to correct the field with (default: the log's own)")
    p.add_argument("--mission", metavar="FILE", help=".waypoints, .plan or a log with a mission "
                                                     "(default: the log's own mission, if any)")
    p.add_argument("--json", metavar="OUT", help="write the report as JSON (default: none)")
    p.add_argument("--csv", metavar="OUT", help="write the per-sample columns as CSV (default: none)")
    p.add_argument("--plot", metavar="FILE.png",
                   help="write a PNG: heading difference (deg), field residual (mG), current (A) and alarms "
                        "against time (s) (default: none)")
    add_params_options(p)
    p.set_defaults(func=cmd_analyze)

    add_simulate_parser(sub)

    add_review_parser(sub)

    p = sub.add_parser("info", help="what is in a log",
                       description="What is in a log: duration, sensors and rates, compasses, parameters, messages.")
    p.add_argument("file", metavar="FILE", help="the log (.tlog .bin .ulg .csv)")
    p.add_argument("--top", type=int, default=25, help="message types to list, most frequent first (default 25)")
    p.set_defaults(func=cmd_info)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except BrokenPipeError:             # output piped into `head` and the like: stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except (IngestError, CliError, OSError, ValueError) as err:
        if os.environ.get("MAGSTATION_DEBUG"):
            raise
        print(f"magstation: error: {printable(err)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
