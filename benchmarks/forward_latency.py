"""Forwarding latency: a fake vehicle at 400 Hz -> MagStation (--forward udpout) -> a fake ground
station, and the ground station's commands back to the vehicle, with the station idle or busy.

The station runs in its own process (a Session with the real estimators, recording, and a
Forwarder, as `magstation serve --connect udpin:... --forward udpout:...` does), which starts the
forwarding process; the vehicle and the ground station run here.  The vehicle sends every packet
to the station and a copy straight to a reference socket of the ground station; the kernel stamps
each datagram as it arrives (SO_TIMESTAMPNS), so added latency = arrival of the forwarded copy -
arrival of the direct copy, packet by packet, untouched by this process's own scheduling.

Station load per row:
  live    the station estimates the live 400 Hz stream and records it (its normal work);
  replay  as live, plus a second hub in the same process replaying recordings/demo.tlog at x20
          (its whole-log analysis rerun every 3 s) and both hubs' state serialised at 10 Hz;
  hog     as replay, plus a thread holding the interpreter lock in ~40 ms C calls (what a long
          numpy/json call does): the worst case for anything forwarded inside the station process.

Same-run reference, "station's copy": when the station's link reader got each packet (its
recording's time stamps, 1 us) minus the direct copy's arrival: the latency an in-process
forwarder (MagStation before the forwarding process; it sent from that reader thread) would have
added, plus one loopback hop.  No mavlink-router/MAVProxy row: neither is installed here.

    python benchmarks/forward_latency.py [--seconds 20] [--modes live,replay,hog] [--quick]
"""
from __future__ import annotations

import argparse
import json
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
MODES = ("live", "replay", "hog")

STATION = r"""
import json, os, sys, tempfile, threading, time
from groundstation.io.forward import Forwarder
from groundstation.station.hub.session import Session
port, gcs_port, mode, demo = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4]
fw = Forwarder([f"udpout:127.0.0.1:{gcs_port}"]).start()
hub = Session(tempfile.mkdtemp(), record_live=True, forwarder=fw)
hub.connect(f"udpin:127.0.0.1:{port}")
stop = threading.Event()

def replaying():
    other = Session(tempfile.mkdtemp(), record_live=False)
    while not stop.is_set():
        other.start_replay(demo, speed=20.0, loop=True)
        t_end = time.monotonic() + 3.0
        while time.monotonic() < t_end and not stop.is_set():
            json.dumps([hub.snapshot(), other.snapshot()], default=str)
            time.sleep(0.1)
    other.close()

def hogging():
    while not stop.is_set():
        sum(range(1_500_000))          # one C call: the interpreter lock is held ~40 ms

def cpu_s(pid):
    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

if mode in ("replay", "hog"):
    threading.Thread(target=replaying, daemon=True).start()
if mode == "hog":
    threading.Thread(target=hogging, daemon=True).start()
print("ready", flush=True)
cpu0, relay0, wall0 = cpu_s(os.getpid()), cpu_s(fw.pid), time.monotonic()
sys.stdin.readline()
cpu1, relay1, wall1 = cpu_s(os.getpid()), cpu_s(fw.pid), time.monotonic()
stop.set()
fw.refresh()
snap = hub.snapshot()
tlog = hub.sources.recording_path
hub.close()
print(json.dumps({"rx": snap["rx_count"], "to_vehicle": snap["vehicles"]["forwarding"]["to_vehicle"],
                  "cpu_pct": 100 * (cpu1 - cpu0) / (wall1 - wall0), "relay_cpu_pct": 100 * (relay1 - relay0) / (wall1 - wall0),
                  "tlog": str(tlog)}), flush=True)
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
        self.arrivals: dict[str, list[tuple[bytes, float]]] = {"forwarded": [], "direct": []}
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
            got += [(p, t) for p in framer.feed(data)]
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


def tlog_times(path: Path) -> dict[bytes, float]:
    """Each packet of a .tlog (8-byte big-endian us time stamp + packet) -> its time stamp (s)."""
    data, out, i = path.read_bytes(), {}, 0
    while i + 11 <= len(data):
        t_us = struct.unpack(">Q", data[i:i + 8])[0]
        packets = MavlinkFramer().feed(data[i + 8:i + 8 + 280])
        if not packets:
            break
        out.setdefault(packets[0], t_us * 1e-6)
        i += 8 + len(packets[0])
    return out


def run(seconds: float, mode: str) -> dict:
    """One row: the station under ``mode`` load, the stream for ``seconds``."""
    gcs = GroundStation()
    port = free_udp_port()
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    station = subprocess.Popen([sys.executable, "-c", STATION, str(port), str(gcs.port), mode,
                                str(ROOT / "recordings" / "demo.tlog")], cwd=ROOT, env=env,
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert station.stdout.readline().strip() == "ready"
    time.sleep(1.0 if mode != "live" else 0.2)        # the load is on before the stream starts
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
    stats = json.loads(station.stdout.readline())
    station.wait(20)
    gcs.close()
    fwd, ref = gcs.arrivals["forwarded"], gcs.arrivals["direct"]
    n = min(len(fwd), len(ref))
    in_order = [p for p, _ in fwd[:n]] == [p for p, _ in ref[:n]]
    added_ms = np.array([(f[1] - r[1]) * 1e3 for f, r in zip(fwd[:n], ref[:n])])
    station_seen = tlog_times(Path(stats["tlog"]))
    station_ms = np.array([(station_seen[p] - t) * 1e3 for p, t in ref if p in station_seen])
    commands = sum(1 for cmd, _ in fv.commands if cmd == GCS_COMMAND)
    return {"mode": mode, "sent": sum(fv.delivered.values()), "arrived": len(fwd), "direct": len(ref),
            "in_order": in_order, "added_ms": added_ms, "station_ms": station_ms, "load": load,
            "commands_sent": gcs.commands_sent, "commands_arrived": commands, "station": stats}


def percentiles(ms: np.ndarray) -> str:
    if not len(ms):
        return f"{'-':>8} {'-':>8} {'-':>8}"
    p50, p99 = np.percentile(ms, [50, 99])
    return f"{p50:8.2f} {p99:8.2f} {ms.max():8.1f}"


def report(rows: list[dict], seconds: float) -> bool:
    print(f"forwarding at {RATE_HZ:.0f} Hz, {seconds:g} s per row: vehicle -> MagStation --forward udpout -> "
          "ground station (added latency, kernel time stamps) and the ground station's commands back; "
          "2 shared cores")
    print(f"  {'station load':<8} {'load avg':<16} {'v->gcs':>11} {'gcs->v':>7} | {'forwarded: p50':>14} "
          f"{'p99':>8} {'max ms':>8} | {'station copy: p50':>17} {'p99':>8} {'max ms':>8} | CPU station/fwd")
    counts_ok, latency_ok = True, True
    for r in rows:
        st = r["station"]
        p99 = float(np.percentile(r["added_ms"], 99)) if len(r["added_ms"]) else float("inf")
        counts_ok &= (r["arrived"] == r["sent"] == r["direct"] and r["in_order"]
                      and r["commands_arrived"] == r["commands_sent"] == st["to_vehicle"] > 0)
        latency_ok &= p99 < TARGET_P99_MS
        print(f"  {r['mode']:<8} {r['load']:<16} {r['arrived']:>5}/{r['sent']:<5} "
              f"{r['commands_arrived']:>3}/{r['commands_sent']:<3} | {percentiles(r['added_ms']):>32} | "
              f"{'':>9}{percentiles(r['station_ms'])} | {st['cpu_pct']:.0f}%/{st['relay_cpu_pct']:.0f}% "
              f"(station rx {st['rx']})")
    print(f"  {'met   ' if counts_ok else 'MISSED'}  every packet both ways, in order (all rows)")
    worst = max(float(np.percentile(r["added_ms"], 99)) if len(r["added_ms"]) else float("inf") for r in rows)
    print(f"  {'met   ' if latency_ok else 'MISSED'}  added latency p99 < {TARGET_P99_MS:g} ms "
          f"(worst row {worst:.2f} ms)")
    return counts_ok and latency_ok


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--modes", default=",".join(MODES), help="station loads to run, of " + ",".join(MODES))
    ap.add_argument("--quick", action="store_true", help="4 s of stream per row (smoke test)")
    a = ap.parse_args(argv)
    modes = [s.strip() for s in a.modes.split(",") if s.strip()]
    if not modes or any(s not in MODES for s in modes):
        ap.error(f"--modes takes a comma list of {', '.join(MODES)}")
    seconds = 4.0 if a.quick else a.seconds
    report([run(seconds, mode) for mode in modes], seconds)
    return 0


if __name__ == "__main__":
    sys.exit(main())
