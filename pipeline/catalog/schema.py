"""The catalog's tables (SQLAlchemy 2 Core), as the head revision of the migrations creates them.

One row of ``sessions`` per recorded session (its id is the session id that
``crossfield run`` gave it, e.g. ``20261203-114730-table3``); its characteristics, its
seal and its station-health figures hang off it by ``session_id`` (deleted with it).

Units: lengths in mm (the report's ``*_mm``), times as naive UTC ``DateTime`` (the
report's ``start_time_utc``; the same on SQLite, where SQLAlchemy stores ISO text, and
PostgreSQL ``timestamp without time zone``) plus the exact ``start_time_ns`` (ns since
the Unix epoch). JSON documents (the job header, the plugins, the package versions, a
characteristic's budget, a signature) are kept as canonical JSON text, the same on both
back ends.

This module describes the head; the database is made and upgraded only by the Alembic
revisions in ``migrations/versions`` (:func:`crossfield.catalog.db.upgrade`). A test
(tests/catalog/test_catalog_store.py) compares the two.
"""

from __future__ import annotations

from sqlalchemy import (
    BigInteger,
    Column,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    MetaData,
    String,
    Table,
    Text,
)

#: Constraint names fixed (Alembic's recommended naming convention), so a migration can
#: name what it changes on SQLite and PostgreSQL alike.
NAMING = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}

metadata = MetaData(naming_convention=NAMING)

sessions = Table(
    "sessions",
    metadata,
    Column("id", String(200), primary_key=True),  # the session id (report.json session.id)
    Column("station", String(200), nullable=False),  # [catalog] station, else the recording machine's hostname
    Column("operator", String(200), nullable=False, default=""),
    Column("part", String(200), nullable=False, default=""),
    Column("serial", String(200), nullable=False, default=""),
    Column("job_order", String(200), nullable=False, default=""),
    Column("job_json", Text, nullable=False, default="{}"),  # the whole job header
    Column("start_utc", DateTime(timezone=False), nullable=False),
    Column("start_time_ns", BigInteger, nullable=False),
    Column("end_utc", DateTime(timezone=False), nullable=True),  # the last frame's time (None: no frame)
    Column("plan_name", String(400), nullable=False, default=""),
    Column("plan_sha256", String(64), nullable=True),
    Column("calibration_source", Text, nullable=False, default=""),
    Column("calibration_sha256", String(64), nullable=True),
    Column("crossfield_version", String(64), nullable=False, default=""),
    Column("plugins_json", Text, nullable=False, default="{}"),  # stage -> {name, package, version}
    Column("packages_json", Text, nullable=False, default="{}"),  # package -> version
    Column("verdict", String(20), nullable=False),  # "pass", "fail" or "incomplete"
    Column("frames_processed", Integer, nullable=False, default=0),
    Column("frames_failed", Integer, nullable=False, default=0),
    Column("folder", Text, nullable=False),  # where it was ingested from (absolute)
    Column("ingested_utc", DateTime(timezone=False), nullable=False),
    Index("ix_sessions_station_start", "station", "start_utc"),
)

characteristics = Table(
    "characteristics",
    metadata,
    Column("session_id", String(200), ForeignKey("sessions.id", ondelete="CASCADE"), primary_key=True),
    Column("no", Integer, primary_key=True),  # the plan's row number
    Column("name", String(200), nullable=False),
    Column("kind", String(64), nullable=False, default=""),
    Column("measured_mm", Float, nullable=True),
    Column("nominal_mm", Float, nullable=True),
    Column("upper_tol_mm", Float, nullable=True),  # the zone is [nominal - lower, nominal + upper]
    Column("lower_tol_mm", Float, nullable=True),
    Column("expanded_uncertainty_mm", Float, nullable=True),  # U
    Column("coverage_factor", Float, nullable=True),  # k
    Column("decision", String(40), nullable=True),  # conforms / does not conform / ... (ISO 14253-1)
    Column("decision_rule", String(40), nullable=True),
    Column("budget_json", Text, nullable=False, default="[]"),  # the uncertainty budget rows
    Index("ix_characteristics_name_session", "name", "session_id"),
)

seals = Table(
    "seals",
    metadata,
    Column("session_id", String(200), ForeignKey("sessions.id", ondelete="CASCADE"), primary_key=True),
    Column("recording", String(200), nullable=False),  # the file name in the folder (session.mcap)
    Column("chain_head", String(64), nullable=False),
    Column("file_sha256", String(64), nullable=False),
    Column("signature_json", Text, nullable=True),  # the sidecar's signature (None: unsigned)
    Column("public_key", String(64), nullable=True),  # the signing key, 64 hex digits (raw Ed25519)
    # revision 0002: SHA-256 of the raw public key bytes (what docs and a key register quote)
    Column("public_key_fingerprint", String(64), nullable=True),
)

station_health = Table(  # revision 0002
    "station_health",
    metadata,
    Column("session_id", String(200), ForeignKey("sessions.id", ondelete="CASCADE"), primary_key=True),
    Column("figure", String(100), primary_key=True),  # e.g. registration_rms_mm (crossfield.catalog.ingest.HEALTH)
    Column("value", Float, nullable=True),
    Column("unit", String(20), nullable=False, default=""),
)

#: Every table, parents first (the order rows are written and read).
TABLES = (sessions, characteristics, seals, station_health)

__all__ = ["NAMING", "TABLES", "characteristics", "metadata", "seals", "sessions", "station_health"]
