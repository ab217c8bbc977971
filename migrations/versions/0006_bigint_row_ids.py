"""job_events, job_metrics and job_evaluations ids as 64-bit integers

Revision ID: 0006
Revises: 0005
A job may record up to DROP_MAX_JOB_METRIC_ROWS (a million) metric rows and rows are kept, so 32-bit ids ran out after
about 2,100 such jobs and every job's next metric insert failed; the API pages these three tables by id and takes any
64-bit cursor. PostgreSQL: each column and its sequence become bigint (this rewrites the tables under an exclusive
lock: run it while the service is stopped). SQLite's INTEGER PRIMARY KEY is already the 64-bit rowid, and stays as it
is, as it must to keep counting ids. The downgrade fails, and changes nothing, once an id is past 2^31 - 1.
"""
from alembic import op

revision = '0006'
down_revision = '0005'
branch_labels = None
depends_on = None

TABLES = ('job_events', 'job_metrics', 'job_evaluations')


def _retype(kind: str) -> None:
    if op.get_bind().dialect.name != 'postgresql':
        return
    for table in TABLES:
        op.execute(f'ALTER TABLE {table} ALTER COLUMN id TYPE {kind}')
        op.execute(f"ALTER SEQUENCE {table}_id_seq AS {kind}")


def upgrade() -> None:
    _retype('bigint')


def downgrade() -> None:
    _retype('integer')
