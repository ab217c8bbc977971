"""Presets compose with the per-dataset table and overrides; bad overrides are rejected by name."""
import pytest

from drop_engine.config import CPU_BC_WEIGHT, PRESETS, TrainConfig, build_config, override_dict, parse_override
from drop_engine.errors import ConfigError


def test_paper_preset_uses_official_dataset_settings():
    cfg = build_config("drop", env="walker2d", preset="paper", task="medium-replay")
    assert cfg.epochs == 3000 and cfg.rollout.horizon == 1
    assert cfg.penalty.eta == 2.0 and cfg.penalty.clip == (0.01, 50.0)
    assert cfg.dice.steps_per_epoch == 600 and cfg.sac.target_entropy == -3.0
    mopo = build_config("mopo", env="halfcheetah", preset="paper", task="medium")
    assert mopo.horizon == 1 and mopo.penalty.mopo_lambda == 1.0


def test_overrides_apply_last_and_nest():
    cfg = build_config("drop", env="hopper", preset="cpu", task="medium", overrides={"dice.lr": 1e-3, "epochs": 7,
                                                                          "penalty": {"g": "tanh"}})
    assert cfg.dice.lr == 1e-3 and cfg.epochs == 7 and cfg.penalty.g == "tanh" and cfg.penalty.eta == 5.0


@pytest.mark.parametrize("overrides, field", [
    ({"dice.lr": 1e-3, "dice": {"lr": 2e-3}}, "dice.lr: given twice"),
    ({"dice": {"lr": 2e-3}, "dice.lr": 1e-3}, "dice.lr: given twice"),
    ({"dice": 1, "dice.lr": 1e-3}, "dice: set as a value and as a group"),
    ({"dice.lr": 1e-3, "dice": 1}, "dice: set as a value and as a group"),
    ({"sac.hidden": [64, 64], "sac": {"hidden": [32]}}, "sac.hidden: given twice"),
])
def test_a_field_given_twice_is_refused_by_name(overrides, field):
    """Neither spelling silently wins; the caller's own dicts are not changed either."""
    before = repr(overrides)
    with pytest.raises(ConfigError, match=field):
        build_config("drop", env="hopper", preset="cpu", overrides=overrides)
    assert repr(overrides) == before
    merged = build_config("drop", env="hopper", preset="cpu", overrides={"dice.lr": 1e-3, "dice": {"lam": 0.5}})
    assert (merged.dice.lr, merged.dice.lam) == (1e-3, 0.5)


@pytest.mark.parametrize("overrides, message", [
    ({"dice.learning_rate": 1}, "dice.learning_rate: Extra inputs are not permitted"),
    ({"epochs": 0}, "epochs: Input should be greater than or equal to 1"),
    ({"penalty.g": "cube"}, "penalty.g: Input should be 'log', 'tanh' or 'tanh_shift'"),
    ({"dynamics.elites": 9}, "elites (9) cannot exceed members (7)"),
    ({"sac.gamma": "high"}, "sac.gamma: Input should be a valid number"),
])
def test_bad_overrides_name_the_field(overrides, message):
    with pytest.raises(ConfigError) as info:
        build_config("drop", env="hopper", preset="cpu", overrides=overrides)
    assert message in str(info.value)


def test_unknown_algorithm_preset_and_task():
    with pytest.raises(ConfigError, match="algorithm"):
        build_config("cql", env="hopper", preset="cpu")
    with pytest.raises(ConfigError, match="unknown preset 'huge'"):
        build_config("drop", env="hopper", preset="huge")
    with pytest.raises(ConfigError, match="task: 'medium_replay' is not one of random, medium, medium-replay"):
        build_config("drop", env="walker2d", preset="cpu", task="medium_replay")
    no_task = build_config("drop", env="walker2d", preset="cpu")
    assert no_task.rollout.horizon == build_config("drop", env="walker2d", preset="cpu", task="medium").rollout.horizon


def test_paper_preset_stays_faithful_and_cpu_adds_the_stabilisers():
    paper = build_config("drop", env="hopper", preset="paper", task="medium")
    assert paper.sac.bc_weight == 0 and not paper.sac.value_bound and not paper.dice.positive and paper.penalty.bonus
    assert paper.dice_discount == paper.sac.gamma
    cpu = {(algo, task): build_config(algo, env="hopper", preset="cpu", task=task)
           for algo in ("drop", "mopo", "mbpo") for task in ("medium", "medium-replay")}
    for task in ("medium", "medium-replay"):  # alike for the three methods, by dataset kind
        assert {(c.sac.bc_weight, c.sac.value_bound) for (_, t), c in cpu.items() if t == task} == {
            (CPU_BC_WEIGHT[task], True)}
    assert all(weight > 0 for weight in CPU_BC_WEIGHT.values())
    assert {c.sac.bc_action for c in cpu.values()} == {"likelihood"}
    assert {c.sac.target_entropy for c in cpu.values()} == {"data"} and paper.sac.target_entropy == -3.0
    drop = build_config("drop", env="hopper", preset="cpu", task="medium")
    assert drop.dice.positive and not drop.penalty.bonus and drop.eval_episodes == 10
    assert drop.dynamics.max_seconds is None and drop.dynamics.max_epochs
    assert drop.dice_discount == pytest.approx(4 / 6)  # h = 5: mean step 2, as uniform over the 5 rollout steps
    assert build_config("drop", env="walker2d", preset="cpu", task="medium-replay").dice_discount == 0.0  # h = 1


def test_dice_discount_override_is_checked():
    assert build_config("drop", env="hopper", preset="cpu", overrides={"dice.discount": 0.5}).dice_discount == 0.5
    with pytest.raises(ConfigError, match="dice.discount: Input should be less than 1"):
        build_config("drop", env="hopper", preset="cpu", overrides={"dice.discount": 1.5})


@pytest.mark.parametrize("preset", PRESETS)
def test_presets_never_cap_dynamics_by_wall_clock(preset):
    """A time cap would make the model, and so the whole run, depend on how busy the machine is."""
    dynamics = build_config("drop", env="hopper", preset=preset).dynamics
    assert dynamics.max_seconds is None
    assert dynamics.max_epochs is not None or preset == "paper"


def _unbounded(schema: dict, defs: dict, path: str):
    """Paths of the numbers and sequences in a JSON schema that have no upper bound."""
    if "$ref" in schema:
        schema = defs[schema["$ref"].rsplit("/", 1)[-1]]
    for branch in schema.get("anyOf", []):
        yield from _unbounded(branch, defs, path)
    kind = schema.get("type")
    if kind in ("integer", "number") and not {"maximum", "exclusiveMaximum"} & schema.keys():
        yield path
    if kind == "array":
        if "maxItems" not in schema:
            yield f"{path} (length)"
        items = schema.get("prefixItems", []) + ([schema["items"]] if isinstance(schema.get("items"), dict) else [])
        for item in items:
            yield from _unbounded(item, defs, f"{path}[]")
    for name, prop in schema.get("properties", {}).items():
        yield from _unbounded(prop, defs, f"{path}.{name}".lstrip("."))


def test_every_number_and_tuple_of_every_config_is_bounded_above():
    schema = TrainConfig.model_json_schema()
    assert list(_unbounded(schema, schema.get("$defs", {}), "")) == []


@pytest.mark.parametrize("overrides, message", [
    ({"rollout.batch_size": 10**9}, "rollout.batch_size: Input should be less than or equal to 1000000"),
    ({"sac.hidden": [256, 10**6]}, "sac.hidden.1: Input should be less than or equal to 4096"),
    ({"dynamics.layers": 100}, "dynamics.layers: Input should be less than or equal to 8"),
    ({"sac.batch_size": 10**7}, "sac.batch_size: Input should be less than or equal to 65536"),
    ({"eval_episodes": 10**6}, "eval_episodes: Input should be less than or equal to 1000"),
    ({"epochs": 10**9}, "epochs: Input should be less than or equal to 100000"),
    ({"log_every": 10**12}, "log_every: Input should be less than or equal to 1000000"),
    ({"dice.hidden": [8] * 50}, "dice.hidden: Tuple should have at most 8 items"),
    ({"seed": 2**32}, "seed: Input should be less than 4294967296"),
])
def test_absurd_values_are_refused_by_name(overrides, message):
    with pytest.raises(ConfigError) as info:
        build_config("drop", env="hopper", preset="cpu", overrides=overrides)
    assert message in str(info.value)


NAN, INF = float("nan"), float("inf")


@pytest.mark.parametrize("overrides, field", [
    ({"sac.actor_lr": NAN}, "sac.actor_lr"),
    ({"penalty.eta": INF}, "penalty.eta"),
    ({"sac.target_entropy": -INF}, "sac.target_entropy"),
    ({"dynamics.max_seconds": INF}, "dynamics.max_seconds"),
    ({"penalty.clip": (0.01, INF)}, "penalty.clip.1"),
    ({"dynamics.weight_decay": (1e-4, NAN)}, "dynamics.weight_decay.1"),
    ({"dice.discount": NAN}, "dice.discount"),  # a union: named without pydantic's branch tag (`.float`)
])
def test_non_finite_numbers_are_refused_by_name(overrides, field):
    with pytest.raises(ConfigError) as info:
        build_config("drop", env="hopper", preset="cpu", overrides=overrides)
    assert str(info.value).startswith(f"{field}: Input should be a finite number")


def test_a_key_set_twice_on_the_command_line_is_refused():
    with pytest.raises(ConfigError, match="dice.lr: given twice"):
        override_dict([parse_override("dice.lr=1e-3"), parse_override("epochs=3"), parse_override("dice.lr=2e-3")])
    assert override_dict([parse_override("dice.lr=1e-3"), parse_override("epochs=3")]) == {"dice.lr": 1e-3, "epochs": 3}


def test_overrides_read_json_values_and_keep_the_rest_as_text():
    """One reading for `drop train --set`, the remote `--set` and the paper table's `--set`: a list stays a list and
    null is None, so `sac.hidden=[64,64]` means the same everywhere."""
    assert parse_override("sac.hidden=[64,64]") == ("sac.hidden", [64, 64])
    assert parse_override("sac.value_bound=true") == ("sac.value_bound", True)
    assert parse_override("sac.target_entropy=data") == ("sac.target_entropy", "data")
    assert parse_override("note=a=b") == ("note", "a=b")
    cfg = build_config("drop", env="hopper", overrides=dict([parse_override("sac.hidden=[64,64]")]))
    assert cfg.sac.hidden == (64, 64)
    with pytest.raises(ConfigError, match="'epochs' is not KEY=VALUE"):
        parse_override("epochs")
