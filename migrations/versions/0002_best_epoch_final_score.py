"""jobs.best_epoch and jobs.final_score

Revision ID: 0002
Revises: 0001
The job shows the epoch of its best evaluation (the `which=best` policy's) and a final score averaged over its last
evaluations. Jobs already recorded get both from their stored evaluations, by the same rule the worker uses.
"""
import sqlalchemy as sa
from alembic import op

# The rule as it was when this migration was written (drop_engine.scores then), copied so that a later change of
# the rule does not change what this old migration computes.
FINAL_WINDOW = 3


def summarize(pairs: list[tuple[int, float]]) -> tuple[int, float]:
    """(best epoch, the earliest of ties; mean of the last FINAL_WINDOW scores)."""
    best_epoch = max(pairs, key=lambda e: e[1])[0]
    window = [score for _, score in pairs[-FINAL_WINDOW:]]
    return best_epoch, sum(window) / len(window)

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
        best_epoch, final = summarize(pairs)
        conn.execute(sa.text("UPDATE jobs SET best_epoch = :epoch, final_score = :final WHERE id = :id"),
                     {"epoch": best_epoch, "final": final, "id": job_id})


def downgrade() -> None:
    with op.batch_alter_table('jobs', schema=None) as batch_op:
        batch_op.drop_column('final_score')
        batch_op.drop_column('best_epoch')
