"""The table's bookkeeping: the row without the average that a run with `sac.actor_average` holds, how records
merge, which a setting's table shows (by the config its runs had), and the code a record names."""
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

spec = importlib.util.spec_from_file_location("paper_table", Path(__file__).parents[1] / "bench" / "paper_table.py")
paper_table = importlib.util.module_from_spec(spec)
spec.loader.exec_module(paper_table)

PLAIN = {"preset": "cpu", "set": [], "revision": 4}
# an ablation no preset turns on, so that these tests hold across preset revisions
BOUND = {**PLAIN, "set": ["sac.critic_layer_norm=true"]}


def _record(algorithm="drop", live=True, dataset="abc", final=7.0, setting=PLAIN):
    """A run as run_one records it: a model-based run carries the config its setting resolves to."""
    evaluations = [{"epoch": e, "step": 1000 * e, "return": 10.0 * e, "return_std": 1.0, "normalized_score": s}
                   | ({"live_return": 20.0 * e, "live_return_std": 2.0, "live_normalized_score": x} if live else {})
                   for e, s, x in ((10, 5.0, 9.0), (20, 6.0, 3.0), (30, 7.0, 4.0), (40, 8.0, 2.0))]
    config = {} if algorithm == "bc" else {"config": paper_table.setting_config(setting)("hopper", "medium", algorithm)}
    return {"final": final, "best": 8.0, "best_epoch": 40, "evaluations": evaluations, "algorithm": algorithm,
            "env": "hopper", "kind": "medium", "seed": 0, "dataset": dataset, **config}


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


def test_a_run_replaces_only_its_own_files_record_of_its_config():
    old = {**_record(dataset="old", final=1.0), "setting": PLAIN}
    same = {**_record(final=2.0), "setting": PLAIN}
    ablation = {**_record(final=3.0, setting=BOUND), "setting": BOUND}
    new = _record(final=4.0)
    assert paper_table.merge([old, same, ablation], new, PLAIN) == [old, ablation, {**new, "setting": PLAIN}]
    # another setting that resolves to the same config ran the same run: its record is the one replaced
    revision_5 = {**PLAIN, "revision": 5}
    assert paper_table.merge([old, same, ablation], new, revision_5) == [old, ablation, {**new, "setting": revision_5}]


def test_behaviour_cloning_is_shown_whichever_setting_ran_it():
    """A new revision or an ablation shows the clone's runs of any setting (it reads neither), the latest per key,
    and only the model-based runs of its configs; a clone of another kind is not shown."""
    older = {**_record(algorithm="bc", final=1.0), "bc": "likelihood-100000", "setting": {**PLAIN, "revision": 3}}
    latest = {**_record(algorithm="bc", final=2.0), "bc": "likelihood-100000", "setting": PLAIN}
    squared = {**_record(algorithm="bc", final=3.0), "bc": "squared-20000", "setting": BOUND, "seed": 1}
    plain_drop = {**_record(final=4.0), "setting": PLAIN}
    ablation_drop = {**_record(final=5.0, setting=BOUND), "setting": BOUND}
    records = [older, latest, squared, plain_drop, ablation_drop]
    assert paper_table.shown(records, paper_table.setting_config(BOUND), "likelihood-100000") == [ablation_drop, latest]
    assert paper_table.shown(records, paper_table.setting_config(PLAIN), "likelihood-100000") == [plain_drop, latest]


def test_a_setting_shows_the_runs_of_its_config_whichever_setting_recorded_them():
    """A revision whose preset turns the value bound on shows the runs an ablation made with it under the revision
    before (and not that revision's plain runs); a run whose record has no config (before configs were recorded) is
    shown by no setting."""
    ablation_drop = {**_record(final=5.0, setting=BOUND), "setting": BOUND}
    plain_drop = {**_record(final=4.0, dataset="other"), "setting": PLAIN}
    unknown = {key: value for key, value in _record(final=3.0, dataset="third").items() if key != "config"}
    records = [ablation_drop, plain_drop, {**unknown, "setting": PLAIN}]

    def revision_5(env, kind, algorithm):  # its preset resolves to the ablation's config
        return paper_table.setting_config(BOUND)(env, kind, algorithm)

    assert paper_table.shown(records, revision_5, "likelihood-100000") == [ablation_drop]
    text = paper_table.carried([ablation_drop], {**PLAIN, "revision": 5})
    assert "1 of these model-based runs" in text and "revision 4 with sac.critic_layer_norm=true" in text
    assert paper_table.carried([ablation_drop], BOUND) == ""


def test_a_recorded_run_is_shown_before_the_run_derived_from_it():
    measured = {**_record(final=1.0), "setting": PLAIN}
    derived, _ = paper_table.latest_iterate(_record(setting={**PLAIN, "set": ["sac.actor_average=0.0001"]}),
                                            ["sac.actor_average=0.0001"])
    assert derived["config"] == measured["config"]  # the averaged run trained as the plain one
    for records in ([measured, {**derived, "setting": PLAIN}], [{**derived, "setting": PLAIN}, measured]):
        assert paper_table.shown(records, paper_table.setting_config(PLAIN), "bc") == [measured]


@pytest.mark.parametrize("change, matches", [
    ({}, True),
    ({"sac.critic_layer_norm": True}, False),
    ({"drop": "sac.actor_average"}, True),  # a field added since, at its default
    ({"drop": "sac.critic_layer_norm", "wanted": {"sac.critic_layer_norm": True}}, False),  # added, not at default
    ({"sac.removed_option": 1}, False),  # a field the engine no longer has
    ({"semantics": 0}, False),  # an option meant something else then
    ({"drop": "semantics"}, False),  # a record of before semantics were recorded
])
def test_same_config(change, matches):
    wanted = paper_table.setting_config(PLAIN)("hopper", "medium", "drop")
    stored = {k: v for k, v in wanted.items() if k != change.get("drop")}
    stored.update({k: v for k, v in change.items() if k not in ("drop", "wanted")})
    assert paper_table.same_config(stored, {**wanted, **change.get("wanted", {})}) is matches
    assert paper_table.same_config(None, wanted) is False


def test_a_config_leaves_out_only_speed_and_disk():
    base = paper_table.identity(paper_table.build_config("drop", env="hopper", task="medium"))
    for overrides in ({"threads": 4}, {"keep_checkpoints": 5}):
        assert paper_table.identity(paper_table.build_config("drop", env="hopper", task="medium", seed=3,
                                                             overrides=overrides)) == base
    assert paper_table.identity(paper_table.build_config("drop", env="hopper", task="medium",
                                                         overrides={"log_every": 100})) != base
    assert base["penalty.eta"] == 5.0 and base["semantics"] == paper_table.SEMANTICS and "seed" not in base


def test_a_finished_run_directory_of_another_config_is_refused(tmp_path):
    cfg = paper_table.build_config("drop", env="hopper", task="medium")
    done = tmp_path / "result.json"
    done.write_text('{"final": 1.0}')  # finished before configs were recorded: the directory's setting ran it
    assert paper_table.finished(done, cfg)["config"] == paper_table.identity(cfg)
    assert paper_table.finished(done, None) == {"final": 1.0}  # behaviour cloning has no config
    done.write_text(json.dumps({"final": 1.0, "config": paper_table.identity(cfg)}))
    assert paper_table.finished(done, cfg)["final"] == 1.0
    with pytest.raises(SystemExit, match="without a revision bump"):
        paper_table.finished(done, paper_table.build_config("drop", env="hopper", task="medium",
                                                            overrides={"sac.critic_layer_norm": True}))


def test_the_report_shows_each_row_by_the_settings_configs(tmp_path, capsys):
    """`--report` end to end on a file: the plain table shows its runs and the clone's; the ablation's table shows
    only the runs of its config, under its own name, and not the plain rows it has no run on."""
    records = [
        {**_record(final=4.0), "setting": PLAIN},
        {**_record(algorithm="mbpo", final=6.0), "setting": PLAIN},
        {**_record(final=5.0, setting=BOUND), "setting": BOUND},
        {**_record(algorithm="bc", final=2.0), "best": 2.0, "bc": "likelihood-100000", "setting": PLAIN},
        {**_record(final=9.0), "kind": "random", "setting": PLAIN,
         "config": paper_table.setting_config(PLAIN)("hopper", "random", "drop")},
        # a run of the ablation's from before configs were recorded: it shows nowhere, and makes no row
        {**{k: v for k, v in _record(final=8.0).items() if k != "config"}, "kind": "random", "setting": BOUND},
    ]
    (tmp_path / "paper_table.json").write_text(json.dumps({
        "behaviour": {"hopper-medium": {"score": 3.0, "dataset": "abc"}, "hopper-random": {"score": 1.0,
                                                                                          "dataset": "abc"}},
        "records": records}))
    assert paper_table.main(["--report", "--out", str(tmp_path)]) == 0
    plain = (tmp_path / "paper_table.md").read_text().splitlines()
    assert any(line.startswith("| hopper-medium | 3.0 | 2.0 ± 0.0 (n=1) | 2.0 ± 0.0 (n=1) | 6.0 ± 0.0 (n=1)")
               and "4.0 ± 0.0 (n=1) |" in line for line in plain)
    assert any(line.startswith("| hopper-random | 1.0 | - | - | - | - | - | - | 9.0") for line in plain)
    assert paper_table.main(["--report", "--out", str(tmp_path), "--set", "sac.critic_layer_norm=true"]) == 0
    ablation = (tmp_path / "paper_table_sac.critic_layer_norm-true.md").read_text()
    assert "| hopper-medium | 3.0 | 2.0 ± 0.0 (n=1) | 2.0 ± 0.0 (n=1) | - | - | - | - | 5.0 ± 0.0 (n=1)" in ablation
    assert "hopper-random" not in ablation
    # beside the preset's run of its file, method and seed; the preset's own table has no such section
    assert "| hopper-medium | DROP | 0 | 5.0 (8.0, 0.62) | 4.0 (8.0, 0.50) | +1.0 |" in ablation
    assert "Each run beside" not in "\n".join(plain)


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


def test_the_runs_owed_are_those_no_shown_record_holds():
    """A run of the setting's config on the table's file is done; one on another file, or of another config, is not;
    a dataset without a file yet is named so, and a file by the CPU kinds its runs were made on."""
    kept = {"behaviour": {"hopper-medium": {"score": 3.0, "dataset": "abc"}},
            "records": [{**_record(), "setting": PLAIN},
                        {**_record(algorithm="mbpo", dataset="other"), "setting": PLAIN},
                        {**_record(algorithm="mopo", setting=BOUND), "setting": BOUND},
                        {**_record(algorithm="bc"), "bc": "likelihood-100000", "setting": BOUND}]}
    lines = paper_table.owed(kept, paper_table.setting_config(PLAIN), "likelihood-100000",
                             [("hopper", "medium"), ("hopper", "random")], ["bc", "mbpo", "mopo", "drop"], [0, 1])
    assert list(lines.values()) == ["hopper-medium (file abc): bc 1; mbpo 0 1; mopo 0 1; drop 1",
                                    "hopper-random (file not made yet): bc 0 1; mbpo 0 1; mopo 0 1; drop 0 1"]
    # The CPU kinds that made the file's runs, of any setting, are named; a run on another file names none.
    kept["records"][1]["cpu"], kept["records"][2]["cpu"], kept["records"][3]["cpu"] = "Intel", "AMD", "AMD"
    lines = paper_table.owed(kept, paper_table.setting_config(PLAIN), "likelihood-100000",
                             [("hopper", "medium"), ("hopper", "random")], ["bc", "mbpo", "mopo", "drop"], [0, 1])
    assert list(lines.values()) == ["hopper-medium (file abc, runs made on AMD): bc 1; mbpo 0 1; mopo 0 1; drop 1",
                                    "hopper-random (file not made yet): bc 0 1; mbpo 0 1; mopo 0 1; drop 0 1"]


def test_the_missing_files_are_collected_in_the_order_that_starts_runs_soonest(tmp_path):
    """random needs no online training, the medium kinds stop it at the medium policy, and the expert kinds continue
    that run: one command per env and stage, every env's quick stages first, only for the files not already there."""
    (tmp_path / "halfcheetah-medium.hdf5").touch()
    owed = [("hopper", "medium-expert"), ("halfcheetah", "medium-expert"), ("halfcheetah", "medium-replay"),
            ("halfcheetah", "medium"), ("halfcheetah", "random"), ("walker2d", "medium")]
    end = f"--out {tmp_path} --threads 1"
    assert paper_table.collect_commands(owed, tmp_path) == [
        f"drop collect --env halfcheetah --kinds random {end}",
        f"drop collect --env halfcheetah --kinds medium-replay {end}",
        f"drop collect --env walker2d --kinds medium {end}",
        f"drop collect --env hopper --kinds medium-expert {end}",
        f"drop collect --env halfcheetah --kinds medium-expert {end}"]
    for kind in ("random", "medium-replay", "medium-expert"):
        (tmp_path / f"halfcheetah-{kind}.hdf5").touch()
    assert paper_table.collect_commands(owed[1:5], tmp_path) == []


def test_a_run_is_trained_recorded_with_its_file_threads_and_cpu_and_shown(tmp_path):
    """End to end as the command is run: a behaviour-cloning run on a small real file, in the worker process the
    table spawns."""
    from drop_engine.collect import collect_transitions, random_policy
    from drop_engine.data import load_dataset, save_hdf5

    data = tmp_path / "data"
    data.mkdir()
    save_hdf5(data / "hopper-random.hdf5", collect_transitions("hopper", random_policy(3, seed=0), 300, seed=0),
              {"env_name": "Hopper-v4", "dataset_normalized_score": 1.5})
    argv = ["--data", str(data), "--runs", str(tmp_path / "runs"), "--out", str(tmp_path / "out"), "--envs", "hopper",
            "--kinds", "random", "--algorithms", "bc", "--seeds", "0", "--bc-steps", "5", "--episodes", "1",
            "--jobs", "2", "--model-cache", str(tmp_path / "models")]
    script = [sys.executable, str(Path(paper_table.__file__))]
    ran = subprocess.run([*script, *argv], capture_output=True, text=True, timeout=600)
    assert ran.returncode == 0, ran.stderr
    assert "hopper-random bc seed 0: final" in ran.stdout
    [record] = json.loads((tmp_path / "out" / "paper_table.json").read_text())["records"]
    assert record["dataset"] == load_dataset(data / "hopper-random.hdf5").content_hash
    assert (record["algorithm"], record["seed"], record["threads"]) == ("bc", 0, 1)
    assert record["cpu"].endswith(f" ({torch.backends.cpu.get_cpu_capability()})") and len(record["cpu"]) > 10
    assert "| hopper-random | 1.5 |" in (tmp_path / "out" / "paper_table.md").read_text()
    again = subprocess.run([*script, *argv], capture_output=True, text=True, timeout=600)  # recorded: not trained again
    assert again.returncode == 0 and "seed 0: final" not in again.stdout, again.stderr
    assert json.loads((tmp_path / "out" / "paper_table.json").read_text())["records"] == [record]


def test_a_run_another_invocation_holds_is_waited_for_and_taken_from_its_result(tmp_path):
    """Two invocations may list one run: the second waits on the run's lock and then reads the first's result instead
    of resuming the same checkpoint beside it (QUALITY.md E63)."""
    import argparse
    import threading

    from drop_engine.collect import collect_transitions, random_policy
    from drop_engine.data import save_hdf5
    from drop_engine.file_lock import exclusive

    path = tmp_path / "hopper-random.hdf5"
    save_hdf5(path, collect_transitions("hopper", random_policy(3, seed=0), 300, seed=0), {"env_name": "Hopper-v4"})
    args = argparse.Namespace(bc_steps=5, episodes=1, code={"commit": None, "changes": None})
    run_dir = tmp_path / "runs" / "hopper-random-abc" / f"bc-{paper_table.bc_setting(5)}-0"
    theirs = {"final": 12.5, "best": 12.5, "evaluations": [], "by": "the other invocation"}
    got = []
    with exclusive(run_dir.with_name(run_dir.name + ".lock")):
        waiter = threading.Thread(target=lambda: got.append(
            paper_table.run_one(path, "abc", "hopper", "random", "bc", 0, args, tmp_path / "runs")))
        waiter.start()
        waiter.join(timeout=3)
        assert waiter.is_alive() and not (run_dir / "result.json").exists()  # waiting, not training
        run_dir.mkdir(parents=True)
        (run_dir / "result.json").write_text(json.dumps(theirs))
    waiter.join(timeout=60)
    assert got == [theirs]


def test_drops_gaps_are_paired_by_seed_and_counted_where_the_seeds_can_tell():
    """The difference is taken seed by seed (a seed's runs share one ensemble), only over the seeds both methods ran;
    a steady gap with a large spread between seeds is told apart, a single seed never is."""
    def run(algorithm, seed, final, kind="medium"):
        return {"algorithm": algorithm, "env": "hopper", "kind": kind, "seed": seed, "final": final}

    records = ([run("drop", s, f) for s, f in ((0, 10.0), (1, 40.0), (2, 70.0))]
               + [run("mbpo", s, f) for s, f in ((0, 4.0), (1, 34.5), (2, 63.5))]  # 6, 5.5 and 6.5 under DROP
               + [run("mopo", s, f) for s, f in ((1, 45.0), (2, 60.0))]  # no seed 0: DROP's seed 0 is left out
               + [run("bc", s, f) for s, f in ((1, 40.0), (2, 70.0))]  # DROP's own finals: no gap and no spread
               + [run("drop", 0, 9.0, "random"), run("bc", 0, 1.0, "random")])
    text = paper_table.paired(records, ["hopper-medium", "hopper-random"])
    assert ("| hopper-medium | +0.0 ± 0.0 (n=2, p=1.00) | +2.5 ± 7.5 (n=2, p=0.80) | +6.0 ± 0.3 (n=3, p=0.0023) |"
            in text)
    assert "| hopper-random | +8.0 (n=1) | - | - |" in text
    assert "BC 0 ahead, 0 behind; MOPO 0 ahead, 0 behind; MBPO 1 ahead, 0 behind." in text


def test_a_seed_whose_runs_trained_on_two_ensembles_is_named_not_paired():
    """The same cache key trains another model on another CPU kind (QUALITY.md E71): that seed's gap would hold the two
    models' difference, so DROP's pairs and an ablation's leave it out and name it. BC uses no model, and a record
    from before ensembles were recorded pairs as before."""
    def run(algorithm, seed, final, errors=None, setting=PLAIN):
        record = {**_record(algorithm, live=False, final=final, setting=setting), "seed": seed, "best": final}
        return record | {"dynamics": {"holdout_mse": errors} if errors else None}  # None: as the trainer records

    one, other = [0.3, 0.4], [0.3, 0.5]
    records = [run("drop", 0, 10.0, one), run("drop", 1, 20.0, one), run("mopo", 0, 4.0, one),
               run("mopo", 1, 50.0, other), run("mbpo", 0, 8.0), run("bc", 1, 5.0)]
    text = paper_table.paired(records, ["hopper-medium"])
    assert "| hopper-medium | +15.0 (n=1) | +6.0 (n=1) | +2.0 (n=1) |" in text
    assert "with DROP's final minus the baseline's: hopper-medium MOPO seed 1 (-30.0)." in text
    assert "Left out" not in paper_table.paired(records[:-3], ["hopper-medium"])

    ablation = [run("drop", 0, 12.0, one, BOUND), run("drop", 1, 25.0, other, BOUND)]
    text = paper_table.against(ablation, records, BOUND["set"])
    assert "| hopper-medium | DROP | 0 | 12.0 (12.0, 1.00) | 10.0 (10.0, 1.00) | +2.0 |" in text
    assert "| hopper-medium | DROP | 1 |" not in text and "final with minus without +2.0 (n=1)" in text
    assert ("(the same cache key on another CPU kind), with sac.critic_layer_norm=true beside without: "
            "hopper-medium DROP seed 1 25.0 (25.0, 1.00) beside 20.0 (20.0, 1.00) (+5.0).") in text
    alone = paper_table.against(ablation[1:], records, BOUND["set"])
    assert "Each run beside" not in alone and "hopper-medium DROP seed 1 25.0" in alone


def test_p_values_under_a_tenth_keep_two_significant_digits():
    """0.004 must not read as 0.00 (a gap the same on every seed), nor 0.049, 0.0496 or 0.04995 as 0.05 (they are
    counted under 0.05), nor 0.09996 as 0.1 beside 0.1's 0.10."""
    assert [paper_table.p_value(p) for p in (1.0, 0.8, 0.09996, 0.0504, 0.0496, 0.04995, 0.049, 0.004, 0.0)] == [
        "p=1.00", "p=0.80", "p=0.10", "p=0.05", "p=0.0496", "p=0.04995", "p=0.049", "p=0.004", "p<0.001"]


def test_holm_multiplies_the_kth_smallest_p_by_the_tests_left_and_keeps_the_order():
    assert paper_table.holm([0.01, 0.04, 0.03, 0.5]) == pytest.approx([0.04, 0.09, 0.09, 0.5])
    assert paper_table.holm([0.3, 0.6]) == pytest.approx([0.6, 0.6]) and paper_table.holm([]) == []


def test_a_gap_that_passes_alone_need_not_pass_the_correction_for_every_test():
    def run(algorithm, seed, final, kind):
        return {"algorithm": algorithm, "env": "hopper", "kind": kind, "seed": seed, "final": final}

    records = ([run("drop", s, 10.0 * s, "medium") for s in range(3)]  # 6, 5.5, 6.5 over MBPO: p 0.002
               + [run("mbpo", s, 10.0 * s - g, "medium") for s, g in enumerate((6.0, 5.5, 6.5))]
               + [run("mopo", s, 10.0 * s + g, "medium") for s, g in enumerate((-1.0, 1.0, 0.0))]  # p 1
               + [run("drop", s, 10.0 * s, "random") for s in range(3)]  # 6, 10, 14 over BC: p 0.049
               + [run("bc", s, 10.0 * s - g, "random") for s, g in enumerate((6.0, 10.0, 14.0))])
    text = paper_table.paired(records, ["hopper-medium", "hopper-random"])
    assert "p under 0.05: BC 1 ahead, 0 behind; MOPO 0 ahead, 0 behind; MBPO 1 ahead, 0 behind." in text
    assert "with Holm's correction for the 3: BC 0 ahead, 0 behind; MOPO 0 ahead, 0 behind; MBPO 1 ahead" in text


def test_collapses_are_counted_per_method_and_told_apart_from_the_evaluations_noise():
    """A run under 0.8 of its best counts against its method; whether the fall is wider than the evaluations' own
    noise comes from their episodes' spread (hopper's D4RL scale, 10 episodes each)."""
    from drop_engine.envs import get_env

    spec = get_env("hopper")

    def run(algorithm, best, final, spread):
        evaluations = [{"normalized_score": s, "return_std": spread * (spec.expert_score - spec.random_score) / 100}
                       for s in (best / 2, best, final, final, final)]
        return {"algorithm": algorithm, "env": "hopper", "kind": "medium", "seed": 0, "final": final, "best": best,
                "evaluations": evaluations, "config": {"eval_episodes": 10}}

    fell = run("drop", 50.0, 20.0, 10.0)  # each evaluation ± 10/sqrt(10), the final's ± that/sqrt(3)
    assert paper_table.swing(fell) == pytest.approx(30 / (10 / np.sqrt(10) * np.sqrt(4 / 3)))
    # a best under zero is no peak: a final by it holds (although under 0.8 of it), one a fifth further down falls
    records = [fell, run("drop", 50.0, 35.0, 60.0), run("drop", 50.0, 45.0, 10.0),
               run("mbpo", 10.0, 9.0, 1.0), run("mbpo", 10.0, 2.0, 1.0),
               run("mopo", -1.0, -1.0, 0.1), run("mopo", -1.0, -1.19, 0.1), run("mopo", -1.0, -1.21, 0.1)]
    text = paper_table.targets(records, ["hopper-medium"])
    assert "DROP 1 of 3, MBPO 1 of 2, MOPO 2 of 3 runs." in text
    assert "(the policy changed, not only its measurement): DROP 1 of 2, MBPO 1 of 1, MOPO 1 of 1." in text


def test_an_ablations_runs_are_set_beside_the_presets_runs_of_their_file_method_and_seed():
    """Paired by seed on the same file; a run whose config the overrides left as the preset's is no ablation."""
    def run(algorithm, seed, final, best, setting, dataset="abc"):
        return {**_record(algorithm, live=False, dataset=dataset, final=final, setting=setting), "seed": seed,
                "best": best}

    same = run("mopo", 0, 5.0, 5.0, PLAIN)
    plain = [run("drop", 0, 5.0, 10.0, PLAIN), run("drop", 1, 9.0, 10.0, PLAIN), run("mbpo", 0, 4.0, 8.0, PLAIN),
             run("drop", 2, 1.0, 2.0, PLAIN, dataset="other"), same]
    ablation = [run("drop", 0, 8.0, 9.0, BOUND), run("drop", 1, 10.0, 10.0, BOUND), run("mbpo", 0, 6.0, 8.0, BOUND),
                run("drop", 2, 3.0, 3.0, BOUND), same]
    text = paper_table.against(ablation, plain, BOUND["set"])
    assert "| hopper-medium | DROP | 0 | 8.0 (9.0, 0.89) | 5.0 (10.0, 0.50) | +3.0 |" in text
    assert "| hopper-medium | DROP | 2 |" not in text and "MOPO" not in text
    assert ("- DROP, every pair above: final with minus without +2.0 ± 1.0 (n=2, p=0.30); no collapse (as the "
            "targets count it) in 2 of 2 runs with, 1 without.") in text
    assert ("- MBPO, every pair above: final with minus without +2.0 (n=1); no collapse (as the targets count it) in "
            "0 of 1 runs with, 0 without.") in text
    assert text.index("- MBPO") < text.index("- DROP")  # the tables' order of methods
    assert paper_table.against([same], plain, BOUND["set"]) == ""
    # a best at or under zero gets no final/best: a ratio of two negative scores would read as a run that held
    fell = paper_table.against([run("drop", 0, -3.0, -1.0, BOUND)], [run("drop", 0, -2.0, 0.0, PLAIN)], BOUND["set"])
    assert "| hopper-medium | DROP | 0 | -3.0 (-1.0) | -2.0 (0.0) | -1.0 |" in fell
    # and it holds when its final stays within a fifth of that best, as `targets` counts it
    flat = paper_table.against([run("drop", 0, -1.0, -1.0, BOUND)], [run("drop", 0, -1.3, -1.0, PLAIN)], BOUND["set"])
    assert "no collapse (as the targets count it) in 1 of 1 runs with, 0 without." in flat
