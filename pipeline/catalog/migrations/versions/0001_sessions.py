"""sessions, characteristics and seals

Revision ID: 0001
Revises:
Create Date: 2026-12-03
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "sessions",
        sa.Column("id", sa.String(200), primary_key=True),
        sa.Column("station", sa.String(200), nullable=False),
        sa.Column("operator", sa.String(200), nullable=False),
        sa.Column("part", sa.String(200), nullable=False),
        sa.Column("serial", sa.String(200), nullable=False),
        sa.Column("job_order", sa.String(200), nullable=False),
        sa.Column("job_json", sa.Text, nullable=False),
        sa.Column("start_utc", sa.DateTime(timezone=False), nullable=False),
        sa.Column("start_time_ns", sa.BigInteger, nullable=False),
        sa.Column("end_utc", sa.DateTime(timezone=False), nullable=True),
        sa.Column("plan_name", sa.String(400), nullable=False),
        sa.Column("plan_sha256", sa.String(64), nullable=True),
        sa.Column("calibration_source", sa.Text, nullable=False),
        sa.Column("calibration_sha256", sa.String(64), nullable=True),
        sa.Column("crossfield_version", sa.String(64), nullable=False),
        sa.Column("plugins_json", sa.Text, nullable=False),
        sa.Column("packages_json", sa.Text, nullable=False),
        sa.Column("verdict", sa.String(20), nullable=False),
        sa.Column("frames_processed", sa.Integer, nullable=False),
        sa.Column("frames_failed", sa.Integer, nullable=False),
        sa.Column("folder", sa.Text, nullable=False),
        sa.Column("ingested_utc", sa.DateTime(timezone=False), nullable=False),
        sa.PrimaryKeyConstraint("id", name="pk_sessions"),
    )
    op.create_table(
        "characteristics",
        sa.Column("session_id", sa.String(200), nullable=False),
        sa.Column("no", sa.Integer, nullable=False),
        sa.Column("name", sa.String(200), nullable=False),
        sa.Column("kind", sa.String(64), nullable=False),
        sa.Column("measured_mm", sa.Float, nullable=True),
        sa.Column("nominal_mm", sa.Float, nullable=True),
        sa.Column("upper_tol_mm", sa.Float, nullable=True),
        sa.Column("lower_tol_mm", sa.Float, nullable=True),
        sa.Column("expanded_uncertainty_mm", sa.Float, nullable=True),
        sa.Column("coverage_factor", sa.Float, nullable=True),
        sa.Column("decision", sa.String(40), nullable=True),
        sa.Column("decision_rule", sa.String(40), nullable=True),
        sa.Column("budget_json", sa.Text, nullable=False),
        sa.PrimaryKeyConstraint("session_id", "no", name="pk_characteristics"),
        sa.ForeignKeyConstraint(
            ["session_id"], ["sessions.id"], ondelete="CASCADE",
            name="fk_characteristics_session_id_sessions",
        ),
    )
    op.create_index("ix_characteristics_name_session", "characteristics", ["name", "session_id"])
    op.create_table(
        "seals",
        sa.Column("session_id", sa.String(200), nullable=False),
        sa.Column("recording", sa.String(200), nullable=False),
        sa.Column("chain_head", sa.String(64), nullable=False),
        sa.Column("file_sha256", sa.String(64), nullable=False),
        sa.Column("signature_json", sa.Text, nullable=True),
        sa.Column("public_key", sa.String(64), nullable=True),
        sa.PrimaryKeyConstraint("session_id", name="pk_seals"),
        sa.ForeignKeyConstraint(
            ["session_id"], ["sessions.id"], ondelete="CASCADE", name="fk_seals_session_id_sessions"
        ),
    )


def downgrade() -> None:
    op.drop_table("seals")
    op.drop_index("ix_characteristics_name_session", table_name="characteristics")
    op.drop_table("characteristics")
    op.drop_table("sessions")
