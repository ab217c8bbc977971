"""The service refuses an unmigrated database, and `drop db upgrade` fixes it."""
from __future__ import annotations

import pytest

from app.cli import main
from app.main import NotMigrated, create_app
from app.settings import Settings


def test_unmigrated_database_is_refused_until_upgrade(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("DROP_DATA_DIR", str(tmp_path))
    settings = Settings()
    with pytest.raises(NotMigrated, match="drop db upgrade"):
        create_app(settings)
    assert main(["api"]) == 2 and "drop db upgrade" in capsys.readouterr().err
    assert main(["worker"]) == 2 and "drop db upgrade" in capsys.readouterr().err
    assert main(["db", "upgrade"]) == 0
    assert create_app(settings).state.settings is settings
    assert main(["token", "create", "--name", "carol"]) == 0
    token = capsys.readouterr().out.strip().splitlines()[-1]
    assert token.startswith("drop_") and len(token) > 40
