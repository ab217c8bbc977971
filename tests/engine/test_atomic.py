"""Write-then-rename: a file that is read back is either the old one or the new one, never half of either."""
import errno
from pathlib import Path

import pytest
import torch

from drop_engine.atomic import save_durably, write_text


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path, monkeypatch):
    path = tmp_path / "summary.json"
    write_text(path, '{"old": 1}')
    real = Path.write_text

    def disk_full(self, text, *args, **kwargs):
        real(self, text[: len(text) // 2])  # half of it reached the disk
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Path, "write_text", disk_full)
    with pytest.raises(OSError, match="No space"):
        write_text(path, '{"new": 2, "padding": "' + "x" * 100 + '"}')
    monkeypatch.undo()
    assert path.read_text() == '{"old": 1}'
    assert [p.name for p in tmp_path.iterdir()] == ["summary.json"]


def test_save_durably_makes_its_directory(tmp_path):
    path = tmp_path / "new" / "dir" / "state.pt"
    save_durably({"step": 3}, path)
    assert torch.load(path) == {"step": 3}
    assert sorted(p.name for p in path.parent.iterdir()) == ["state.pt"]
