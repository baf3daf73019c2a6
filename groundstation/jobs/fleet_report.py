"""The fleet report of `magstation review --out DIR`: ``rows.parquet`` (every row, for notebooks:
``duckdb.sql("select * from 'rows.parquet'")`` or ``pandas.read_parquet``) and ``report.html``
(one self-contained page: summary, alerts, plots as inline PNG, worst flights first).

Plots: fitted offsets of each airframe against its first flights over time; motor interference (%
of the Earth field) by airframe and payload; sites on a lat/lon scatter with their alarm rate;
worst flights (sorted by combined alarms, then the compass-vs-autopilot heading disagreement, then
cross-track) with a link that opens the log in the station's fleet page (the station replays only
logs in its recordings folder: copy the file there first).
"""
from __future__ import annotations

import base64
import html
import io
import math
import time
import urllib.parse
from pathlib import Path

import numpy as np

from groundstation.io import fleet_db
from groundstation.jobs.compass_history import FleetFindings

__all__ = ["write_parquet", "write_html", "worst_flights", "STATION_URL"]

STATION_URL = "http://127.0.0.1:8000"
_ARROW = {"TEXT": "string", "REAL": "float64", "INTEGER": "int64"}


def write_parquet(rows: list[dict], site_of: dict[str, str], path: str | Path) -> Path:
    """Every row (``fleet_db.ROW_COLUMNS`` + site) as one Parquet file."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    fields = [pa.field(n, _ARROW[t]) for n, t in fleet_db.ROW_COLUMNS] + [pa.field("site", "string")]
    columns = {n: [r.get(n) for r in rows] for n, _ in fleet_db.ROW_COLUMNS}
    columns["site"] = [site_of.get(r["log_hash"]) for r in rows]
    table = pa.Table.from_pydict(columns, schema=pa.schema(fields))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, path)
    return path


def worst_flights(rows: list[dict], limit: int = 30) -> list[dict]:
    """Reviewed rows, most concerning first: alarms, then heading disagreement, then cross-track."""
    ok = [r for r in rows if r.get("status") == "ok"]
    return sorted(ok, key=fleet_db.concern_key, reverse=True)[:limit]


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    import matplotlib.pyplot as plt
    plt.close(fig)
    return f'<img alt="plot" src="data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()}">'


def _dates(rows: list[dict]) -> np.ndarray:
    return np.array([np.datetime64(int(r["start_unix_s"]), "s") for r in rows])


def _plot_drift(rows: list[dict], alerted: set[str], findings: FleetFindings):
    import matplotlib.pyplot as plt

    site_ofs = {s["name"]: np.asarray(s.get("offset_effect_mG") or np.zeros(3), float) for s in findings.sites}
    fig, ax = plt.subplots(figsize=(9, 4))
    for airframe in sorted({r["airframe"] for r in rows}):
        mine = [r for r in rows if r["airframe"] == airframe and r.get("fit_ofs_x_mG") is not None and r.get("start_unix_s")]
        if len(mine) < 2:
            continue
        ofs = np.array([[r[f"fit_ofs_{a}_mG"] for a in "xyz"] for r in mine], float)
        ofs -= np.array([site_ofs.get(findings.site_of.get(r["log_hash"]), np.zeros(3)) for r in mine])
        ref = np.median(ofs[: min(5, len(ofs))], axis=0)
        ax.plot(_dates(mine), np.linalg.norm(ofs - ref, axis=1), "-" if airframe in alerted else ":",
                lw=1.8 if airframe in alerted else 0.8, label=airframe if airframe in alerted else None)
    ax.set_ylabel("|fitted offsets − first flights| [mG]")
    ax.set_title("Offset drift per airframe, site effects removed (solid: drift alert)")
    if alerted:
        ax.legend(fontsize=8)
    fig.autofmt_xdate()
    return fig


def _plot_interference(rows: list[dict]):
    import matplotlib.pyplot as plt

    airframes = sorted({r["airframe"] for r in rows})
    payloads = sorted({r.get("payload") or "unknown" for r in rows})
    fig, ax = plt.subplots(figsize=(9, 4))
    for k, payload in enumerate(payloads):
        xs, ys = [], []
        for i, a in enumerate(airframes):
            vals = [r["interference_pct"] for r in rows if r["airframe"] == a and (r.get("payload") or "unknown") == payload
                    and r.get("interference_pct") is not None]
            xs += [i + (k - (len(payloads) - 1) / 2) * 0.15] * len(vals)
            ys += vals
        ax.plot(xs, ys, "o", ms=3, alpha=0.6, label=payload)
    ax.set_xticks(range(len(airframes)), airframes, rotation=60, fontsize=7)
    ax.set_ylabel("motor interference [% of Earth field]")
    ax.set_title("Interference at the highest current, by airframe and payload")
    ax.legend(fontsize=8)
    return fig


def _plot_sites(findings: FleetFindings, rows: list[dict]):
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 5))
    for site in findings.sites:
        flights = [r for r in rows if findings.site_of.get(r["log_hash"]) == site["name"]]
        rate = np.mean([(r.get("alarm_count") or 0) > 0 for r in flights]) if flights else 0.0
        sc = ax.scatter(site["lon_deg"], site["lat_deg"], s=20 + 4 * site["flights"], c=[rate], cmap="viridis_r",
                        vmin=0, vmax=max(0.2, rate), edgecolors="red" if site.get("anomaly") else "k",
                        linewidths=2.5 if site.get("anomaly") else 0.5)
        ax.annotate(f"{site['name']}\n{site['strength_effect_mG']:+.0f} mG", (site["lon_deg"], site["lat_deg"]),
                    fontsize=7, xytext=(6, 6), textcoords="offset points")
    if findings.sites:
        fig.colorbar(sc, ax=ax, label="share of flights with alarms")
    ax.ticklabel_format(useOffset=False)
    ax.tick_params(axis="x", labelrotation=45)
    ax.set_xlabel("longitude [deg]")
    ax.set_ylabel("latitude [deg]")
    ax.set_title("Sites (size: flights; red ring: anomaly site)")
    return fig


def _table(rows: list[dict], columns: list[tuple[str, str]]) -> str:
    head = "".join(f"<th>{html.escape(label)}</th>" for _, label in columns)
    body = []
    for r in rows:
        cells = []
        for key, _ in columns:
            v = r.get(key)
            text = f"{v:.4g}" if isinstance(v, float) and math.isfinite(v) else ("" if v is None else str(v))
            cells.append(f"<td>{text if key == 'link' else html.escape(text)}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><tr>{head}</tr>{''.join(body)}</table>"


def _station_link(row: dict, station_url: str) -> str:
    q = urllib.parse.quote(row["file_name"])
    return (f'<a href="{html.escape(station_url)}/fleet.html?replay={q}">open in station</a> '
            "(from its recordings folder: copy the log there first)")


def write_html(rows: list[dict], findings: FleetFindings, path: str | Path, *, failures: list[dict] = (),
               station_url: str = STATION_URL, title: str = "MagStation fleet review") -> Path:
    """The self-contained report page."""
    import matplotlib
    matplotlib.use("Agg")

    ok = [r for r in rows if r.get("status") == "ok"]
    alerted = {a["airframe"] for a in findings.alerts if a["kind"] == "offset_drift"}
    worst = [dict(r, link=_station_link(r, station_url), site=findings.site_of.get(r["log_hash"]))
             for r in worst_flights(ok)]
    failed = [r for r in rows if r.get("status") in ("error", "timeout")] or list(failures)
    parts = [f"<h1>{html.escape(title)}</h1>",
             f"<p>{len(rows)} rows, {len(ok)} reviewed logs, {len({r['airframe'] for r in ok})} airframes, "
             f"{len(findings.sites)} sites, {len(failed)} failed logs; written {time.strftime('%Y-%m-%d %H:%M')}.</p>",
             "<h2>Alerts</h2>", _table([a for a in findings.alerts if a["kind"] != "interference"],
                                       [("kind", "kind"), ("airframe", "airframe"), ("site", "site"), ("message", "finding")]),
             "<h2>Offset drift</h2>", _png(_plot_drift(ok, alerted, findings)),
             "<h2>Motor interference</h2>", _png(_plot_interference(ok)),
             "<h2>Sites and alarms</h2>", _png(_plot_sites(findings, ok)),
             "<h2>Worst flights</h2>", _table(worst, [
                 ("date", "date"), ("airframe", "airframe"), ("file_name", "log"), ("site", "site"),
                 ("alarm_count", "alarms"), ("alarm_evidence", "evidence"), ("first_alarm_s", "first alarm [s]"),
                 ("heading_vs_autopilot_max_deg", "heading vs autopilot p99 [deg]"),
                 ("max_cross_track_m", "max cross-track [m]"), ("ofs_change_mG", "offset change [mG]"), ("link", "")]),
             "<h2>Logs that failed</h2>", _table(failed, [("path", "log"), ("status", "status"), ("error", "error")])]
    style = ("body{font-family:sans-serif;margin:2em;max-width:1100px} table{border-collapse:collapse;font-size:12px}"
             "td,th{border:1px solid #ccc;padding:2px 6px;text-align:left} img{max-width:100%}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
                    f"<style>{style}</style></head><body>{''.join(parts)}</body></html>", encoding="utf-8")
    return path
