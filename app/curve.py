"""The learning curve as a PNG: normalised score per evaluation, drawn headless."""
from __future__ import annotations

import io


def render(job_id: str, epochs: list[int], scores: list[float]) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 3.5), dpi=100)
    ax = fig.add_subplot()
    if epochs:
        ax.plot(epochs, scores, marker="o")
    else:
        ax.text(0.5, 0.5, "no evaluations yet", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel("epoch")
    ax.set_ylabel("D4RL normalised score")
    ax.set_title(job_id)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()
