"""The table's bookkeeping: the row without the average that a run with `sac.actor_average` holds, how records
merge, which a setting's table shows, and the code a record names."""
import importlib.util
import subprocess
from pathlib import Path

import pytest

spec = importlib.util.spec_from_file_location("paper_table", Path(__file__).parents[1] / "bench" / "paper_table.py")
paper_table = importlib.util.module_from_spec(spec)
spec.loader.exec_module(paper_table)

PLAIN = {"preset": "cpu", "set": [], "revision": 4}


def _record(algorithm="drop", live=True, dataset="abc", final=7.0):
    evaluations = [{"epoch": e, "step": 1000 * e, "return": 10.0 * e, "return_std": 1.0, "normalized_score": s}
                   | ({"live_return": 20.0 * e, "live_return_std": 2.0, "live_normalized_score": x} if live else {})
                   for e, s, x in ((10, 5.0, 9.0), (20, 6.0, 3.0), (30, 7.0, 4.0), (40, 8.0, 2.0))]
    return {"final": final, "best": 8.0, "best_epoch": 40, "evaluations": evaluations, "algorithm": algorithm,
            "env": "hopper", "kind": "medium", "seed": 0, "dataset": dataset}


def test_an_averaged_run_holds_the_plain_runs_record():
    plain, rest = paper_table.latest_iterate(_record(), ["sac.actor_average=0.0001"])
    assert rest == []
    assert plain["evaluations"][0] == {"epoch": 10, "step": 10_000, "return": 200.0, "return_std": 2.0,
                                       "normalized_score": 9.0}
    assert [e["normalized_score"] for e in plain["evaluations"]] == [9.0, 3.0, 4.0, 2.0]
    assert (plain["final"], plain["best"], plain["best_epoch"]) == (pytest.approx(3.0), 9.0, 10)
    assert plain["derived_from"] == ["sac.actor_average=0.0001"] and plain["dataset"] == "abc"


def test_an_averaged_ablation_holds_the_ablations_record():
    derived, rest = paper_table.latest_iterate(_record(), ["sac.actor_average=0.0001", "sac.value_bound=true"])
    assert rest == ["sac.value_bound=true"] and [e["normalized_score"] for e in derived["evaluations"]] == [9, 3, 4, 2]
    assert derived["derived_from"] == ["sac.actor_average=0.0001", "sac.value_bound=true"]


@pytest.mark.parametrize("record, overrides", [
    (_record(), ["sac.value_bound=true"]),
    (_record(), []),
    (_record(live=False), ["sac.actor_average=1"]),  # no average, so no latest iterate beside it
    ({**_record(algorithm="bc"), "evaluations": []}, ["sac.actor_average=0.0001"]),
])
def test_no_plain_record_from_other_settings(record, overrides):
    assert paper_table.latest_iterate(record, overrides) is None


def test_a_derived_record_never_replaces_a_recorded_run():
    measured = {**_record(final=1.0), "setting": PLAIN}
    derived, _ = paper_table.latest_iterate(_record(), ["sac.actor_average=0.0001"])
    assert paper_table.merge([measured], derived, PLAIN) == [measured]
    # where none is recorded on that file it goes in, and a run merged later replaces it (paper_table itself counts
    # the derived row as done, as it is that run's reproduction)
    other_file = {**_record(dataset="old", final=1.0), "setting": PLAIN}
    merged = paper_table.merge([other_file], derived, PLAIN)
    assert merged == [other_file, {**derived, "setting": PLAIN}]
    rerun = _record(final=5.0)
    assert paper_table.merge(merged, rerun, PLAIN) == [other_file, {**rerun, "setting": PLAIN}]


def test_a_run_replaces_only_its_own_files_record():
    old = {**_record(dataset="old", final=1.0), "setting": PLAIN}
    same = {**_record(final=2.0), "setting": PLAIN}
    ablation = {**_record(final=3.0), "setting": {**PLAIN, "set": ["sac.value_bound=true"]}}
    new = _record(final=4.0)
    assert paper_table.merge([old, same, ablation], new, PLAIN) == [old, ablation, {**new, "setting": PLAIN}]


def test_behaviour_cloning_is_shown_whichever_setting_ran_it():
    """A new revision or an ablation shows the clone's runs of any setting (it reads neither), the latest per key,
    and only its own model-based runs; a clone of another kind is not shown."""
    ablation = {**PLAIN, "set": ["sac.value_bound=true"]}
    older = {**_record(algorithm="bc", final=1.0), "bc": "likelihood-100000", "setting": {**PLAIN, "revision": 3}}
    latest = {**_record(algorithm="bc", final=2.0), "bc": "likelihood-100000", "setting": PLAIN}
    squared = {**_record(algorithm="bc", final=3.0), "bc": "squared-20000", "setting": ablation, "seed": 1}
    plain_drop = {**_record(final=4.0), "setting": PLAIN}
    ablation_drop = {**_record(final=5.0), "setting": ablation}
    records = [older, latest, squared, plain_drop, ablation_drop]
    assert paper_table.shown(records, ablation, "likelihood-100000") == [ablation_drop, latest]
    assert paper_table.shown(records, PLAIN, "likelihood-100000") == [plain_drop, latest]


def test_code_version_tells_uncommitted_engine_changes_apart(tmp_path):
    def git(*argv):
        subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *argv], cwd=tmp_path, check=True,
                       capture_output=True)

    engine = tmp_path / "drop_engine"
    engine.mkdir()
    (tmp_path / "bench" / "results").mkdir(parents=True)
    (engine / "sac.py").write_text("gamma = 0.99\n")
    git("init", "-q")
    git("add", ".")
    git("commit", "-qm", "base")
    clean = paper_table.code_version(tmp_path)
    assert len(clean["commit"]) == 40 and clean["changes"] is None

    (tmp_path / "bench" / "results" / "paper_table.json").write_text("{}")  # what the runs write is not code
    (tmp_path / "bench" / "results" / "notes.py").write_text("x = 1\n")
    assert paper_table.code_version(tmp_path) == clean
    (tmp_path / "bench" / "paper_table.py").write_text("REVISION = 5\n")
    script = paper_table.code_version(tmp_path)["changes"]
    assert script is not None
    (tmp_path / "bench" / "paper_table.py").unlink()

    (engine / "sac.py").write_text("gamma = 0.9\n")
    edited = paper_table.code_version(tmp_path)["changes"]
    (engine / "dice.py").write_text("lam = 1\n")
    with_new_file = paper_table.code_version(tmp_path)["changes"]
    (engine / "dice.py").write_text("lam = 2\n")
    assert len({None, script, edited, with_new_file, paper_table.code_version(tmp_path)["changes"]}) == 5


def test_code_version_outside_a_checkout_is_unknown(tmp_path):
    assert paper_table.code_version(tmp_path) == {"commit": None, "changes": None}


def test_a_file_of_another_machine_does_not_take_a_row_over():
    """Only a dataset whose table entry names another file, with runs on it, is displaced."""
    kept = {"behaviour": {"hopper-medium": {"score": 1.0, "dataset": "abc"}, "hopper-random": 2.0,
                          "walker2d-medium": {"score": 1.0, "dataset": "unused"}},
            "records": [{**_record(), "setting": PLAIN}]}
    local = {"hopper-medium": {"score": 1.5, "dataset": "def"}, "hopper-random": {"score": 2.0, "dataset": "x"},
             "walker2d-medium": {"score": 1.0, "dataset": "new"}, "halfcheetah-medium": {"score": 0, "dataset": "y"}}
    assert paper_table.displaced(kept, local) == [
        "hopper-medium: this file is def, the table's runs (1) were made on abc"]
    assert paper_table.displaced(kept, {**local, "hopper-medium": {"score": 1.0, "dataset": "abc"}}) == []
