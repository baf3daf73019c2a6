"""Live latency benchmark: UDP packet sent by a vehicle -> state showing it on the WebSocket.

The station runs in a child process (FastAPI + uvicorn + viser + the session hub, as
`magstation serve`), listening on udpin:127.0.0.1:PORT and recording to a temporary
recordings/ directory.  This process plays the vehicle: SCALED_IMU at the IMU rate, ATTITUDE
at 50 Hz, GPS_RAW_INT at 5 Hz, HEARTBEAT at 1 Hz, as real MAVLink on loopback; and N WebSocket
clients (acknowledging each push, like the web page).  The snapshot carries ``rx_count`` (packets
the station has decoded and processed); the latency of packet k is the time from its send to
the first push with rx_count >= k, over every packet and every client.

Prints p50 / p99 / max latency, the p99 of the first and last third (a growing backlog shows
as a rising p99), pushes per second per client, and the station's CPU (% of one core).

    .venv/bin/python benchmarks/live.py            # 20 s per rate
    .venv/bin/python benchmarks/live.py --quick    # 4 s per rate (smoke run)
"""
from __future__ import annotations

import argparse
import json
import math
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.proc_cpu import cpu_seconds  # noqa: E402

TARGET_P99_MS = 50.0
TARGET_CPU_50HZ = 50.0


def free_port(kind=socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ------------------------------------------------------------------------------------ station

def run_station(recordings: str, viser: bool) -> None:
    """Child process: start the station and print its ports as one JSON line."""
    from groundstation.station.app import Station

    st = Station(port=0, viser_port=free_port() if viser else None, recordings_dir=recordings)
    st.start()
    print(json.dumps({"port": st.port, "viser_port": st.viser_port}), flush=True)
    try:
        while True:
            time.sleep(1)
    except KeyboardInterrupt:
        pass


# ------------------------------------------------------------------------------------ vehicle

class Vehicle(threading.Thread):
    """Sends the stream; ``send_times[k-1]`` = time.perf_counter() when packet k left."""

    def __init__(self, port: int, imu_hz: float, duration_s: float) -> None:
        super().__init__(daemon=True)
        from groundstation.io.mavlink import mavlink2, new_encoder
        self.m = mavlink2
        self.enc = new_encoder(1, 1)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.target = ("127.0.0.1", port)
        self.imu_hz, self.duration_s = imu_hz, duration_s
        self.send_times: list[float] = []

    def _send(self, msg) -> None:
        buf = bytes(msg.pack(self.enc))
        self.sock.sendto(buf, self.target)
        self.send_times.append(time.perf_counter())

    def run(self) -> None:
        m = self.m
        n = int(self.duration_s * self.imu_hz)
        att_every = max(1, round(self.imu_hz / 50))
        gps_every = max(1, round(self.imu_hz / 5))
        hb_every = max(1, round(self.imu_hz))
        start = time.perf_counter()
        for i in range(n):
            due = start + i / self.imu_hz
            while (delay := due - time.perf_counter()) > 0:
                time.sleep(min(delay, 0.002) if delay > 0.0005 else 0)
            t = i / self.imu_hz
            boot_ms = int(t * 1000)
            yaw = 0.3 * t
            if i % hb_every == 0:
                self._send(m.MAVLink_heartbeat_message(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                       0, 0, m.MAV_STATE_ACTIVE, 3))
            mx, my = 400 * math.cos(yaw), -400 * math.sin(yaw)
            self._send(m.MAVLink_scaled_imu_message(boot_ms, 0, 0, -1000, 0, 0, 300, int(mx), int(my), 300))
            if i % att_every == 0:
                self._send(m.MAVLink_attitude_message(boot_ms, 0.0, 0.0, yaw, 0.0, 0.0, 0.3))
            if i % gps_every == 0:
                self._send(m.MAVLink_gps_raw_int_message(int(t * 1e6), 6, 302600000 + i, 1201200000, 30000,
                                                         2, 4, 500, int(math.degrees(yaw) * 100) % 36000, 20))


class Client(threading.Thread):
    def __init__(self, url: str, stop: threading.Event) -> None:
        super().__init__(daemon=True)
        self.url, self.stop = url, stop
        self.rows: list[tuple[float, int]] = []
        self.ready = threading.Event()

    def run(self) -> None:
        import websockets.sync.client as wsc
        with wsc.connect(self.url, max_size=None) as ws:
            self.ready.set()
            while not self.stop.is_set():
                try:
                    text = ws.recv(timeout=1.0)
                except TimeoutError:
                    continue
                t = time.perf_counter()
                ws.send("ack")
                self.rows.append((t, json.loads(text)["rx_count"]))


def measure(base_url: str, pid: int, imu_hz: float, duration_s: float, n_clients: int) -> dict:
    import httpx

    port = free_port(socket.SOCK_DGRAM)
    r = httpx.post(base_url + "/api/source", json={"connect": f"udpin:127.0.0.1:{port}"}, timeout=10)
    r.raise_for_status()
    stop = threading.Event()
    ws_url = base_url.replace("http://", "ws://") + "/ws"
    clients = [Client(ws_url, stop) for _ in range(n_clients)]
    for c in clients:
        c.start()
        c.ready.wait(5)
    time.sleep(0.5)
    # rx_count starts at the first packet of this link; clients may hold older rows
    vehicle = Vehicle(port, imu_hz, duration_s)
    cpu0, wall0 = cpu_seconds(pid), time.perf_counter()
    vehicle.start()
    vehicle.join()
    cpu1, wall1 = cpu_seconds(pid), time.perf_counter()
    time.sleep(0.5)
    stop.set()
    for c in clients:
        c.join(3)
    sends = np.array(vehicle.send_times)
    lat_all, pushes = [], []
    for c in clients:
        rows = np.array([row for row in c.rows if row[0] >= wall0], dtype=float).reshape(-1, 2)
        if not len(rows):
            continue
        pushes.append(len(rows) / (wall1 - wall0))
        seen = np.maximum.accumulate(rows[:, 1])
        k = np.arange(1, len(sends) + 1)
        idx = np.searchsorted(seen, k, side="left")      # first push with rx_count >= k
        ok = idx < len(rows)
        lat_all.append((rows[idx[ok], 0] - sends[ok]) * 1000.0)
        lost = int((~ok).sum())
        if lost:
            print(f"  (client saw {lost} of {len(sends)} packets never counted)")
    lat = np.concatenate(lat_all)
    third = len(sends) // 3
    per_packet = np.stack([x[: min(map(len, lat_all))] for x in lat_all]).max(axis=0)
    return {
        "imu_hz": imu_hz, "packets": len(sends), "clients": n_clients,
        "p50_ms": float(np.percentile(lat, 50)), "p99_ms": float(np.percentile(lat, 99)),
        "max_ms": float(lat.max()),
        "p99_first_ms": float(np.percentile(per_packet[:third], 99)),
        "p99_last_ms": float(np.percentile(per_packet[-third:], 99)),
        "pushes_per_s": float(np.mean(pushes)),
        "cpu_pct": 100.0 * (cpu1 - cpu0) / (wall1 - wall0),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="4 s per rate (smoke run)")
    ap.add_argument("--duration", type=float, default=20.0, help="seconds per rate")
    ap.add_argument("--clients", type=int, default=5)
    ap.add_argument("--rates", default="50,400", help="IMU rates (Hz), comma separated")
    ap.add_argument("--no-viser", action="store_true", help="station without the 3-D view")
    ap.add_argument("--_station", metavar="DIR", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args._station:
        run_station(args._station, viser=not args.no_viser)
        return 0
    duration = 4.0 if args.quick else args.duration
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, __file__, "--_station", tmp] + (["--no-viser"] if args.no_viser else [])
        child = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, cwd=ROOT)
        try:
            line = ""
            while not line.startswith("{"):
                line = child.stdout.readline()
                if not line and child.poll() is not None:
                    raise SystemExit("station failed to start")
            base = f"http://127.0.0.1:{json.loads(line)['port']}"
            results = [measure(base, child.pid, float(r), duration, args.clients)
                       for r in args.rates.split(",")]
        finally:
            child.terminate()
            child.wait(10)
    print(f"\nUDP packet -> WebSocket state latency, {args.clients} clients, {duration:.0f} s per rate "
          f"(station {'with' if not args.no_viser else 'without'} viser), {os.cpu_count()} CPUs")
    print(f"{'IMU Hz':>7} {'packets':>8} {'p50 ms':>7} {'p99 ms':>7} {'max ms':>7} {'p99 1st/3':>10} "
          f"{'p99 last/3':>10} {'push/s':>7} {'CPU %':>6}  target")
    for r in results:
        target = f"p99<{TARGET_P99_MS:.0f} ms" + (f", CPU<{TARGET_CPU_50HZ:.0f}%" if r["imu_hz"] <= 50 else "")
        print(f"{r['imu_hz']:7.0f} {r['packets']:8d} {r['p50_ms']:7.1f} {r['p99_ms']:7.1f} {r['max_ms']:7.1f} "
              f"{r['p99_first_ms']:10.1f} {r['p99_last_ms']:10.1f} {r['pushes_per_s']:7.1f} {r['cpu_pct']:6.1f}  {target}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
