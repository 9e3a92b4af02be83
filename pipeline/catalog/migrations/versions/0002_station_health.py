"""station health per session; the seal's public-key fingerprint; sessions by station and time

Revision ID: 0002
Revises: 0001
Create Date: 2026-12-03

The fingerprint of a key already catalogued by revision 0001 is filled in from its
``public_key`` (SHA-256 of the 32 raw key bytes), so an upgraded catalog answers "which
sessions did this key sign" as a new one does. Health figures of sessions catalogued
before this revision are not recomputed (``crossfield catalog add`` of their folders
adds nothing: a session is added once); they stay absent.
"""

from __future__ import annotations

import hashlib

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "station_health",
        sa.Column("session_id", sa.String(200), nullable=False),
        sa.Column("figure", sa.String(100), nullable=False),
        sa.Column("value", sa.Float, nullable=True),
        sa.Column("unit", sa.String(20), nullable=False),
        sa.PrimaryKeyConstraint("session_id", "figure", name="pk_station_health"),
        sa.ForeignKeyConstraint(
            ["session_id"], ["sessions.id"], ondelete="CASCADE", name="fk_station_health_session_id_sessions"
        ),
    )
    with op.batch_alter_table("seals") as batch:
        batch.add_column(sa.Column("public_key_fingerprint", sa.String(64), nullable=True))
    op.create_index("ix_sessions_station_start", "sessions", ["station", "start_utc"])
    seals = sa.table(
        "seals",
        sa.column("session_id", sa.String),
        sa.column("public_key", sa.String),
        sa.column("public_key_fingerprint", sa.String),
    )
    bind = op.get_bind()
    rows = bind.execute(sa.select(seals.c.session_id, seals.c.public_key).where(seals.c.public_key.is_not(None)))
    for session_id, key in rows.all():
        fingerprint = hashlib.sha256(bytes.fromhex(key)).hexdigest()
        bind.execute(
            seals.update().where(seals.c.session_id == session_id).values(public_key_fingerprint=fingerprint)
        )


def downgrade() -> None:
    op.drop_index("ix_sessions_station_start", table_name="sessions")
    with op.batch_alter_table("seals") as batch:
        batch.drop_column("public_key_fingerprint")
    op.drop_table("station_health")
