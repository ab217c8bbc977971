"""`drop`, the one command: the engine's (train, plot, diagnose, evaluate, collect), the service's (serve, api, worker,
token, db) and those that drive a server from anywhere (datasets, jobs). It sits above all three packages it gathers."""
from __future__ import annotations

import sys

import click

from app.cli import service
from drop_engine.cli import Group, engine, run

from .remote import datasets, jobs


@click.group(cls=Group)
@click.version_option(package_name="drop-rl", prog_name="drop")
def drop() -> None:
    """DROP offline RL: train and evaluate policies here, run the service, or use a server from anywhere."""


for command in [*engine.commands.values(), *service.commands.values(), datasets, jobs]:
    drop.add_command(command)


def main(argv: list[str] | None = None) -> int:
    try:
        return run(drop, argv)
    except ModuleNotFoundError as exc:  # a service command where only the library is installed
        print(f"drop: {exc.name} is not installed; the service's commands need `pip install 'drop-rl[service]'`",
              file=sys.stderr)
        return 2
