"""Which GradientDICE settings give a ratio that is normalised on the data and tracks the model's error?

Takes a DROP run's checkpoint (its ensemble and actor, frozen), trains fresh estimators with each setting for the
same number of steps, and reports E_D[tau] as it trains, and how DROP's penalty from those estimators and MOPO's
uncertainty rank the true model error (Spearman, as bench/penalty_vs_error.py) on model-rollout and offline samples.

    python bench/dice_settings.py --run RUN_DIR --dataset FILE.hdf5 --steps 4000 [--set lam=1,lr=1e-3 ...]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from drop_engine.dice import GradientDice
from drop_engine.replay_buffer import ReplayBuffer
from drop_engine.rollout import model_rollout
from penalty_vs_error import correlations, penalties_and_error, restore

DEFAULT_SETTINGS = ["", "lam=1", "lr=1e-3", "lam=1,lr=1e-3", "lam=1,lr=1e-3,discount=sac"]


def parse(setting: str) -> dict:
    out = {}
    for item in filter(None, setting.split(",")):
        k, v = item.split("=")
        out[k] = v if v in ("sac", "horizon") else float(v)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dataset", required=True)
    p.add_argument("--run", required=True)
    p.add_argument("--steps", type=int, default=4000)
    p.add_argument("--samples", type=int, default=5000)
    p.add_argument("--set", action="append", default=None, help="comma-separated DiceConfig fields, e.g. lam=1,lr=1e-3")
    p.add_argument("--out", default="bench/results")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    trainer, data = restore(args.dataset, args.run)
    base = trainer.cfg
    rng = np.random.default_rng(0)
    idx = rng.choice(len(data), size=min(args.samples, len(data)), replace=False)
    rows = []
    for setting in args.set or DEFAULT_SETTINGS:
        torch.manual_seed(0)
        dice_cfg = base.dice.model_copy(update=parse(setting))
        cfg = base.model_copy(update={"dice": dice_cfg})
        trainer.cfg = cfg
        trainer.dice = GradientDice(cfg.dynamics.elites, data.obs_dim, data.act_dim, dice_cfg, cfg.dice_discount)
        trainer.dice.norm.set(trainer.sac.actor.norm.mean, trainer.sac.actor.norm.std)
        curve, start, done = [], time.perf_counter(), 0
        for mark in (400, 1000, 2000, args.steps):
            if mark > args.steps or mark <= done:
                continue
            stats = trainer.train_dice(mark - done)
            done = mark
            curve.append({"step": mark, "tau_data_mean": float(stats["dice/tau_data_mean"]),
                          "tau_data_std": float(stats["dice/tau_data_std"])})
        seconds = time.perf_counter() - start
        offline = penalties_and_error(trainer, data.observations[idx], data.actions[idx])
        buffer = ReplayBuffer(args.samples * cfg.horizon, data.obs_dim, data.act_dim)
        model_rollout(trainer.sac.actor, trainer.model, trainer.dice, trainer.real.sample(args.samples)[0], cfg.horizon,
                      "drop", cfg.penalty, trainer.termination, buffer)
        obs, act, *_ = buffer.take(torch.randperm(len(buffer))[: args.samples])
        rollout = penalties_and_error(trainer, obs.numpy(), act.numpy())
        both = {k: np.concatenate([offline[k], rollout[k]]) for k in offline}
        row = {"setting": setting or "run's own", "lam": dice_cfg.lam, "lr": dice_cfg.lr,
               "discount": cfg.dice_discount, "curve": curve, "seconds": seconds,
               "spearman": {g: {k: c["spearman"] for k, c in correlations(r).items()}
                            for g, r in (("offline", offline), ("rollout", rollout), ("all", both))}}
        rows.append(row)
        print(json.dumps(row), flush=True)
    out = Path(args.out)
    stem = f"dice_settings_{base.env}"
    (out / f"{stem}.json").write_text(json.dumps({"run": args.run, "dataset": args.dataset, "steps": args.steps,
                                                  "rows": rows}, indent=2))
    lines = [f"# GradientDICE settings on a frozen {base.env} DROP run ({args.steps} steps each)", "",
             "| setting | lambda | lr | discount | E_D[tau] by step | Spearman with true error: rollout DROP / MOPO | "
             "all DROP / MOPO |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        curve = ", ".join(f"{c['tau_data_mean']:.2f}" for c in r["curve"])
        s = r["spearman"]
        lines.append(f"| {r['setting']} | {r['lam']} | {r['lr']} | {r['discount']:.3f} | {curve} | "
                     f"{s['rollout']['drop']:.2f} / {s['rollout']['mopo']:.2f} | {s['all']['drop']:.2f} / "
                     f"{s['all']['mopo']:.2f} |")
    (out / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
