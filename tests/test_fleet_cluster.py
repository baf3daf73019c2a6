"""`magstation review` through real Dask clusters, checked against the simulated fleet's truth:
a LocalCluster of 2 worker processes (run_review), and an explicitly started `dask scheduler` +
`dask worker` pair of processes on loopback driven by the CLI (`--scheduler`)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from contextlib import closing
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from groundstation.io import fleet_db
from groundstation.jobs.airframes import load_airframes
from groundstation.jobs.compass_history import analyse_fleet
from groundstation.jobs.fleet import fleet_client, run_review
from groundstation.jobs.fleet_report import write_parquet
from groundstation.jobs.review_row import review_log
from groundstation.sim.fleet import FleetSettings, simulate_fleet
from groundstation.sim.fleet_score import score_review

from conftest import free_tcp_port

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    out = tmp_path_factory.mktemp("fleet")
    settings = FleetSettings(vehicles=3, flights=10, drift_vehicles=1, payload_vehicles=1, flight_s=(66.0, 70.0),
                             interference_fraction=0.1, anomaly_visit_fraction=0.15, corrupt_files=5, seed=3,
                             drift_total_mG=70.0)
    truth = simulate_fleet(out, settings, workers=2)
    return out, truth


def _check_against_truth(rows: list[dict], alerts: list[dict], truth: dict) -> dict:
    score = score_review(truth, rows, alerts)
    assert score["logs"] == {"planted": 35, "rows": 35}, score["logs"]
    assert score["corrupt"]["reported"] == 5, score["corrupt"]
    assert score["drift"]["found"] == 1 and not score["drift"]["false"], score["drift"]
    assert score["anomaly_sites"]["found"] == 1 and not score["anomaly_sites"]["false"], score["anomaly_sites"]
    assert score["interference"]["found"] == score["interference"]["planted"] > 0, score["interference"]
    assert {r["airframe"] for r in rows if r["status"] == "ok"} == {v["airframe"] for v in truth["vehicles"]}
    return score


def _hangs_on_the_empty_file(path, settings, skip):
    """The per-log job, except that it never returns for one file (a reader stuck in a loop)."""
    if Path(path).name.endswith("-empty.tlog"):
        while True:
            time.sleep(0.01)
    return review_log(path, settings, skip)


@pytest.fixture(scope="module")
def cluster():
    """One LocalCluster of 2 worker processes for the module (its start-up is most of a review's cost
    on 2 cores): the review below and the benchmark's 2-worker side run on it."""
    with fleet_client(workers=2) as (client, dashboard):
        yield client, dashboard


@pytest.fixture(scope="module")
def reviewed(fleet, cluster, tmp_path_factory):
    """The fleet reviewed on a LocalCluster of 2 worker processes (one log hangs), then again."""
    out, _ = fleet
    db = tmp_path_factory.mktemp("history") / "fleet.sqlite"
    mapping = load_airframes(out / "airframes.json")
    seen = []
    client, dashboard = cluster
    info = client.scheduler_info()["workers"]
    summary = run_review(client, [out], db, airframes=mapping, job=_hangs_on_the_empty_file, timeout_s=15.0,
                         on_progress=lambda p: seen.append((p.done, p.failed, p.left)))
    again = run_review(client, [out], db, airframes=mapping)
    return {"db": db, "workers": list(info), "dashboard": dashboard, "summary": summary, "again": again, "seen": seen}


def test_review_on_a_local_cluster_matches_truth_and_reruns_skip(fleet, reviewed, tmp_path):
    """A failing log gives an error row and the run goes on; a hung log times out; a rerun skips
    by content hash (the failed ones are tried again)."""
    out, truth = fleet
    db, summary, again, seen = (reviewed[k] for k in ("db", "summary", "again", "seen"))
    assert len(reviewed["workers"]) == 2 and all(w.startswith("tcp://127.0.0.1:") for w in reviewed["workers"])
    assert reviewed["dashboard"] is None or reviewed["dashboard"].startswith("http://127.0.0.1:")   # loopback only
    p = summary.progress
    assert (p.total, p.done, p.failed, p.skipped, p.left) == (35, 35, 3, 0, 0)
    assert seen[0] == (1, seen[0][1], 34) and seen[-1] == (35, 3, 0) and len(seen) == 35
    assert (again.progress.done, again.progress.skipped) == (3, 32)        # only the failed ones again
    assert sorted(f["status"] for f in summary.failures) == ["error", "error", "timeout"]
    assert [f["status"] for f in again.failures] == ["error"] * 3            # the hung one, read normally now
    with closing(fleet_db.connect(db, read_only=True)) as con:
        rows, alerts = fleet_db.flight_rows(con), fleet_db.alert_rows(con)
    assert len(rows) == 35 and sum(r["status"] == "timeout" for r in rows) == 0   # the timeout row replaced
    assert len({r["worker"] for r in rows if r["worker"]}) == 2                # both workers did logs
    assert summary.peak_worker_rss_MB and summary.peak_worker_rss_MB < 1024
    score = _check_against_truth(rows, alerts, truth)
    assert score["payload"]["found"] == 1 and not score["payload"]["false"], score["payload"]

    findings = analyse_fleet(rows)
    table = pq.read_table(write_parquet(rows, findings.site_of, tmp_path / "rows.parquet"))
    assert table.num_rows == 35 and table.column_names[:3] == ["log_hash", "compass", "path"]
    quarry = next(s for s in truth["sites"] if s["anomaly_ned_mG"])
    anomaly_site = next(s["name"] for s in findings.sites if s["anomaly"])
    data = table.to_pylist()
    for f in truth["flights"]:
        row = next(r for r in data if r["path"].endswith(f["file"]))
        assert (row["site"] == anomaly_site) == (f["site"] == quarry["name"]), (f["file"], row["site"])
        assert row["airframe"] == f["airframe"] and row["status"] == "ok"


def _start(args: list[str], log: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.Popen([sys.executable, "-m", "dask", *args], cwd=ROOT, env=env, stdout=log.open("wb"),
                            stderr=subprocess.STDOUT, start_new_session=True)


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=5)


def test_review_cli_on_explicit_scheduler_and_worker_processes(fleet, reviewed, tmp_path):
    """The drifting airframe's folder through the CLI on an explicit scheduler and worker processes,
    into a copy of the LocalCluster's history without that airframe's rows (the other airframes'
    flights give the site effects; the drift alert needs the new rows)."""
    import shutil

    out, truth = fleet
    drifting = next(v["airframe"] for v in truth["vehicles"] if v["role"] == "drift")
    files = sorted(p.relative_to(out).as_posix() for p in (out / drifting).iterdir())
    db, report = tmp_path / "history.sqlite", tmp_path / "report"
    shutil.copy(reviewed["db"], db)
    with closing(fleet_db.connect(db)) as con, con:
        con.execute("DELETE FROM flights WHERE path LIKE ?", (f"%/{drifting}/%",))
        total = con.execute("SELECT COUNT(*) FROM flights").fetchone()[0] + len(files)
    port, dash = free_tcp_port(), free_tcp_port()
    address = f"tcp://127.0.0.1:{port}"
    scheduler = _start(["scheduler", "--host", "127.0.0.1", "--port", str(port), "--dashboard-address",
                        f"127.0.0.1:{dash}"], tmp_path / "scheduler.log")
    worker = None
    try:
        worker = _start(["worker", address, "--nworkers", "2", "--nthreads", "1", "--host", "127.0.0.1",
                         "--dashboard-address", "127.0.0.1:0", "--memory-limit", "2GiB"], tmp_path / "worker.log")
        from dask.distributed import Client
        with Client(address, timeout="30s") as c:
            c.wait_for_workers(2, timeout=60)
            explicit_workers = set(c.scheduler_info()["workers"])
        cmd = [sys.executable, "-m", "groundstation.cli", "review", str(out / drifting), "--scheduler", address,
               "--db", str(db), "--out", str(report), "--airframes", str(out / "airframes.json")]
        res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=240)
        assert res.returncode == 0, res.stderr[-3000:]
        errors = [c["file"] for c in truth["corrupt"] if c["expected"] == "error" and c["file"] in files]
        assert f"reviewed {len(files)} logs ({len(errors)} failed)" in res.stdout, res.stdout
        assert f"offset_drift: 1\n  {drifting}: fitted offsets moved" in res.stdout, res.stdout
        assert "s per flight-minute" in res.stdout and f"Dask dashboard: http://127.0.0.1:{dash}/status" in res.stderr
    finally:
        for proc in (worker, scheduler):
            if proc is not None:
                _stop(proc)
    assert scheduler.poll() is not None and worker.poll() is not None          # cleaned up
    with closing(fleet_db.connect(db, read_only=True)) as con:
        rows = [r for r in fleet_db.flight_rows(con) if f"/{drifting}/" in r["path"]]
    assert sorted(r["path"] for r in rows) == sorted(str(out / f) for f in files)
    assert len(explicit_workers) == 2 and {r["worker"] for r in rows if r["worker"]} <= explicit_workers
    assert sorted(r["path"] for r in rows if r["status"] == "error") == sorted(str(out / f) for f in errors)
    assert {r["airframe"] for r in rows if r["status"] == "ok"} == {drifting}
    table = pq.read_table(report / "rows.parquet")
    assert table.num_rows == total and "site" in table.column_names
    page = (report / "report.html").read_text()
    assert "fleet.html?replay=flight-" in page and "copy the log there first" in page and "data:image/png" in page
    for f in errors:
        assert Path(f).name in page                                             # listed under failed logs


def test_review_benchmark_smoke(fleet, cluster, monkeypatch, capsys):
    """The benchmark's table on four logs of the test fleet (speed figures are not asserted: load).
    Run in this process, its 2-worker side on the module's cluster (its 1-worker cluster is its own):
    a second interpreter and a second 2-worker start-up cost more than the run itself."""
    import importlib.util
    from contextlib import contextmanager

    out, _ = fleet
    spec = importlib.util.spec_from_file_location("review_benchmark", ROOT / "benchmarks" / "review.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    started = []

    @contextmanager
    def clients(scheduler=None, workers=2, **kw):
        started.append(workers)
        if workers == 2:
            yield cluster
        else:
            with fleet_client(scheduler, workers, **kw) as own:
                yield own

    monkeypatch.setattr(bench, "fleet_client", clients)
    assert bench.main(["--fleet", str(out), "--vehicles", "3", "--flights", "10", "--seed", "3", "--max-logs", "4",
                       "--serial-logs", "1", "--throughput-logs", "2", "--repeats", "1"]) == 0
    stdout = capsys.readouterr().out
    assert sorted(started) == [1, 2]
    assert "(reused)" in stdout and "| 2 workers / 1 worker | " in stdout, stdout
    for metric in ("serial loop, no Dask (peer)", "repeat 1: 1 worker(s), 2 logs", "repeat 1: 2 worker(s), 2 logs",
                   "per-log cost", "per-log CPU", "peak memory per worker", "planted drifts found",
                   "interference events found"):
        assert f"| {metric}" in stdout, stdout


def test_fleet_page_lists_airframes_and_the_drift_alert(fleet, reviewed, playwright_instance, artifacts, tmp_path,
                                                       monkeypatch):
    """web/fleet.html on the station, its history (the reviewed fleet) in the recordings folder."""
    import shutil

    from conftest import CHROMIUM, CHROMIUM_ARGS
    from groundstation.station.app import Station

    _, truth = fleet
    drifting = next(v["airframe"] for v in truth["vehicles"] if v["role"] == "drift")
    monkeypatch.delenv("MAGSTATION_FLEET_DB", raising=False)
    recordings = tmp_path / "recordings"
    recordings.mkdir()
    shutil.copy(reviewed["db"], recordings / fleet_db.DB_NAME)
    station = Station(port=0, viser_port=free_tcp_port(), recordings_dir=recordings).start()
    browser = playwright_instance.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
    try:
        page = browser.new_context(viewport={"width": 1280, "height": 1100}).new_page()
        errors = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(station.url + "/fleet.html")
        page.wait_for_function("document.querySelectorAll('#airframes tr.pick').length === 4 && "
                               "document.querySelector('#chart polyline') !== null", polling=200, timeout=60_000)
        airframes = page.locator("#airframes tr.pick td:first-child").all_text_contents()
        alerts = page.locator("#alerts").inner_text()
        title = page.locator("#history-title").inner_text()
        page.screenshot(path=str(artifacts / "fleet_page.png"), full_page=True)
        for w, h in ((1280, 720), (1920, 1080)):        # the two sizes of the screenshots
            page.set_viewport_size({"width": w, "height": h})
            page.wait_for_function("document.querySelector('#chart polyline') !== null", polling=200, timeout=30_000)
            # drawn in its own pixels at every width: the text and the dots keep their shape
            page.wait_for_function("(() => { const c = document.getElementById('chart');"
                                   " return Math.abs(c.viewBox.baseVal.width - c.getBoundingClientRect().width) < 2; })()",
                                   polling=200, timeout=30_000)
            page.screenshot(path=str(artifacts / f"fleet_page_{w}.png"))
            overflow = page.evaluate("document.documentElement.scrollWidth - document.documentElement.clientWidth")
            assert overflow <= 0, (w, overflow)           # nothing runs off the right edge
    finally:
        browser.close()
        station.close()
    assert sorted(airframes) == sorted([v["airframe"] for v in truth["vehicles"]] + ["(unreadable logs)"])
    assert "offset_drift" in alerts and f"{drifting}: fitted offsets moved" in alerts, alerts
    assert "anomaly_site" in alerts and "payload_change" in alerts, alerts
    assert title == f"Airframe history: {drifting}" and not errors, errors
