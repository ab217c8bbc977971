"""Job timings for /metrics, indexes for the hot reads, and a NOTIFY per new job event on PostgreSQL

Revision ID: 0003
Revises: 0002
- jobs.queue_wait_s (created to first claimed), jobs.run_s (seconds its attempts ran) and jobs.dynamics_from_cache:
  /metrics aggregates them in SQL at scrape time, so every worker's jobs count without workers serving metrics.
- (job_id, id) on job_events and (owner_id, id) on jobs: the event cursor and the newest-first job list read an index
  range instead of sorting.
- On PostgreSQL a trigger sends NOTIFY drop_job_events with the job id after each new event, which wakes the API's
  event streams at once instead of their polling the table.
"""
import sqlalchemy as sa
from alembic import op

revision = '0003'
down_revision = '0002'
branch_labels = None
depends_on = None

NOTIFY_FUNCTION = """
CREATE OR REPLACE FUNCTION drop_notify_job_event() RETURNS trigger AS $$
BEGIN
    PERFORM pg_notify('drop_job_events', NEW.job_id);
    RETURN NEW;
END
$$ LANGUAGE plpgsql
"""
NOTIFY_TRIGGER = ("CREATE TRIGGER job_events_notify AFTER INSERT ON job_events "
                  "FOR EACH ROW EXECUTE FUNCTION drop_notify_job_event()")


def upgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.add_column(sa.Column('queue_wait_s', sa.Float(), nullable=True))
        batch_op.add_column(sa.Column('run_s', sa.Float(), nullable=True))
        batch_op.add_column(sa.Column('dynamics_from_cache', sa.Boolean(), nullable=True))
        batch_op.create_index('ix_jobs_owner_id_id', ['owner_id', 'id'], unique=False)
    with op.batch_alter_table('job_events', schema=None) as batch_op:
        batch_op.create_index('ix_job_events_job_id_id', ['job_id', 'id'], unique=False)
    if op.get_bind().dialect.name == 'postgresql':
        op.execute(NOTIFY_FUNCTION)
        op.execute(NOTIFY_TRIGGER)


def downgrade() -> None:
    if op.get_bind().dialect.name == 'postgresql':
        op.execute("DROP TRIGGER IF EXISTS job_events_notify ON job_events")
        op.execute("DROP FUNCTION IF EXISTS drop_notify_job_event()")
    with op.batch_alter_table('job_events', schema=None) as batch_op:
        batch_op.drop_index('ix_job_events_job_id_id')
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.drop_index('ix_jobs_owner_id_id')
        batch_op.drop_column('dynamics_from_cache')
        batch_op.drop_column('run_s')
        batch_op.drop_column('queue_wait_s')
