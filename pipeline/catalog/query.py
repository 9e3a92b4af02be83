"""Reading the catalog: :func:`open` and :class:`Catalog` (sessions, characteristics, station
health as pandas DataFrames; the seal of one session).

Filters (every one optional): ``station`` (exact), ``since`` / ``until`` (a date or a
datetime, ISO 8601 text or ``datetime``; a time without a zone is UTC; ``until`` excludes
the instant), ``name`` (a characteristic's name, exact). Rows come in session start
order (then the plan's row number). Times are naive UTC ``datetime64``.
"""

from __future__ import annotations

import datetime as _dt
import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import sqlalchemy as sa

from crossfield.catalog import db
from crossfield.catalog import schema as S
from crossfield.catalog.ingest import IngestResult, add_folder, session_folders
from crossfield.errors import ConfigError

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["Catalog", "open", "parse_time"]


def parse_time(value: str | _dt.date | _dt.datetime | None, what: str = "--since") -> _dt.datetime | None:
    """``value`` as a naive UTC datetime (None stays None); ConfigError naming ``what``."""
    if value is None or value == "":
        return None
    if isinstance(value, _dt.datetime):
        t = value
    elif isinstance(value, _dt.date):
        t = _dt.datetime(value.year, value.month, value.day)
    else:
        text = str(value).strip()
        try:
            t = _dt.datetime.fromisoformat(text.replace("Z", "+00:00"))
        except ValueError:
            raise ConfigError(f"{what} {text!r}: not a date (YYYY-MM-DD) or ISO 8601 time") from None
    if t.tzinfo is not None:
        t = t.astimezone(_dt.UTC).replace(tzinfo=None)
    return t


class Catalog:
    """An open catalog (:func:`open`). Use as a context manager or call :meth:`close`."""

    def __init__(self, engine: sa.Engine):
        self.engine = engine

    @property
    def url(self) -> str:
        """The catalog's URL, password hidden."""
        return db.redacted(self.engine.url)

    def close(self) -> None:
        self.engine.dispose()

    def __enter__(self) -> "Catalog":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---------------------------------------------------------------- writing

    def add(self, *paths: str | Path, station: str | None = None) -> list[IngestResult]:
        """Add every session folder under ``paths`` (in this process, one transaction each):
        one result per folder (added / present / error)."""
        return [add_folder(self.engine, f, station=station) for f in session_folders(paths)]

    # ---------------------------------------------------------------- reading

    def _where(self, q, station: str | None, since: Any, until: Any):
        t0, t1 = parse_time(since, "--since"), parse_time(until, "--until")
        if station:
            q = q.where(S.sessions.c.station == station)
        if t0 is not None:
            q = q.where(S.sessions.c.start_utc >= t0)
        if t1 is not None:
            q = q.where(S.sessions.c.start_utc < t1)
        return q

    def _frame(self, q, dates: Sequence[str]) -> "pd.DataFrame":
        import pandas as pd

        with self.engine.connect() as conn:
            df = pd.read_sql_query(q, conn)
        for col in dates:
            if col in df:
                df[col] = pd.to_datetime(df[col])
        return df

    def sessions(
        self, *, station: str | None = None, since: Any = None, until: Any = None, name: str | None = None
    ) -> "pd.DataFrame":
        """One row per session (columns: the ``sessions`` table without its JSON documents,
        plus the seal's chain_head, file_sha256 and public_key_fingerprint). ``name``: only
        sessions that measured that characteristic."""
        s = S.sessions.c
        cols = [c for c in S.sessions.c if not c.name.endswith("_json")]
        q = sa.select(*cols, S.seals.c.chain_head, S.seals.c.file_sha256, S.seals.c.public_key_fingerprint)
        q = q.select_from(S.sessions.join(S.seals, S.seals.c.session_id == s.id, isouter=True))
        if name:
            q = q.where(
                sa.exists().where(
                    (S.characteristics.c.session_id == s.id) & (S.characteristics.c.name == name)
                )
            )
        q = self._where(q, station, since, until).order_by(s.start_time_ns, s.id)
        return self._frame(q, ("start_utc", "end_utc", "ingested_utc"))

    def characteristics(
        self, *, name: str | None = None, station: str | None = None, since: Any = None, until: Any = None,
        budget: bool = False,
    ) -> "pd.DataFrame":
        """One row per characteristic of each session: session_id, station, start_utc,
        start_time_ns, no, name, kind, measured_mm, nominal_mm, upper_tol_mm, lower_tol_mm,
        expanded_uncertainty_mm (U), coverage_factor (k), decision, decision_rule, and with
        ``budget`` the budget rows (a list per row, decoded from JSON)."""
        c, s = S.characteristics.c, S.sessions.c
        cols = [col for col in S.characteristics.c if budget or col.name != "budget_json"]
        q = sa.select(s.station, s.start_utc, s.start_time_ns, *cols)
        q = q.select_from(S.characteristics.join(S.sessions, s.id == c.session_id))
        if name:
            q = q.where(c.name == name)
        q = self._where(q, station, since, until).order_by(s.start_time_ns, c.session_id, c.no)
        df = self._frame(q, ("start_utc",))
        if budget and "budget_json" in df:
            df["budget"] = [json.loads(t) for t in df.pop("budget_json")]
        return df

    def health(
        self, *, station: str | None = None, since: Any = None, until: Any = None, figure: str | None = None
    ) -> "pd.DataFrame":
        """Station-health figures, long form: session_id, station, start_utc, figure, value,
        unit (:data:`crossfield.catalog.ingest.HEALTH`)."""
        h, s = S.station_health.c, S.sessions.c
        q = sa.select(h.session_id, s.station, s.start_utc, s.start_time_ns, h.figure, h.value, h.unit)
        q = q.select_from(S.station_health.join(S.sessions, s.id == h.session_id))
        if figure:
            q = q.where(h.figure == figure)
        q = self._where(q, station, since, until).order_by(s.start_time_ns, h.session_id, h.figure)
        return self._frame(q, ("start_utc",))

    def seal(self, session_id: str) -> dict[str, Any] | None:
        """The ``seals`` row of ``session_id`` with the session's folder (None: not catalogued)."""
        q = (
            sa.select(*S.seals.c, S.sessions.c.folder)
            .select_from(S.seals.join(S.sessions, S.sessions.c.id == S.seals.c.session_id))
            .where(S.seals.c.session_id == session_id)
        )
        with self.engine.connect() as conn:
            row = conn.execute(q).mappings().first()
        if row is None:
            return None
        out = dict(row)
        out["signature"] = json.loads(out.pop("signature_json")) if out.get("signature_json") else None
        return out

    def seals(self) -> list[dict[str, Any]]:
        """Every session's seal row and folder (for :func:`crossfield.catalog.anchor.verify_all`)."""
        q = sa.select(S.seals.c.session_id, S.seals.c.recording, S.seals.c.chain_head, S.seals.c.file_sha256,
                      S.seals.c.signature_json, S.sessions.c.folder).select_from(
            S.seals.join(S.sessions, S.sessions.c.id == S.seals.c.session_id)
        ).order_by(S.sessions.c.start_time_ns)
        with self.engine.connect() as conn:
            return [dict(r) for r in conn.execute(q).mappings()]

    def count(self) -> dict[str, int]:
        """Rows per table."""
        with self.engine.connect() as conn:
            return {
                t.name: conn.execute(sa.select(sa.func.count()).select_from(t)).scalar_one() for t in S.TABLES
            }


def open(url: str | Path, *, migrate: bool = True) -> Catalog:  # noqa: A001 - crossfield.catalog.open(url)
    """Open the catalog at ``url`` (a SQLAlchemy URL or a SQLite file path), creating or
    upgrading its schema to this crossfield's head revision unless ``migrate`` is False."""
    eng = db.engine(url)
    if migrate:
        db.upgrade(eng)
    return Catalog(eng)


