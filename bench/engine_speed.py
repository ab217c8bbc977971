"""Engine speed: each phase of a `cpu`-preset epoch timed alone, a whole epoch, and the machine's own ceilings.

Useful FLOPs are counted by torch's FlopCounterMode (matmuls of forward and backward), so "share of ceiling" is the
engine's matmul FLOP/s over a large fp32 matmul's in the same run and thread setting.

    python bench/engine_speed.py [--dataset FILE] [--threads 1 2] [--device cpu] [--out bench/results]
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from drop_engine.collect import collect_transitions, random_policy
from drop_engine.config import build_config
from drop_engine.data import Dataset, from_arrays, load_dataset
from drop_engine.dynamics import GaussianEnsemble, train_dynamics
from drop_engine.evaluation import evaluate
from drop_engine.replay_buffer import ReplayBuffer
from drop_engine.rollout import model_rollout
from drop_engine.seeding import cpu_kind
from drop_engine.trainer import Trainer


def seconds_per_call(fn, device: torch.device, min_time: float = 1.5, warmup: int = 2) -> float:
    for _ in range(warmup):
        fn()
    sync = (lambda: torch.cuda.synchronize(device)) if device.type == "cuda" else (lambda: None)
    sync()
    calls, start = 0, time.perf_counter()
    while True:
        fn()
        calls += 1
        sync()
        elapsed = time.perf_counter() - start
        if elapsed >= min_time and calls >= 3:
            return elapsed / calls


def flops_of(fn) -> int:
    with FlopCounterMode(display=False) as counter:
        fn()
    return counter.get_total_flops()


def matmul_ceiling(device: torch.device, n: int = 2048) -> float:
    a, b = torch.randn(n, n, device=device), torch.randn(n, n, device=device)
    return 2 * n**3 / seconds_per_call(lambda: a @ b, device)


def mlp_adam_step(device: torch.device):
    """A plain 256-256 MLP Adam step at batch 256: the practical ceiling of a batch-256 update on this machine,
    since its matmuls have the SAC update's shapes and nothing else runs."""
    net = torch.nn.Sequential(torch.nn.Linear(256, 256), torch.nn.ReLU(), torch.nn.Linear(256, 256)).to(device)
    opt = torch.optim.Adam(net.parameters(), fused=True)
    x = torch.randn(256, 256, device=device)

    def step():
        loss = net(x).pow(2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return step


def make_dataset(path: str | None, n: int) -> Dataset:
    if path:
        return load_dataset(path, env="hopper")
    return from_arrays(collect_transitions("hopper", random_policy(3, 0), n, seed=0), env="hopper")


def ready_trainer(data: Dataset, algorithm: str, device: str, out: Path) -> Trainer:
    """A cpu-preset trainer with a briefly trained ensemble and a filled model buffer."""
    cfg = build_config(algorithm, env="hopper", preset="cpu", task="medium", overrides={"dynamics.max_epochs": 1},
                       device=device)
    trainer = Trainer(data, cfg, out)
    trainer.train_dynamics()
    trainer._start_epoch()
    trainer.epoch_started = True
    return trainer


def bench_threads(data: Dataset, threads: int, device: torch.device, work: Path) -> dict:
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    ceiling_at_start = matmul_ceiling(device)
    row: dict = {"threads": threads, "device": str(device)}

    def phase(name: str, fn, calls_per_unit: int = 1):
        seconds = seconds_per_call(fn, device)
        flops = flops_of(fn)
        row[name] = {"seconds": seconds, "per_second": calls_per_unit / seconds,
                     "gflops": flops / seconds / 1e9}

    phase("mlp256_adam_step", mlp_adam_step(device))
    drop = ready_trainer(data, "drop", str(device), work / f"drop-{threads}")
    cfg = drop.cfg
    phase("sac_update", drop.sac_update)
    phase("dice_update", lambda: drop.train_dice(1))
    buffer = ReplayBuffer(cfg.rollout.batch_size * cfg.horizon, data.obs_dim, data.act_dim, device)
    starts = drop.real.sample(50_000)[0]
    phase("rollout_50k", lambda: model_rollout(drop.sac.actor, drop.model, drop.dice, starts, cfg.horizon, "drop",
                                               cfg.penalty, drop.termination, buffer))

    # Dynamics: one epoch over 100k transitions (the bootstrap resample is the same size as the training split).
    rng = np.random.default_rng(0)
    idx = rng.integers(0, len(data), 100_000)
    sub = data.take(idx)
    dyn_cfg = cfg.dynamics.model_copy(update={"max_epochs": 1})
    model = GaussianEnsemble(data.obs_dim, data.act_dim, dyn_cfg).to(device)
    start = time.perf_counter()
    train_dynamics(model, sub, dyn_cfg, rng, device)
    row["dynamics_epoch_per_100k_s"] = time.perf_counter() - start

    # Per env step, not per episode: the actor changes with every phase above, and how long it keeps hopper alive
    # (20 steps or 1000) would otherwise decide the figure.
    start = time.perf_counter()
    result = evaluate(lambda o: drop.sac.actor.act(torch.as_tensor(o, device=device), True).detach().cpu().numpy(),
                      "hopper", 10, seed=0)
    row["evaluation_steps"] = int(sum(result.lengths))
    row["evaluation_steps_per_s"] = row["evaluation_steps"] / (time.perf_counter() - start)

    def epoch_seconds(trainer: Trainer) -> float:
        trainer.epoch_started, trainer.step_in_epoch = False, 0
        start = time.perf_counter()
        trainer._start_epoch()
        trainer._sac_steps()
        trainer._flush_metrics()
        return time.perf_counter() - start

    epoch_cpu = cfg.rollout.batch_size / 50_000
    parts = (cfg.dice.steps_per_epoch * row["dice_update"]["seconds"] + epoch_cpu * row["rollout_50k"]["seconds"]
             + cfg.steps_per_epoch * row["sac_update"]["seconds"])
    drop.epoch = 1  # not the pretraining epoch
    row["drop_epoch_s"] = epoch_seconds(drop)
    row["drop_epoch_sum_of_parts_s"] = parts
    row["drop_epoch_over_parts"] = row["drop_epoch_s"] / parts
    mbpo = ready_trainer(data, "mbpo", str(device), work / f"mbpo-{threads}")
    mbpo.epoch = 1
    row["mbpo_epoch_s"] = epoch_seconds(mbpo)
    row["drop_over_mbpo"] = row["drop_epoch_s"] / row["mbpo_epoch_s"]

    # The ceiling is the better of two measurements, at the start and the end: on a shared host one can land in a
    # moment of stolen time, and a low ceiling would flatter every share.
    ceiling = max(ceiling_at_start, matmul_ceiling(device))
    row["matmul_gflops"] = ceiling / 1e9
    for name in ("mlp256_adam_step", "sac_update", "dice_update", "rollout_50k"):
        row[name]["share_of_matmul"] = row[name]["gflops"] * 1e9 / ceiling
    return row


def markdown(rows: list[dict], meta: dict) -> str:
    lines = [f"# Engine speed ({meta['date']}, {meta['machine']}, torch {meta['torch']})", "",
             "| threads | device | matmul GFLOP/s | MLP-256 Adam step/s (share) | SAC upd/s (share) "
             "| DICE upd/s (share) | rollout 50k x h s (share) | dyn epoch/100k s | eval steps/s "
             "| DROP epoch s (x parts) | MBPO epoch s | DROP/MBPO |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        m, s, d, ro = r["mlp256_adam_step"], r["sac_update"], r["dice_update"], r["rollout_50k"]
        lines.append(
            f"| {r['threads']} | {r['device']} | {r['matmul_gflops']:.0f} "
            f"| {m['per_second']:.0f} ({m['share_of_matmul']:.0%}) "
            f"| {s['per_second']:.0f} ({s['share_of_matmul']:.0%}) "
            f"| {d['per_second']:.0f} ({d['share_of_matmul']:.0%}) | {ro['seconds']:.2f} ({ro['share_of_matmul']:.0%}) "
            f"| {r['dynamics_epoch_per_100k_s']:.1f} | {r['evaluation_steps_per_s']:.0f} "
            f"| {r['drop_epoch_s']:.1f} ({r['drop_epoch_over_parts']:.2f}) | {r['mbpo_epoch_s']:.1f} "
            f"| {r['drop_over_mbpo']:.2f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dataset", help="hopper dataset (default: 50k random-policy transitions made now)")
    p.add_argument("--transitions", type=int, default=50_000)
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", default="bench/results")
    p.add_argument("--tag", default="", help="suffix of the result files, e.g. 'before'")
    args = p.parse_args(argv)
    device = torch.device(args.device)
    data = make_dataset(args.dataset, args.transitions)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as work:
        rows = [bench_threads(data, t, device, Path(work)) for t in args.threads]
    meta = {"date": time.strftime("%Y-%m-%d %H:%M"), "machine": cpu_kind(),
            "torch": torch.__version__, "python": sys.version.split()[0], "transitions": len(data)}
    name = "engine_speed" + (f"_{args.tag}" if args.tag else "") + ("_cuda" if device.type == "cuda" else "")
    (out / f"{name}.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    (out / f"{name}.md").write_text(markdown(rows, meta))
    print(markdown(rows, meta))
    return 0


if __name__ == "__main__":
    sys.exit(main())
