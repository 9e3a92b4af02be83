"""Connecting to a catalog and bringing its schema to the head revision (Alembic, no alembic.ini).

A catalog is named by a SQLAlchemy URL: ``sqlite:///recordings/catalog.sqlite`` (the
embedded default: one file, nothing to start) or ``postgresql://user@host/db`` (a plant's
server, through psycopg 3: ``postgresql+psycopg://`` is what is used whichever is
written). A plain path (no ``://``) is a SQLite file.

SQLite is opened in WAL mode with a 60 s busy timeout, and every transaction begins with
``BEGIN IMMEDIATE`` (the SQLAlchemy documentation's pysqlite recipe, "Serializable
isolation / Savepoints / Transactional DDL"): a writer takes the write lock when it
starts instead of failing half way when another process holds it, so two ``crossfield
catalog add`` processes at once queue instead of losing a session.
"""

from __future__ import annotations

from functools import lru_cache
from importlib import resources
from pathlib import Path

import sqlalchemy as sa
from sqlalchemy import event
from sqlalchemy.engine import Engine, make_url

from crossfield.errors import ConfigError

#: The file name of the embedded catalog in a sessions folder (``recordings/catalog.sqlite``).
DEFAULT_FILE = "catalog.sqlite"
#: SQLite: how long a writer waits for another's lock (ms).
BUSY_TIMEOUT_MS = 60_000


def normalise_url(url: str | Path) -> str:
    """``url`` as SQLAlchemy takes it: a path becomes ``sqlite:///PATH``; ``postgresql://``
    (and ``postgres://``) becomes ``postgresql+psycopg://`` (psycopg 3). ConfigError if it
    is neither."""
    text = str(url).strip()
    if not text:
        raise ConfigError("--catalog: an empty catalog URL")
    if "://" not in text:
        return f"sqlite:///{Path(text).expanduser()}"
    try:
        parsed = make_url(text)
    except sa.exc.ArgumentError as exc:
        raise ConfigError(f"--catalog {redacted(text)}: not a database URL ({exc})") from None
    if parsed.drivername in ("postgresql", "postgres"):
        parsed = parsed.set(drivername="postgresql+psycopg")
    if parsed.get_backend_name() not in ("sqlite", "postgresql"):
        raise ConfigError(
            f"--catalog {redacted(text)}: a catalog is SQLite (sqlite:///FILE) or PostgreSQL "
            f"(postgresql://...), not {parsed.get_backend_name()!r}"
        )
    return parsed.render_as_string(hide_password=False)


def redacted(url: str | Path) -> str:
    """``url`` with any password hidden (for messages and logs)."""
    text = str(url)
    try:
        return make_url(text).render_as_string(hide_password=True) if "://" in text else text
    except sa.exc.ArgumentError:
        return "<unparseable URL>"


def engine(url: str | Path) -> Engine:
    """An engine on the catalog ``url`` (not connected yet; SQLite: its folder is made)."""
    full = normalise_url(url)
    parsed = make_url(full)
    if parsed.get_backend_name() != "sqlite":
        return sa.create_engine(full)
    if parsed.database and parsed.database != ":memory:":
        Path(parsed.database).parent.mkdir(parents=True, exist_ok=True)
    eng = sa.create_engine(full, connect_args={"timeout": BUSY_TIMEOUT_MS / 1000})

    @event.listens_for(eng, "connect")
    def _connect(dbapi_connection, _record) -> None:  # pragma: no cover - exercised by every test
        dbapi_connection.isolation_level = None  # pysqlite: no implicit BEGIN; we emit our own
        cursor = dbapi_connection.cursor()
        cursor.execute("PRAGMA journal_mode=WAL")
        cursor.execute(f"PRAGMA busy_timeout={BUSY_TIMEOUT_MS}")
        cursor.execute("PRAGMA foreign_keys=ON")
        cursor.close()

    @event.listens_for(eng, "begin")
    def _begin(conn) -> None:  # pragma: no cover
        conn.exec_driver_sql("BEGIN IMMEDIATE")

    return eng


def _alembic_config(connection: sa.Connection):
    from alembic.config import Config

    cfg = Config()
    cfg.set_main_option("script_location", str(resources.files("crossfield.catalog") / "migrations"))
    cfg.attributes["connection"] = connection
    return cfg


def upgrade(eng: Engine, revision: str = "head") -> None:
    """Bring the catalog's schema to ``revision`` (Alembic ``upgrade``; from an empty
    database too). Safe to run on an up-to-date catalog (nothing happens)."""
    from alembic import command

    try:
        with eng.begin() as connection:
            command.upgrade(_alembic_config(connection), revision)
    except sa.exc.OperationalError as exc:
        raise ConfigError(f"catalog {redacted(eng.url)}: cannot be opened: {exc.orig}") from None


def current_revision(eng: Engine) -> str | None:
    """The catalog's schema revision (None: an empty database)."""
    from alembic.runtime.migration import MigrationContext

    with eng.connect() as connection:
        return MigrationContext.configure(connection).get_current_revision()


@lru_cache(maxsize=1)
def head_revision() -> str:
    """The newest revision this crossfield ships."""
    from alembic.script import ScriptDirectory

    cfg = _alembic_config(None)  # type: ignore[arg-type]
    return ScriptDirectory.from_config(cfg).get_current_head()
