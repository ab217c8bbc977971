"""The table's derived row: a run with only `sac.actor_average` set also yields the plain setting's record."""
import importlib.util
from pathlib import Path

import pytest

spec = importlib.util.spec_from_file_location("paper_table", Path(__file__).parents[1] / "bench" / "paper_table.py")
paper_table = importlib.util.module_from_spec(spec)
spec.loader.exec_module(paper_table)


def _record(algorithm="drop"):
    evaluations = [{"epoch": e, "step": 1000 * e, "return": 10.0 * e, "return_std": 1.0, "normalized_score": s,
                    "live_return": 20.0 * e, "live_normalized_score": live}
                   for e, s, live in ((10, 5.0, 9.0), (20, 6.0, 3.0), (30, 7.0, 4.0), (40, 8.0, 2.0))]
    return {"final": 7.0, "best": 8.0, "best_epoch": 40, "evaluations": evaluations, "algorithm": algorithm,
            "env": "hopper", "kind": "medium", "seed": 0, "dataset": "abc"}


def test_an_averaged_run_holds_the_plain_runs_record():
    plain = paper_table.latest_iterate(_record(), ["sac.actor_average=0.0001"])
    assert [e["normalized_score"] for e in plain["evaluations"]] == [9.0, 3.0, 4.0, 2.0]
    assert [e["return"] for e in plain["evaluations"]] == [200.0, 400.0, 600.0, 800.0]
    assert not any(k.startswith("live_") for e in plain["evaluations"] for k in e)
    assert (plain["final"], plain["best"], plain["best_epoch"]) == (pytest.approx(3.0), 9.0, 10)
    assert plain["derived_from"] == ["sac.actor_average=0.0001"] and plain["dataset"] == "abc"


@pytest.mark.parametrize("algorithm, overrides", [
    ("drop", ["sac.actor_average=0.0001", "sac.value_bound=true"]),  # another change: not the plain run
    ("drop", ["sac.value_bound=true"]),
    ("drop", []),
    ("bc", ["sac.actor_average=0.0001"]),
])
def test_no_plain_record_from_other_settings(algorithm, overrides):
    assert paper_table.latest_iterate(_record(algorithm), overrides) is None
