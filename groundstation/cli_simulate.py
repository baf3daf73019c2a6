"""`magstation simulate`: argument parsing, writing a scenario's log, or streaming it as a live
vehicle (the flights are made in ``groundstation.sim.scenarios``; ``simulate fleet`` is in
``groundstation.cli_fleet``)."""
from __future__ import annotations

import argparse
import time

from groundstation.cli_common import CliError, printable
from groundstation.cli_fleet import add_fleet_simulate_options

__all__ = ["add_simulate_parser", "cmd_simulate", "SCENARIO_HELP"]

# what each scenario of `magstation simulate` is (groundstation/sim/scenarios.py)
SCENARIO_HELP = {
    "calibration": "80 s handheld rotation dance (the wizard's input)",
    "static-headings": "the vehicle held still at a series of headings",
    "mission-clean": "300 s survey mission, no interference",
    "mission-slow": "150 s mission, a slow ramp of interference (12.5 mG/s)",
    "mission-fast": "150 s mission, a fast ramp of interference (60 mG/s)",
    "mission-step": "150 s mission, a 150 mG step for 20 s",
    "mission-bump": "200 s mission, a 250 mG horizontal bump over 60 s",
    "mission-motor": "300 s mission, a payload switching 10 A every 10 s",
    "mission-payload": "150 s mission, a payload on its own lead past the compass",
    "mission-anomaly": "200 s mission over a magnetised mass on the ground",
    "gps-outage": "300 s mission, GPS lost from 100 to 180 s",
    "demo": "the calibration dance, then mission-slow (recordings/demo.tlog)",
    "fleet": "a folder of logs of many vehicles with known truth (for review)",
}


def add_simulate_parser(sub) -> None:
    scenarios = "\n".join(f"  {name:<16} {text}" for name, text in SCENARIO_HELP.items())
    p = sub.add_parser("simulate", help="write a simulated flight as a .tlog (+ truth JSON), stream it live, "
                                        "or write a fleet",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description="Simulate a flight with known truth: write it as a .tlog (+ truth JSON) with "
                                   "--out, or stream it as a live vehicle with --live.\n\nscenarios:\n" + scenarios
                                   + "\n\nexample: magstation simulate calibration --live udpout:127.0.0.1:14550")
    p.add_argument("scenario", metavar="SCENARIO", help="one of the scenarios listed above")
    p.add_argument("--out", metavar="FILE.tlog|DIR", help="write the log here (fleet: a folder)")
    p.add_argument("--live", metavar="udpout:HOST:PORT",
                   help="stream the scenario in real time as an ArduPilot vehicle that answers parameter "
                        "reads/writes and the calibration commands (default: off)")
    p.add_argument("--speed", type=float, default=1.0, help="--live: times real time (default 1)")
    p.add_argument("--loop", action="store_true", help="--live: start the scenario again at its end (default: off)")
    p.add_argument("--seed", type=int, default=0, help="random seed: the vehicle's sensor errors, wind, ... "
                                                       "(default 0)")
    p.add_argument("--onboard-calibration", action="store_true",
                   help="the vehicle was calibrated on board: it streams the corrected field (default: the raw sensor)")
    add_fleet_simulate_options(p)
    p.set_defaults(func=cmd_simulate)


def cmd_simulate(args: argparse.Namespace) -> int:
    from groundstation.sim.scenarios import SCENARIOS, simulate

    if args.scenario == "fleet":
        if args.out is None or args.live is not None:
            raise CliError("simulate fleet writes a folder: give --out DIR (no --live)")
        from groundstation.cli_fleet import cmd_simulate_fleet
        return cmd_simulate_fleet(args)
    if args.scenario not in SCENARIOS:
        raise CliError(f"unknown scenario '{args.scenario}' (choose from {', '.join(SCENARIOS)})")
    if (args.live is None) == (args.out is None):
        raise CliError("give --out FILE.tlog (write the log) or --live udpout:HOST:PORT (stream it), one of them")
    if not 0 < args.speed <= 100:
        raise CliError("--speed must be in (0, 100]")
    target = _udpout_target(args.live) if args.live is not None else None
    sim = simulate(args.scenario, seed=args.seed, onboard_calibration=args.onboard_calibration)
    if target is not None:
        return _simulate_live(sim, target, args)
    sim.write(args.out)
    print(f"wrote {printable(args.out)} ({len(sim.messages)} messages) and its truth JSON")
    return 0


def _udpout_target(url: str) -> tuple[str, int]:
    """HOST, PORT of ``udpout:HOST:PORT`` (the station listens with ``--connect udpin:...:PORT``)."""

    kind, _, rest = url.partition(":")
    host, _, port = rest.rpartition(":")
    if kind != "udpout" or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise CliError(f"--live {printable(url)}: expected udpout:HOST:PORT, e.g. udpout:127.0.0.1:14550")
    return host, int(port)


def _simulate_live(sim, target: tuple[str, int], args: argparse.Namespace) -> int:
    """Stream ``sim`` as a live ArduPilot vehicle until Ctrl-C (``groundstation.sim.fake_vehicle``)."""
    from groundstation.sim.fake_vehicle import FakeVehicle

    host, port = target
    try:
        vehicle = FakeVehicle(sim.messages, port, speed=args.speed, host=host, loop=args.loop).start()
    except OSError as err:
        raise CliError(f"--live udpout:{host}:{port}: {err.strerror or err}") from None
    print(f"streaming '{args.scenario}' ({sim.duration_s:.0f} s at x{args.speed:g}) as a live ArduPilot vehicle "
          f"to udpout:{host}:{port}; it answers parameter reads/writes and the calibration commands. "
          f"Start the station with: magstation serve --connect udpin:{host}:{port}   (Ctrl-C stops)", flush=True)
    try:
        vehicle.finished.wait()
        print(f"'{args.scenario}' ended; the vehicle still answers (heartbeats, parameters, commands) "
              "until Ctrl-C", flush=True)
        while True:
            time.sleep(3600)
    finally:
        vehicle.stop()
