"""`drop train` and `drop evaluate` as a newcomer runs them."""
import json

import torch

from drop_engine.cli import main
from drop_engine.data import save_hdf5


def test_train_then_evaluate(tmp_path, hopper_arrays, capsys, monkeypatch):
    data = tmp_path / "hopper.hdf5"
    save_hdf5(data, hopper_arrays, {"env_name": "Hopper-v5"})  # a Minari-era dataset: trained and evaluated in v5
    monkeypatch.setenv("HOME", str(tmp_path / "home"))  # the default model cache lives there

    def train(out: str, *cache: str) -> dict:
        code = main(["train", "--dataset", str(data), "--env", "hopper", "--algorithm", "mopo", "--preset", "smoke",
                     "--set", "epochs=1", "--set", "eval_episodes=1", "--threads", "1", "--out", str(tmp_path / out),
                     *cache])
        assert code == 0
        return json.loads(capsys.readouterr().out)

    printed = train("run")
    assert printed["status"] == "completed" and printed["epochs"] == 1 and printed["dynamics_from_cache"] is False
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["evaluations"][0]["epoch"] == 1
    # What else made its numbers: the same seed sums in another order at another thread count or on another CPU kind.
    assert summary["machine"]["threads"] == 1 and summary["machine"]["torch"] == torch.__version__
    assert summary["machine"]["cpu"].endswith(f" ({torch.backends.cpu.get_cpu_capability()})")
    assert summary["dynamics"]["cache_path"].startswith(str(tmp_path / "home" / ".cache" / "drop-rl" / "models"))
    assert train("again")["dynamics_from_cache"] is True
    assert train("elsewhere", "--model-cache", str(tmp_path / "models"))["dynamics_from_cache"] is False
    assert train("uncached", "--no-model-cache")["dynamics_from_cache"] is False
    assert json.loads((tmp_path / "uncached" / "summary.json").read_text())["dynamics"]["cache_path"] is None
    # One evaluation: the best policy is the last one, and every score is that evaluation's.
    assert printed["best_epoch"] == 1 and printed["last_score"] == printed["best_score"] == printed["final_score"]
    for which in ("last", "best"):
        assert printed["policy"][which]["torchscript"] == str(tmp_path / "run" / "policy" / which / "policy.pt")
    assert (tmp_path / "run" / "metrics.jsonl").stat().st_size and (tmp_path / "run" / "evaluations.csv").exists()

    # The env and its version come from the policy's metadata unless given.
    assert main(["evaluate", "--policy", printed["policy"]["best"]["torchscript"], "--episodes", "2"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert len(result["returns"]) == 2 and result["normalized_score"] < 100
    assert (result["env"], result["env_version"]) == ("hopper", "v5")
    assert main(["evaluate", "--policy", printed["policy"]["best"]["torchscript"], "--env-version", "v4",
                 "--episodes", "1"]) == 0
    assert json.loads(capsys.readouterr().out)["env_version"] == "v4"


def test_train_rejects_bad_input(tmp_path, capsys):
    bad = tmp_path / "bad.hdf5"
    save_hdf5(bad, {"observations": [[0.0] * 11] * 3, "actions": [[0.0] * 3] * 2, "rewards": [0.0] * 3,
                    "terminals": [0, 0, 0]})
    assert main(["train", "--dataset", str(bad), "--preset", "smoke", "--out", str(tmp_path / "r")]) == 2
    assert "actions: has 2 rows but observations has 3" in capsys.readouterr().err
    assert main(["train", "--dataset", str(bad), "--set", "dice.rate=1", "--out", str(tmp_path / "r")]) == 2
    assert "dice.rate" in capsys.readouterr().err


def test_onnx_copy_matches_torchscript(tmp_path, hopper_dataset):
    import numpy as np
    import onnxruntime
    import torch

    from drop_engine.config import build_config
    from drop_engine.export import export_onnx, load_policy
    from drop_engine.trainer import train

    config = build_config("mbpo", env="hopper", preset="smoke", overrides={"epochs": 1})
    result = train(hopper_dataset, config, tmp_path)
    onnx_path = export_onnx(result.policy["last"]["torchscript"], 11, tmp_path / "policy.onnx")
    obs = hopper_dataset.observations[:7]
    session = onnxruntime.InferenceSession(str(onnx_path))
    (onnx_act,) = session.run(None, {"obs": obs})
    np.testing.assert_allclose(onnx_act, load_policy(result.policy["last"]["torchscript"])(obs), atol=1e-5)
    assert not torch.equal(torch.as_tensor(onnx_act[0]), torch.as_tensor(onnx_act[1]))
