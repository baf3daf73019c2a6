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

Same-run reference, "station's copy": when the station's link reader got each packet (stamped
by this benchmark as the reader returns it; the link's own samples and recording carry the
kernel's arrival stamp, which a busy station does not delay) minus the direct copy's arrival: the latency an in-process
forwarder (MagStation before the forwarding process; it sent from that reader thread) would have
added, plus one loopback hop.  The direct copy leaves the vehicle just after the station's (two
sendto calls), so figures near zero can come out slightly negative.

Peer (optional, ``--mavproxy``): MAVProxy forwarding the same stream, idle otherwise; its row is
printed beside ours but not judged.  MAVProxy's package pulls in opencv and vtk, so it is not a
dependency: ``pip install --no-deps --target DIR MAVProxy`` and pass ``DIR/bin/mavproxy.py``.
mavlink-router (C++) is not installed here.

    python benchmarks/forward_latency.py [--seconds 20] [--modes live,replay,hog] [--quick]
                                         [--mavproxy DIR/bin/mavproxy.py]
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

from benchmarks.proc_cpu import cpu_seconds  # noqa: E402
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
from benchmarks.proc_cpu import cpu_seconds
from groundstation.io.forward import Forwarder
from groundstation.station.hub.session import Session
port, gcs_port, mode, demo = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4]
fw = Forwarder([f"udpout:127.0.0.1:{gcs_port}"]).start()
hub = Session(tempfile.mkdtemp(), record_live=True, forwarder=fw)
hub.connect(f"udpin:127.0.0.1:{port}")
stop = threading.Event()
read_at = {}                       # packet -> when the station's link reader got it (the link
read = hub.sources.link._read_available   # itself keeps the kernel's arrival stamp)

def reading(max_messages=1000):
    got = read(max_messages)
    now = time.time()
    for _, packet, _ in got:
        read_at.setdefault(packet.hex(), now)
    return got

hub.sources.link._read_available = reading

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

if mode in ("replay", "hog"):
    threading.Thread(target=replaying, daemon=True).start()
if mode == "hog":
    threading.Thread(target=hogging, daemon=True).start()
print("ready", flush=True)
cpu0, relay0, wall0 = cpu_seconds(os.getpid()), cpu_seconds(fw.pid), time.monotonic()
sys.stdin.readline()
cpu1, relay1, wall1 = cpu_seconds(os.getpid()), cpu_seconds(fw.pid), time.monotonic()
stop.set()
fw.refresh()
snap = hub.snapshot()
hub.close()
read_path = os.path.join(tempfile.mkdtemp(), "read_at.json")
with open(read_path, "w") as f:
    json.dump(dict(read_at), f)
print(json.dumps({"read_at": read_path, "rx": snap["rx_count"], "to_vehicle": snap["vehicles"]["forwarding"]["to_vehicle"],
                  "cpu_pct": 100 * (cpu1 - cpu0) / (wall1 - wall0), "relay_cpu_pct": 100 * (relay1 - relay0) / (wall1 - wall0)}), flush=True)
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


def read_times(path: Path) -> dict[bytes, float]:
    """The station's read times (packet hex -> unix s), written by its process at the end."""
    return {bytes.fromhex(k): v for k, v in json.loads(path.read_text()).items()}


class StationUnderTest:
    """MagStation (Session + Forwarder) in its own process under one of MODES."""

    def __init__(self, mode: str, gcs_port: int) -> None:
        self.port = free_udp_port()
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        self.proc = subprocess.Popen([sys.executable, "-c", STATION, str(self.port), str(gcs_port), mode,
                                      str(ROOT / "recordings" / "demo.tlog")], cwd=ROOT, env=env,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout.readline().strip() == "ready"
        time.sleep(1.0 if mode != "live" else 0.2)        # the load is on before the stream starts

    def finish(self) -> dict:
        self.proc.stdin.write("\n")
        self.proc.stdin.flush()
        stats = json.loads(self.proc.stdout.readline())
        self.proc.wait(20)
        return stats


class MavproxyUnderTest:
    """The peer: MAVProxy forwarding the vehicle link (--master udpin) to the ground station
    (--out udpout), idle otherwise (no modules, no stream-rate requests)."""

    def __init__(self, script: Path, gcs_port: int, state_dir: Path) -> None:
        self.port = free_udp_port()
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(script.parent.parent), str(ROOT)]))
        self.proc = subprocess.Popen([sys.executable, str(script), f"--master=udpin:127.0.0.1:{self.port}",
                                      f"--out=udpout:127.0.0.1:{gcs_port}", "--daemon", "--non-interactive",
                                      "--default-modules=", "--streamrate=-1", f"--state-basedir={state_dir}"],
                                     env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL)
        time.sleep(3.0)                                    # its start-up prints nothing we could wait for
        self.cpu0, self.wall0 = cpu_seconds(self.proc.pid), time.monotonic()

    def finish(self) -> dict:
        cpu = 100 * (cpu_seconds(self.proc.pid) - self.cpu0) / (time.monotonic() - self.wall0)
        self.proc.terminate()
        self.proc.wait(10)
        return {"cpu_pct": cpu, "relay_cpu_pct": float("nan"), "rx": "-", "to_vehicle": None, "read_at": None}


def run(seconds: float, mode: str, mavproxy: Path | None = None) -> dict:
    """One row: the station under ``mode`` load (or MAVProxy), the stream for ``seconds``."""
    gcs = GroundStation()
    if mode == "mavproxy":
        import tempfile
        under_test = MavproxyUnderTest(mavproxy, gcs.port, Path(tempfile.mkdtemp()))
    else:
        under_test = StationUnderTest(mode, gcs.port)
    fv = FakeVehicle(stream(seconds), under_test.port, speed=1.0)
    fv.mirror = ("127.0.0.1", gcs.ref_port)
    load = " ".join(open("/proc/loadavg").read().split()[:3])
    fv.start()
    fv.finished.wait(seconds + 30)
    time.sleep(0.5)                            # the ground station's last answers reach the vehicle
    fv.stop()                                  # nothing more is sent (heartbeats included)
    deadline = time.monotonic() + 10           # a loaded machine may hold the last packets a while
    while time.monotonic() < deadline and len(gcs.arrivals["forwarded"]) < sum(fv.delivered.values()):
        time.sleep(0.1)
    stats = under_test.finish()
    gcs.close()
    fwd, ref = gcs.arrivals["forwarded"], gcs.arrivals["direct"]
    n = min(len(fwd), len(ref))
    in_order = [p for p, _ in fwd[:n]] == [p for p, _ in ref[:n]]
    added_ms = np.array([(f[1] - r[1]) * 1e3 for f, r in zip(fwd[:n], ref[:n])])
    # MAVProxy (no station reader) has no copy: shown "-"
    station_seen = read_times(Path(stats["read_at"])) if stats.get("read_at") else {}
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
    """The table (MagStation rows, then the peer's) and the verdicts on MagStation's rows."""
    print(f"forwarding at {RATE_HZ:.0f} Hz, {seconds:g} s per row: vehicle -> forwarder -> ground station "
          "(added latency from kernel time stamps) and the ground station's commands back; 2 shared cores")
    print(f"  {'forwarder (load)':<22} {'load avg':<15} {'v->gcs':>11} {'gcs->v':>7} | {'forwarded: p50':>14} "
          f"{'p99':>8} {'max ms':>8} | {'station copy: p50':>17} {'p99':>8} {'max ms':>8} | CPU station/fwd")
    ours = [r for r in rows if r["mode"] != "mavproxy"]
    counts_ok, worst = True, 0.0
    for r in rows:
        st = r["station"]
        p99 = float(np.percentile(r["added_ms"], 99)) if len(r["added_ms"]) else float("inf")
        counts = (r["arrived"] == r["sent"] == r["direct"] and r["in_order"] and r["commands_sent"] > 0
                  and r["commands_arrived"] == r["commands_sent"] == (st["to_vehicle"] or r["commands_sent"]))
        if r in ours:
            counts_ok &= counts
            worst = max(worst, p99)
        name = f"MagStation ({r['mode']})" if r in ours else "peer: MAVProxy (idle)"
        cpu = f"{st['cpu_pct']:.0f}%/{st['relay_cpu_pct']:.0f}%" if r in ours else f"-/{st['cpu_pct']:.0f}%"
        print(f"  {name:<22} {r['load']:<15} {r['arrived']:>5}/{r['sent']:<5} "
              f"{r['commands_arrived']:>3}/{r['commands_sent']:<3} | {percentiles(r['added_ms']):>32} | "
              f"{'':>9}{percentiles(r['station_ms'])} | {cpu} (station rx {st['rx']})")
    print(f"  {'met   ' if counts_ok else 'MISSED'}  every packet both ways, in order (MagStation rows)")
    print(f"  {'met   ' if worst < TARGET_P99_MS else 'MISSED'}  added latency p99 < {TARGET_P99_MS:g} ms "
          f"(worst MagStation row {worst:.2f} ms)")
    return counts_ok and worst < TARGET_P99_MS


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--modes", default=",".join(MODES), help="station loads to run, of " + ",".join(MODES))
    ap.add_argument("--quick", action="store_true", help="4 s of stream per row (smoke test)")
    ap.add_argument("--mavproxy", type=Path, help="mavproxy.py of a MAVProxy install: adds the peer's row")
    a = ap.parse_args(argv)
    modes = [s.strip() for s in a.modes.split(",") if s.strip()]
    if not modes or any(s not in MODES for s in modes):
        ap.error(f"--modes takes a comma list of {', '.join(MODES)}")
    if a.mavproxy is not None and not a.mavproxy.is_file():
        ap.error(f"--mavproxy: no such file {a.mavproxy}")
    seconds = 4.0 if a.quick else a.seconds
    if a.mavproxy is not None:
        modes.insert(1 if modes[0] == "live" else 0, "mavproxy")
    report([run(seconds, mode, a.mavproxy) for mode in modes], seconds)
    return 0


if __name__ == "__main__":
    sys.exit(main())
