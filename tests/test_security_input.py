"""Hostile input, second round: digits that are not 0-9 in ports and bauds, non-finite numbers in
rejected request values, symlinks in recordings/, parallel uploads of one name, a backslash in a
tokened first visit's path, and the pseudo-terminal multiplexer under another name.

Each test drives the real station (uvicorn on a free loopback port) or the real parser, and
checks the exact refusal, that nothing was opened or read, and that no request became a 500."""
from __future__ import annotations

import os
import shutil
import threading
from pathlib import Path

import httpx
import pytest

from groundstation.io.endpoints import parse_connection_string
from groundstation.io.errors import IngestError

DATA = Path(__file__).parent / "data"
DEMO = Path(__file__).resolve().parents[1] / "recordings" / "demo.tlog"

# '²' passes str.isdigit() but not int(); Arabic-Indic and full-width digits pass both and int()
# reads them as the ASCII number (14550), while the page would show the other text
ODD_DIGITS = {"superscript two": "\u00b2", "Arabic-Indic 14550": "\u0661\u0664\u0665\u0665\u0660",
              "full-width 14550": "\uff11\uff14\uff15\uff15\uff10", "Devanagari 5760": "\u096b\u096d\u096c\u0966"}


@pytest.mark.parametrize("kind", ["udpin", "udp", "udpout", "tcp", "tcpin"])
@pytest.mark.parametrize("digits", list(ODD_DIGITS.values()), ids=list(ODD_DIGITS))
def test_ports_take_ascii_digits_only(kind, digits):
    with pytest.raises(IngestError, match=r"port 1\.\.65535 \(digits 0-9\)") as err:
        parse_connection_string(f"{kind}:127.0.0.1:{digits}")
    assert "\n" not in str(err.value) and str(err.value).isascii()     # the odd text shown escaped
    assert parse_connection_string(f"{kind}:127.0.0.1:14550").port == 14550


@pytest.mark.parametrize("digits", list(ODD_DIGITS.values()) + ["\uff15\uff17\uff16\uff10\uff10"], ids=
                         list(ODD_DIGITS) + ["full-width 57600"])
def test_bauds_take_ascii_digits_only(digits):
    with pytest.raises(IngestError, match=r"baud rate after ',' must be a number 50\.\.20000000 \(digits 0-9\)"):
        parse_connection_string(f"/dev/ttyS0,{digits}")


def test_odd_digits_over_http_are_one_line_400s(station_no_viser):
    base = station_no_viser.url
    for text in ("udpin:127.0.0.1:\u00b2", "tcp:127.0.0.1:\u00b2", "udpout:127.0.0.1:\u00b2",
                 "tcpin:127.0.0.1:\u00b2", "/dev/ttyS0,\u00b2", "udpin:127.0.0.1:" + ODD_DIGITS["Arabic-Indic 14550"],
                 "udpin:127.0.0.1:" + ODD_DIGITS["full-width 14550"]):
        r = httpx.post(base + "/api/source", json={"connect": text})
        assert r.status_code == 400, (text, r.status_code, r.text[:200])
        assert "digits 0-9" in r.json()["detail"] and "\n" not in r.json()["detail"]
    assert httpx.get(base + "/api/state").json()["source"]["kind"] != "live"   # nothing was opened


@pytest.mark.parametrize("path,method,raw", [
    ("/api/vehicles/select", "POST", '{"sysid": 1e400}'),
    ("/api/vehicles/select", "POST", '{"sysid": NaN}'),
    ("/api/vehicles/select", "POST", '{"sysid": -Infinity}'),
    ("/api/calibration/compasses/0", "PUT", '{"included": NaN}'),
    ("/api/calibration/fitness", "PUT", '{"level": Infinity}'),
    ("/api/calibration/fitness", "PUT", '{"level": [1e400, {"x": NaN}]}'),
])
def test_a_422_never_fails_on_the_value_it_reports(station_no_viser, path, method, raw):
    r = httpx.request(method, station_no_viser.url + path, content=raw,
                      headers={"Content-Type": "application/json"})
    assert r.status_code == 422, (r.status_code, r.text[:200])
    detail = r.json()["detail"]                      # strict JSON: no NaN/Infinity tokens
    assert "NaN" not in r.text and "Infinity" not in r.text
    assert detail and all(e["msg"] for e in detail)


# ------------------------------------------------------------------------------ symlinks in recordings/

@pytest.mark.skipif(not hasattr(os, "symlink") or os.name == "nt", reason="needs POSIX symlinks")
def test_symlinks_in_recordings_are_not_listed_read_or_replayed(station_no_viser, recordings_dir, tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    secret = outside / "secret.csv"
    secret.write_text("root:x:0:0:root:/root:/bin/bash\n")
    shutil.copy(DEMO, outside / "away.tlog")
    (recordings_dir / "passwd.csv").symlink_to(secret)
    (recordings_dir / "away.tlog").symlink_to(outside / "away.tlog")
    (recordings_dir / "inside.tlog").symlink_to(recordings_dir / "real.tlog")
    shutil.copy(DEMO, recordings_dir / "real.tlog")
    base = station_no_viser.url
    info = httpx.get(base + "/api/recordings/info")
    assert info.status_code == 200
    assert [e["name"] for e in info.json()] == ["real.tlog"], info.json()
    assert "root:x" not in info.text
    assert httpx.get(base + "/api/recordings").json() == ["real.tlog"]
    for name in ("passwd.csv", "away.tlog", "inside.tlog"):
        r = httpx.post(base + "/api/source", json={"recording": name})
        assert r.status_code == 404, (name, r.status_code, r.text[:200])
        assert "root:x" not in r.text


# ------------------------------------------------------------------------------ parallel uploads

def test_parallel_uploads_of_one_name_keep_every_body(station_no_viser, recordings_dir):
    """40 uploads of race.tlog at once: 40 files, each with the bytes of its own upload."""
    demo = DEMO.read_bytes()
    records = _tlog_record_ends(demo)
    bodies = [demo[:records[200 + 7 * i]] for i in range(40)]        # 40 different valid logs
    assert len(set(bodies)) == 40
    results: list = [None] * 40
    start = threading.Barrier(40)

    def upload(i: int) -> None:
        start.wait()
        results[i] = httpx.post(station_no_viser.url + "/api/recordings/upload", params={"filename": "race.tlog"},
                                content=bodies[i], headers={"Content-Type": "application/octet-stream"},
                                timeout=60)

    threads = [threading.Thread(target=upload, args=(i,)) for i in range(40)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(90)
    assert all(r is not None and r.status_code == 201 for r in results), \
        [(r.status_code, r.text[:100]) if r is not None else None for r in results]
    names = [r.json()["name"] for r in results]
    assert len(set(names)) == 40, sorted(names)
    for name, body in zip(names, bodies):
        assert (recordings_dir / name).read_bytes() == body, name
    assert not [p.name for p in recordings_dir.iterdir() if p.name.startswith(".")]   # no part file left


def _tlog_record_ends(data: bytes) -> list[int]:
    out, i = [], 0
    while i + 10 <= len(data):
        assert data[i + 8] == 0xFD
        i += 8 + 12 + data[i + 9] + (13 if data[i + 10] & 1 else 0)
        out.append(i)
    return out


def test_new_names_are_created_never_replaced(tmp_path):
    from groundstation.station.hub.recordings import RecordingsFolder
    folder = RecordingsFolder(tmp_path, max_upload_bytes=1000)
    part = tmp_path / ".x.part"
    part.write_bytes(b"mine")
    first = folder.new_path("upload", ".tlog", "a")
    first.write_bytes(b"someone else's")
    second = folder.new_path("upload", ".tlog", "a", content=part)
    assert second != first and first.read_bytes() == b"someone else's" and second.read_bytes() == b"mine"
    assert folder.new_session_path().stat().st_size == 0                    # created, empty


# ------------------------------------------------------------------------------ the first visit's redirect

@pytest.mark.parametrize("path", ["/%5Clocalhost:28999/index.html", "/%5C%5Cevil.example/x", "//evil.example/x",
                                  "/%2F%2Fevil.example/x", "/%5C/evil.example", "/%09/evil.example"])
def test_the_token_redirect_stays_on_this_station(remote_station_input, path):
    base = remote_station_input.url
    token = remote_station_input.settings.access_token
    r = httpx.get(f"{base}{path}?token={token}&a=1")
    assert r.status_code == 303, (path, r.status_code)
    location = r.headers["location"]
    assert location.startswith("/") and location[1:2] not in ("/", "\\"), location
    assert httpx.URL(base).join(location).host == "127.0.0.1", location
    assert "token" not in location and location.endswith("?a=1")


@pytest.fixture
def remote_station_input(recordings_dir):
    from groundstation.station.app import Station
    st = Station(host="127.0.0.1", allow_remote=True, port=0, viser_port=None,
                 recordings_dir=recordings_dir).start()
    yield st
    st.close()


# ------------------------------------------------------------------------------ the terminal multiplexer

@pytest.mark.skipif(not Path("/dev/pts/ptmx").exists(), reason="no /dev/pts/ptmx here")
@pytest.mark.parametrize("device", ["/dev/ptmx", "/dev/pts/ptmx"])
def test_the_pseudo_terminal_multiplexer_is_not_a_serial_port(device):
    with pytest.raises(IngestError, match="is a console or this program's own terminal, not a serial port"):
        parse_connection_string(device + ",57600")


def test_new_names_without_hard_links_still_never_replace(tmp_path, monkeypatch):
    """On a file system without hard links (os.link fails) the upload still gets a name of its own."""
    from groundstation.station.hub.recordings import RecordingsFolder

    def no_links(*_):
        raise PermissionError(1, "Operation not permitted")

    folder = RecordingsFolder(tmp_path, max_upload_bytes=1000)
    taken = folder.new_path("upload", ".tlog", "a")
    taken.write_bytes(b"someone else's")
    monkeypatch.setattr(os, "link", no_links)
    part = tmp_path / ".y.part"
    part.write_bytes(b"mine")
    path = folder.new_path("upload", ".tlog", "a", content=part)
    assert path != taken and path.read_bytes() == b"mine" and taken.read_bytes() == b"someone else's"
    assert not part.exists()
