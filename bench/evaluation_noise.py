"""How much of a run's final/best gap is the evaluation's own noise?

The issue's no-collapse bar asks each run's final score (the mean of its last 3 evaluations) to be at least 0.8 of its
best (the highest of at least 9). Both are 10-episode evaluations with fresh episode seeds, and the best is a maximum,
so a policy that never changed would still show final < best. This bench measures that for trained policies: it
evaluates one policy `--repeats` times on new seeds (10 episodes each, as a run does), then resamples those scores as
if a run of `--evaluations` evaluations had never changed its policy, and reports the final/best ratio such a run would
show and how often it would fall under 0.8.

    python bench/evaluation_noise.py RUN_DIR... [--which last best] [--repeats 30] [--evaluations 9]

RUN_DIR is a `drop train` output (or a paper_table run directory) with `policy/last` and `policy/best`.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np
import torch

from drop_engine.evaluation import evaluate
from drop_engine.export import load_policy
from drop_engine.policy_files import FILE_NAMES
from drop_engine.scores import FINAL_WINDOW, summarize

BAR = 0.8


def static_ratios(scores: np.ndarray, evaluations: int, draws: int, rng: np.random.Generator) -> np.ndarray:
    """final/best of `draws` simulated runs whose `evaluations` scores are drawn from one policy's `scores`."""
    ratios = np.empty(draws)
    for i, run in enumerate(rng.choice(scores, size=(draws, evaluations))):
        summary = summarize(list(enumerate(run.tolist())))
        ratios[i] = summary.final_score / summary.best_score if summary.best_score > 0 else np.nan
    return ratios


def number(value: float | None, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def measure(run_dir: Path, which: str, repeats: int, evaluations: int, draws: int) -> dict:
    exported = run_dir / "policy" / which
    summary = json.loads((exported / FILE_NAMES["metadata"]).read_text())  # the run's scores as of its last export
    env = summary["env"]
    policy = load_policy(exported / FILE_NAMES["torchscript"])
    # Seeds far from any a run uses (10,000 x (seed + 1) + epoch), so no episode repeats one of the run's own.
    scores = np.array([evaluate(policy, env, episodes=10, seed=1_000_000 + 100 * k).normalized_score
                       for k in range(repeats)])
    ratios = static_ratios(scores, evaluations, draws, np.random.default_rng(0))
    ratios = ratios[np.isfinite(ratios)]  # runs whose best is not positive have no ratio
    return {"run": str(run_dir), "env": env, "which": which, "scores": scores.tolist(),
            "mean": float(scores.mean()), "std": float(scores.std(ddof=1)),
            "static_ratio_median": float(np.median(ratios)) if ratios.size else None,
            "static_below_bar": float(np.mean(ratios < BAR)) if ratios.size else None,
            "run_final": summary.get("final_score"),
            "run_best": summary.get("best_score")}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--which", nargs="+", choices=("last", "best"), default=["last"])
    p.add_argument("--repeats", type=int, default=30, help="10-episode evaluations of the policy on new seeds")
    p.add_argument("--evaluations", type=int, default=9, help="evaluations of the simulated unchanging run")
    p.add_argument("--draws", type=int, default=10_000)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = p.parse_args()
    torch.set_num_threads(1)
    rows = [measure(r, which, args.repeats, args.evaluations, args.draws) for r in args.runs for which in args.which]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "evaluation_noise.json").write_text(json.dumps(rows, indent=2))
    lines = [f"# Evaluation noise: one unchanging policy, {args.repeats} evaluations of 10 episodes on new seeds",
             "", f"Simulated run: {args.evaluations} evaluations drawn from those scores, final = mean of the last "
             f"{FINAL_WINDOW}, best = the highest. `python bench/{Path(__file__).name} {' '.join(sys.argv[1:])}`",
             "", "| run | policy | score mean ± std | min-max | static final/best (median) | static runs under "
             f"{BAR} | the run's final / best |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        scores = np.array(r["scores"])
        run = os.path.join(*Path(r["run"]).parts[-3:])
        lines.append(f"| {run} | {r['which']} | {r['mean']:.1f} ± {r['std']:.1f} | "
                     f"{scores.min():.1f}-{scores.max():.1f} | {number(r['static_ratio_median'], '.2f')} | "
                     f"{number(r['static_below_bar'], '.0%')} | "
                     f"{number(r['run_final'], '.1f')} / {number(r['run_best'], '.1f')} |")
    (args.out / "evaluation_noise.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
