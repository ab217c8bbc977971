"""Learning-curve figures, drawn headless: one run's (the API's `curve.png` and `drop train`'s `OUT/curve.png`, the
same figure) and several runs overlaid (`drop plot`)."""
from __future__ import annotations

import io
from collections import defaultdict
from dataclasses import dataclass

import numpy as np

SCORE_LABEL = "D4RL normalised score"


@dataclass
class Curve:
    """One run's evaluations, and what it was: runs that differ only by seed are averaged together."""
    algorithm: str
    env: str
    seed: int
    epochs: list[int]
    scores: list[float]


def _figure():
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    return Figure(figsize=(6, 3.5), dpi=100)


def _png(fig) -> bytes:
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def learning_curve(title: str, epochs: list[int], scores: list[float]) -> bytes:
    """Normalised score per evaluation of one run, as PNG bytes."""
    fig = _figure()
    ax = fig.add_subplot()
    if epochs:
        ax.plot(epochs, scores, marker="o")
    else:
        ax.text(0.5, 0.5, "no evaluations yet", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel("epoch")
    ax.set_ylabel(SCORE_LABEL)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    return _png(fig)


def mean_and_std(curves: list[Curve]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(epochs, mean, std) over the runs that reached each epoch: a seed that stopped early narrows the tail."""
    by_epoch: dict[int, list[float]] = defaultdict(list)
    for curve in curves:
        for epoch, score in zip(curve.epochs, curve.scores):
            by_epoch[epoch].append(score)
    epochs = np.array(sorted(by_epoch))
    values = [np.asarray(by_epoch[e]) for e in epochs]
    return epochs, np.array([v.mean() for v in values]), np.array([v.std() for v in values])


def overlay(curves: list[Curve], title: str = "") -> bytes:
    """Runs grouped by (env, algorithm): each group's mean over seeds with a band of one standard deviation; a colour
    per algorithm, a line style per env."""
    import matplotlib

    groups: dict[tuple[str, str], list[Curve]] = defaultdict(list)
    for curve in curves:
        groups[(curve.env, curve.algorithm)].append(curve)
    algorithms = list(dict.fromkeys(c.algorithm for c in curves))
    envs = list(dict.fromkeys(c.env for c in curves))
    colours = matplotlib.colormaps["tab10"]
    styles = ["-", "--", ":", "-."]
    fig = _figure()
    ax = fig.add_subplot()
    for (env, algorithm), members in groups.items():
        epochs, mean, std = mean_and_std(members)
        colour, style = colours(algorithms.index(algorithm) % 10), styles[envs.index(env) % len(styles)]
        seeds = f"{len(members)} seeds" if len(members) > 1 else f"seed {members[0].seed}"
        label = f"{algorithm} ({seeds})" if len(envs) == 1 else f"{env} {algorithm} ({seeds})"
        ax.plot(epochs, mean, style, color=colour, marker="o", markersize=3, label=label)
        if len(members) > 1:
            ax.fill_between(epochs, mean - std, mean + std, color=colour, alpha=0.2, linewidth=0)
    ax.set_xlabel("epoch")
    ax.set_ylabel(SCORE_LABEL + (" (mean ± std)" if any(len(m) > 1 for m in groups.values()) else ""))
    ax.set_title(title or ", ".join(envs))
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    return _png(fig)
