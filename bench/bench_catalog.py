"""The session catalog: ingest rate into SQLite and PostgreSQL, and a trend query's time.

Run on demand (never part of the tests)::

    .venv/bin/python bench/bench_catalog.py [--sessions 1000] [--rows 100000] [--repeat 3] [--no-postgres]

PostgreSQL is a throw-away server started here (tests/catalog/pg_server.py: the Debian
``postgresql`` package's initdb + pg_ctl on a loopback port, fsync off as in the tests).

1. Ingest: ``--sessions`` synthetic session folders (crossfield.catalog.synthetic: a real
   tiny MCAP with its seal, report.json with 10 characteristics) added with
   ``Catalog.add`` in one process, one transaction per session, into a new SQLite file and
   a new PostgreSQL database; sessions per second. Baseline in the same run: reading the
   same folders into their rows without a database (``read_session``: JSON parse, the
   recording's SHA-256 and metadata), so the ratio is what the database adds.
2. Trend query: ``--rows`` characteristic rows (``--rows``/10 sessions of 10
   characteristics, bulk-inserted with Core), then the median of ``--repeat`` runs of
   ``Catalog.characteristics(name="L03")`` (a tenth of the rows, as a DataFrame) and of
   the SPC of that characteristic (``trends(..., names=["L03"])``: query + limits + the
   Nelson tests + Cpk). Baseline in the same run: the whole table read into a DataFrame
   (``Catalog.characteristics()``) and filtered in pandas.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "catalog"))

import numpy as np  # noqa: E402

import crossfield.catalog  # noqa: E402
from crossfield.catalog import schema as S  # noqa: E402
from crossfield.catalog.ingest import read_session, session_folders  # noqa: E402
from crossfield.catalog.synthetic import write_session  # noqa: E402
from crossfield.catalog.trends import Baseline, trends  # noqa: E402

T0 = 1_796_298_450_000_000_000
NAMES = [f"L{k:02d}" for k in range(1, 11)]


def timed(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def make_folders(parent: Path, n: int) -> list[Path]:
    rng = np.random.default_rng(0)
    for i in range(n):
        write_session(parent, f"s{i:05d}", T0 + i * 600 * 10**9,
                      {name: 300.0 + 0.002 * rng.standard_normal() for name in NAMES},
                      nominal_mm={name: 300.0 for name in NAMES})
    return list(session_folders([parent]))


def ingest(url: str, parent: Path, n: int) -> float:
    with crossfield.catalog.open(url) as cat:
        t = time.perf_counter()
        results = cat.add(parent)
        dt = time.perf_counter() - t
        assert [r.status for r in results] == ["added"] * n, {r.status for r in results}
        assert cat.count()["characteristics"] == 10 * n
    return n / dt


def fill_rows(url: str, rows: int) -> None:
    """rows / 10 sessions of 10 characteristics, bulk-inserted (Core executemany)."""
    n = rows // len(NAMES)
    rng = np.random.default_rng(1)
    now = _dt.datetime(2026, 12, 3)
    with crossfield.catalog.open(url) as cat, cat.engine.begin() as conn:
        base = dict(station="bench", operator="", part="", serial="", job_order="", job_json="{}",
                    plan_name="bench", calibration_source="", crossfield_version="0.1.0", plugins_json="{}",
                    packages_json="{}", verdict="pass", frames_processed=3, frames_failed=0, folder="/bench",
                    ingested_utc=now)
        step = 5000
        for a in range(0, n, step):
            ids = range(a, min(n, a + step))
            conn.execute(S.sessions.insert(), [
                {**base, "id": f"q{i:07d}", "start_time_ns": T0 + i * 60 * 10**9,
                 "start_utc": now + _dt.timedelta(minutes=i)} for i in ids])
            values = 300.0 + 0.002 * rng.standard_normal((len(ids), len(NAMES)))
            conn.execute(S.characteristics.insert(), [
                {"session_id": f"q{i:07d}", "no": k + 1, "name": name, "kind": "point_line",
                 "measured_mm": float(values[j, k]), "nominal_mm": 300.0, "upper_tol_mm": 0.01,
                 "lower_tol_mm": 0.01, "expanded_uncertainty_mm": 0.002, "coverage_factor": 2.0,
                 "decision": "conforms", "decision_rule": "simple", "budget_json": "[]"}
                for j, i in enumerate(ids) for k, name in enumerate(NAMES)])


def query(url: str, repeat: int) -> dict[str, float]:
    with crossfield.catalog.open(url) as cat:
        n = len(cat.characteristics(name="L03"))
        full = timed(lambda: cat.characteristics().query("name == 'L03'"), repeat)
        one = timed(lambda: cat.characteristics(name="L03"), repeat)
        spc = timed(lambda: trends(cat, names=["L03"], baseline=Baseline(n=100)), repeat)
    return {"rows_out": n, "full_read_s": full, "query_s": one, "spc_s": spc}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sessions", type=int, default=1000)
    ap.add_argument("--rows", type=int, default=100_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-postgres", action="store_true")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench-catalog-"))
    try:
        t = time.perf_counter()
        folders = make_folders(work / "sessions", args.sessions)
        print(f"{args.sessions} synthetic session folders written in {time.perf_counter() - t:.1f} s")
        t = time.perf_counter()
        for f in folders:
            read_session(f)
        read_rate = args.sessions / (time.perf_counter() - t)
        print(f"baseline: read_session alone          {read_rate:8.1f} sessions/s")
        stores = {"SQLite": lambda: f"sqlite:///{work / 'ingest.sqlite'}"}
        server = None
        if not args.no_postgres:
            from pg_server import new_database, running_server

            server = running_server()
            pg = server.__enter__()
            stores["PostgreSQL"] = lambda: new_database(pg)
        try:
            for label, make_url in stores.items():
                rate = ingest(make_url(), work / "sessions", args.sessions)
                print(f"ingest into {label:<10}                {rate:8.1f} sessions/s  "
                      f"({rate / read_rate:.2f} x the read alone)")
            for label, make_url in stores.items():
                url = make_url() if label == "PostgreSQL" else f"sqlite:///{work / 'rows.sqlite'}"
                t = time.perf_counter()
                fill_rows(url, args.rows)
                fill = time.perf_counter() - t
                q = query(url, args.repeat)
                print(f"{label}: {args.rows} characteristic rows (filled in {fill:.1f} s); L03 = {q['rows_out']} rows:")
                print(f"  whole table read + pandas filter   {1000 * q['full_read_s']:8.1f} ms  (baseline)")
                print(f"  characteristics(name='L03')        {1000 * q['query_s']:8.1f} ms  "
                      f"({q['query_s'] / q['full_read_s']:.2f} x)")
                print(f"  trends(names=['L03']) (query+SPC)  {1000 * q['spc_s']:8.1f} ms  "
                      f"({q['spc_s'] / q['full_read_s']:.2f} x)")
        finally:
            if server is not None:
                server.__exit__(None, None, None)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
