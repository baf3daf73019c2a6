"""What the station page costs the browser while a replay runs: CPU seconds of chromium's page
(renderer) and GPU processes and of the station, over a window, with the page's own main-thread
figures from the DevTools protocol (task, script, layout time; layouts).

    .venv/bin/python benchmarks/page_cpu.py [--seconds 20] [--view]

The demo replay plays at 1× from 100 s; the page is opened at 1280x720 and left alone for
``--seconds`` after an 8 s settle.  Without ``--view`` the 3-D view's server is not reached (its
software-WebGL frames dominate otherwise and hide the page's own cost).  The CPU figures are
read from /proc (Linux), for every process of the browser.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from benchmarks.proc_cpu import cpu_seconds_of  # noqa: E402

SETTLE_S = 8.0


def measure(seconds: float, view: bool) -> dict:
    from playwright.sync_api import sync_playwright

    from browser_checks import launch_browser, replay
    from conftest import free_tcp_port
    from groundstation.station.app import Station

    rec = Path(tempfile.mkdtemp(prefix="page-cpu-"))
    shutil.copy(ROOT / "recordings" / "demo.tlog", rec)
    station = Station(port=0, viser_port=free_tcp_port(), recordings_dir=rec).start()
    try:
        replay(station, "demo.tlog", seek=100.0, paused=False)
        with sync_playwright() as p:
            browser = launch_browser(p, station.viser_port)
            ctx = browser.new_context(viewport={"width": 1280, "height": 720})
            if not view:
                ctx.route(f"http://127.0.0.1:{station.viser_port}/**", lambda route: route.abort())
            page = ctx.new_page()
            page.goto(station.url + "/index.html")
            time.sleep(SETTLE_S)
            cdp = ctx.new_cdp_session(page)
            cdp.send("Performance.enable")
            names = ("TaskDuration", "ScriptDuration", "LayoutDuration", "LayoutCount")
            before = {m["name"]: m["value"] for m in cdp.send("Performance.getMetrics")["metrics"]}
            cpu0 = {k: cpu_seconds_of(f"--type={k}") for k in ("renderer", "gpu-process")}
            own0, t0 = time.process_time(), time.monotonic()
            time.sleep(seconds)
            wall = time.monotonic() - t0
            own = time.process_time() - own0
            cpu = {k: cpu_seconds_of(f"--type={k}") - v for k, v in cpu0.items()}
            after = {m["name"]: m["value"] for m in cdp.send("Performance.getMetrics")["metrics"]}
            browser.close()
    finally:
        station.close()
        shutil.rmtree(rec, ignore_errors=True)
    return {"seconds": round(wall, 1), "view": view, "renderer_cpu_s": round(cpu["renderer"], 1),
            "gpu_cpu_s": round(cpu["gpu-process"], 1), "station_cpu_s": round(own, 1),
            **{f"page_{k}": round(after[k] - before[k], 2) for k in names}}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--view", action="store_true", help="let the page load the 3-D view")
    args = ap.parse_args(argv)
    r = measure(args.seconds, args.view)
    print(f"station page, demo replay at 1x, {r['seconds']} s, 3-D view {'on' if r['view'] else 'off'}")
    print(f"  CPU s: page (renderer) {r['renderer_cpu_s']}  GPU process {r['gpu_cpu_s']}  "
          f"station (+ the driver) {r['station_cpu_s']}")
    print(f"  page main thread: tasks {r['page_TaskDuration']} s, script {r['page_ScriptDuration']} s, "
          f"layout {r['page_LayoutDuration']} s ({int(r['page_LayoutCount'])} layouts)")
    print(json.dumps(r))
    return 0


if __name__ == "__main__":
    sys.exit(main())
