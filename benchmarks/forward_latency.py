"""Forwarding latency: a fake vehicle at 400 Hz -> MagStation (--forward udpout) -> a fake ground
station, and the ground station's commands back to the vehicle.

The station runs in its own process (a Session with the real estimators and a Forwarder, as
`magstation serve --connect udpin:... --forward udpout:...` does); the vehicle and the ground
station run here.  The vehicle sends every packet to the station and a copy straight to a
reference socket of the ground station; the kernel stamps each datagram as it arrives
(SO_TIMESTAMPNS), so added latency = arrival of the forwarded copy - arrival of the direct copy,
packet by packet, untouched by this process's own scheduling.

No peer row: mavlink-router and MAVProxy are not installed here (MAVProxy's forwarding is a
Python loop like ours; mavlink-router is C++).

    python benchmarks/forward_latency.py [--seconds 20] [--quick]
"""
from __future__ import annotations

import argparse
import os
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from groundstation.io.forward import MavlinkFramer  # noqa: E402
from groundstation.io.mavlink import mavlink2 as m, new_encoder  # noqa: E402
from groundstation.sim.fake_vehicle import FakeVehicle  # noqa: E402

TARGET_P99_MS = 5.0
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
RATE_HZ = 400.0
GCS_COMMAND = 31010

STATION = """
import os, sys, time, tempfile
from groundstation.io.forward import Forwarder
from groundstation.station.hub.session import Session
port, gcs_port = int(sys.argv[1]), int(sys.argv[2])
fw = Forwarder([f"udpout:127.0.0.1:{gcs_port}"]).start()
hub = Session(tempfile.mkdtemp(), record_live=True, forwarder=fw)
hub.connect(f"udpin:127.0.0.1:{port}")
print("ready", flush=True)
cpu0, wall0 = os.times(), time.monotonic()
sys.stdin.readline()
cpu1, wall1 = os.times(), time.monotonic()
snap = hub.snapshot()
cpu = (cpu1.user + cpu1.system - cpu0.user - cpu0.system) / (wall1 - wall0) * 100
print("rx", snap["rx_count"], "to_vehicle", snap["vehicles"]["forwarding"]["to_vehicle"],
      f"CPU {cpu:.0f} % of one core", flush=True)
hub.close()
"""


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def stream(seconds: float) -> list:
    return [(1.8e9 + i / RATE_HZ, m.MAVLink_scaled_imu_message(int(i * 1000 / RATE_HZ), 0, 0, -1000, 1, 2, 3,
                                                                200 + i % 50, -50, 400))
            for i in range(int(seconds * RATE_HZ))]


def timestamped_socket() -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.05)
    return sock


def kernel_time_s(ancdata) -> float:
    """The kernel's receive time of a datagram (SO_TIMESTAMPNS), seconds (CLOCK_REALTIME)."""
    for level, kind, data in ancdata:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
            sec, nsec = struct.unpack("qq", data[:16])
            return sec + nsec * 1e-9
    return float("nan")


class GroundStation:
    """Listens on UDP (``sock``: what MagStation forwards; ``ref``: the vehicle's direct copy),
    keeps the kernel's arrival time of each packet, answers with one COMMAND_LONG per 40 received."""

    def __init__(self) -> None:
        self.sock, self.ref = timestamped_socket(), timestamped_socket()
        self.port, self.ref_port = self.sock.getsockname()[1], self.ref.getsockname()[1]
        self.arrivals: dict[str, list[tuple[int, float]]] = {"forwarded": [], "direct": []}
        self.commands_sent = 0
        self.stop = threading.Event()
        self.threads = [threading.Thread(target=self._run, args=(s, k), daemon=True)
                        for s, k in ((self.sock, "forwarded"), (self.ref, "direct"))]
        for t in self.threads:
            t.start()

    def _run(self, sock: socket.socket, kind: str) -> None:
        enc, framer = new_encoder(255, 190), MavlinkFramer()
        got = self.arrivals[kind]
        while not self.stop.is_set():
            try:
                data, anc, _, peer = sock.recvmsg(65535, 64)
            except socket.timeout:
                continue
            t = kernel_time_s(anc)
            got += [(p[4], t) for p in framer.feed(data)]
            if kind == "forwarded" and len(got) >= 40 * (self.commands_sent + 1):
                cmd = m.MAVLink_command_long_message(1, 1, GCS_COMMAND, 0, self.commands_sent, 0, 0, 0, 0, 0, 0)
                sock.sendto(bytes(cmd.pack(enc)), peer)
                enc.seq = (enc.seq + 1) % 256
                self.commands_sent += 1

    def close(self) -> None:
        self.stop.set()
        for t in self.threads:
            t.join(2)
        self.sock.close()
        self.ref.close()


def run(seconds: float) -> dict:
    gcs = GroundStation()
    port = free_udp_port()
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    station = subprocess.Popen([sys.executable, "-c", STATION, str(port), str(gcs.port)], cwd=ROOT, env=env,
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert station.stdout.readline().strip() == "ready"
    fv = FakeVehicle(stream(seconds), port, speed=1.0)
    fv.mirror = ("127.0.0.1", gcs.ref_port)
    load = " ".join(open("/proc/loadavg").read().split()[:3])
    fv.start()
    fv.finished.wait(seconds + 30)
    time.sleep(0.5)                            # the ground station's last answers reach the vehicle
    fv.stop()                                  # nothing more is sent (heartbeats included)
    deadline = time.monotonic() + 10           # a loaded machine may hold the last packets a while
    while time.monotonic() < deadline and len(gcs.arrivals["forwarded"]) < sum(fv.delivered.values()):
        time.sleep(0.1)
    station.stdin.write("\n")
    station.stdin.flush()
    stats = station.stdout.readline().strip()
    station.wait(10)
    gcs.close()
    fwd, ref = gcs.arrivals["forwarded"], gcs.arrivals["direct"]
    n = min(len(fwd), len(ref))
    in_order = [s for s, _ in fwd[:n]] == [s for s, _ in ref[:n]]
    added_ms = np.array([(f[1] - r[1]) * 1e3 for f, r in zip(fwd[:n], ref[:n])])
    commands = sum(1 for cmd, _ in fv.commands if cmd == GCS_COMMAND)
    return {"sent": sum(fv.delivered.values()), "arrived": len(fwd), "direct": len(ref), "in_order": in_order,
            "added_ms": added_ms, "load": load, "commands_sent": gcs.commands_sent, "commands_arrived": commands,
            "station": stats}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--quick", action="store_true", help="5 s of stream (smoke test)")
    a = ap.parse_args(argv)
    seconds = 5.0 if a.quick else a.seconds
    r = run(seconds)
    p50, p90, p99 = np.percentile(r["added_ms"], [50, 90, 99])
    print(f"forwarding at {RATE_HZ:.0f} Hz for {seconds:.0f} s (station in its own process with the estimators "
          f"and recording); load average at start {r['load']} on 2 shared cores")
    print(f"  {'':<34} {'packets':>15} {'p50 ms':>8} {'p90 ms':>8} {'p99 ms':>8} {'max ms':>8}")
    print(f"  {'added by MagStation (kernel ts)':<34} {r['arrived']:>7}/{r['sent']:<7} {p50:8.2f} {p90:8.2f} "
          f"{p99:8.2f} {r['added_ms'].max():8.2f}")
    print(f"  GCS -> vehicle commands through MagStation: {r['commands_arrived']}/{r['commands_sent']}; "
          f"station: {r['station']}")
    counts_ok = (r["arrived"] == r["sent"] == r["direct"] and r["in_order"]
                 and r["commands_arrived"] == r["commands_sent"] > 0)
    print(f"  {'met   ' if counts_ok else 'MISSED'}  every packet both ways, in order")
    print(f"  {'met   ' if p99 < TARGET_P99_MS else 'MISSED'}  added latency p99 < {TARGET_P99_MS:g} ms "
          f"(measured {p99:.2f} ms)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
