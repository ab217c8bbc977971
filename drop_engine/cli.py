"""The engine's commands: train, plot, diagnose, evaluate, collect. A click group that needs nothing above the
engine; the `drop` command (drop_cli) adds the service's and the remote commands to these."""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import get_args

import click

from .atomic import write_text
from .collect_config import KINDS, CollectConfig, OnlineConfig
from .config import PRESETS, TASKS, Algorithm, build_config, override_dict, parse_override
from .envs import DEFAULT_VERSION, VERSIONS
from .errors import ConfigError
from .policy_files import FILE_NAMES

DEFAULT_MODEL_CACHE = "~/.cache/drop-rl/models"
ENV_VERSIONS = click.Choice(VERSIONS)


class _Command(click.Command):
    """A command whose function returns its exit code (None or 0: success)."""

    def invoke(self, ctx: click.Context):
        code = super().invoke(ctx)
        if code:
            ctx.exit(code)
        return code


class Group(click.Group):
    """A group whose commands return their exit codes, and which, as argparse did, also takes -h for help; its
    subgroups are of this class too."""

    command_class = _Command
    group_class = type

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("context_settings", {"help_option_names": ["-h", "--help"]})
        super().__init__(*args, **kwargs)


def run(group: click.Group, argv: list[str] | None = None) -> int:
    """Run `group` as the `drop` command on `argv` (default: the process's arguments) and return its exit code, which
    click would otherwise pass to sys.exit."""
    try:
        group.main(args=argv, prog_name="drop")
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0


class Override(click.ParamType):
    """A config override on the command line, read by `parse_override`."""

    name = "KEY=VALUE"

    def convert(self, value, param, ctx) -> tuple[str, object]:
        if isinstance(value, tuple):
            return value
        try:
            return parse_override(value)
        except ConfigError as exc:
            self.fail(str(exc), param, ctx)


def write_curve(run_dir: Path) -> Path:
    """`curve.png` beside the run's evaluations.csv: the figure the API serves for a job."""
    from .plots import learning_curve
    from .run_log import RunLog

    rows = RunLog.read_evaluations(run_dir / "evaluations.csv")
    path = run_dir / "curve.png"
    path.write_bytes(learning_curve(run_dir.name, [int(r["epoch"]) for r in rows],
                                    [float(r["normalized_score"]) for r in rows]))
    return path


@click.group(cls=Group)
@click.version_option(package_name="drop-rl", prog_name="drop")
def engine() -> None:
    """DROP offline RL: train, evaluate and plot policies, and make datasets."""


@engine.command()
@click.option("--dataset", required=True, help="D4RL-layout .hdf5 or .npz, or a Minari dataset's zip")
@click.option("--env", default="hopper", show_default=True, help="hopper | walker2d | halfcheetah")
@click.option("--algorithm", default="drop", show_default=True, type=click.Choice(get_args(Algorithm)))
@click.option("--preset", default="cpu", show_default=True, type=click.Choice(PRESETS))
@click.option("--task", default=None, type=click.Choice(TASKS),
              help="dataset kind selecting the paper's settings (default: medium's)")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--device", default="cpu", show_default=True, help="cpu or cuda")
@click.option("--threads", type=int, default=None, help="torch intra-op threads")
@click.option("--set", "overrides", multiple=True, type=Override(),
              help="override any config field, e.g. --set dice.lr=1e-3 --set epochs=50")
@click.option("--out", required=True, help="run directory (checkpoints, policy/last and policy/best, metrics.jsonl, "
              "evaluations.csv, curve.png, summary.json); an existing one is resumed")
@click.option("--model-cache", default=DEFAULT_MODEL_CACHE, show_default=True, metavar="DIR",
              help="trained dynamics ensembles shared between runs, by dataset, dynamics config and seed")
@click.option("--no-model-cache", is_flag=True, help="always train the dynamics ensemble, store nothing")
@click.option("--no-progress", is_flag=True,
              help="no progress output (default: a bar on a terminal, plain lines when stderr is a file or pipe)")
def train(dataset: str, env: str, algorithm: str, preset: str, task: str | None, seed: int, device: str,
          threads: int | None, overrides: tuple[tuple[str, object], ...], out: str, model_cache: str,
          no_model_cache: bool, no_progress: bool) -> int:
    """Train a policy on a dataset file."""
    from .callbacks import CallbackList, progress_reporter
    from .errors import DatasetError
    from .run_log import RunLog
    from .trainer import train as run_training

    try:
        fields = override_dict(overrides)
        if threads:
            fields["threads"] = threads
        config = build_config(algorithm, env=env, preset=preset, task=task, overrides=fields, seed=seed,
                              device=device)
    except ConfigError as exc:
        print(f"drop train: {exc}", file=sys.stderr)
        return 2
    progress = progress_reporter(not no_progress, sys.stderr)
    try:
        callback = CallbackList(progress, RunLog(out, config.steps_per_epoch))
        result = run_training(dataset, config, out, callback, None if no_model_cache else model_cache)
    except DatasetError as exc:
        print(f"drop train: {dataset}: {exc}", file=sys.stderr)
        return 2
    finally:
        getattr(progress, "close", lambda: None)()
    summary = result.to_dict()
    write_text(Path(out, "summary.json"), json.dumps({**summary, "config": config.model_dump(mode="json")}, indent=2))
    write_curve(Path(out))
    keys = ("status", "epochs", "last_return", "last_score", "best_score", "best_epoch", "final_score", "policy",
            "timings")
    shown = {k: summary[k] for k in keys}
    if summary["dynamics"]:
        shown["dynamics_from_cache"] = summary["dynamics"]["from_cache"]
    print(json.dumps(shown, indent=2))
    return 0 if result.status == "completed" else 1


@engine.command()
@click.argument("runs", nargs=-1, required=True, metavar="RUN_DIR...")
@click.option("--out", required=True, help="the PNG to write")
@click.option("--title", default="", help="default: the envs")
def plot(runs: tuple[str, ...], out: str, title: str) -> int:
    """Overlay runs' learning curves. Seeds are drawn as mean and band, algorithms as colours; RUN_DIR: run
    directories of drop train (or the paper table)."""
    from .plots import overlay
    from .run_log import NotARun, read_curve

    try:
        curves = [read_curve(run) for run in runs]
    except NotARun as exc:
        print(f"drop plot: {exc}", file=sys.stderr)
        return 2
    Path(out).write_bytes(overlay(curves, title))
    print(out)
    return 0


@engine.command()
@click.argument("runs", nargs=-1, required=True, metavar="RUN_DIR...")
@click.option("--every", type=click.IntRange(1), default=10, show_default=True, help="epochs per column")
@click.option("--key", "keys", multiple=True, help="a metric of metrics.jsonl (repeatable; default: the diagnostics "
              "of tau, the penalty, Q on data and model rows, the behaviour term, alpha, entropy, model rewards)")
def diagnose(runs: tuple[str, ...], every: int, keys: tuple[str, ...]) -> int:
    """Print each run's diagnostics as a markdown table: the mean of each metric over blocks of epochs."""
    from .run_log import NotARun
    from .run_summary import DEFAULT_KEYS, diagnostics_markdown

    try:
        tables = [f"{run}\n\n{diagnostics_markdown(run, every, keys or DEFAULT_KEYS)}" for run in runs]
    except NotARun as exc:
        print(f"drop diagnose: {exc}", file=sys.stderr)
        return 2
    print("\n\n".join(tables))
    return 0


@engine.command()
@click.option("--policy", required=True, help="policy.pt written by train (OUT/policy/last/ or OUT/policy/best/)")
@click.option("--env", default=None, help="default: the env in metadata.json beside the policy, else hopper")
@click.option("--env-version", default=None, type=ENV_VERSIONS,
              help="default: the version of the gym id in metadata.json beside the policy, else v4")
@click.option("--episodes", type=int, default=10, show_default=True)
@click.option("--seed", type=int, default=0, show_default=True)
def evaluate(policy: str, env: str | None, env_version: str | None, episodes: int, seed: int) -> int:
    """Evaluate an exported policy in the real env it was trained for."""
    from .envs import gym_version
    from .evaluation import evaluate as run_episodes
    from .export import load_policy

    meta_path = Path(policy).with_name(FILE_NAMES["metadata"])
    meta = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
    env = env or meta.get("env") or "hopper"
    env_version = env_version or gym_version(meta.get("gym_id", "")) or DEFAULT_VERSION
    result = run_episodes(load_policy(policy), env, episodes, seed, env_version)
    print(json.dumps({"env": env, "env_version": env_version, "mean_return": result.mean_return,
                      "std_return": result.std_return, "normalized_score": result.normalized_score,
                      "returns": result.returns}, indent=2))
    return 0


@engine.command()
@click.option("--env", default="hopper", show_default=True, help="hopper | walker2d | halfcheetah")
@click.option("--out", required=True, help="output directory; an existing one is resumed")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--steps", type=int, default=None,
              help="online SAC env steps, one update each (default: 200,000; measured times in the README)")
@click.option("--transitions", type=int, default=CollectConfig.transitions, show_default=True,
              help="rows recorded per behaviour policy (random, medium, expert; medium-expert holds twice this)")
@click.option("--kinds", default=None,
              help=f"comma-separated subset of {','.join(KINDS)} (default all); "
                   "random alone needs no online training; without expert or medium-expert, training stops at "
                   "the medium policy")
@click.option("--warmup", type=int, default=OnlineConfig.warmup, show_default=True,
              help="uniform-random steps before SAC updates start")
@click.option("--eval-every", type=int, default=OnlineConfig.eval_every, show_default=True,
              help="env steps between evaluations and checkpoints")
@click.option("--eval-episodes", type=int, default=OnlineConfig.eval_episodes, show_default=True)
@click.option("--medium-return", type=float, default=None, help="medium threshold (default: expert return / 3)")
@click.option("--env-version", default=DEFAULT_VERSION, show_default=True, type=ENV_VERSIONS)
@click.option("--num-envs", type=int, default=CollectConfig.num_envs, show_default=True,
              help="envs stepped side by side while recording")
@click.option("--threads", type=click.IntRange(min=1), default=1, show_default=True,
              help="torch intra-op threads; part of what makes the files: the same seed at another thread count sums "
                   "in another order and, over 100,000s of online steps, makes other datasets (bench/QUALITY.md E22)")
@click.option("--no-progress", is_flag=True, help="no progress bars")
def collect(env: str, out: str, seed: int, steps: int | None, transitions: int, kinds: str | None,
            warmup: int, eval_every: int, eval_episodes: int, medium_return: float | None, env_version: str,
            num_envs: int, threads: int, no_progress: bool) -> int:
    """Make D4RL-style datasets by training SAC online in the real env. SIGINT or SIGTERM stop it at a step boundary
    with a checkpoint."""
    import signal
    import time

    import torch

    from .collect import collect_datasets, summary_table
    from .file_lock import Busy

    torch.set_num_threads(threads)
    chosen = tuple(kinds.split(",")) if kinds else KINDS
    unknown = [k for k in chosen if k not in KINDS]
    if unknown:
        print(f"drop collect: unknown kinds {', '.join(unknown)}; known: {', '.join(KINDS)}", file=sys.stderr)
        return 2
    try:
        online = OnlineConfig(env=env, version=env_version, seed=seed, steps=steps, warmup=warmup,
                              eval_every=eval_every, eval_episodes=eval_episodes, medium_return=medium_return)
    except (KeyError, ValueError) as exc:
        print(f"drop collect: {exc}", file=sys.stderr)
        return 2
    stop = {"asked": False}

    def ask_stop(signum, frame) -> None:
        stop["asked"] = True

    previous = {sig: signal.signal(sig, ask_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    started = time.time()
    try:
        config = CollectConfig(online, transitions, num_envs)
        rows = collect_datasets(config, out, chosen, not no_progress, should_stop=lambda: stop["asked"])
    except ValueError as exc:
        print(f"drop collect: {exc}", file=sys.stderr)
        return 2
    except Busy as exc:
        print(f"drop collect: {exc}", file=sys.stderr)
        return 75  # EX_TEMPFAIL: the same command succeeds once the other collection ends
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if rows is None:
        print(f"drop collect: stopped; run the same command again to resume from {out}", file=sys.stderr)
        return 130
    print(summary_table(rows))
    print(f"wall time: {time.time() - started:.0f} s this invocation; SAC training {rows[0]['train_seconds']:.0f} s "
          f"over all invocations, recording {rows[0]['record_seconds']:.0f} s")
    write_text(Path(out, f"{online.env}-summary.json"), json.dumps(rows, indent=2))
    return 0


def main(argv: list[str] | None = None) -> int:
    return run(engine, argv)


if __name__ == "__main__":
    sys.exit(main())
