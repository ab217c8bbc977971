"""jobs.best_epoch and jobs.final_score

Revision ID: 0002
Revises: 0001
The job shows the epoch of its best evaluation (the `which=best` policy's) and a final score averaged over its last
evaluations. Jobs already recorded get both from their stored evaluations, by the same rule the worker uses.
"""
from alembic import op
import sqlalchemy as sa

from drop_engine.scores import summarize

revision = '0002'
down_revision = '0001'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.add_column(sa.Column('best_epoch', sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column('final_score', sa.Float(), nullable=True))
    conn = op.get_bind()
    evaluations: dict[str, list[tuple[int, float]]] = {}
    for job_id, epoch, score in conn.execute(sa.text(
            "SELECT job_id, epoch, normalized_score FROM job_evaluations ORDER BY job_id, epoch, id")):
        evaluations.setdefault(job_id, []).append((epoch, score))
    for job_id, pairs in evaluations.items():
        summary = summarize(pairs)
        conn.execute(sa.text("UPDATE jobs SET best_epoch = :epoch, final_score = :final WHERE id = :id"),
                     {"epoch": summary.best_epoch, "final": summary.final_score, "id": job_id})


def downgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.drop_column('final_score')
        batch_op.drop_column('best_epoch')
