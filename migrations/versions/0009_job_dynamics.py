"""jobs.dynamics: the ensemble a job trains on, shown by the API; jobs.result goes

Revision ID: 0009
Revises: 0008
jobs.result held the engine's whole report of a finished job, absolute server paths included, and nothing read it.
What a user needs of it, which dynamics ensemble the job used and whether it came from the model cache (issue #12), is
now a column the API shows, written as soon as the ensemble is ready. Recorded jobs keep theirs: the upgrade copies
`result.dynamics`, less the server's path, into the new column; the downgrade puts it back as `{"dynamics": ...}`.
"""
import json

import sqlalchemy as sa
from alembic import op

revision = '0009'
down_revision = '0008'
branch_labels = None
depends_on = None

_jobs = sa.table('jobs', sa.column('id', sa.String), sa.column('result', sa.JSON), sa.column('dynamics', sa.JSON))


def _parsed(value):
    return json.loads(value) if isinstance(value, str) else value


def upgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.add_column(sa.Column('dynamics', sa.JSON(), nullable=True))
    conn = op.get_bind()
    recorded = conn.execute(sa.select(_jobs.c.id, _jobs.c.result).where(_jobs.c.result.isnot(None))).all()
    for job_id, result in recorded:
        dynamics = (_parsed(result) or {}).get('dynamics')
        if dynamics:  # a job of before the model cache has no key: null, as the API documents
            shown = {'cache_key': None, 'from_cache': None, **{k: v for k, v in dynamics.items() if k != 'cache_path'}}
            conn.execute(_jobs.update().where(_jobs.c.id == job_id).values(dynamics=shown))
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.drop_column('result')


def downgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.add_column(sa.Column('result', sa.JSON(), nullable=True))
    conn = op.get_bind()
    shown = conn.execute(sa.select(_jobs.c.id, _jobs.c.dynamics).where(_jobs.c.dynamics.isnot(None))).all()
    for job_id, dynamics in shown:
        conn.execute(_jobs.update().where(_jobs.c.id == job_id).values(result={'dynamics': _parsed(dynamics)}))
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.drop_column('dynamics')
