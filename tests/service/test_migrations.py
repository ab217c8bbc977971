"""The service refuses an unmigrated database, and `drop db upgrade` fixes it (SQLite and PostgreSQL)."""
from __future__ import annotations

import subprocess
import sys

import pytest

from app.main import NotMigrated, create_app
from app.settings import Settings

from .conftest import REPO, settings_env


def test_unmigrated_database_is_refused_until_upgrade(tmp_path):
    settings = Settings(data_dir=tmp_path)
    with pytest.raises(NotMigrated, match="drop db upgrade"):
        create_app(settings)
    env = settings_env(settings)
    refused = subprocess.run([sys.executable, "-m", "app.cli", "api"], cwd=REPO, env=env, capture_output=True,
                             text=True, timeout=60)
    assert refused.returncode == 2 and "drop db upgrade" in refused.stderr
    done = subprocess.run([sys.executable, "-m", "app.cli", "db", "upgrade"], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert create_app(settings).state.settings is settings
    token = subprocess.run([sys.executable, "-m", "app.cli", "token", "create", "--name", "carol"], cwd=REPO,
                           env=env, capture_output=True, text=True, timeout=60)
    assert token.returncode == 0 and token.stdout.strip().startswith("drop_")
