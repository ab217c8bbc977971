"""How broad are the bench files' behaviour policies, against SAC's entropy target of -|A|?

For each `ENV-KIND.hdf5` of the `make bench-data` cache, reads the behaviour policies it was recorded with from the
collection's online-SAC checkpoint (`ENV-sac/online.pt`) and reports the data's mean negative log-likelihood under
the policy that chose each row, which is that policy's entropy at the data's states (medium-replay, the replay of a
learning actor, has no single one). Beside it, `drop_engine.bc.behaviour_entropy`, the estimate a run can make from
the data alone, after several numbers of fitting steps. A policy trained to an entropy above the data's samples
actions the data does not have, and the density ratio on the data is then small (bench/QUALITY.md E28).

    python bench/behaviour_entropy.py --envs hopper halfcheetah [--kinds medium ...] [--steps 2000 5000 20000]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np
import torch

from drop_engine.bc import behaviour_entropy, entropy_rows
from drop_engine.data import Dataset, load_dataset
from drop_engine.online import CHECKPOINT_NAME
from drop_engine.sac import Actor

CACHE = Path(os.environ.get("DROP_BENCH_DATA", Path.home() / ".cache/drop-rl/bench-data"))
KINDS = ("random", "medium", "medium-replay", "medium-expert")


@torch.no_grad()
def recorded_entropy(data: Dataset, path: Path, env: str) -> float | None:
    """The data actions' mean negative log-likelihood under the snapshot that recorded each row, on the rows the
    estimate reads; None for a file not recorded by snapshots (medium-replay)."""
    steps = [int(s) for s in np.atleast_1d(data.attrs["policy_steps"])]
    if "replay" in str(data.attrs.get("behaviour", "")):
        return None
    state = torch.load(path.parent / f"{env}-sac" / CHECKPOINT_NAME, map_location="cpu", weights_only=False)
    snaps = {s["step"]: s["actor"] for s in state["snapshots"]}
    per_policy = int(data.attrs["transitions_per_policy"])
    hidden = tuple(state["config"]["sac"]["hidden"])  # the collection's actor, as its checkpoint records it
    rows = entropy_rows(data)
    nll = np.empty(len(rows))
    for i, step in enumerate(steps):  # medium-expert: the medium policy's rows, then the expert's
        mine = (rows >= i * per_policy) & (rows < (i + 1) * per_policy)
        actor = Actor(data.obs_dim, data.act_dim, hidden)
        actor.load_state_dict(snaps[step])
        obs, act = torch.as_tensor(data.observations[rows[mine]]), torch.as_tensor(data.actions[rows[mine]])
        nll[mine] = -actor.log_prob(obs, act).numpy()
    return float(nll.mean())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--envs", nargs="+", default=["hopper", "halfcheetah"])
    p.add_argument("--kinds", nargs="+", default=list(KINDS), choices=KINDS)
    p.add_argument("--steps", nargs="+", type=int, default=[2000, 5000, 20000])
    p.add_argument("--out", default="bench/results")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    rows = []
    for env in args.envs:
        for kind in args.kinds:
            path = CACHE / f"{env}-{kind}.hdf5"
            if not path.is_file():
                print(f"skip {path}: not collected", file=sys.stderr)
                continue
            data = load_dataset(path, env=env)
            row = {"env": env, "kind": kind, "act_dim": data.act_dim, "target": -float(data.act_dim),
                   "content_hash": data.content_hash, "recorded": recorded_entropy(data, path, env),
                   "estimate": {str(s): behaviour_entropy(data, s) for s in args.steps}}
            rows.append(row)
            print(json.dumps(row), flush=True)
    out = Path(args.out)
    (out / "behaviour_entropy.json").write_text(json.dumps(rows, indent=2))
    lines = ["# The bench files' behaviour entropy (nats) against SAC's target -\\|A\\|", "",
             "| dataset | -\\|A\\| | recording policies | "
             + " | ".join(f"estimate, {s} steps" for s in args.steps) + " |",
             "|---|---|---|" + "---|" * len(args.steps)]
    for r in rows:
        rec = "-" if r["recorded"] is None else f"{r['recorded']:.2f}"
        est = " | ".join(f"{r['estimate'][str(s)]:.2f}" for s in args.steps)
        lines.append(f"| {r['env']}-{r['kind']} | {r['target']:.0f} | {rec} | {est} |")
    (out / "behaviour_entropy.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
