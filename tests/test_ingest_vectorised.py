"""The column-wise .tlog reader gives the same FlightLog as decoding packet by packet.

``_reference_read_tlog`` is the per-packet reader as it was before the vectorised one (kept here,
and only here, as the reference): pymavlink's ``decode`` on each framed record
(``tlog_records``), one ``MavlinkDecoder.decode`` per message, one ``LogBuilder.add`` per sample.
Both are compared table by table, sample by sample, with params, param_history, warnings,
message_counts, mag_cal and status events, on every .tlog of tests/data, recordings/,
../shared/data (skipped when absent) and a seeded corpus of corrupt and truncated files
(benchmarks/fuzz.py's mutations), plus constructed cases (MAVLink 1 and 2 mixed, signed,
truncated payloads, a rebooting vehicle, a late clock, garbage between records).
"""
from __future__ import annotations

import math
import struct
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from conftest import SHARED_DATA
from groundstation.io.boot_clock import BootClock
from groundstation.io.decode import MavlinkDecoder
from groundstation.io.logs import read_log
from groundstation.io.logs import tlog as tlog_module
from groundstation.io.logs.builder import LogBuilder
from groundstation.io.logs.mavlink_bulk import payload_dtype, x25_crc_rows
from groundstation.io.logs.tlog import SPIKE, STAMP_JUMP_S, tlog_records
from groundstation.io.mavlink import mavlink2 as m

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data"
sys.path.insert(0, str(ROOT / "benchmarks"))


# ------------------------------------------------------------------ the reference (per packet)

def _reference_despiked(records, warnings: Counter, jump_s: float = STAMP_JUMP_S):
    prev = None
    pending = None
    for unix, msg in records:
        if pending is not None:
            p_unix, p_msg = pending
            pending = None
            if abs(unix - prev) <= jump_s < abs(unix - p_unix):
                warnings[SPIKE] += 1
                yield prev, p_msg
            else:
                prev = p_unix
                yield p_unix, p_msg
        if prev is not None and abs(unix - prev) > jump_s:
            pending = (unix, msg)
            continue
        prev = unix
        yield unix, msg
    if pending is not None:
        yield pending


def _reference_read_tlog(path: Path, progress=None):
    builder = LogBuilder(str(path))
    decoder = MavlinkDecoder()
    counts, warnings = builder.log.message_counts, builder.log.warnings
    first_unix, last_arrival, backwards_shift = None, -math.inf, 0.0
    with open(path, "rb") as f:
        for unix, msg in _reference_despiked(tlog_records(f, warnings), warnings):
            counts[msg.get_type()] += 1
            if first_unix is None:
                first_unix = unix
            arrival = unix - first_unix + backwards_shift
            if arrival < last_arrival:
                warnings["timestamps going backwards (re-based)"] += 1
                backwards_shift += last_arrival - arrival
                arrival = last_arrival
            last_arrival = arrival
            for s in decoder.decode(msg, arrival):
                builder.add(s)
    warnings.update(decoder.warnings)
    log = builder.finish()
    log.start_unix_s = first_unix
    if log.autopilot is None:
        log.autopilot = decoder.autopilot
    if log.autopilot == "ardupilot":
        log.mag_calibration_applied = True
    return log


def _read_both(path: Path, monkeypatch):
    """(reference, ours) through read_log (so the shared post-processing runs on both); an
    IngestError is a result too (its message)."""
    from groundstation.io.logs import READERS, IngestError

    out = []
    for reader in (_reference_read_tlog, tlog_module.read_tlog):
        monkeypatch.setitem(READERS, ".tlog", reader)
        try:
            out.append(read_log(path))
        except IngestError as err:
            out.append(str(err).replace(path.name, "<file>"))
    return out


def _same_array(a: np.ndarray, b: np.ndarray, what: str) -> None:
    assert a.shape == b.shape, (what, a.shape, b.shape)
    assert np.array_equal(a, b, equal_nan=True), (what, np.argwhere(~((a == b) | (np.isnan(a) & np.isnan(b))))[:5])


def assert_same_log(ref, new) -> None:
    if isinstance(ref, str) or isinstance(new, str):
        assert ref == new
        return
    for name in ("mag", "imu", "attitude", "gps", "battery", "throttle"):
        _same_array(getattr(ref, name), getattr(new, name), name)
    assert [(c.compass, c.source, c.device_id, c.calibration_applied, c.source_note) for c in ref.compasses] == \
           [(c.compass, c.source, c.device_id, c.calibration_applied, c.source_note) for c in new.compasses]
    for a, b in zip(ref.compasses, new.compasses):
        _same_array(a.field, b.field, f"compass {a.compass}")
        assert (a.motor_offset_mG is None) == (b.motor_offset_mG is None)
    assert ref.imus.keys() == new.imus.keys()
    for k in ref.imus:
        _same_array(ref.imus[k], new.imus[k], f"imu {k}")
    assert ref.attitudes.keys() == new.attitudes.keys()
    for k in ref.attitudes:
        _same_array(ref.attitudes[k], new.attitudes[k], f"attitude {k}")
    assert ref.primary_compass == new.primary_compass
    assert ref.params == new.params
    assert ref.param_history == new.param_history
    assert ref.warnings == new.warnings
    assert ref.message_counts == new.message_counts
    assert ref.mag_cal == new.mag_cal
    assert ref.status == new.status
    assert ref.mission == new.mission
    assert (ref.start_unix_s, ref.autopilot, ref.mag_calibration_applied) == \
           (new.start_unix_s, new.autopilot, new.mag_calibration_applied)


# ------------------------------------------------------------------ the logs

def _tlogs(folder: Path) -> list[Path]:
    return sorted(folder.rglob("*.tlog")) if folder.is_dir() else []


SHIPPED = _tlogs(DATA) + _tlogs(ROOT / "recordings")


@pytest.mark.parametrize("path", SHIPPED, ids=[p.name for p in SHIPPED])
def test_shipped_tlogs_read_the_same(path, monkeypatch):
    ref, new = _read_both(path, monkeypatch)
    assert_same_log(ref, new)


def test_shared_tlogs_read_the_same(monkeypatch):
    paths = _tlogs(SHARED_DATA)
    if not paths:
        pytest.skip(f"needs .tlog files in {SHARED_DATA} (beside the checkout; not shipped)")
    for path in paths:
        ref, new = _read_both(path, monkeypatch)
        assert_same_log(ref, new)


def test_fuzz_corpus_reads_the_same(tmp_path, monkeypatch):
    """300 seeded mutations of the tlog seeds (bit flips, overwrites, truncation, inserted and
    deleted bytes, huge lengths): the same log, warnings and all, or the same one-line error."""
    from fuzz import make_cases

    cases = [c for c in make_cases(1200, seed=3) if c.kind == "tlog"]
    assert len(cases) > 250
    for k, case in enumerate(cases):
        path = tmp_path / f"case{k}.tlog"
        path.write_bytes(case.data)
        ref, new = _read_both(path, monkeypatch)
        try:
            assert_same_log(ref, new)
        except AssertionError as err:
            raise AssertionError(f"fuzz case {k} ({case.name}): {err}") from err


# ------------------------------------------------------------------ constructed structures

def _packet(msg, v1: bool = False, signed: bool = False, trim: bool = True, sysid: int = 1) -> bytes:
    enc = m.MAVLink(None, srcSystem=sysid, srcComponent=1)
    if signed:
        enc.signing.secret_key = b"k" * 32
        enc.signing.link_id = 3
        enc.signing.sign_outgoing = True
    raw = bytes(msg.pack(enc, force_mavlink1=v1))
    if not trim and not v1:      # the full payload, untrimmed (a sender that does not trim)
        cls = type(msg)
        values = [getattr(msg, "_" + n + "_raw") if hasattr(msg, "_" + n + "_raw") else getattr(msg, n)
                  for n in cls.ordered_fieldnames]
        payload = cls.unpacker.pack(*[x for v in values for x in (v if isinstance(v, list) else [v])])
        hdr = struct.pack("<BBBBBBBHB", 0xFD, len(payload), 0, 0, 0, sysid, 1, cls.id & 0xFFFF, cls.id >> 16)
        crc = m.x25crc(hdr[1:] + payload + bytes((cls.crc_extra,))).crc
        raw = hdr + payload + struct.pack("<H", crc)
    return raw


def _write(path: Path, records: list[tuple[float, bytes]]) -> None:
    path.write_bytes(b"".join(struct.pack(">Q", int(round(u * 1e6))) + p for u, p in records))


def _mixed_records(seed: int) -> list[tuple[float, bytes]]:
    rng = np.random.default_rng(seed)
    out, unix, boot = [], 1.75e9, 0
    for k in range(1500):
        unix += float(rng.uniform(0.0, 0.03))
        boot += int(rng.integers(5, 30))
        if k == 700:
            boot = 50                                                     # a reboot
        if 900 <= k < 1200:
            unix += 0.02                                                  # the link falls behind
        v1, signed = bool(rng.random() < 0.3), bool(rng.random() < 0.2)
        opts = dict(v1=v1, signed=signed and not v1, trim=bool(rng.random() < 0.5), sysid=1 if rng.random() < 0.95 else 7)
        a = 0.01 * k
        # RAW_IMU/HIGHRES_IMU time_usec: boot times, now and then a UNIX time or 0 (timed on arrival)
        raw_us = boot * 1000 if k % 11 else int(unix * 1e6)
        msgs = [m.MAVLink_scaled_imu2_message(boot, 10, -5, -1000, 3, -2, 300, int(200 * math.cos(a)), 120, -400, 0),
                m.MAVLink_raw_imu_message(raw_us, 11, -6, -990, 2, -1, 301, int(250 * math.sin(a)), 110, -390, 0, 0),
                m.MAVLink_attitude_message(boot, 0.01 * math.sin(a), -0.02, math.remainder(a, 2 * math.pi), 0, 0, 0.3),
                m.MAVLink_attitude_quaternion_message(boot, math.cos(a / 2), 0.0, 0.0, math.sin(a / 2), 0, 0, 0,
                                                      [0.0] * 4),
                m.MAVLink_highres_imu_message(boot * 1000 if k % 13 else 0, 0.1, 0.2, -9.8, 0.01, 0.02, 0.03,
                                              0.3 if k % 7 else float("nan"), -0.1, 0.4, 1013, 0, 10, 25,
                                              0x1FF if k % 3 else 0x3F, k % 2)]
        if k % 5 == 0:
            msgs.append(m.MAVLink_gps_raw_int_message(boot * 1000, 3 if k > 100 else 1, 302600000 + k, 1201200000,
                                                      50000, 80, 120, 200 if k % 50 else 65535, 9000, 18))
        if k % 7 == 0 and k > 300:
            msgs.append(m.MAVLink_global_position_int_message(boot, 302600000, 1201200000, 50000, 20000, 200, -30, 5, 0))
        if k % 10 == 0:
            msgs += [m.MAVLink_vfr_hud_message(0, 2.0, 0, 50 if k % 20 else 150, 20, 0),
                     m.MAVLink_sys_status_message(0, 0, 0, 500, 12000, -1 if k % 30 == 0 else 100, 80, 0, 0, 0, 0, 0, 0),
                     m.MAVLink_sensor_offsets_message(10 + k // 200, -3, 7, 0.1, 0, 0, 0, 0, 0, 0, 0, 0)]
        if k % 50 == 0:
            msgs += [m.MAVLink_heartbeat_message(2, 3, 81, 0, 4, 3),
                     m.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3),              # a GCS
                     m.MAVLink_system_time_message(int((unix + 3) * 1e6), boot)]
        if k % 97 == 0:
            msgs += [m.MAVLink_param_value_message(b"COMPASS_OFS_X", 10.0 + k // 300, 9, 1, 9),
                     m.MAVLink_statustext_message(4, f"status {k}".encode(), 0, 0),
                     m.MAVLink_mag_cal_progress_message(0, 1, 2, 1, 50, [0] * 10, 0.0, 0.0, 0.0)]
        for msg in msgs:
            out.append((unix, _packet(msg, **opts)))
    return out


@pytest.mark.parametrize("seed", [0, 1])
def test_mixed_versions_signed_truncated_reboot_and_late_clock(tmp_path, monkeypatch, seed):
    records = _mixed_records(seed)
    path = tmp_path / "mixed.tlog"
    _write(path, records)
    ref, new = _read_both(path, monkeypatch)
    assert_same_log(ref, new)
    assert len(new.attitude) > 2000 and len(new.imus) >= 2 and len(new.compasses) >= 2
    _damage(path, seed)
    ref, new = _read_both(path, monkeypatch)
    assert_same_log(ref, new)
    assert new.warnings["corrupt packets skipped (bad CRC or garbage)"] > 20


def _damage(path: Path, seed: int) -> None:
    """Garbage between records, a flipped stamp, a clock going back, a record cut off at the end."""
    rng = np.random.default_rng(seed)
    blob = bytearray(path.read_bytes())
    for k in rng.integers(0, len(blob), 40).tolist():
        blob[k:k] = rng.integers(0, 256, int(rng.integers(1, 400))).astype(np.uint8).tobytes()
    blob[5000] ^= 0x10
    path.write_bytes(bytes(blob[:-7]))


def test_framed_a_window_and_decoded_a_run_at_a_time_it_reads_the_same(tmp_path, monkeypatch):
    """The reader frames a window of the file and decodes a run of records at a time, carrying
    from run to run what the rules need (the vehicle, the boot clock and its lag, the last GPS
    fix and position, each compass's unit).  Cut small (windows of 4096 bytes,
    runs of 211 records: tens of cuts in each file), the mixed logs whole and damaged, the logs of
    tests/data (real and SITL ones among them) and a fifth of the fuzz corpus read as packet by
    packet."""
    from fuzz import make_cases

    monkeypatch.setattr(tlog_module, "_BLOCK", 4096)
    monkeypatch.setattr(tlog_module, "DECODE_RECORDS", 211)
    paths = _tlogs(DATA)
    for seed in (0, 1):
        paths.append(tmp_path / f"mixed{seed}.tlog")
        _write(paths[-1], _mixed_records(seed))
        paths.append(tmp_path / f"damaged{seed}.tlog")
        paths[-1].write_bytes(paths[-2].read_bytes())
        _damage(paths[-1], seed)
    cases = [c for c in make_cases(1200, seed=3) if c.kind == "tlog"][::5]
    for k, case in enumerate(cases):
        paths.append(tmp_path / f"case{k}.tlog")
        paths[-1].write_bytes(case.data)
    for path in paths:
        ref, new = _read_both(path, monkeypatch)
        try:
            assert_same_log(ref, new)
        except AssertionError as err:
            raise AssertionError(f"{path.name}: {err}") from err


def test_a_compass_first_heard_runs_after_the_gps_is_judged_against_that_position(tmp_path, monkeypatch):
    """A compass first heard many runs after the last GPS position is judged against that
    position's WMM field (carried from run to run): its 5 400 mG field is implausible there, as
    the per-packet decoder says."""
    monkeypatch.setattr(tlog_module, "DECODE_RECORDS", 100)
    records = [(1.75e9, _packet(m.MAVLink_heartbeat_message(2, 3, 81, 0, 4, 3))),
               (1.75e9 + 0.01, _packet(m.MAVLink_gps_raw_int_message(10_000, 3, 302600000, 1201200000, 50000,
                                                                      80, 120, 200, 9000, 18)))]
    for k in range(350):
        records.append((1.75e9 + 0.02 + 0.01 * k, _packet(m.MAVLink_attitude_message(20 + 10 * k, 0, 0, 0, 0, 0, 0))))
    records.append((1.75e9 + 4.0, _packet(m.MAVLink_scaled_imu3_message(3600, 0, 0, -1000, 0, 0, 0, 4000, 3000, -2000, 0))))
    path = tmp_path / "late_compass.tlog"
    _write(path, records)
    ref, new = _read_both(path, monkeypatch)
    assert_same_log(ref, new)
    assert [w for w in new.warnings if "implausible magnetometer field" in w], new.warnings


def test_x25_crc_and_layouts_match_pymavlink():
    rng = np.random.default_rng(5)
    for width in (0, 1, 2, 9, 40, 265):
        rows = rng.integers(0, 256, (30, width), dtype=np.uint8)
        assert x25_crc_rows(rows).tolist() == [m.x25crc(bytes(r)).crc for r in rows]
    for msg_id, cls in m.mavlink_map.items():
        assert payload_dtype(msg_id).itemsize == cls.unpacker.size
    msg = m.MAVLink_highres_imu_message(123456789, 0.1, 0.2, -9.8, 0.01, 0.02, 0.03, 0.3, -0.1, 0.4, 1013, 0, 10, 25,
                                        0x1FF, 2)
    payload = m.mavlink_map[105].unpacker.pack(*[getattr(msg, n) for n in m.mavlink_map[105].ordered_fieldnames])
    row = np.frombuffer(payload, dtype=payload_dtype(105))[0]
    assert [row[n].item() for n in ("time_usec", "fields_updated", "id")] == [123456789, 0x1FF, 2]
    assert float(row["zacc"]) == float(np.float32(-9.8))


def test_boot_clock_in_bulk_is_the_per_message_clock():
    rng = np.random.default_rng(0)
    for _ in range(50):
        n = int(rng.integers(1, 2000))
        boot = np.cumsum(rng.integers(0, 60, n))
        for r in rng.integers(0, n, int(rng.integers(0, 4))):
            boot[r:] -= boot[r] - int(rng.integers(0, 3))                 # reboots
        arrival = boot * 1e-3 + 100 + np.cumsum(rng.normal(0, 0.01, n))
        for r in rng.integers(0, n, int(rng.integers(0, 5))):
            arrival[r:r + int(rng.integers(1, 800))] += rng.uniform(0, 6)  # late stretches
        one, bulk = BootClock(), BootClock()
        expected = [one(int(b), float(a)) for b, a in zip(boot, arrival)]
        cut = int(rng.integers(0, n))
        got = np.concatenate([bulk.times(boot[:cut], arrival[:cut]), bulk.times(boot[cut:], arrival[cut:])])
        assert np.array_equal(expected, got)
        assert vars(one) == vars(bulk)


# ------------------------------------------------------------------ DataFlash (.bin)

def _read_both_bin(path: Path, monkeypatch):
    """(per record, bulk) through read_log; the per-record path is the module's fallback
    (``_read_messages_per_record``), forced by making the bulk path decline."""
    from groundstation.io.logs import IngestError
    from groundstation.io.logs import dataflash

    out = []
    for force_per_record in (True, False):
        if force_per_record:
            monkeypatch.setattr(dataflash, "decode_records", lambda *a: None)
        else:
            monkeypatch.undo()
        try:
            out.append(read_log(path))
        except IngestError as err:
            out.append(str(err).replace(path.name, "<file>"))
    return out


def _bins(folder: Path) -> list[Path]:
    return sorted(folder.rglob("*.bin")) if folder.is_dir() else []


SHIPPED_BIN = _bins(DATA)


@pytest.mark.parametrize("path", SHIPPED_BIN, ids=[p.name for p in SHIPPED_BIN])
def test_shipped_bins_read_the_same(path, monkeypatch):
    ref, new = _read_both_bin(path, monkeypatch)
    assert_same_log(ref, new)


def test_other_attitude_estimators_read_the_same(tmp_path, monkeypatch):
    """AHR2, XKF1 (two cores: only core 0 kept), NKF1 beside ATT: the bulk path keeps the same
    tables as the per-record one (the in-flight fit chooses among them)."""
    from groundstation.sim import dataflash_writer as dfw
    w = dfw.DataFlashWriter("attitudes")
    for k in range(40):
        t = 1_000_000 + 100_000 * k
        w.write("ATT", t, 0, 10.0 + k, 0, -5.0, 0, 90.0, 0, 0)
        w.write("AHR2", t, 11.0 - k, -6.0, 91.0, 0, 0, 0, 1, 0, 0, 0)
        for c, roll in ((0, 12.0 + 0.5 * k), (1, 40.0)):
            w.write("XKF1", t, c, roll, -7.0, 92.0 + k, *([0.0] * 7), 0, 0, 0, 0)
        w.write("NKF1", t, 0, 13.0, -8.0 - k, 93.0, *([0.0] * 7), 0, 0, 0, 0)
    path = w.save(tmp_path / "att.bin")
    ref, new = _read_both_bin(path, monkeypatch)
    assert set(new.attitudes) == {"AHR2", "XKF1", "NKF1"} and len(new.attitudes["XKF1"]) == 40
    assert_same_log(ref, new)


def test_shared_bins_read_the_same(monkeypatch):
    paths = _bins(SHARED_DATA)
    if not paths:
        pytest.skip(f"needs .bin files in {SHARED_DATA} (beside the checkout; none there)")
    for path in paths:
        ref, new = _read_both_bin(path, monkeypatch)
        assert_same_log(ref, new)


def test_bin_fuzz_corpus_reads_the_same(tmp_path, monkeypatch):
    from fuzz import make_cases

    cases = [c for c in make_cases(1200, seed=4) if c.kind == "bin"]
    assert len(cases) > 200
    for k, case in enumerate(cases):
        path = tmp_path / f"case{k}.bin"
        path.write_bytes(case.data)
        ref, new = _read_both_bin(path, monkeypatch)
        try:
            assert_same_log(ref, new)
        except AssertionError as err:
            raise AssertionError(f"fuzz case {k} ({case.name}): {err}") from err


# ------------------------------------------------------------------ memory

_FRAME_PEAK = """
from groundstation.process_memory import status_MB
import sys
from collections import Counter
from groundstation.io.logs import tlog
before = status_MB("VmRSS")
with open(sys.argv[1], "rb") as f:
    file = tlog._FileBytes(f)
    starts, stamps = tlog.frame_records(file.read, file.n, Counter())
print(len(starts), status_MB("VmHWM") - before)
"""


def test_framing_holds_a_window_of_the_file_not_the_file(tmp_path):
    """Framing a 30-minute 50 Hz tlog (9.7 MB) with its stamps: the process grows by its
    record offsets and stamps (16 bytes a record, 32 allowed), not by the file or by temporaries
    of the whole file (before: 2.7x the file); measured in a process of its own (its peak resident set,
    VmHWM)."""
    import subprocess
    from ingest import write_tlog

    path = tmp_path / "half_hour.tlog"
    write_tlog(path, 30.0)
    file_mb = path.stat().st_size / 2**20
    out = subprocess.run([sys.executable, "-c", _FRAME_PEAK, str(path)], capture_output=True, text=True,
                         cwd=ROOT, check=True).stdout.split()
    records, grown_mb = int(out[0]), float(out[1])
    assert records == 30 * 60 * 50 * 2 + 30 * 60 * (10 + 3 * 5 + 1)     # every record framed
    assert grown_mb < 32 * records / 2**20 + 0.25 * file_mb, (grown_mb, file_mb)
