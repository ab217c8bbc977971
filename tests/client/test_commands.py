"""The one `drop` command, and the import boundaries that let the engine's commands and the client stand alone."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def test_drop_gathers_every_command_and_has_a_version(capsys):
    from drop_cli import drop, main

    assert set(drop.commands) == {"train", "plot", "evaluate", "collect", "serve", "api", "worker", "token", "db",
                                  "datasets", "jobs"}
    assert set(drop.commands["jobs"].commands) == {"submit", "list", "status", "logs", "cancel", "download"}
    assert set(drop.commands["datasets"].commands) == {"upload", "list", "rm"}
    assert main(["--version"]) == 0 and capsys.readouterr().out.startswith("drop, version 0.")
    assert main(["train", "--dataset", "x.hdf5", "--out", "run", "--set", "epochs"]) == 2
    assert "'epochs' is not KEY=VALUE" in capsys.readouterr().err


@pytest.mark.parametrize("module, forbidden", [
    ("drop_engine.cli", {"app", "worker", "drop_client", "drop_cli"}),
    ("drop_client", {"app", "worker", "drop_engine", "drop_cli"}),
])
def test_imports_point_one_way(module, forbidden):
    code = f"import sys, {module}; print(sorted({{m.split('.')[0] for m in sys.modules}} & {forbidden!r}))"
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
