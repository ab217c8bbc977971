"""The paper's Table 1 at CPU scale: DROP, MOPO, MBPO (same loop, same budget) and behaviour cloning.

Reads `ENV-KIND.hdf5` from the `make bench-data` cache, trains every (dataset, algorithm, seed) not yet finished
(an interrupted run resumes from its checkpoint), and writes the final and best D4RL normalised scores, mean and std
over seeds, beside the behaviour policy's own score, and DROP's gap to each baseline seed by seed (`paired`).

    python bench/paper_table.py --envs hopper --kinds medium medium-replay --seeds 0 1 2 [--preset cpu] [--jobs 2]

Finished runs are kept in bench/results/paper_table.json, so the table fills up across machines and sessions: a run
already recorded there with the same resolved config and dataset content is not repeated, whichever preset revision or
overrides gave that config (behaviour cloning, which reads neither, is shared by every setting's table). `make
bench-data` is
seeded, but the same seed collects other files on other CPUs or at another thread count (the floating-point sums
differ, QUALITY.md E9 and E22), so every record carries its dataset's content hash and the table shows, for each
dataset, only the runs on the file whose behaviour score it prints.
"""
from __future__ import annotations

import argparse
import fcntl
import functools
import hashlib
import json
import os
import shlex
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import ExitStack
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import torch
from scipy import stats

from drop_engine.atomic import write_text
from drop_engine.bc import evaluate_actor, train_bc
from drop_engine.config import TASKS, TrainConfig, build_config, override_dict, parse_override
from drop_engine.data import load_dataset
from drop_engine.envs import get_env
from drop_engine.file_lock import Busy, exclusive
from drop_engine.run_log import RunLog
from drop_engine.scores import FINAL_WINDOW, summarize
from drop_engine.seeding import cpu_kind
from drop_engine.stopping import never
from drop_engine.trainer import train

ALGORITHMS = ("bc", "mbpo", "mopo", "drop")
CACHE = Path(os.environ.get("DROP_BENCH_DATA", Path.home() / ".cache/drop-rl/bench-data"))
# The cpu preset's meaning, named in table titles and run directories; bumped when a preset changes. Which runs a table
# shows is decided by their configs (`identity`), not by this number.
# 2: the cpu preset of bench/QUALITY.md (converged dynamics, behaviour term, positive DICE, no bonus).
# 3: the behaviour term on the data actions' likelihood instead of the mean action's squared error (E23).
# 4: the policy's entropy target no higher than the data's behaviour entropy (sac.target_entropy='data', E28).
# 5: the value bound on every kind, and a behaviour weight of 0.1 on medium and medium-expert data (E55, E56).
REVISION = 5
# A run's numbers follow from its dataset, its seed and its config, less the fields that set only its speed or what it
# keeps on disk. Each record carries that config, so a setting (a revision, an ablation) whose config for a row is one
# that a run already had shows that run rather than training it again. `threads` and the CPU change the float sums,
# not what is computed; records name both beside the config.
NOT_IDENTITY = {"seed", "threads", "keep_checkpoints"}
# Bumped when an existing option's meaning changes (as the value bound's did in ba8b4a7), and part of every run's
# identity: runs of the old meaning then match no setting.
SEMANTICS = 1


def identity(cfg: TrainConfig) -> dict:
    """The config a run's numbers follow from, flat with dotted keys."""
    def flat(tree: dict, prefix: str = "") -> dict:
        return {k: v for name, value in tree.items()
                for k, v in (flat(value, f"{prefix}{name}.") if isinstance(value, dict)
                             else {f"{prefix}{name}": value}).items()}

    return {**flat(cfg.model_dump(mode="json", exclude=NOT_IDENTITY)), "semantics": SEMANTICS}


DEFAULTS = {k: v for k, v in identity(TrainConfig()).items() if k != "semantics"}


def same_config(stored: dict | None, wanted: dict) -> bool:
    """Whether a record ran `wanted`. A field the record lacks was added to the engine after that run, which behaved
    as its default (options are added switched off); a field only the record has was removed, and matches nothing;
    so does a record of other semantics, or of none."""
    return (stored is not None and stored.keys() <= wanted.keys()
            and all(stored.get(k, DEFAULTS.get(k)) == v for k, v in wanted.items()))


def setting_config(setting: dict, device: str = "cpu"):
    """The config each (env, kind, algorithm) resolves to under a setting, with this checkout's presets."""
    def wanted(env: str, kind: str, algorithm: str) -> dict:
        overrides = override_dict(parse_override(kv) for kv in setting["set"])
        return identity(build_config(algorithm, env=env, preset=setting["preset"], task=kind, overrides=overrides,
                                     device=device))

    return functools.cache(wanted)


def bc_setting(steps: int) -> str:
    """Which behaviour cloning a BC record holds. A record of another clone (before QUALITY.md E20: squared error,
    20,000 steps) is neither counted nor shown, and its run directory is not this one's."""
    return f"likelihood-{steps}"


def shown(records: list[dict], wanted, bc: str) -> list[dict]:
    """The records a setting's table shows: the model-based runs of the configs it resolves to (`wanted(env, kind,
    algorithm)`), whichever setting recorded them, and the clone `bc`'s runs whichever setting ran them (it reads
    neither the preset nor the overrides), the latest one per key and file. A recorded run is shown before a derived
    one (`latest_iterate`), which only reproduces it."""
    runs: dict[tuple, dict] = {}
    for r in records:
        here = (*key(r), r.get("dataset"))
        if r["algorithm"] == "bc":
            if r.get("bc") == bc:
                runs[here] = r
        elif same_config(r.get("config"), wanted(r["env"], r["kind"], r["algorithm"])) and (
                here not in runs or "derived_from" not in r or "derived_from" in runs[here]):
            runs[here] = r
    return [r for r in runs.values() if r["algorithm"] != "bc"] + [r for r in runs.values() if r["algorithm"] == "bc"]


def code_version(root: Path) -> dict:
    """The commit of the code this invocation runs, and a hash of the uncommitted changes to the engine and the bench
    scripts (None when there are none), taken at launch. Two runs of one seed and setting that differ can then be told
    apart: other code, or the same code behaving otherwise (QUALITY.md E50). A run resumed by a later invocation
    names that one's code. Unknown outside a git checkout."""
    def git(*argv: str) -> bytes:
        return subprocess.run(["git", *argv], cwd=root, capture_output=True, check=True).stdout

    paths = ("drop_engine", ":(glob)bench/*.py")  # not bench/results, which the runs themselves write
    try:
        commit = git("rev-parse", "HEAD").decode().strip()
        diff = git("diff", "HEAD", "--binary", "--no-ext-diff", "--no-textconv", "--", *paths)
        new = [name for name in git("ls-files", "--others", "--exclude-standard", "-z", "--", *paths).split(b"\0")
               if name]
        digest = hashlib.sha256(diff)
        for name in new:
            digest.update(name + b"\0" + (root / name.decode()).read_bytes())
    except (OSError, UnicodeError, subprocess.CalledProcessError):
        return {"commit": None, "changes": None}
    return {"commit": commit, "changes": digest.hexdigest()[:16] if diff or new else None}


def run_one(data_path: Path, dataset: str, env: str, kind: str, algorithm: str, seed: int, args, runs: Path) -> dict:
    name = f"bc-{bc_setting(args.bc_steps)}" if algorithm == "bc" else algorithm
    run_dir = runs / f"{env}-{kind}-{dataset[:12]}" / f"{name}-{seed}"
    done = run_dir / "result.json"
    cfg = None if algorithm == "bc" else build_config(
        algorithm, env=env, preset=args.preset, task=kind, seed=seed, device=args.device,
        overrides=override_dict(parse_override(kv) for kv in args.set))
    # Another invocation may list the same run (each lists its runs at start): it trains it while this one waits, then
    # this one takes its record. Two processes resuming one checkpoint would interleave their writes (QUALITY.md E63).
    with ExitStack() as held:
        lock = run_dir.with_name(run_dir.name + ".lock")
        try:
            held.enter_context(exclusive(lock))
        except Busy:
            print(f"{run_dir}: another invocation is training this run; waiting for its result", flush=True)
            held.enter_context(exclusive(lock, should_stop=never))
        if done.exists():
            return finished(done, cfg)
        run_dir.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        if cfg is None:
            data = load_dataset(data_path, env=env)
            actor = train_bc(data, args.bc_steps, seed=seed)
            evaluation = evaluate_actor(actor, env, args.episodes, seed=10_000 + seed)
            record = {"final": evaluation.normalized_score, "best": evaluation.normalized_score, "evaluations": [],
                      "bc": bc_setting(args.bc_steps)}
        else:
            result = train(data_path, cfg, run_dir, RunLog(run_dir, cfg.steps_per_epoch), model_cache=args.model_cache)
            if result.status != "completed":
                raise SystemExit(f"{run_dir}: stopped before the end")
            record = {"final": result.final_score, "best": result.best_score, "best_epoch": result.best_epoch,
                      "evaluations": result.evaluations, "dynamics": result.dynamics, "config": identity(cfg)}
        record.update({"env": env, "kind": kind, "algorithm": algorithm, "seed": seed, "dataset": dataset,
                       "seconds": time.perf_counter() - start, "code": args.code, "threads": torch.get_num_threads(),
                       "cpu": cpu_kind()})
        write_text(done, json.dumps(record, indent=2))  # its presence means finished: never half a file
        return record


def finished(done: Path, cfg: TrainConfig | None) -> dict:
    """The record of a run already finished in this directory. The directory is named by revision and overrides, so
    a run of before configs were recorded had `cfg`; a recorded config that is not `cfg` means a preset changed
    without a revision bump, and its run is not this one."""
    record = json.loads(done.read_text())
    if cfg is None:
        return record
    record.setdefault("config", identity(cfg))
    if not same_config(record["config"], identity(cfg)):
        raise SystemExit(f"{done.parent} holds a run of another config than this setting's: a preset changed without "
                         "a revision bump (bump REVISION in bench/paper_table.py)")
    return record


def latest_iterate(record: dict, overrides: list[str]) -> tuple[dict, list[str]] | None:
    """The record, and its overrides, of the setting that is `overrides` less `sac.actor_average`, held by a run of
    `overrides`: a run that averages the actor's iterates trains as the run without the average and also scores its
    latest iterate on the same episodes (`live_*`), so one run gives both rows of the ablation
    (tests/engine/test_trainer.py holds the two runs' numbers equal)."""
    evaluations = record.get("evaluations") or [{}]
    rest = [o for o in overrides if o.split("=", 1)[0] != "sac.actor_average"]
    if len(rest) == len(overrides) or not all("live_normalized_score" in e for e in evaluations):
        return None
    evaluations = [{"epoch": e["epoch"], "step": e["step"],
                    **{k.removeprefix("live_"): v for k, v in e.items() if k.startswith("live_")}}
                   for e in evaluations]
    summary = summarize([(e["epoch"], e["normalized_score"]) for e in evaluations])
    derived = {**record, "evaluations": evaluations, "final": summary.final_score, "best": summary.best_score,
               "best_epoch": summary.best_epoch, "derived_from": overrides}
    if "config" in record:
        derived["config"] = {**record["config"], "sac.actor_average": DEFAULTS["sac.actor_average"]}
    return derived, rest


def key(r: dict) -> tuple:
    return r["env"], r["kind"], r["algorithm"], r["seed"]


def merge(records: list[dict], record: dict, setting: dict) -> list[dict]:
    """`records` with `record` in: it replaces the record of its config (of its setting, for behaviour cloning) and
    key on the same file (a run on another file is another run, and stays); a derived record (`latest_iterate`)
    replaces nothing, as a recorded run is the measurement and the derived one only its reproduction."""
    def same(r: dict) -> bool:
        if key(r) != key(record) or r.get("dataset") != record["dataset"]:
            return False
        if "config" in record:
            return same_config(r.get("config"), record["config"])
        return r["setting"] == setting

    if "derived_from" in record and any(same(r) for r in records):
        return records
    return [r for r in records if not same(r)] + [{**record, "setting": setting}]


def describe(path: Path) -> dict:
    """The file's behaviour score and content hash: what a record must match to be counted for this dataset."""
    data = load_dataset(path)
    value = data.attrs.get("dataset_normalized_score")
    return {"score": float(value) if value is not None else None, "dataset": data.content_hash}


def described(entry: float | dict | None) -> dict:
    """A behaviour entry; files of before content hashes stored the bare score, and match records without one."""
    return entry if isinstance(entry, dict) else {"score": entry, "dataset": None}


def on_file(records: list[dict], behaviour: dict[str, dict]) -> list[dict]:
    """The records made on the very file each dataset's behaviour entry describes."""
    return [r for r in records if (d := behaviour.get(f"{r['env']}-{r['kind']}")) is not None
            and r.get("dataset") == d["dataset"]]


def displaced(kept: dict, behaviour: dict[str, dict]) -> list[str]:
    """The datasets whose local file is not the one the table's records were made on. Collection is not bit-identical
    across CPU kinds, so a file made on another machine would take its dataset's row over and hide those records.
    An entry of before content hashes names no file, and guards nothing."""
    table_files = {name: described(entry)["dataset"] for name, entry in kept.get("behaviour", {}).items()}
    return [f"{name}: this file is {entry['dataset'][:8]}, the table's runs ({n}) were made on {table_files[name][:8]}"
            for name, entry in behaviour.items()
            if table_files.get(name) not in (None, entry["dataset"])
            and (n := len(on_file(kept.get("records", []), {name: {"dataset": table_files[name]}})))]


def owed(kept: dict, wanted, bc: str, datasets: list[tuple[str, str]], algorithms: list[str],
         seeds: list[int]) -> dict[tuple[str, str], str]:
    """The runs this setting's table still lacks, a line per (env, kind), each with the file they must run on and the
    CPU kinds whose runs are on it: files differ between CPU kinds, so this says which machine can make them."""
    behaviour = {name: described(entry) for name, entry in kept.get("behaviour", {}).items()}
    records = on_file(kept.get("records", []), behaviour)
    done = {key(r) for r in shown(records, wanted, bc)}
    lines = {}
    for env, kind in datasets:
        missing = {algo: [str(seed) for seed in seeds if (env, kind, algo, seed) not in done] for algo in algorithms}
        if any(missing.values()):
            file = (behaviour.get(f"{env}-{kind}") or {}).get("dataset")
            cpus = sorted({r["cpu"] for r in records if (r["env"], r["kind"]) == (env, kind) and "cpu" in r})
            lines[env, kind] = (f"{env}-{kind} (file {file[:8] if file else 'not made yet'}"
                                + (f", runs made on {', '.join(cpus)}" if cpus else "") + "): "
                                + "; ".join(f"{algo} {' '.join(left)}" for algo, left in missing.items() if left))
    return lines


def collect_commands(datasets: list[tuple[str, str]], data: Path) -> list[str]:
    """The `drop collect` commands that make the missing files of `datasets`, in the order that starts runs soonest:
    random needs no online training, the medium kinds only the training up to the medium policy, and the expert kinds
    then continue that same run."""
    lacking = [(env, kind) for env, kind in datasets if not (data / f"{env}-{kind}.hdf5").exists()]
    commands = []
    for group in (["random"], ["medium", "medium-replay"], ["expert", "medium-expert"]):
        for env in dict.fromkeys(env for env, _ in lacking):
            if chosen := [kind for kind in group if (env, kind) in lacking]:
                commands.append(f"drop collect --env {env} --kinds {','.join(chosen)} --out {shlex.quote(str(data))}"
                                " --threads 1")
    return commands


def runs_of(records: list[dict], dataset: str, algo: str) -> list[dict]:
    """The records of one row's method."""
    return [r for r in records if f"{r['env']}-{r['kind']}" == dataset and r["algorithm"] == algo]


def table(records: list[dict], behaviour: dict[str, float | None], algorithms: list[str]) -> str:
    def cell(scores: list[float]) -> str:
        return f"{np.mean(scores):.1f} ± {np.std(scores):.1f} (n={len(scores)})" if scores else "-"

    columns = " | ".join(f"{a.upper()} final | {a.upper()} best" for a in algorithms)
    lines = [f"| dataset | behaviour | {columns} |",
             "|---|---|" + "---|---|" * len(algorithms)]
    for dataset in behaviour:
        row = [dataset, f"{behaviour[dataset]:.1f}" if behaviour[dataset] is not None else "-"]
        for algo in algorithms:
            runs = runs_of(records, dataset, algo)
            row += [cell([r["final"] for r in runs]), cell([r["best"] for r in runs])]
        lines.append("| " + " | ".join(row) + " |")
    derived = [f"{r['env']}-{r['kind']} {r['algorithm'].upper()} seed {r['seed']} ({' '.join(r['derived_from'])})"
               for r in records if "derived_from" in r]
    if derived:
        lines += ["", "From the latest iterate of a run that evaluated an average of the actor's iterates beside it "
                      "(it trains as the run without the average; bench/QUALITY.md E41): " + "; ".join(derived) + "."]
    return "\n".join(lines) + "\n" + targets(records, list(behaviour)) + paired(records, list(behaviour))


def carried(records: list[dict], setting: dict) -> str:
    """A line naming the settings, other than this one, whose runs the table shows because their config is its own."""
    others = [r["setting"] for r in records if r["algorithm"] != "bc" and r["setting"] != setting]
    if not others:
        return ""
    names = sorted({f"revision {s.get('revision', '-')}{' with ' + ' '.join(s['set']) if s['set'] else ''}"
                    for s in others})
    return (f"\n{len(others)} of these model-based runs were recorded under another setting with the same config: "
            f"{'; '.join(names)}.\n")


def targets(records: list[dict], datasets: list[str]) -> str:
    """The issue's bars: DROP's final against each baseline's, dataset by dataset, and DROP's runs against collapse,
    beside the baselines' runs for scale."""
    def mean_final(dataset: str, algo: str) -> float | None:
        scores = [r["final"] for r in runs_of(records, dataset, algo)]
        return float(np.mean(scores)) if scores else None

    lines = ["", "| DROP's final at least | datasets with both | met |", "|---|---|---|"]
    for algo in ("bc", "mopo", "mbpo"):
        pairs = [(mean_final(d, "drop"), mean_final(d, algo)) for d in datasets]
        pairs = [(a, b) for a, b in pairs if a is not None and b is not None]
        lines.append(f"| {algo.upper()}'s | {len(pairs)} | {sum(a >= b for a, b in pairs)} |")
    held, fell = [], []
    for algo in ("drop", "mbpo", "mopo"):
        runs = [r for r in records if r["algorithm"] == algo]
        under = [r for r in runs if not holds(r)]
        held.append(f"{algo.upper()} {len(runs) - len(under)} of {len(runs)}")
        fell.append(f"{algo.upper()} {sum(swing(r) > 2 for r in under)} of {len(under)}")
    lines += ["", f"No collapse (final at least 0.8 of best, or for a best under zero at most a fifth of it under; "
                  f"final is the mean of the last {FINAL_WINDOW} evaluations): {', '.join(held)} runs. Of the runs "
                  f"that fell, those whose best stands more than twice the evaluations' standard error above their "
                  f"final (the policy changed, not only its measurement): {', '.join(fell)}."]
    return "\n".join(lines) + "\n"


def holds(r: dict) -> bool:
    """The issue's no-collapse bar, final at least 0.8 of best, read as a fall of at most a fifth of the best: a run
    whose best is under zero climbed to no peak, and its final beside that best is no collapse (0.8 of it is higher)."""
    return r["best"] is None or r["final"] >= r["best"] - 0.2 * abs(r["best"])


def swing(r: dict) -> float:
    """How many standard errors of its evaluations separate a run's best from its final. An evaluation's error is its
    episodes' spread over the square root of their count; the final's, the mean of the last evaluations' errors in
    quadrature. Above about 2 the policy changed between them; below, the gap may be the measurement's."""
    spec = get_env(r["env"])
    errors = [100 * e["return_std"] / (spec.expert_score - spec.random_score) / np.sqrt(r["config"]["eval_episodes"])
              for e in r["evaluations"]]
    best = int(np.argmax([e["normalized_score"] for e in r["evaluations"]]))  # the first of ties, as `summarize`
    window = errors[-FINAL_WINDOW:]
    error = float(np.hypot(errors[best], np.sqrt(np.sum(np.square(window))) / len(window)))
    return (r["best"] - r["final"]) / max(error, 1e-12)


def same_model(a: dict, b: dict) -> bool:
    """Whether two runs of one file and seed trained on one ensemble. The model cache's key leaves out the CPU kind,
    and another kind trains another model under it (QUALITY.md E66, E71). A run with no recorded ensemble (behaviour
    cloning, or a run from before ensembles were recorded) is taken to share its seed's."""
    errors = [(r.get("dynamics") or {}).get("holdout_mse") for r in (a, b)]
    return None in errors or errors[0] == errors[1]


def paired(records: list[dict], datasets: list[str]) -> str:
    """DROP's final minus each baseline's, seed by seed: a seed's DROP, MOPO and MBPO share one ensemble, so the
    difference leaves out how good that seed's model came out, which is most of the spread between seeds; a seed whose
    runs trained on different ensembles is left out of the pairs, and named. The ± is the standard error of the mean
    difference and p a paired t-test's (two-sided): at 2 or 3 seeds a gap needs 12.7 or 4.3 standard errors for p
    under 0.05."""
    def finals(dataset: str, algo: str) -> dict[int, dict]:
        return {r["seed"]: r for r in runs_of(records, dataset, algo)}

    baselines = ("bc", "mopo", "mbpo")
    lines = ["", "DROP's final minus each baseline's on the same seeds (mean ± standard error of the differences, "
                 "paired t-test's p):", "",
             "| dataset | " + " | ".join(f"DROP − {b.upper()}" for b in baselines) + " |",
             "|---|" + "---|" * len(baselines)]
    tests = []  # (baseline, mean gap, p) of every gap with at least two seeds
    apart = []  # the seeds left out: two models
    for dataset in datasets:
        drop, row = finals(dataset, "drop"), [dataset]
        for b in baselines:
            other = finals(dataset, b)
            gaps = []
            for s in sorted(drop.keys() & other.keys()):
                gap = drop[s]["final"] - other[s]["final"]
                if same_model(drop[s], other[s]):
                    gaps.append(gap)
                else:
                    apart.append(f"{dataset} {b.upper()} seed {s} ({gap:+.1f})")
            row.append(gap_text(gaps))
            if len(gaps) >= 2:
                tests.append((b, *gap_test(gaps)[::2]))
        lines.append("| " + " | ".join(row) + " |")

    def counts(ps: list[float]) -> str:
        clear = {b: {"ahead": 0, "behind": 0} for b in baselines}
        for (b, mean, _), p in zip(tests, ps):
            if p < 0.05:
                clear[b]["ahead" if mean > 0 else "behind"] += 1
        return "; ".join(f"{b.upper()} {c['ahead']} ahead, {c['behind']} behind" for b, c in clear.items())

    if apart:
        lines += ["", f"Left out of the pairs, as the seed's DROP run and the baseline's trained on two ensembles (the "
                      f"same cache key on two CPU kinds), with DROP's final minus the baseline's: {'; '.join(apart)}."]
    raw = [p for _, _, p in tests]
    lines += ["", f"Datasets where DROP's gap has p under 0.05: {counts(raw)}. Of {len(tests)} tests, about "
              f"{0.05 * len(tests):.1f} would pass 0.05 by chance if no method differed from DROP; with Holm's "
              f"correction for the {len(tests)}: {counts(holm(raw))}."]
    return "\n".join(lines) + "\n"


def gap_test(gaps: list[float]) -> tuple[float, float, float]:
    """The mean of paired differences, its standard error and a two-sided one-sample t-test's p (two or more)."""
    mean, error = float(np.mean(gaps)), float(stats.sem(gaps))
    if error > 0:
        return mean, error, float(stats.ttest_1samp(gaps, 0.0).pvalue)
    # the same gap on every seed: the t-test's statistic is undefined (scipy: nan), the seeds agree
    return mean, error, 1.0 if mean == 0 else 0.0


def gap_text(gaps: list[float]) -> str:
    if len(gaps) < 2:
        return f"{gaps[0]:+.1f} (n=1)" if gaps else "-"
    mean, error, p = gap_test(gaps)
    return f"{mean:+.1f} ± {error:.1f} (n={len(gaps)}, {p_value(p)})"


def against(records: list[dict], plain: list[dict], overrides: list[str]) -> str:
    """An ablation's runs beside the preset's runs of the same file, method and seed. A seed's runs share one
    ensemble (the model cache's key leaves SAC's settings out), so the pairs differ by the overrides alone, and the
    difference is the ablation's effect on that seed; the collapse counts say whether it held the runs' scores. A run
    whose preset run trained on another ensemble (another CPU kind) is named apart, with no pair."""
    base = {(*key(r), r.get("dataset")): r for r in plain if r["algorithm"] != "bc"}
    found = sorted(((r, b) for r in records if r["algorithm"] != "bc"
                    and (b := base.get((*key(r), r.get("dataset")))) is not None
                    and not same_config(r.get("config"), b.get("config"))), key=lambda pair: key(pair[0]))
    if not found:
        return ""
    pairs, apart = [], []
    for r, b in found:
        (pairs if same_model(r, b) else apart).append((r, b))

    def run(r: dict) -> str:  # final/best only where best is positive: a ratio of negatives reads as held
        ratio = f", {r['final'] / r['best']:.2f}" if r["best"] > 0 else ""
        return f"{r['final']:.1f} ({r['best']:.1f}{ratio})"

    name = " ".join(overrides)
    lines = [""]
    if pairs:
        lines += [f"Each run beside the preset's run of the same file, method and seed, without {name} (final (best, "
                  "final/best)):", "", f"| dataset | method | seed | with {name} | without | difference |",
                  "|---|---|---|---|---|---|"]
        lines += [f"| {r['env']}-{r['kind']} | {r['algorithm'].upper()} | {r['seed']} | {run(r)} | {run(b)} | "
                  f"{r['final'] - b['final']:+.1f} |" for r, b in pairs]
        lines.append("")
    for algo in [a for a in ALGORITHMS if any(r["algorithm"] == a for r, _ in pairs)]:
        mine = [(r, b) for r, b in pairs if r["algorithm"] == algo]
        gaps = [r["final"] - b["final"] for r, b in mine]
        lines.append(f"- {algo.upper()}, every pair above: final with minus without {gap_text(gaps)}; no collapse "
                     f"(as the targets count it) in {sum(holds(r) for r, _ in mine)} of {len(mine)} runs with, "
                     f"{sum(holds(b) for _, b in mine)} without.")
    if apart:
        named = "; ".join(f"{r['env']}-{r['kind']} {r['algorithm'].upper()} seed {r['seed']} {run(r)} beside {run(b)} "
                          f"({r['final'] - b['final']:+.1f})" for r, b in apart)
        lines.append(f"- No pair, as the preset's run of the seed trained on another ensemble (the same cache key on "
                     f"another CPU kind), with {name} beside without: {named}.")
    return "\n".join(lines) + "\n"


def p_value(p: float) -> str:
    """Two significant digits under 0.1, so 0.0042 does not read as 0.00, nor 0.046 (counted under 0.05) as 0.05;
    more where two would round a p under 0.05 up to it (0.0496, 0.04995)."""
    if p < 0.001:
        return "p<0.001"
    if float(f"{p:.2g}") >= 0.1:
        return f"p={p:.2f}"
    digits = 2
    while p < 0.05 <= float(f"{p:.{digits}g}"):
        digits += 1
    return f"p={p:.{digits}g}"


def holm(pvalues: list[float]) -> list[float]:
    """Holm's step-down adjustment: the k-th smallest p is multiplied by (m - k + 1), and the adjusted values are kept
    in order. It holds the chance of any false "DROP differs" among the m tests under 0.05 without assuming them
    independent."""
    m, adjusted, running = len(pvalues), [0.0] * len(pvalues), 0.0
    for rank, index in enumerate(sorted(range(m), key=lambda i: pvalues[i])):
        running = max(running, min(1.0, (m - rank) * pvalues[index]))
        adjusted[index] = running
    return adjusted


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", default=str(CACHE), help="directory of ENV-KIND.hdf5 files (make bench-data)")
    p.add_argument("--envs", nargs="+", default=["hopper", "walker2d", "halfcheetah"])
    p.add_argument("--kinds", nargs="+", default=list(TASKS), choices=TASKS)
    p.add_argument("--algorithms", nargs="+", default=list(ALGORITHMS), choices=ALGORITHMS)
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--preset", default="cpu")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override for all runs")
    p.add_argument("--device", default="cpu", help="also which runs the table shows: a config names its device")
    p.add_argument("--episodes", type=int, default=10, help="evaluation episodes for BC")
    p.add_argument("--bc-steps", type=int, default=100_000)
    p.add_argument("--runs", default=str(Path.home() / ".cache/drop-rl/bench-runs"))
    p.add_argument("--model-cache", default=str(Path.home() / ".cache/drop-rl/models"),
                   help="trained ensembles shared by DROP, MOPO and MBPO on the same dataset and seed")
    p.add_argument("--out", default="bench/results")
    p.add_argument("--jobs", type=int, default=1, help="runs at once, one torch thread each")
    p.add_argument("--threads", type=int, default=None, help="torch threads per run (default: 1 with --jobs > 1)")
    p.add_argument("--new-file", action="store_true",
                   help="let a dataset file other than the one its table row was made on take that row over")
    p.add_argument("--owed", action="store_true",
                   help="only list the runs this setting's table lacks for --envs, --kinds, --algorithms and --seeds, "
                        "with the dataset file each must run on, and the drop collect commands for the files --data "
                        "lacks; train nothing")
    p.add_argument("--report", action="store_true",
                   help="only rewrite this setting's table (paper_table.md; paper_table_KEY-VALUE.md with --set) "
                        "from the recorded runs; train nothing")
    args = p.parse_args(argv)
    args.code = code_version(Path(__file__).resolve().parent.parent)  # what this invocation's runs import

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = out / "paper_table.json"
    same_setting = {"preset": args.preset, "set": sorted(args.set), "revision": REVISION}
    bc = bc_setting(args.bc_steps)
    kept = json.loads(results.read_text()) if results.exists() else {}
    behaviour: dict[str, dict] = {}
    # Each setting trains in its own directory, so a finished run of one setting is never taken for another's.
    runs = Path(args.runs) / "_".join([f"{args.preset}-r{REVISION}", *same_setting["set"]]).replace("/", "-")

    def write(record: dict | None = None, setting: dict = same_setting) -> str:
        """Merge into the file as it is now (another invocation may be filling other rows), under a lock."""
        with open(results.with_suffix(".lock"), "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            now = json.loads(results.read_text()) if results.exists() else {}
            merged = now.get("records", []) if record is None else merge(now.get("records", []), record, setting)
            scores = {name: described(entry) for name, entry in {**now.get("behaviour", {}), **behaviour}.items()}
            write_text(results, json.dumps({"behaviour": scores, "records": merged}, indent=2))
        mine = sorted(shown(on_file(merged, scores), setting_config(setting, args.device), bc), key=key)
        plain = shown(on_file(merged, scores), setting_config({**setting, "set": []}, args.device), bc)
        datasets = {f"{r['env']}-{r['kind']}" for r in mine if r["algorithm"] != "bc" or r["setting"] == setting}
        overrides = " ".join(setting["set"])
        text = (f"# Table 1 at CPU scale (preset `{args.preset}` revision {REVISION}"
                f"{', ' + overrides if overrides else ''}; D4RL normalised scores, mean ± std over n seeds)\n\n"
                f"BC: a tanh-Gaussian actor fitted by maximum likelihood for {args.bc_steps:,} steps, acting with its "
                f"mode, {args.episodes} episodes.\n\n"
                + table(mine, {d: v["score"] for d, v in sorted(scores.items()) if d in datasets}, list(ALGORITHMS))
                + carried(mine, setting)
                + (against(mine, plain, setting["set"]) if setting["set"] else ""))
        # Another preset, or a setting with overrides (an ablation), gets a table of its own: never the cpu preset's.
        preset = [] if args.preset == "cpu" else [args.preset]
        name = "_".join(["paper_table", *preset, *setting["set"]]).replace("/", "-").replace("=", "-")
        (out / f"{name}.md").write_text(text)
        return text

    if args.owed:
        datasets = [(env, kind) for env in args.envs for kind in args.kinds]
        lines = owed(kept, setting_config(same_setting, args.device), bc, datasets, args.algorithms, args.seeds)
        print("\n".join(lines.values()) or "nothing owed")
        if commands := collect_commands(list(lines), Path(args.data)):
            print(f"\nfiles these runs need that {args.data} lacks (made on another CPU kind, a file may differ "
                  "from the table's; one env's commands in turn, other envs beside them; then run the table with "
                  "--envs and --kinds naming rows whose files are there):\n" + "\n".join(commands))
        return 0
    if args.report:
        print(write())
        return 0

    paths = {(env, kind): Path(args.data) / f"{env}-{kind}.hdf5" for env in args.envs for kind in args.kinds}
    for (env, kind), path in paths.items():
        if not path.exists():
            raise SystemExit(f"{path} is missing: run `make bench-data` first")
        behaviour[f"{env}-{kind}"] = describe(path)
    if (others := displaced(kept, behaviour)) and not args.new_file:
        raise SystemExit("not the files of the table's rows (pass --new-file to start those rows over):\n  "
                         + "\n  ".join(others))
    wanted = setting_config(same_setting, args.device)
    done = {key(r) for r in shown(on_file(kept.get("records", []), behaviour), wanted, bc)}
    # Seed-major, so a stopped table has every algorithm on the same seeds rather than all seeds of a few; then
    # algorithm by algorithm across the datasets, so runs side by side are on different datasets and each trains its
    # own ensemble, instead of one waiting for the ensemble the other is training (the cache's lock).
    todo = [(path, behaviour[f"{env}-{kind}"]["dataset"], env, kind, algorithm, seed)
            for seed in args.seeds for algorithm in args.algorithms for (env, kind), path in paths.items()
            if (env, kind, algorithm, seed) not in done]

    # Runs side by side get one torch thread each, behaviour cloning included: two threads per run on a machine whose
    # cores are all taken spin-wait (BC took 5x longer). A speed setting, not part of a run's identity.
    threads = args.threads or (1 if args.jobs > 1 else None)
    with ProcessPoolExecutor(args.jobs, mp_context=get_context("spawn"),
                             initializer=torch.set_num_threads if threads else None, initargs=(threads,)) as pool:
        futures = [pool.submit(run_one, *job, args, Path(args.runs) / "bc" if job[4] == "bc" else runs)
                   for job in todo]
        for future in as_completed(futures):  # recorded as each ends: a stopped table keeps every finished run
            record = future.result()
            print(f"{record['env']}-{record['kind']} {record['algorithm']} seed {record['seed']}: "
                  f"final {record['final']:.1f}", flush=True)
            write(record)
            if (derived := latest_iterate(record, same_setting["set"])) is not None:
                without_average, rest = derived
                write(without_average, {**same_setting, "set": rest})
    print(write())
    return 0

if __name__ == "__main__":
    sys.exit(main())
