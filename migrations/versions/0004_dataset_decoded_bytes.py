"""datasets.decoded_bytes

Revision ID: 0004
Revises: 0003
A dataset counts toward its owner's storage quota at the larger of its file size and its decoded size (rows x bytes
of a float32 transition), so a small file that declares millions of rows counts for what it holds. Datasets already
recorded get the decoded size of their report's transitions, by the rule the service uses.
"""
import sqlalchemy as sa
from alembic import op

from drop_engine.data_rows import DataShape

revision = '0004'
down_revision = '0003'
branch_labels = None
depends_on = None

datasets = sa.table('datasets', sa.column('id', sa.String), sa.column('obs_dim', sa.Integer),
                    sa.column('act_dim', sa.Integer), sa.column('report', sa.JSON),
                    sa.column('decoded_bytes', sa.BigInteger))


def upgrade() -> None:
    with op.batch_alter_table('datasets', schema=None) as batch_op:
        batch_op.add_column(sa.Column('decoded_bytes', sa.BigInteger(), nullable=False, server_default='0'))
    conn = op.get_bind()
    rows = conn.execute(sa.select(datasets.c.id, datasets.c.obs_dim, datasets.c.act_dim, datasets.c.report)).all()
    for dataset_id, obs_dim, act_dim, report in rows:
        decoded = DataShape(int(report["transitions"]), obs_dim, act_dim).decoded_bytes
        conn.execute(sa.update(datasets).where(datasets.c.id == dataset_id).values(decoded_bytes=decoded))


def downgrade() -> None:
    with op.batch_alter_table('datasets', schema=None) as batch_op:
        batch_op.drop_column('decoded_bytes')
