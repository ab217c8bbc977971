"""`drop` command line for the engine: train and evaluate. The service adds its own subcommands to this parser."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .config import PRESETS, build_config
from .errors import ConfigError

DEFAULT_MODEL_CACHE = "~/.cache/drop-rl/models"


def _parse_override(text: str) -> tuple[str, object]:
    """KEY=VALUE with VALUE parsed as JSON when it is JSON (numbers, lists, booleans), else kept as a string."""
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"override {text!r} is not KEY=VALUE")
    key, raw = text.split("=", 1)
    try:
        return key, json.loads(raw)
    except json.JSONDecodeError:
        return key, raw


def write_curve(run_dir: Path) -> Path:
    """`curve.png` beside the run's evaluations.csv: the figure the API serves for a job."""
    from .plots import learning_curve
    from .run_log import RunLog

    rows = RunLog.read_evaluations(run_dir / "evaluations.csv")
    path = run_dir / "curve.png"
    path.write_bytes(learning_curve(run_dir.name, [int(r["epoch"]) for r in rows],
                                    [float(r["normalized_score"]) for r in rows]))
    return path


def cmd_train(args: argparse.Namespace) -> int:
    from .callbacks import CallbackList, progress_reporter
    from .errors import DatasetError
    from .run_log import RunLog
    from .trainer import train

    try:
        overrides = dict(args.set or [])
        if args.threads:
            overrides["threads"] = args.threads
        config = build_config(args.algorithm, env=args.env, preset=args.preset, task=args.task, overrides=overrides,
                              seed=args.seed, device=args.device)
    except ConfigError as exc:
        print(f"drop train: {exc}", file=sys.stderr)
        return 2
    progress = progress_reporter(not args.no_progress, sys.stderr)
    try:
        callback = CallbackList(progress, RunLog(args.out, config.steps_per_epoch))
        result = train(args.dataset, config, args.out, callback, None if args.no_model_cache else args.model_cache)
    except DatasetError as exc:
        print(f"drop train: {args.dataset}: {exc}", file=sys.stderr)
        return 2
    finally:
        getattr(progress, "close", lambda: None)()
    summary = result.to_dict()
    Path(args.out, "summary.json").write_text(json.dumps({**summary, "config": config.model_dump(mode="json")},
                                                         indent=2))
    write_curve(Path(args.out))
    keys = ("status", "epochs", "last_return", "last_score", "best_score", "best_epoch", "final_score", "policy",
            "timings")
    shown = {k: summary[k] for k in keys}
    if summary["dynamics"]:
        shown["dynamics_from_cache"] = summary["dynamics"]["from_cache"]
    print(json.dumps(shown, indent=2))
    return 0 if result.status == "completed" else 1


def cmd_plot(args: argparse.Namespace) -> int:
    from .plots import overlay
    from .run_log import NotARun, read_curve

    try:
        curves = [read_curve(run) for run in args.runs]
    except NotARun as exc:
        print(f"drop plot: {exc}", file=sys.stderr)
        return 2
    Path(args.out).write_bytes(overlay(curves, args.title))
    print(args.out)
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from .evaluation import evaluate
    from .export import load_policy

    result = evaluate(load_policy(args.policy), args.env, args.episodes, args.seed, args.env_version)
    print(json.dumps({"mean_return": result.mean_return, "std_return": result.std_return,
                      "normalized_score": result.normalized_score, "returns": result.returns}, indent=2))
    return 0


def cmd_collect(args: argparse.Namespace) -> int:
    """Train SAC online and write the D4RL kinds; SIGINT/SIGTERM stop at a step boundary with a checkpoint."""
    import signal
    import time

    import torch

    from .collect import DEFAULT_TRANSITIONS, KINDS, CollectConfig, collect_datasets, summary_table
    from .online import OnlineConfig

    if args.threads:
        torch.set_num_threads(args.threads)
    kinds = tuple(args.kinds.split(",")) if args.kinds else KINDS
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        print(f"drop collect: unknown kinds {', '.join(unknown)}; known: {', '.join(KINDS)}", file=sys.stderr)
        return 2
    try:
        online = OnlineConfig(env=args.env, version=args.env_version, seed=args.seed,
                              steps=args.steps,
                              warmup=args.warmup, eval_every=args.eval_every, eval_episodes=args.eval_episodes,
                              medium_return=args.medium_return)
    except (KeyError, ValueError) as exc:
        print(f"drop collect: {exc}", file=sys.stderr)
        return 2
    stop = {"asked": False}

    def ask_stop(signum, frame) -> None:
        stop["asked"] = True

    previous = {sig: signal.signal(sig, ask_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    started = time.time()
    try:
        config = CollectConfig(online, args.transitions or DEFAULT_TRANSITIONS, args.num_envs)
        rows = collect_datasets(config, args.out, kinds, not args.no_progress, should_stop=lambda: stop["asked"])
    except ValueError as exc:
        print(f"drop collect: {exc}", file=sys.stderr)
        return 2
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if rows is None:
        print(f"drop collect: stopped; run the same command again to resume from {args.out}", file=sys.stderr)
        return 130
    print(summary_table(rows))
    print(f"wall time: {time.time() - started:.0f} s this invocation; SAC training {rows[0]['train_seconds']:.0f} s "
          f"over all invocations, recording {rows[0]['record_seconds']:.0f} s")
    Path(args.out, f"{online.env}-summary.json").write_text(json.dumps(rows, indent=2))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="drop", description="DROP offline RL: engine and service")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("train", help="train a policy on a dataset file")
    p.add_argument("--dataset", required=True, help="D4RL-layout .hdf5 or .npz, or a Minari dataset's zip")
    p.add_argument("--env", default="hopper", help="hopper | walker2d | halfcheetah")
    p.add_argument("--algorithm", default="drop", choices=["drop", "mopo", "mbpo"])
    p.add_argument("--preset", default="cpu", choices=PRESETS)
    p.add_argument("--task", default=None, help="dataset kind (random, medium, ...) selecting the paper's settings")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--threads", type=int, default=None, help="torch intra-op threads")
    p.add_argument("--set", action="append", type=_parse_override, metavar="KEY=VALUE",
                   help="override any config field, e.g. --set dice.lr=1e-3 --set epochs=50")
    p.add_argument("--out", required=True, help="run directory (checkpoints, policy/last and policy/best, metrics.jsonl, "
                   "evaluations.csv, curve.png, summary.json); an existing one is resumed")
    p.add_argument("--model-cache", default=DEFAULT_MODEL_CACHE, metavar="DIR",
                   help="trained dynamics ensembles shared between runs, by dataset, dynamics config and seed "
                        f"(default {DEFAULT_MODEL_CACHE})")
    p.add_argument("--no-model-cache", action="store_true", help="always train the dynamics ensemble, store nothing")
    p.add_argument("--no-progress", action="store_true",
                   help="no progress output (default: a bar on a terminal, plain lines when stderr is a file or pipe)")
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("plot", help="overlay runs' learning curves: seeds as mean and band, algorithms as colours")
    p.add_argument("runs", nargs="+", metavar="RUN_DIR", help="run directories of drop train (or the paper table)")
    p.add_argument("--out", required=True, help="the PNG to write")
    p.add_argument("--title", default="", help="default: the envs")
    p.set_defaults(func=cmd_plot)

    p = sub.add_parser("evaluate", help="evaluate an exported policy in the real env")
    p.add_argument("--policy", required=True, help="policy.pt written by train (OUT/policy/last/ or OUT/policy/best/)")
    p.add_argument("--env", default="hopper")
    p.add_argument("--env-version", default="v4", choices=["v4", "v5"])
    p.add_argument("--episodes", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("collect", help="make D4RL-style datasets by training SAC online in the real env")
    p.add_argument("--env", default="hopper", help="hopper | walker2d | halfcheetah")
    p.add_argument("--out", required=True, help="output directory; an existing one is resumed")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--steps", type=int, default=None,
                   help="online SAC env steps, one update each (default: 120,000 for hopper, about 20 min on 2 idle "
                        "cores; 200,000 for walker2d and halfcheetah, about 40 min on one core)")
    p.add_argument("--transitions", type=int, default=None, help="rows recorded per behaviour policy (random, "
                   "medium, expert; medium-expert holds twice this; default 200,000)")
    p.add_argument("--kinds", default=None, help="comma-separated subset of random,medium,medium-replay,expert,"
                                                 "medium-expert (default all)")
    p.add_argument("--warmup", type=int, default=5000, help="uniform-random steps before SAC updates start")
    p.add_argument("--eval-every", type=int, default=5000, help="env steps between evaluations and checkpoints")
    p.add_argument("--eval-episodes", type=int, default=10)
    p.add_argument("--medium-return", type=float, default=None, help="medium threshold (default: expert return / 3)")
    p.add_argument("--env-version", default="v4", choices=["v4", "v5"])
    p.add_argument("--num-envs", type=int, default=8, help="envs stepped side by side while recording")
    p.add_argument("--threads", type=int, default=None, help="torch intra-op threads")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_collect)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
