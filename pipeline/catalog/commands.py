"""``crossfield catalog ...`` (docs/catalog.md) and the two small calls the other commands
make: :func:`ingest_after_run` (``crossfield run`` with a catalog configured) and
:func:`add_audit_flag` / :func:`audit_command` (``crossfield audit --catalog``).

:func:`add_arguments` and :func:`run` are the ``catalog`` command of the CLI
(:mod:`crossfield.cli.catalog`); ``python -m crossfield.catalog`` runs the same commands
on their own.

Which catalog: ``--catalog URL`` (a SQLAlchemy URL or a SQLite file), else ``[catalog]
url`` of ``--config FILE``, else ``recordings/catalog.sqlite`` (the embedded default in
the default sessions folder).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from crossfield.errors import CrossfieldError

#: The default catalog: the embedded SQLite file in the default sessions folder
#: (``crossfield.catalog.db.DEFAULT_FILE`` in ``[session] output_dir``'s default).
DEFAULT_URL = "recordings/catalog.sqlite"


def catalog_url(given: str | None, config_path: str | Path | None = None, *, default: str | None = DEFAULT_URL) -> str | None:
    """The catalog to use: ``given`` (--catalog), else ``[catalog] url`` of the config file,
    else ``default``."""
    if given:
        return given
    if config_path:
        from crossfield.config import load_config

        url = load_config(config_path).catalog.get("url")
        if url:
            return url
    return default


def _station(given: str | None, config_path: str | Path | None) -> str | None:
    if given:
        return given
    if config_path:
        from crossfield.config import load_config

        return load_config(config_path).catalog.get("station") or None
    return None


# --------------------------------------------------------------------------
# Hooks for `crossfield run` and `crossfield audit`
# --------------------------------------------------------------------------


def ingest_after_run(
    out_dir: str | Path, url: str | None, *, station: str | None = None, say: Callable[[str], None] = print
) -> str | None:
    """Add the session just written to ``out_dir`` to the catalog ``url`` (None: no catalog
    configured, nothing done). Never raises: a catalog that cannot be reached or refuses
    the session is reported by ``say`` and the recording stays as written (``crossfield
    catalog add`` catches up later). Returns the status ("added", "present", "error")."""
    if not url:
        return None
    from crossfield.catalog.db import redacted

    try:
        from crossfield.catalog.query import open as open_catalog

        with open_catalog(url) as cat:
            (result,) = cat.add(out_dir, station=station) or (None,)
    except Exception as exc:  # noqa: BLE001 - the recording must never be lost to the catalog
        say(f"catalog: NOT added to {redacted(url)}: {type(exc).__name__}: {exc} "
            f"(the session is kept; add it later: crossfield catalog add {out_dir})")
        return "error"
    if result is None:
        say(f"catalog: NOT added to {redacted(url)}: no session folder at {out_dir}")
        return "error"
    if result.status == "error":
        say(f"catalog: NOT added to {redacted(url)}: {result.error} (the session is kept; "
            f"add it later: crossfield catalog add {out_dir})")
    else:
        say(f"catalog: session {result.session_id} {result.status} ({redacted(url)})")
    return result.status


def add_run_flag(parser: argparse.ArgumentParser) -> None:
    """``--catalog URL`` on ``crossfield run``."""
    parser.add_argument(
        "--catalog", metavar="URL",
        help="add the session to this catalog when it is written (default: [catalog] url of the config; "
        "docs/catalog.md)",
    )


def ingest_run(args: argparse.Namespace, config: Any, out_dir: str | Path) -> str | None:
    """``crossfield run``'s ingest: the session in ``out_dir`` into ``--catalog`` or the config's
    ``[catalog] url`` (nothing when neither is set), station ``[catalog] station``
    (:func:`ingest_after_run`: never raises). Only a recorded session (``session.mcap``) is added."""
    url = getattr(args, "catalog", None) or (getattr(config, "catalog", None) or {}).get("url")
    if not url:
        return None
    if not (Path(out_dir) / "session.mcap").exists():
        print("catalog: not added (no recording: --no-record); the catalog keeps recorded sessions only")
        return None
    return ingest_after_run(out_dir, url, station=(config.catalog or {}).get("station"))


def add_audit_flag(parser: argparse.ArgumentParser) -> None:
    """``--catalog URL`` on ``crossfield audit``."""
    parser.add_argument(
        "--catalog", metavar="URL",
        help="compare the chain head, SHA-256 and signature with the catalog's row of the session "
        "(docs/catalog.md); a catalog URL or SQLite file",
    )


def audit_command(args: argparse.Namespace, pm: Any) -> Any:
    """The AuditReport of ``crossfield audit RECORDING --catalog URL``."""
    from crossfield.catalog.anchor import audit_with_catalog

    return audit_with_catalog(
        args.recording, pm, args.catalog, reproduce=not args.no_replay,
        expect_head=args.expect_head, public_key=args.public_key,
    )


# --------------------------------------------------------------------------
# crossfield catalog ...
# --------------------------------------------------------------------------


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--catalog", metavar="URL",
                   help=f"sqlite:///FILE, a SQLite file, or postgresql://... (default: [catalog] url of "
                   f"--config, else {DEFAULT_URL})")
    p.add_argument("--config", metavar="FILE", help="a session config whose [catalog] table names the catalog")


def _filters(p: argparse.ArgumentParser, *, name: bool = True) -> None:
    p.add_argument("--station", metavar="S", help="only this station's sessions")
    p.add_argument("--since", metavar="DATE", help="only sessions started at or after DATE (YYYY-MM-DD or ISO time; UTC)")
    p.add_argument("--until", metavar="DATE", help="only sessions started before DATE")
    if name:
        p.add_argument("--name", metavar="NAME", help="only this characteristic (e.g. L03)")


def _output(p: argparse.ArgumentParser) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--json", action="store_true", help="JSON records")
    g.add_argument("--csv", action="store_true", help="CSV with a header row")


def _engine_flags(p: argparse.ArgumentParser) -> None:
    from crossfield.batch.engine import add_engine_flags

    add_engine_flags(p)


def add_arguments(catalog: argparse.ArgumentParser) -> None:
    """The ``catalog`` command's own subcommands on ``catalog``'s parser."""
    sub = catalog.add_subparsers(dest="catalog_command", required=True, metavar="SUBCOMMAND")
    add = sub.add_parser("add", help="add session folders (idempotent; a different recording under a "
                         "catalogued session id is refused)")
    _common(add)
    add.add_argument("paths", nargs="+", metavar="PATH", help="session folders, or folders holding them")
    add.add_argument("--station", metavar="S",
                     help="the station's name (default: [catalog] station, else the recording machine's hostname)")
    add.add_argument("--json", action="store_true", help="one JSON result per folder")
    _engine_flags(add)
    verify = sub.add_parser("verify", help="check every catalogued recording against its catalog row")
    _common(verify)
    verify.add_argument("--json", action="store_true", help="JSON results")
    _engine_flags(verify)
    for name, text in (("sessions", "list the catalogued sessions"),
                       ("characteristics", "list the catalogued characteristics")):
        p = sub.add_parser(name, help=text)
        _common(p)
        _filters(p)
        _output(p)
    for name, text in (("report", "write the trends / SPC page (individuals charts, Nelson tests, Cp/Cpk, "
                                  "station health)"),
                       ("check", "exit 1 when a Nelson test fires on a characteristic (scheduled jobs)")):
        p = sub.add_parser(name, help=text)
        _common(p)
        _filters(p)
        p.add_argument("--baseline-since", metavar="DATE", help="the baseline period's start (limits from it)")
        p.add_argument("--baseline-until", metavar="DATE", help="the baseline period's end (excluded)")
        p.add_argument("--baseline-n", type=int, default=20, metavar="N",
                       help="without a baseline period: the first N sessions (default 20)")
        if name == "report":
            p.add_argument("-o", "--output", metavar="FILE", default="trends.html", help="the page (default trends.html)")
            p.add_argument("--templates", metavar="DIR", help="a folder with a lab's trends.html.j2 / report.css")
        else:
            p.add_argument("--json", action="store_true", help="the firings as JSON")
    up = sub.add_parser("upgrade", help="create the catalog or bring its schema to this crossfield's revision")
    _common(up)


#: ``crossfield --help``'s line and ``crossfield catalog --help``'s paragraph.
HELP = "the session catalog: add, verify, query, trends (docs/catalog.md)"
DESCRIPTION = (
    "The station's memory: sessions, characteristics, seals and station health in SQLite or PostgreSQL, "
    "with SPC trends and the audit's outside anchor."
)


def _open(args: argparse.Namespace):
    from crossfield.catalog.query import open as open_catalog

    return open_catalog(catalog_url(args.catalog, args.config))


def _table(df: Any, args: argparse.Namespace) -> str:
    if getattr(args, "json", False):
        return df.to_json(orient="records", date_format="iso", indent=1) + "\n"
    if getattr(args, "csv", False):
        buf = io.StringIO()
        df.to_csv(buf, index=False, quoting=csv.QUOTE_MINIMAL, lineterminator="\n")
        return buf.getvalue()
    if df.empty:
        return "(no rows)\n"
    import pandas as pd

    brief = [c for c in _BRIEF.get(args.catalog_command, ()) if c in df]
    if brief:  # the terminal: the columns one reads; --json / --csv give every column
        df = df[brief].copy()
        for col in ("chain_head",):
            if col in df:
                df[col] = df[col].str.slice(0, 16)
        for col in ("start_utc",):
            df[col] = df[col].dt.strftime("%Y-%m-%d %H:%M:%S")

    with pd.option_context("display.max_rows", None, "display.max_columns", None, "display.width", 200):
        return df.to_string(index=False) + "\n"


#: The columns printed on the terminal (without --json / --csv).
_BRIEF = {
    "sessions": ("id", "station", "start_utc", "operator", "part", "serial", "plan_name", "verdict",
                 "frames_processed", "chain_head"),
    "characteristics": ("session_id", "station", "start_utc", "no", "name", "measured_mm", "nominal_mm",
                        "expanded_uncertainty_mm", "coverage_factor", "decision"),
}


def _baseline(args: argparse.Namespace):
    from crossfield.catalog.query import parse_time
    from crossfield.catalog.trends import Baseline

    if args.baseline_n < 2:
        raise CrossfieldError(f"--baseline-n {args.baseline_n}: at least 2 sessions")
    return Baseline(parse_time(args.baseline_since, "--baseline-since"),
                    parse_time(args.baseline_until, "--baseline-until"), args.baseline_n)


def _run_add(args: argparse.Namespace) -> int:
    from crossfield.catalog.ingest import add_folder, session_folders

    station = _station(args.station, args.config)
    folders = list(session_folders(args.paths))
    url = catalog_url(args.catalog, args.config)
    with _open(args) as cat:  # creates / upgrades the schema once, before any worker writes
        shown = cat.url
        if args.scheduler is None and args.workers is None:
            results = [add_folder(cat.engine, f, station=station) for f in folders]
        else:
            results = _add_on_dask(url, folders, station, args)
    for r in results:
        if args.json:
            print(json.dumps(r.to_json()))
        elif r.status == "error":
            print(f"ERROR  {r.error}")
        else:
            print(f"{r.status:<7} {r.session_id}  {r.folder}")
    n = {s: sum(r.status == s for r in results) for s in ("added", "present", "error")}
    print(f"{len(results)} folder(s): {n['added']} added, {n['present']} already present, {n['error']} refused "
          f"({shown})", file=sys.stderr if args.json else sys.stdout)
    return 1 if n["error"] else 0


def _add_task(url: str, folder: str, station: str | None) -> dict[str, Any]:
    """One Dask task: add one folder (its own engine, in the worker)."""
    from crossfield.catalog.db import engine
    from crossfield.catalog.ingest import add_folder

    eng = engine(url)
    try:
        return add_folder(eng, folder, station=station).to_json()
    finally:
        eng.dispose()


def _add_on_dask(url: str, folders: list[Path], station: str | None, args: argparse.Namespace) -> list[Any]:
    from crossfield.batch import engine
    from crossfield.catalog.ingest import IngestResult

    out: list[Any] = [None] * len(folders)

    def done(i: int, result: Any, error: str | None) -> None:
        out[i] = IngestResult(**result) if error is None else IngestResult(str(folders[i]), None, "error", error)

    with engine.client(args.scheduler, args.workers, memory_limit=args.memory_limit) as c:
        engine.run_each(c, _add_task, [(url, str(f), station) for f in folders], done, prefix="catalog-add",
                        progress=False)
    return out


def _run_verify(args: argparse.Namespace) -> int:
    from crossfield.catalog.anchor import verify_all

    with _open(args) as cat:
        results = verify_all(cat, scheduler=args.scheduler, workers=args.workers, memory_limit=args.memory_limit)
    bad = [r for r in results if not r["passed"]]
    if args.json:
        print(json.dumps(results, indent=1))
    else:
        for r in results:
            print(f"{'PASS' if r['passed'] else 'FAIL'}  {r['session_id']}  {r['path']}")
            for p in r["problems"]:
                print(f"  - {p}")
        print(f"{len(results)} session(s): {len(results) - len(bad)} match the catalog, {len(bad)} do not")
    return 1 if bad else 0


def _run_query(args: argparse.Namespace) -> int:
    with _open(args) as cat:
        kw = dict(station=args.station, since=args.since, until=args.until, name=args.name)
        df = cat.sessions(**kw) if args.catalog_command == "sessions" else cat.characteristics(**kw)
    sys.stdout.write(_table(df, args))
    return 0


def _run_report(args: argparse.Namespace) -> int:
    from crossfield.catalog.trends import render

    with _open(args) as cat:
        page, found = render(cat, station=args.station, since=args.since, until=args.until,
                             names=[args.name] if args.name else (), baseline=_baseline(args),
                             templates=args.templates)
    out = Path(args.output)
    try:
        out.write_text(page, encoding="utf-8")
    except OSError as exc:
        raise CrossfieldError(f"{out}: cannot write: {exc.strerror}") from None
    fired = sum(len(t.firings) for t in found)
    print(f"{out}: {len(found)} characteristic(s), {fired} Nelson test firing(s)")
    return 0


def _run_check(args: argparse.Namespace) -> int:
    from crossfield.catalog.trends import trends

    with _open(args) as cat:
        found = trends(cat, station=args.station, since=args.since, until=args.until,
                       names=[args.name] if args.name else (), baseline=_baseline(args))
    firings = [f for t in found for f in t.firings]
    if args.json:
        print(json.dumps([f.__dict__ for f in firings], indent=1))
    else:
        for f in firings:
            print(f.text())
        print(f"{len(found)} characteristic(s) checked: "
              + (f"{len(firings)} Nelson test firing(s)" if firings else "in control"))
    return 1 if firings else 0


def _run_upgrade(args: argparse.Namespace) -> int:
    from crossfield.catalog import db

    eng = db.engine(catalog_url(args.catalog, args.config))
    try:
        before = db.current_revision(eng)
        db.upgrade(eng)
        print(f"{db.redacted(eng.url)}: schema revision {before or '(empty)'} -> {db.current_revision(eng)}")
    finally:
        eng.dispose()
    return 0


def run(args: argparse.Namespace) -> int:
    """Run ``crossfield catalog SUBCOMMAND`` (exit status: 0 ok, 1 refused / not matching / fired)."""
    return {
        "add": _run_add, "verify": _run_verify, "sessions": _run_query, "characteristics": _run_query,
        "report": _run_report, "check": _run_check, "upgrade": _run_upgrade,
    }[args.catalog_command](args)


def main(argv: list[str] | None = None) -> int:
    """``python -m crossfield.catalog ...``: the catalog commands without the rest of the CLI."""
    parser = argparse.ArgumentParser(prog="crossfield catalog", description=DESCRIPTION)
    add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return run(args)
    except CrossfieldError as exc:
        print(f"crossfield: error: {exc}", file=sys.stderr)
        return 2
