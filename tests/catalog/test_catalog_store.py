"""The catalog's storage on SQLite and on a real PostgreSQL server (conftest.py): schema
migrations, ingest, idempotence, a refused conflicting recording, two writers at once, a
killed ingest, ``crossfield run``'s ingest that never loses the recording."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import sqlalchemy as sa

import crossfield.catalog
from crossfield.catalog import db, schema
from crossfield.catalog.commands import ingest_after_run, main as catalog_main
from crossfield.catalog.ingest import key_fingerprint
from crossfield.catalog.synthetic import write_session

T0 = 1_796_298_450_000_000_000  # 2026-12-03 ~11:47 UTC, ns
HOUR = 3600 * 10**9


def sessions(parent: Path, n: int, *, prefix: str = "s", first: int = 0, station: str = "station-a") -> list[Path]:
    return [
        write_session(parent, f"{prefix}{i:04d}", T0 + i * HOUR, {"L01": 300.0 + 0.001 * i, "L02": 200.01},
                      hostname=station)
        for i in range(first, first + n)
    ]


def test_migration_from_empty_gives_the_schema_module(catalog_url):
    from alembic.autogenerate import compare_metadata
    from alembic.migration import MigrationContext

    eng = db.engine(catalog_url)
    assert db.current_revision(eng) is None
    db.upgrade(eng)
    assert db.current_revision(eng) == db.head_revision() == "0002"
    with eng.connect() as conn:
        diff = compare_metadata(MigrationContext.configure(conn), schema.metadata)
    assert diff == [], diff
    db.upgrade(eng)  # again: nothing to do
    assert db.current_revision(eng) == "0002"
    eng.dispose()


def test_migration_from_the_previous_revision_keeps_rows_and_fills_the_fingerprint(catalog_url, tmp_path):
    eng = db.engine(catalog_url)
    db.upgrade(eng, "0001")
    assert db.current_revision(eng) == "0001"
    record = crossfield.catalog.ingest.read_session(sessions(tmp_path, 1)[0])
    key = "ab" * 32
    with eng.begin() as conn:  # a catalog written by revision 0001: no health table, no fingerprint column
        assert not sa.inspect(conn).has_table("station_health")
        conn.execute(schema.sessions.insert(), [dict(record.session)])
        conn.execute(schema.characteristics.insert(), [dict(r) for r in record.characteristics])
        seal = {k: v for k, v in record.seal.items() if k != "public_key_fingerprint"}
        conn.execute(sa.table("seals", *[sa.column(k) for k in seal]).insert(), [{**seal, "public_key": key}])
    db.upgrade(eng)
    assert db.current_revision(eng) == "0002"
    with crossfield.catalog.Catalog(eng) as cat:
        row = cat.seal(record.id)
        assert row["public_key_fingerprint"] == key_fingerprint(key)
        assert cat.count() == {"sessions": 1, "characteristics": 2, "seals": 1, "station_health": 0}
        assert list(cat.characteristics()["measured_mm"]) == [300.0, 200.01]


def test_ingest_and_queries(catalog_url, tmp_path):
    a = sessions(tmp_path / "a", 3, station="station-a")
    b = sessions(tmp_path / "b", 2, prefix="b", first=3, station="station-b")
    with crossfield.catalog.open(catalog_url) as cat:
        results = cat.add(tmp_path)
        assert [r.status for r in results] == ["added"] * 5
        assert cat.count() == {"sessions": 5, "characteristics": 10, "seals": 5, "station_health": 40}
        df = cat.characteristics(name="L01")
        assert list(df["session_id"]) == ["s0000", "s0001", "s0002", "b0003", "b0004"]
        assert list(df["measured_mm"]) == pytest.approx([300.0, 300.001, 300.002, 300.003, 300.004])
        report = json.loads((a[1] / "report.json").read_text())
        row = df.iloc[1]
        c = report["characteristics"][0]
        assert (row["expanded_uncertainty_mm"], row["coverage_factor"], row["decision"], row["nominal_mm"]) == (
            c["expanded_uncertainty_mm"], c["coverage_factor"], c["decision"], c["nominal_mm"])
        assert list(cat.characteristics(station="station-b")["session_id"].unique()) == ["b0003", "b0004"]
        since = cat.characteristics(name="L02", since="2026-12-03T13:00:00Z")
        assert list(since["session_id"]) == ["s0002", "b0003", "b0004"]  # 11:47 + 2 h onwards
        s = cat.sessions(station="station-a")
        assert list(s["id"]) == ["s0000", "s0001", "s0002"] and set(s["verdict"]) == {"pass"}
        sidecar = json.loads((b[0] / "session.mcap.seal.json").read_text())
        assert cat.seal("b0003")["chain_head"] == sidecar["chain_head"]
        assert cat.seal("b0003")["file_sha256"] == sidecar["file_sha256"]
        health = cat.health(figure="registration_rms_mm")
        assert list(health["value"]) == pytest.approx([0.018] * 5)
        with pytest.raises(crossfield.errors.ConfigError, match="--since 'yesterday'"):
            cat.characteristics(since="yesterday")


def test_the_same_session_twice_is_one_row_and_another_file_under_its_id_is_refused(catalog_url, tmp_path, capsys):
    (first,) = sessions(tmp_path / "one", 1)
    other = write_session(tmp_path / "two", "s0000", T0, {"L01": 300.05, "L02": 200.01}, note="another file")
    assert catalog_main(["add", str(first), "--catalog", catalog_url]) == 0
    assert catalog_main(["add", str(first), "--catalog", catalog_url]) == 0
    out = capsys.readouterr().out
    assert "added   s0000" in out and "present s0000" in out
    assert catalog_main(["add", str(other), "--catalog", catalog_url]) == 1
    out = capsys.readouterr().out
    assert "ERROR" in out and str(other / "session.mcap") in out and str(first / "session.mcap") in out
    assert "already catalogued with another recording" in out
    with crossfield.catalog.open(catalog_url) as cat:
        assert cat.count()["sessions"] == 1 and cat.count()["characteristics"] == 2
        assert cat.characteristics(name="L01")["measured_mm"].tolist() == [300.0]  # the first one kept
        assert cat.seal("s0000")["folder"] == str(first.resolve())


def test_a_recording_changed_after_its_seal_is_refused(catalog_url, tmp_path):
    (folder,) = sessions(tmp_path, 1)
    with open(folder / "session.mcap", "r+b") as f:
        f.seek(40)
        byte = f.read(1)
        f.seek(40)
        f.write(bytes([byte[0] ^ 1]))
    with crossfield.catalog.open(catalog_url) as cat:
        (r,) = cat.add(folder)
        assert r.status == "error" and "differs from its seal" in r.error and str(folder / "session.mcap") in r.error
        assert cat.count()["sessions"] == 0


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "crossfield.catalog", *args]


WRITER = """
import pathlib, sys, time
import crossfield.catalog, crossfield.catalog.ingest
folders = sorted(p for p in pathlib.Path(sys.argv[2]).iterdir() if p.is_dir())
go, ready, first, other_first = (pathlib.Path(a) for a in sys.argv[3:7])
with crossfield.catalog.open(sys.argv[1], migrate=False) as cat:
    ready.touch()  # imported and connected
    while not go.exists():
        time.sleep(0.005)
    for i, folder in enumerate(folders):
        assert all(r.status == "added" for r in cat.add(folder))
        if i == 0:  # the rest only once the other writer has written too: the writes interleave
            first.touch()
            while not other_first.exists():
                time.sleep(0.005)
"""


def test_two_writer_processes_at_once_lose_nothing(catalog_url, tmp_path):
    sessions(tmp_path / "a", 40, prefix="a")
    sessions(tmp_path / "b", 40, prefix="b")
    crossfield.catalog.open(catalog_url).close()  # the schema first (as `crossfield catalog upgrade`)
    go = tmp_path / "go"
    ready = [tmp_path / f"ready-{d}" for d in "ab"]
    first = [tmp_path / f"first-{d}" for d in "ab"]
    procs = [subprocess.Popen([sys.executable, "-c", WRITER, catalog_url, str(tmp_path / d), str(go), str(r), str(f),
                               str(other)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for d, r, f, other in zip("ab", ready, first, first[::-1])]
    deadline = time.monotonic() + 60
    while not all(r.exists() for r in ready):  # both started and imported: then they write at once
        assert all(p.poll() is None for p in procs) and time.monotonic() < deadline
        time.sleep(0.01)
    go.touch()
    outs = [p.communicate(timeout=120) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    with crossfield.catalog.open(catalog_url) as cat:
        assert cat.count() == {"sessions": 80, "characteristics": 160, "seals": 80, "station_health": 640}
        s = cat.sessions()
    a, b = (s[s["id"].str.startswith(p)]["ingested_utc"] for p in "ab")
    assert a.min() < b.max() and b.min() < a.max(), "the two writers did not overlap in time"


KILLED = """
import pathlib, sys, time
import crossfield.catalog.ingest as I
def slow(conn, record):
    conn.execute(I.S.sessions.insert(), [dict(record.session)])
    conn.execute(I.S.characteristics.insert(), [dict(r) for r in record.characteristics])
    pathlib.Path(sys.argv[3]).touch()   # half of the session written, inside its transaction
    time.sleep(120)
I._insert_rows = slow
import crossfield.catalog
crossfield.catalog.open(sys.argv[1]).add(sys.argv[2])
"""


def test_a_killed_ingest_leaves_no_partial_row(catalog_url, tmp_path):
    (folder,) = sessions(tmp_path, 1)
    crossfield.catalog.open(catalog_url).close()
    marker = tmp_path / "half-written"
    proc = subprocess.Popen([sys.executable, "-c", KILLED, catalog_url, str(folder), str(marker)])
    deadline = time.monotonic() + 60
    while not marker.exists():
        assert proc.poll() is None and time.monotonic() < deadline, "the ingest did not reach its half"
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    with crossfield.catalog.open(catalog_url) as cat:
        assert cat.count() == {"sessions": 0, "characteristics": 0, "seals": 0, "station_health": 0}
        (r,) = cat.add(folder)  # and the lock the killed writer held is gone
        assert r.status == "added"
        assert cat.count()["characteristics"] == 2


def test_run_ingest_reports_an_unreachable_catalog_and_keeps_the_recording(tmp_path):
    (folder,) = sessions(tmp_path, 1)
    before = sorted(p.name for p in folder.iterdir())
    said: list[str] = []
    status = ingest_after_run(folder, "postgresql://nobody@127.0.0.1:1/none", say=said.append)
    assert status == "error" and len(said) == 1
    assert "NOT added" in said[0] and f"crossfield catalog add {folder}" in said[0]
    assert sorted(p.name for p in folder.iterdir()) == before
    url = f"sqlite:///{tmp_path / 'c.sqlite'}"  # the catch-up
    assert ingest_after_run(folder, url, say=said.append) == "added"
    assert ingest_after_run(folder, None, say=said.append) is None  # no catalog configured: nothing


def test_add_and_verify_on_dask(tmp_path, capsys):
    from dask.distributed import LocalCluster

    sessions(tmp_path / "archive", 6)
    url = f"sqlite:///{tmp_path / 'c.sqlite'}"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      host="127.0.0.1") as cluster:
        address = cluster.scheduler_address
        assert catalog_main(["add", str(tmp_path / "archive"), "--catalog", url, "--scheduler", address]) == 0
        assert "6 folder(s): 6 added" in capsys.readouterr().out
        victim = tmp_path / "archive" / "s0003" / "session.mcap"
        victim.write_bytes(victim.read_bytes() + b"\0")  # one recording changed after it was catalogued
        assert catalog_main(["verify", "--catalog", url, "--scheduler", address]) == 1
    out = capsys.readouterr().out
    assert "6 session(s): 5 match the catalog, 1 do not" in out and f"FAIL  s0003  {victim}" in out
    with crossfield.catalog.open(url) as cat:
        assert cat.count()["sessions"] == 6


def test_the_catalog_table_of_a_session_config(tmp_path):
    from crossfield.catalog.commands import catalog_url
    from crossfield.config import load_config, with_overrides
    from crossfield.errors import ConfigError

    good = tmp_path / "station.toml"
    good.write_text('[catalog]\nurl = "postgresql://crossfield@db/plant"\nstation = "cell-3"\n')
    config = load_config(good)
    assert dict(config.catalog) == {"url": "postgresql://crossfield@db/plant", "station": "cell-3"}
    assert "catalog" not in config.to_dict()  # not recorded with the session (a URL may hold a password)
    assert with_overrides(config, {}, ["acquire.frames=2"]).catalog == config.catalog
    assert catalog_url(None, good) == "postgresql://crossfield@db/plant"
    assert catalog_url("other.sqlite", good) == "other.sqlite"
    assert catalog_url(None, None) == "recordings/catalog.sqlite"
    bad = tmp_path / "bad.toml"
    bad.write_text('[catalog]\nadress = "x"\n')
    with pytest.raises(ConfigError, match=r"bad.toml: \[catalog\] unknown key 'adress'"):
        load_config(bad)
    with pytest.raises(ConfigError, match="a catalog is SQLite .* or PostgreSQL"):
        crossfield.catalog.open("mysql://u@h/db")


def test_a_password_in_the_url_is_not_shown(postgres_server, capsys):
    url = postgres_server.replace("crossfield@", "crossfield:s3cret@") + "/postgres"
    with crossfield.catalog.open(url, migrate=False) as cat:
        assert "s3cret" not in cat.url and "***" in cat.url
    said: list[str] = []
    ingest_after_run("/nonexistent", "postgresql://u:s3cret@127.0.0.1:1/x", say=said.append)
    assert said and "s3cret" not in said[0]
