"""The one `drop` command: every command under it, a version, and click's usage errors as exit status 2."""
from __future__ import annotations


def test_drop_gathers_every_command_and_has_a_version(capsys):
    from drop_cli import drop, main

    assert set(drop.commands) == {"train", "plot", "diagnose", "evaluate", "collect", "serve", "api", "worker",
                                  "token", "db", "datasets", "jobs"}
    assert set(drop.commands["jobs"].commands) == {"submit", "list", "status", "logs", "cancel", "rm", "download"}
    assert set(drop.commands["datasets"].commands) == {"upload", "list", "rm"}
    assert main(["--version"]) == 0 and capsys.readouterr().out.startswith("drop, version 0.")
    assert main(["train", "--dataset", "x.hdf5", "--out", "run", "--set", "epochs"]) == 2
    assert "'epochs' is not KEY=VALUE" in capsys.readouterr().err
    # A status the API does not know is a usage error here, not a round trip to the server.
    assert main(["jobs", "list", "--status", "runing", "--server", "http://127.0.0.1:9"]) == 2
    assert "'runing' is not one of" in capsys.readouterr().err

