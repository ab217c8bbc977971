"""deleted_datasets: the tombstone of a dataset until its folder is gone

Revision ID: 0008
Revises: 0007
DELETE /v1/datasets/{id} commits the row's removal, then removes the folder. A process killed in between left a folder
that nothing pointed to and nothing removed. The delete now writes a tombstone in its transaction and removes it after
the folder; the next API start removes the folders of the tombstones left behind (app/leftovers.py).
"""
import sqlalchemy as sa
from alembic import op

revision = '0008'
down_revision = '0007'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        'deleted_datasets',
        sa.Column('id', sa.String(length=40), nullable=False),
        sa.Column('deleted_at', sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint('id'),
    )


def downgrade() -> None:
    op.drop_table('deleted_datasets')
