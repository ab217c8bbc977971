"""jobs.status CHECK: a job's status is one of the job state machine's

Revision ID: 0005
Revises: 0004
kernel/job_state.py is the one writer of jobs.status; the CHECK makes the database refuse any other value, whoever
writes it. The statuses are written out here as they were at this revision, not imported from JobStatus: a migration
stays what it was when it ran (tests/service/test_migrations.py checks that every JobStatus passes it). On SQLite
batch mode recreates the table, with foreign keys off (migrations/env.py) so the rows that refer to jobs stay.
"""
from alembic import op

revision = '0005'
down_revision = '0004'
branch_labels = None
depends_on = None

STATUSES = ('queued', 'running', 'cancelling', 'succeeded', 'failed', 'cancelled')
NAME = 'ck_jobs_status'


def upgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.create_check_constraint(NAME, f"status IN ({', '.join(repr(s) for s in STATUSES)})")


def downgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.drop_constraint(NAME, type_='check')
