"""Checkpoints are ordered by the epoch and step in their names, read as numbers, at any size."""
from drop_engine.checkpoint import list_checkpoints, load_latest, save_checkpoint


def test_epochs_past_six_digits_are_newest_and_pruned_in_order(tmp_path):
    for epoch, step in ((999_998, 0), (999_999, 0), (999_999, 1_234_567), (1_000_000, 0)):
        save_checkpoint({"epoch": epoch, "step": step}, tmp_path, epoch, step, keep=3)
    assert [p.name for p in list_checkpoints(tmp_path)] == [
        "ckpt-e999999-s000000.pt", "ckpt-e999999-s1234567.pt", "ckpt-e1000000-s000000.pt"]
    assert load_latest(tmp_path) == {"epoch": 1_000_000, "step": 0}


def test_other_files_are_ignored(tmp_path):
    save_checkpoint({"epoch": 2}, tmp_path, 2, 0, keep=2)
    for name in ("ckpt-e000003-s000000.pt.tmp", "ckpt-e3-s0.pt", "notes.txt"):
        (tmp_path / name).write_text("x")
    assert [p.name for p in list_checkpoints(tmp_path)] == ["ckpt-e000002-s000000.pt"]
