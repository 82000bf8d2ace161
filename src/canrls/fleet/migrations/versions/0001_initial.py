"""The first schema: drives, models, recordings, parameters, candidates.

Revision ID: 0001
Revises:
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
        "drives",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("name", sa.String(128), nullable=False, unique=True),
        sa.Column("type", sa.String(128), nullable=False, server_default=""))
    op.create_table(
        "models",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("key", sa.String(64), nullable=False, unique=True),
        sa.Column("description", sa.Text, nullable=False))
    op.create_table(
        "recordings",
        sa.Column("id", sa.Integer, primary_key=True),
        sa.Column("drive_id", sa.Integer, sa.ForeignKey("drives.id"), nullable=False),
        sa.Column("model_id", sa.Integer, sa.ForeignKey("models.id"), nullable=False),
        sa.Column("content_hash", sa.String(64), nullable=False),
        sa.Column("status", sa.String(8), nullable=False),
        sa.Column("source", sa.String(8), nullable=False),
        sa.Column("path", sa.Text, nullable=False, server_default=""),
        sa.Column("t_start", sa.Float),
        sa.Column("t_end", sa.Float),
        sa.Column("samples", sa.Integer, nullable=False, server_default="0"),
        sa.Column("frames", sa.BigInteger, nullable=False, server_default="0"),
        sa.Column("residual_rms", sa.Float),
        sa.Column("fit_percent", sa.Float),
        sa.Column("unit", sa.String(32), nullable=False, server_default=""),
        sa.Column("verdicts", sa.JSON),
        sa.Column("error", sa.Text),
        sa.Column("session", sa.String(64)),
        sa.Column("canrls_version", sa.String(32), nullable=False, server_default=""),
        sa.Column("ingested_at", sa.DateTime(timezone=True), nullable=False),
        sa.UniqueConstraint("content_hash", "model_id", name="uq_recordings_hash_model"))
    op.create_index("ix_recordings_drive_time", "recordings", ["drive_id", "t_start"])
    op.create_table(
        "parameters",
        sa.Column("recording_id", sa.Integer,
                  sa.ForeignKey("recordings.id", ondelete="CASCADE"), primary_key=True),
        sa.Column("name", sa.String(128), primary_key=True),
        sa.Column("value", sa.Float),
        sa.Column("sigma", sa.Float),
        sa.Column("unit", sa.String(32), nullable=False, server_default=""),
        sa.Column("fixed", sa.Float),
        sa.Column("identifiable", sa.Boolean, nullable=False),
        sa.Column("prior_share", sa.Float))
    op.create_table(
        "candidates",
        sa.Column("recording_id", sa.Integer,
                  sa.ForeignKey("recordings.id", ondelete="CASCADE"), primary_key=True),
        sa.Column("rank", sa.Integer, primary_key=True),
        sa.Column("effect", sa.String(64), nullable=False),
        sa.Column("explained", sa.Float),
        sa.Column("delta_bic", sa.Float),
        sa.Column("rms_after", sa.Float),
        sa.Column("identifiable", sa.Boolean, nullable=False),
        sa.Column("suggested", sa.Boolean, nullable=False))


def downgrade() -> None:
    op.drop_table("candidates")
    op.drop_table("parameters")
    op.drop_index("ix_recordings_drive_time", table_name="recordings")
    op.drop_table("recordings")
    op.drop_table("models")
    op.drop_table("drives")
