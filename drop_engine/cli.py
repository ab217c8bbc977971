"""`drop` command line for the engine: train and evaluate. The service adds its own subcommands to this parser."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .config import PRESETS, ConfigError, build_config


def _parse_override(text: str) -> tuple[str, object]:
    """KEY=VALUE with VALUE parsed as JSON when it is JSON (numbers, lists, booleans), else kept as a string."""
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"override {text!r} is not KEY=VALUE")
    key, raw = text.split("=", 1)
    try:
        return key, json.loads(raw)
    except json.JSONDecodeError:
        return key, raw


def cmd_train(args: argparse.Namespace) -> int:
    from .callbacks import ProgressBar
    from .data import DatasetError
    from .trainer import train

    try:
        config = build_config(args.algorithm, args.env, args.preset, args.task, dict(args.set or []), args.seed, args.device)
        if args.threads:
            config.threads = args.threads
    except ConfigError as exc:
        print(f"drop train: {exc}", file=sys.stderr)
        return 2
    bar = ProgressBar()
    try:
        result = train(args.dataset, config, args.out, bar)
    except DatasetError as exc:
        print(f"drop train: {args.dataset}: {exc}", file=sys.stderr)
        return 2
    finally:
        bar.close()
    summary = result.to_dict()
    Path(args.out, "summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps({k: summary[k] for k in ("status", "epochs", "last_return", "last_score", "best_score", "policy",
                                              "timings")}, indent=2))
    return 0 if result.status == "completed" else 1


def cmd_evaluate(args: argparse.Namespace) -> int:
    from .evaluate import evaluate
    from .export import load_policy

    result = evaluate(load_policy(args.policy), args.env, args.episodes, args.seed, args.env_version)
    print(json.dumps({"mean_return": result.mean_return, "std_return": result.std_return,
                      "normalized_score": result.normalized_score, "returns": result.returns}, indent=2))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="drop", description="DROP offline RL: engine and service")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("train", help="train a policy on a dataset file")
    p.add_argument("--dataset", required=True, help="D4RL-layout .hdf5 or .npz")
    p.add_argument("--env", default="hopper", help="hopper | walker2d | halfcheetah")
    p.add_argument("--algorithm", default="drop", choices=["drop", "mopo", "mbpo"])
    p.add_argument("--preset", default="cpu", choices=PRESETS)
    p.add_argument("--task", default=None, help="dataset kind (random, medium, ...) selecting the paper's settings")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--threads", type=int, default=None, help="torch intra-op threads")
    p.add_argument("--set", action="append", type=_parse_override, metavar="KEY=VALUE",
                   help="override any config field, e.g. --set dice.lr=1e-3 --set epochs=50")
    p.add_argument("--out", required=True, help="run directory (checkpoints, policy); an existing one is resumed")
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("evaluate", help="evaluate an exported policy in the real env")
    p.add_argument("--policy", required=True, help="policy.pt written by train")
    p.add_argument("--env", default="hopper")
    p.add_argument("--env-version", default="v4", choices=["v4", "v5"])
    p.add_argument("--episodes", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_evaluate)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
