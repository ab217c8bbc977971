"""deleted_jobs: what /metrics counts of a deleted job

Revision ID: 0007
Revises: 0006
DELETE /v1/jobs/{id} removes a finished job's row. /metrics aggregates its counters (attempts, queue wait, run
seconds, model-cache hits and misses) from the job rows, so the deleted job's share moves here in the same
transaction, and the counters never go down.
"""
import sqlalchemy as sa
from alembic import op

revision = '0007'
down_revision = '0006'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        'deleted_jobs',
        sa.Column('id', sa.String(length=40), nullable=False),
        sa.Column('attempts', sa.Integer(), nullable=False),
        sa.Column('queue_wait_s', sa.Float(), nullable=True),
        sa.Column('run_s', sa.Float(), nullable=True),
        sa.Column('dynamics_from_cache', sa.Boolean(), nullable=True),
        sa.Column('deleted_at', sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint('id'),
    )


def downgrade() -> None:
    op.drop_table('deleted_jobs')
