"""The fleet's compass history: one SQLite file written by `magstation review` and by accepted
calibrations, read by the review report and the station's fleet page.

SQLite (Python's own ``sqlite3``), not DuckDB: the station must read the history *while* a review
or a calibration writes it, from another process.  SQLite in WAL mode gives any number of readers
beside one writer across processes; DuckDB lets one process hold a database file read-write and
no other process open it at all meanwhile.  The history is small (a row per log and compass, a few
thousand a month) and written row by row, so a column store gains nothing here; the Parquet export
(``magstation review --out``) is the analytics copy for DuckDB/pandas notebooks.

Tables (``SCHEMA_VERSION``):
  flights       one row per log and compass (``ROW_COLUMNS``), key (log_hash, compass)
  calibrations  every calibration accepted (station wizard, written to a vehicle) or imported, with
                the whole calibration object (``calibration_json``, ``relative_to``) since the calibration in use
  in_use        the calibration the station chose per airframe (``set_in_use`` / ``get_in_use``)
  alerts        derived: drift / payload / anomaly-site / interference findings
  sites         derived: take-off sites with their field effect; flight_sites: log hash -> site
                (the derived tables are rebuilt together after every write)
  meta          key/value (schema version)
Readers open the file read-only (``connect(path, read_only=True)``: ``mode=ro`` URI); a missing
file is an empty history.  Units are in the column names (mG, mG/A, deg, s, Hz, MB).
"""
from __future__ import annotations

import json
import os
import sqlite3
from pathlib import Path
from typing import Iterable, Sequence

from groundstation.paths import RECORDINGS_DIR

__all__ = ["ROW_COLUMNS", "CALIBRATION_COLUMNS", "ALERT_COLUMNS", "SCHEMA_VERSION", "connect", "upsert_rows",
           "known_hashes", "flight_rows", "insert_calibration", "calibration_rows",
           "alert_rows", "airframe_summary", "airframe_of_identity", "DB_NAME", "set_airframes", "empty_row", "default_db_path", "replace_findings",
           "site_rows", "worst_flight_rows", "concern_key", "calibration_in_force", "set_in_use", "get_in_use",
           "IN_USE_COLUMNS"]

SCHEMA_VERSION = 1
XYZ = ("x", "y", "z")


def _vec(prefix: str, unit: str, kind: str = "REAL") -> list[tuple[str, str]]:
    return [(f"{prefix}_{a}_{unit}", kind) for a in XYZ]


# (name, SQLite type); the order is the Parquet column order too
ROW_COLUMNS: tuple[tuple[str, str], ...] = tuple([
    ("log_hash", "TEXT"), ("compass", "INTEGER"), ("path", "TEXT"), ("file_name", "TEXT"), ("file_bytes", "INTEGER"),
    ("status", "TEXT"), ("error", "TEXT"),
    ("airframe", "TEXT"), ("identity", "TEXT"), ("identity_source", "TEXT"), ("payload", "TEXT"),
    ("autopilot", "TEXT"), ("sysid", "INTEGER"), ("serial", "TEXT"), ("board_uid", "TEXT"), ("compasses", "INTEGER"),
    ("start_unix_s", "REAL"), ("date", "TEXT"), ("duration_s", "REAL"),
    ("lat_deg", "REAL"), ("lon_deg", "REAL"), ("alt_m", "REAL"),
    ("device_id", "INTEGER"), ("compass_source", "TEXT"), ("cal_state", "TEXT"), *_vec("cal_ofs", "mG"),
    ("fit_model", "TEXT"), ("fit_status", "TEXT"), ("fit_samples", "INTEGER"), ("fit_yaw_dependence", "REAL"),
    ("fit_heading_coverage", "REAL"), *_vec("fit_ofs", "mG"), *_vec("fit_ofs_sd", "mG"), ("motor_status", "TEXT"),
    *_vec("ofs_change", "mG"), ("ofs_change_mG", "REAL"), ("fit_residual_rms_mG", "REAL"),
    *_vec("motor", "mG_per_A"), ("motor_sd_mG_per_A", "REAL"), ("current_max_A", "REAL"), ("interference_pct", "REAL"),
    ("wmm_strength_mG", "REAL"), ("wmm_inclination_deg", "REAL"), ("wmm_declination_deg", "REAL"),
    ("field_inclination_deg", "REAL"), ("field_inclination_sd_deg", "REAL"),
    ("strength_resid_mG", "REAL"), ("inclination_resid_deg", "REAL"),
    ("alarm_count", "INTEGER"), ("alarm_kinds", "TEXT"), ("first_alarm_s", "REAL"), ("alarm_evidence", "TEXT"),
    ("alarm_intervals_s", "TEXT"), ("calibration_used", "TEXT"), ("attitude_source", "TEXT"),
    ("heading_vs_autopilot_rms_deg", "REAL"), ("heading_vs_autopilot_max_deg", "REAL"), ("compass_spread_deg", "REAL"),
    ("max_cross_track_m", "REAL"), ("rtk", "INTEGER"),
    ("mag_rate_hz", "REAL"), ("imu_rate_hz", "REAL"), ("att_rate_hz", "REAL"), ("gps_rate_hz", "REAL"),
    ("max_gap_s", "REAL"), ("corrupt_packets", "INTEGER"), ("warnings", "TEXT"),
    ("ellipsoid_status", "TEXT"), *_vec("ellipsoid_ofs", "mG"),
    ("review_s", "REAL"), ("review_cpu_s", "REAL"), ("worker_peak_rss_MB", "REAL"), ("worker", "TEXT"),
    ("reviewed_unix_s", "REAL"),
    ("row_version", "INTEGER"),
])
ROW_NAMES = tuple(n for n, _ in ROW_COLUMNS)

CALIBRATION_COLUMNS: tuple[tuple[str, str], ...] = tuple([
    ("id", "INTEGER PRIMARY KEY AUTOINCREMENT"), ("airframe", "TEXT"), ("unix_s", "REAL"), ("source", "TEXT"),
    ("compass", "INTEGER"), *_vec("ofs", "mG"), ("matrix_json", "TEXT"), ("fitness_mG", "REAL"),
    ("orientation", "TEXT"), ("wmm_strength_mG", "REAL"), ("wmm_inclination_deg", "REAL"),
    ("wmm_declination_deg", "REAL"), ("lat_deg", "REAL"), ("lon_deg", "REAL"), ("site", "TEXT"),
    ("written_to_vehicle", "INTEGER"), ("note", "TEXT"), ("relative_to", "TEXT"), ("calibration_json", "TEXT"),
    ("recorded_unix_s", "REAL"),
])
# the calibration in use the station chose per airframe (one row each; survives restarts)
IN_USE_COLUMNS: tuple[tuple[str, str], ...] = (
    ("airframe", "TEXT PRIMARY KEY"), ("unix_s", "REAL"), ("source", "TEXT"), ("label", "TEXT"),
    ("calibration_json", "TEXT"))

ALERT_COLUMNS: tuple[tuple[str, str], ...] = tuple([
    ("kind", "TEXT"), ("airframe", "TEXT"), ("site", "TEXT"), ("lat_deg", "REAL"), ("lon_deg", "REAL"),
    ("unix_s", "REAL"), ("log_hash", "TEXT"),
    ("value", "REAL"), ("threshold", "REAL"), ("sigma", "REAL"), ("unit", "TEXT"), ("message", "TEXT"),
])


DB_NAME = "fleet.sqlite"


def default_db_path(folder: str | Path | None = None) -> Path:
    """Where review and the station meet: $MAGSTATION_FLEET_DB when set, else ``fleet.sqlite`` in
    ``folder`` (the station's recordings folder; default ``groundstation.paths.RECORDINGS_DIR``)."""
    env = os.environ.get("MAGSTATION_FLEET_DB")
    if env:
        return Path(env).expanduser()
    return Path(folder if folder is not None else RECORDINGS_DIR) / DB_NAME

SITE_COLUMNS: tuple[tuple[str, str], ...] = (
    ("name", "TEXT"), ("lat_deg", "REAL"), ("lon_deg", "REAL"), ("flights", "INTEGER"), ("airframes_json", "TEXT"),
    ("strength_effect_mG", "REAL"), ("inclination_effect_deg", "REAL"), ("anomaly", "INTEGER"),
    *_vec("offset_effect", "mG"))

# worst flights first: combined alarms, then compass-vs-autopilot heading disagreement, then cross-track
_CONCERN_SQL = "COALESCE(alarm_count, 0) DESC, COALESCE(heading_vs_autopilot_max_deg, 0) DESC, " \
               "COALESCE(max_cross_track_m, 0) DESC"


def concern_key(row: dict) -> tuple:
    """Sort key (descending) of ``worst_flight_rows``, for rows already in memory."""
    return (row.get("alarm_count") or 0, row.get("heading_vs_autopilot_max_deg") or 0.0,
            row.get("max_cross_track_m") or 0.0)


def empty_row() -> dict:
    """A row with every column None (rows are built on top of it)."""
    return {n: None for n in ROW_NAMES}


def _create(con: sqlite3.Connection) -> None:
    cols = ", ".join(f'"{n}" {t}' for n, t in ROW_COLUMNS)
    con.execute(f"CREATE TABLE IF NOT EXISTS flights ({cols}, PRIMARY KEY (log_hash, compass))")
    con.execute("CREATE INDEX IF NOT EXISTS flights_airframe ON flights (airframe, start_unix_s)")
    con.execute("CREATE INDEX IF NOT EXISTS flights_path ON flights (path)")   # upsert drops a path's failure rows
    con.execute(f"CREATE TABLE IF NOT EXISTS calibrations ({', '.join(f'{n} {t}' for n, t in CALIBRATION_COLUMNS)})")
    have_cal = {r[1] for r in con.execute("PRAGMA table_info(calibrations)")}
    for name, kind in CALIBRATION_COLUMNS:  # an older history's calibrations gain the new columns
        if name not in have_cal:
            con.execute(f'ALTER TABLE calibrations ADD COLUMN "{name}" {kind}')
    con.execute(f"CREATE TABLE IF NOT EXISTS in_use ({', '.join(f'{n} {t}' for n, t in IN_USE_COLUMNS)})")
    for table, spec in (("alerts", ALERT_COLUMNS), ("sites", SITE_COLUMNS)):   # derived: rebuilt when the spec changed
        have = [r[1] for r in con.execute(f"PRAGMA table_info({table})")]
        if have and have != [n for n, _ in spec]:
            con.execute(f"DROP TABLE {table}")
    con.execute(f"CREATE TABLE IF NOT EXISTS alerts ({', '.join(f'{n} {t}' for n, t in ALERT_COLUMNS)})")
    con.execute(f"CREATE TABLE IF NOT EXISTS sites ({', '.join(f'{n} {t}' for n, t in SITE_COLUMNS)})")
    con.execute("CREATE TABLE IF NOT EXISTS flight_sites (log_hash TEXT PRIMARY KEY, site TEXT)")
    con.execute("CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT)")
    con.execute("INSERT OR IGNORE INTO meta VALUES ('schema_version', ?)", (str(SCHEMA_VERSION),))
    have = {r[1] for r in con.execute("PRAGMA table_info(flights)")}
    for name, kind in ROW_COLUMNS:          # a history written by an older version gains new columns
        if name not in have:
            con.execute(f'ALTER TABLE flights ADD COLUMN "{name}" {kind}')


def connect(path: str | Path, read_only: bool = False) -> sqlite3.Connection:
    """Open the history.  Writers create it (WAL mode); readers open ``mode=ro`` and raise
    FileNotFoundError when it does not exist.  Rows come back as ``sqlite3.Row``."""
    path = Path(path)
    if read_only:
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no fleet history yet")
        con = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True, timeout=10.0)
    else:
        path.parent.mkdir(parents=True, exist_ok=True)
        con = sqlite3.connect(path, timeout=30.0)
        con.execute("PRAGMA journal_mode=WAL")
        con.execute("PRAGMA synchronous=NORMAL")
        _create(con)
        con.commit()
    con.row_factory = sqlite3.Row
    return con


def upsert_rows(con: sqlite3.Connection, rows: Iterable[dict]) -> int:
    """Insert or replace flight rows (keyed by log hash and compass); an earlier failure row of the
    same path is dropped.  Returns how many rows were written."""
    names = ", ".join(f'"{n}"' for n in ROW_NAMES)
    marks = ", ".join("?" for _ in ROW_NAMES)
    rows = list(rows)
    data = [tuple(r.get(n) for n in ROW_NAMES) for r in rows]
    with con:
        con.executemany("DELETE FROM flights WHERE path = ? AND status IN ('error', 'timeout')",
                        [(r.get("path"),) for r in rows])
        con.executemany(f"INSERT OR REPLACE INTO flights ({names}) VALUES ({marks})", data)
    return len(data)


def known_hashes(con: sqlite3.Connection, only_ok: bool = False,
                 min_row_version: int | None = None) -> dict[str, tuple[str, int]]:
    """log hash -> (path, file bytes) of every reviewed log (``only_ok``: those that did not fail;
    ``min_row_version``: rows written by that version of the per-log job or a later one)."""
    where = ["status NOT IN ('error', 'timeout')"] if only_ok else []
    if min_row_version is not None:
        where.append(f"COALESCE(row_version, 0) >= {int(min_row_version)}")
    sql = "SELECT log_hash, path, file_bytes FROM flights" + (" WHERE " + " AND ".join(where) if where else "")
    return {r[0]: (r[1], r[2]) for r in con.execute(sql)}


def flight_rows(con: sqlite3.Connection, airframe: str | None = None, limit: int | None = None,
                order: str = "start_unix_s") -> list[dict]:
    """Flight rows as dicts, oldest first (``order`` is one of a fixed set of columns).  With an
    ``airframe``, each row also has its site and that site's apparent offset (``site_offset_*_mG``)."""
    if order not in ("start_unix_s", "reviewed_unix_s", "ofs_change_mG", "alarm_count"):
        raise ValueError(f"cannot order by {order!r}")
    sql, args = "SELECT * FROM flights f", []
    if airframe is not None:
        sql = ("SELECT f.*, s.name AS site, s.offset_effect_x_mG AS site_offset_x_mG, s.offset_effect_y_mG AS "
               "site_offset_y_mG, s.offset_effect_z_mG AS site_offset_z_mG FROM flights f LEFT JOIN flight_sites fs "
               "ON fs.log_hash = f.log_hash LEFT JOIN sites s ON s.name = fs.site WHERE f.airframe = ?")
        args.append(airframe)
    sql += f' ORDER BY f."{order}", f.log_hash, f.compass'
    if limit is not None:
        sql += " LIMIT ?"
        args.append(int(limit))
    return [dict(r) for r in con.execute(sql, args)]


def set_airframes(con: sqlite3.Connection, assignments: Sequence[tuple[str, str | None, str, int]]) -> None:
    """(airframe, payload, log_hash, compass) updates after a mapping change."""
    with con:
        con.executemany("UPDATE flights SET airframe = ?, payload = ? WHERE log_hash = ? AND compass = ?",
                        assignments)


def insert_calibration(con: sqlite3.Connection, record: dict) -> int:
    """Append one calibration record (keys from ``CALIBRATION_COLUMNS`` except id); returns its id."""
    names = [n for n, _ in CALIBRATION_COLUMNS if n != "id"]
    with con:
        cur = con.execute(f"INSERT INTO calibrations ({', '.join(names)}) VALUES ({', '.join('?' for _ in names)})",
                          tuple(record.get(n) for n in names))
    return int(cur.lastrowid)


def calibration_rows(con: sqlite3.Connection, airframe: str | None = None) -> list[dict]:
    sql, args = "SELECT * FROM calibrations", ()
    if airframe is not None:
        sql, args = sql + " WHERE airframe = ?", (airframe,)
    rows = [dict(r) for r in con.execute(sql + " ORDER BY unix_s, id", args)]
    for r in rows:
        r["matrix"] = json.loads(r.pop("matrix_json")) if r.get("matrix_json") else None
    return rows


def calibration_in_force(con: sqlite3.Connection, airframe: str, unix_s: float | None = None,
                         compass: int = 0) -> dict | None:
    """The airframe's latest calibration record at ``unix_s`` (None: the latest of all) that holds
    the whole calibration object (``calibration_json``), with ``calibration`` parsed; None when none."""
    sql = "SELECT * FROM calibrations WHERE airframe = ? AND COALESCE(compass, 0) = ? AND calibration_json IS NOT NULL"
    args: tuple = (airframe, int(compass))
    if unix_s is not None:
        sql, args = sql + " AND unix_s <= ?", args + (float(unix_s),)
    return _with_calibration(con.execute(sql + " ORDER BY unix_s DESC, id DESC LIMIT 1", args).fetchone())


def set_in_use(con: sqlite3.Connection, airframe: str, source: str, label: str, calibration: dict | None,
               unix_s: float) -> None:
    """The station's choice of calibration for an airframe (replaces the previous one; None clears it)."""
    with con:
        if calibration is None:
            con.execute("DELETE FROM in_use WHERE airframe = ?", (airframe,))
            return
        con.execute("INSERT OR REPLACE INTO in_use VALUES (?, ?, ?, ?, ?)",
                    (airframe, float(unix_s), source, label, json.dumps(calibration, allow_nan=False)))


def get_in_use(con: sqlite3.Connection, airframe: str) -> dict | None:
    """{airframe, unix_s, source, label, calibration} the station chose, or None."""
    try:
        row = con.execute("SELECT * FROM in_use WHERE airframe = ?", (airframe,)).fetchone()
    except sqlite3.OperationalError:           # a read-only older history without the table
        return None
    return _with_calibration(row)


def _with_calibration(row) -> dict | None:
    """A row with a ``calibration_json`` column as a dict with ``calibration`` parsed; None when
    there is no row or its JSON does not parse."""
    if row is None:
        return None
    out = dict(row)
    try:
        out["calibration"] = json.loads(out.pop("calibration_json"))
    except ValueError:
        return None
    return out


def replace_findings(con: sqlite3.Connection, alerts: Iterable[dict], sites: Iterable[dict],
                     site_of: dict[str, str]) -> None:
    """The derived tables (alerts, sites, flight_sites) rebuilt in one transaction: readers see the
    old findings or the new ones, never half."""
    names = [n for n, _ in ALERT_COLUMNS]
    snames = [n for n, _ in SITE_COLUMNS]
    site_data = [(s["name"], s["lat_deg"], s["lon_deg"], s["flights"], json.dumps(list(s.get("airframes", []))),
                  s.get("strength_effect_mG"), s.get("inclination_effect_deg"), int(bool(s.get("anomaly"))),
                  *(list(s.get("offset_effect_mG") or [None] * 3)))
                 for s in sites]
    with con:
        for table in ("alerts", "sites", "flight_sites"):
            con.execute(f"DELETE FROM {table}")
        con.executemany(f"INSERT INTO alerts ({', '.join(names)}) VALUES ({', '.join('?' for _ in names)})",
                        [tuple(a.get(n) for n in names) for a in alerts])
        con.executemany(f"INSERT INTO sites ({', '.join(snames)}) VALUES ({', '.join('?' for _ in snames)})", site_data)
        con.executemany("INSERT INTO flight_sites VALUES (?, ?)", list(site_of.items()))


def site_rows(con: sqlite3.Connection) -> list[dict]:
    rows = [dict(r) for r in con.execute("SELECT * FROM sites ORDER BY name")]
    for r in rows:
        r["airframes"] = json.loads(r.pop("airframes_json") or "[]")
        r["anomaly"] = bool(r["anomaly"])
    return rows


def worst_flight_rows(con: sqlite3.Connection, limit: int = 50) -> list[dict]:
    """Reviewed flights, most concerning first (``concern_key``), with their site."""
    sql = (f"SELECT f.*, s.site AS site FROM flights f LEFT JOIN flight_sites s ON s.log_hash = f.log_hash "
           f"WHERE f.status = 'ok' ORDER BY {_CONCERN_SQL} LIMIT ?")
    return [dict(r) for r in con.execute(sql, (int(limit),))]


def alert_rows(con: sqlite3.Connection) -> list[dict]:
    return [dict(r) for r in con.execute("SELECT * FROM alerts ORDER BY kind, airframe, unix_s")]


def airframe_of_identity(con: sqlite3.Connection, identity: str) -> str | None:
    """The airframe name the history last gave a vehicle identity (``serial:N``, ``uid:...``), or None."""
    row = con.execute("SELECT airframe FROM flights WHERE identity = ? AND airframe IS NOT NULL "
                      "ORDER BY start_unix_s DESC LIMIT 1", (identity,)).fetchone()
    return row[0] if row else None


def airframe_summary(con: sqlite3.Connection) -> list[dict]:
    """Per airframe: flights, failed logs, first/last date, alarms, latest offset change and interference."""
    sql = """
        SELECT COALESCE(airframe, '(unreadable logs)') AS airframe, COUNT(DISTINCT log_hash) AS flights,
               COUNT(DISTINCT CASE WHEN status NOT IN ('ok', 'no_mag') THEN log_hash END) AS failed,
               MIN(start_unix_s) AS first_unix_s, MAX(start_unix_s) AS last_unix_s,
               SUM(COALESCE(alarm_count, 0)) AS alarms,
               AVG(interference_pct) AS mean_interference_pct,
               (SELECT f2.ofs_change_mG FROM flights f2 WHERE f2.airframe = f.airframe AND f2.fit_status = 'ok'
                ORDER BY f2.start_unix_s DESC LIMIT 1) AS latest_ofs_change_mG
        FROM flights f GROUP BY airframe ORDER BY airframe"""
    return [dict(r) for r in con.execute(sql)]

