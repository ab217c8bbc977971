"""CLI runs get the service's curve: `drop train` writes curve.png and log-friendly progress, `drop plot` overlays
runs (seeds as mean and band, algorithms as colours)."""
import csv
import json

import numpy as np
import pytest

from drop_engine.cli import main
from drop_engine.data import save_hdf5
from drop_engine.plots import Curve, mean_and_std
from drop_engine.run_log import EVALUATION_FIELDS, read_curve

PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture
def data(tmp_path, hopper_arrays):
    path = tmp_path / "hopper.hdf5"
    save_hdf5(path, hopper_arrays, {"env_name": "Hopper-v4"})
    return path


def _train(data, out, *extra) -> int:
    return main(["train", "--dataset", str(data), "--env", "hopper", "--algorithm", "mopo", "--preset", "smoke",
                 "--set", "epochs=2", "--set", "eval_episodes=1", "--set", "eval_every=1", "--threads", "1",
                 "--no-model-cache", "--out", str(out), *extra])


def test_train_writes_curve_and_plain_progress_lines(tmp_path, data, capsys):
    assert _train(data, tmp_path / "run") == 0
    err = capsys.readouterr().err  # not a terminal here: lines, no bars
    assert "\r" not in err and "it/s" not in err
    assert "train: epoch 1" in err and "evaluation: epoch 2" in err
    assert (tmp_path / "run" / "curve.png").read_bytes().startswith(PNG)
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["config"]["algorithm"] == "mopo"
    curve = read_curve(tmp_path / "run")
    assert (curve.algorithm, curve.env, curve.seed, curve.epochs) == ("mopo", "hopper", 0, [1, 2])

    assert _train(data, tmp_path / "quiet", "--no-progress") == 0
    assert capsys.readouterr().err == ""


def _fake_run(folder, algorithm: str, seed: int, scores: list[float], where: str = "summary.json"):
    folder.mkdir(parents=True)
    with (folder / "evaluations.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, EVALUATION_FIELDS)
        writer.writeheader()
        writer.writerows({"epoch": i + 1, "mean_return": 0, "normalized_score": s, "time": 0}
                         for i, s in enumerate(scores))
    meta = folder / where
    meta.parent.mkdir(parents=True, exist_ok=True)
    meta.write_text(json.dumps({"config": {"algorithm": algorithm, "env": "hopper", "seed": seed}}))
    return folder


def test_plot_overlays_seeds_and_algorithms(tmp_path, capsys):
    runs = [_fake_run(tmp_path / f"drop-{s}", "drop", s, [10.0 * s, 20.0 * s, 30.0]) for s in (1, 2, 3)]
    runs.append(_fake_run(tmp_path / "mopo-0", "mopo", 0, [5.0, 6.0], where="policy/last/metadata.json"))
    out = tmp_path / "overlay.png"
    assert main(["plot", *map(str, runs), "--out", str(out)]) == 0
    assert out.read_bytes().startswith(PNG) and capsys.readouterr().out.strip() == str(out)

    epochs, mean, std = mean_and_std([read_curve(r) for r in runs[:3]])
    assert epochs.tolist() == [1, 2, 3]
    np.testing.assert_allclose(mean, [20.0, 40.0, 30.0])
    np.testing.assert_allclose(std, [np.std([10, 20, 30]), np.std([20, 40, 60]), 0.0])
    assert read_curve(runs[3]).algorithm == "mopo"  # config from the exported policy's metadata


def test_mean_and_std_over_seeds_of_different_lengths():
    epochs, mean, std = mean_and_std([Curve("drop", "hopper", 0, [1, 2], [1.0, 3.0]),
                                      Curve("drop", "hopper", 1, [1], [3.0])])
    assert epochs.tolist() == [1, 2] and mean.tolist() == [2.0, 3.0] and std.tolist() == [1.0, 0.0]


def test_plot_refuses_a_folder_that_is_not_a_run(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert main(["plot", str(tmp_path / "empty"), "--out", str(tmp_path / "x.png")]) == 2
    assert "no evaluations.csv" in capsys.readouterr().err and not (tmp_path / "x.png").exists()


def test_progress_is_a_bar_only_on_a_terminal():
    import io

    from drop_engine.callbacks import Callback, ProgressBar, ProgressLine, progress_reporter

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    assert isinstance(progress_reporter(True, Terminal()), ProgressBar)
    assert isinstance(progress_reporter(True, io.StringIO()), ProgressLine)
    assert type(progress_reporter(False, Terminal())) is Callback

    lines = io.StringIO()
    line = ProgressLine(lines)
    line.on_progress("dynamics", 0, 7, 0)  # a fit without an epoch cap (the paper preset): no total to show
    line.on_progress("dynamics", 0, 3, 60)
    line.on_progress("train", 1, 500, 1000)
    assert lines.getvalue().splitlines() == ["dynamics: 7", "train: epoch 1, step 500/1000 (50.0%)"]


def test_diagnose_averages_metrics_by_blocks_of_epochs(tmp_path, capsys):
    run = _fake_run(tmp_path / "drop-0", "drop", 0, [1.0])
    config = json.loads((run / "summary.json").read_text())
    config["config"]["steps_per_epoch"] = 10
    (run / "summary.json").write_text(json.dumps(config))
    lines = [{"step": 0, "time": 0, "dice/tau_data_mean": 100.0},  # pretraining: left out
             {"step": 10, "time": 0, "dice/tau_data_mean": 0.5, "sac/q_data": 1.0},  # epoch 1
             {"step": 20, "time": 0, "dice/tau_data_mean": 1.5, "sac/q_data": float("nan")},  # epoch 2
             {"step": 21, "time": 0, "dice/tau_data_mean": 0.25}]  # epoch 3
    (run / "metrics.jsonl").write_text("".join(json.dumps(m) + "\n" for m in lines))

    assert main(["diagnose", str(run), "--every", "2"]) == 0
    out = capsys.readouterr().out
    assert "| metric (mean by epochs) | 1-2 | 3-4 |" in out
    assert "| dice/tau_data_mean | 1 | 0.25 |" in out
    assert "| sac/q_data | 1 | - |" in out  # a NaN is not a value
    assert "sac/alpha" not in out  # never reported: no row

    assert main(["diagnose", str(run), "--key", "sac/q_data", "--every", "1"]) == 0
    assert "| sac/q_data | 1 | - | - |" in capsys.readouterr().out
    (tmp_path / "empty").mkdir()
    assert main(["diagnose", str(tmp_path / "empty")]) == 2
    assert "no metrics.jsonl" in capsys.readouterr().err
