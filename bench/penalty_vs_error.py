"""The paper's Fig. 2: does each penalty track the model's true error?

For offline (s, a) from the dataset and model-rollout (s, a) of a trained DROP run, the true error
||T^(s, a) - T(s, a)|| over [r, s'] is measured by stepping the real simulator, and set beside DROP's penalty
eta * g(tau_k(s, a)) and MOPO's u(s, a) from the same ensemble. Writes JSON, a markdown summary and a scatter plot.

    python bench/penalty_vs_error.py --dataset hopper-medium.hdf5 --run runs/hopper-drop [--samples 10000]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import h5py
import numpy as np
import torch
import torch.nn.functional as F
from scipy import stats
from torch import nn

from drop_engine.checkpoint import load_latest
from drop_engine.config import TrainConfig
from drop_engine.data import load_dataset
from drop_engine.dice import GradientDice
from drop_engine.penalties import ratio_penalty, uncertainty_penalty
from drop_engine.replay_buffer import ReplayBuffer
from drop_engine.rollout import model_rollout
from drop_engine.trainer import Trainer
from drop_engine.true_dynamics import true_step


def restore(dataset: str, run: str) -> tuple[Trainer, object]:
    state = load_latest(Path(run) / "checkpoints")
    if state is None:
        raise SystemExit(f"no checkpoint under {run}/checkpoints")
    cfg = TrainConfig.model_validate(state["config"])
    if cfg.algorithm != "drop":
        raise SystemExit(f"{run} is a {cfg.algorithm} run; DROP's ratio estimators are needed")
    data = load_dataset(dataset, env=cfg.env)
    trainer = Trainer(data, cfg, Path(run) / ".bench")
    trainer.load_state_dict(state)
    return trainer, data


@torch.no_grad()
def penalties_and_error(trainer: Trainer, obs, act, qpos=None, qvel=None) -> dict[str, np.ndarray]:
    cfg, model = trainer.cfg, trainer.model
    o, a = torch.as_tensor(obs), torch.as_tensor(act)
    mean, logvar = model(o, a)
    elite_mean = mean[model.elites].mean(0).numpy()
    true_r, true_next = true_step(cfg.env, obs, act, qpos, qvel, trainer.env_version)
    truth = np.concatenate([true_r[:, None], true_next - obs], 1)
    # The unclamped g(tau): the figure compares how each penalty ranks (s, a), whatever the run's bonus setting.
    unclamped = cfg.penalty.model_copy(update={"bonus": True})
    tau = trainer.dice.tau(o, a)
    drop = (cfg.penalty.eta * ratio_penalty(tau, unclamped)).mean(0).numpy()
    mopo = (cfg.penalty.mopo_lambda * uncertainty_penalty(logvar)).numpy()
    return {"error": np.linalg.norm(elite_mean - truth, axis=1), "drop": drop, "mopo": mopo, "tau": tau.mean(0).numpy()}


def model_input(trainer: Trainer, obs, act) -> torch.Tensor:
    """(s, a) in the dynamics model's standardised input space, where distances from the data are measured."""
    model = trainer.model
    return (torch.cat([torch.as_tensor(obs), torch.as_tensor(act)], -1) - model.in_mean) / model.in_std


@torch.no_grad()
def rollout_rows(trainer: Trainer, samples: int) -> ReplayBuffer:
    """The final policy's h-step model rollouts from `samples` data states, as the run's DROP rollouts are made."""
    cfg, data = trainer.cfg, trainer.data
    buffer = ReplayBuffer(samples * cfg.horizon, data.obs_dim, data.act_dim)
    model_rollout(trainer.sac.actor, trainer.model, trainer.dice, trainer.real.sample(samples)[0], cfg.horizon, "drop",
                  cfg.penalty, trainer.termination, buffer)
    return buffer


@torch.no_grad()
def nearest_data_row(trainer: Trainer, obs, act, reference: np.ndarray, chunk: int = 256):
    """Each (s, a)'s distance to the nearest of the `reference` data rows, in the dynamics model's standardised input
    space (how far from the data it lies, what a density ratio ranks by), and that row's index in the data."""
    ref = model_input(trainer, trainer.data.observations[reference], trainer.data.actions[reference])
    x = model_input(trainer, obs, act)
    nearest = [torch.cdist(x[i:i + chunk], ref).min(1) for i in range(0, len(x), chunk)]
    distance = torch.cat([n.values for n in nearest]).numpy()
    return distance, reference[torch.cat([n.indices for n in nearest]).numpy()]


def fresh_estimator(trainer: Trainer, hidden: tuple[int, ...], seed: int) -> GradientDice:
    """An untrained ratio estimator of other widths, with the run's other DICE settings and observation scaling."""
    cfg = trainer.cfg
    torch.manual_seed(seed)
    dice = GradientDice(cfg.dynamics.elites, trainer.data.obs_dim, trainer.data.act_dim,
                        cfg.dice.model_copy(update={"hidden": hidden}), cfg.dice_discount)
    dice.norm.load_state_dict(trainer.dice.norm.state_dict())
    return dice


def classifier_log_ratio(trainer: Trainer, reference: np.ndarray, samples: int, steps: int = 3000):
    """log d_rollout(s, a) / d_D(s, a) by a plain method, as a reference for what DROP's tau estimates: the logit of a
    classifier between the final policy's model-rollout (s, a), from fresh starts, and data rows (`reference`, none of
    the scored ones), fitted on balanced batches so that its logit is the log density ratio. If this ratio tracks the
    model's error where tau does not, the bound is the GradientDICE estimate; if it does not either, the occupancy
    ratio itself does not rank (s, a) by the model's error on this file."""
    buffer = rollout_rows(trainer, samples)
    pos = model_input(trainer, *buffer.take(torch.arange(len(buffer)))[:2])
    neg = model_input(trainer, trainer.data.observations[reference], trainer.data.actions[reference])
    net = nn.Sequential(nn.Linear(pos.shape[1], 256), nn.ReLU(), nn.Linear(256, 256), nn.ReLU(), nn.Linear(256, 1))
    optim = torch.optim.Adam(net.parameters(), lr=1e-3)
    labels = torch.cat([torch.ones(256), torch.zeros(256)])
    for _ in range(steps):
        x = torch.cat([pos[torch.randint(len(pos), (256,))], neg[torch.randint(len(neg), (256,))]])
        loss = F.binary_cross_entropy_with_logits(net(x).squeeze(-1), labels)
        optim.zero_grad()
        loss.backward()
        optim.step()

    @torch.no_grad()
    def log_ratio(obs, act) -> np.ndarray:
        return net(model_input(trainer, obs, act)).squeeze(-1).numpy()

    return log_ratio


def correlations(rows: dict[str, np.ndarray]) -> dict:
    """Each penalty against the true error; and the penalties and the error against the distance from the data
    (where the error does not rise with the distance, no penalty that measures the distance can track the error)."""
    out = {}
    penalties = [name for name in ("drop", "mopo", "classifier") if name in rows]
    for name in penalties:
        out[name] = {"spearman": float(stats.spearmanr(rows[name], rows["error"]).statistic),
                     "pearson": float(stats.pearsonr(rows[name], rows["error"]).statistic)}
    for against in ("distance", "policy_logp"):
        if against in rows:
            out[f"vs_{against}"] = {name: float(stats.spearmanr(rows[name], rows[against]).statistic)
                                    for name in (*penalties, "error")}
    return out


def scatter(groups: dict[str, dict[str, np.ndarray]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for ax, name in zip(axes, ("drop", "mopo")):
        for label, rows in groups.items():
            p = rows[name]
            p = (p - p.min()) / max(p.max() - p.min(), 1e-12)
            ax.scatter(rows["error"], p, s=2, alpha=0.3, label=label)
        ax.set_xlabel("true model error ||T^(s,a) - T(s,a)||")
        ax.set_title(f"{name.upper()} penalty (normalised)")
        ax.legend(markerscale=5)
    axes[0].set_ylabel("penalty, scaled to [0, 1]")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dataset", required=True)
    p.add_argument("--run", required=True, help="a DROP run directory (its newest checkpoint is used)")
    p.add_argument("--samples", type=int, default=10_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="bench/results")
    p.add_argument("--threads", type=int, default=1, help="torch threads (two probes side by side: 1 each)")
    p.add_argument("--stem", help="output file names, without suffix (default: penalty_vs_error_ENV)")
    p.add_argument("--dice-steps", type=int, default=0,
                   help="first train the run's ratio estimators this many more steps, the final policy fixed: does a "
                        "longer-trained tau rank (s, a) otherwise? (reference implementations: about 100,000 steps)")
    p.add_argument("--dice-batch", type=int, help="their batch for --dice-steps (default: the run's)")
    p.add_argument("--dice-hidden", type=lambda v: tuple(int(w) for w in v.split(",")),
                   help="train a fresh estimator of these widths (e.g. 256,256) for --dice-steps instead of the run's: "
                        "does a larger tau resolve the data's density where the model's error changes?")
    p.add_argument("--classifier-ratio", action="store_true",
                   help="also rank (s, a) by a classifier's log density ratio of the policy's model rollouts to the "
                        "data: the ratio DROP estimates, by a plain method")
    args = p.parse_args(argv)
    if args.dice_hidden and not args.dice_steps:
        p.error("--dice-hidden needs --dice-steps: a fresh estimator must be trained")
    torch.set_num_threads(args.threads)
    trainer, data = restore(args.dataset, args.run)
    if args.dice_hidden:
        trainer.dice = fresh_estimator(trainer, args.dice_hidden, args.seed)
    if args.dice_steps:
        dice = trainer.cfg.dice.model_copy(update={"batch_size": args.dice_batch or trainer.cfg.dice.batch_size})
        trainer.cfg = trainer.cfg.model_copy(update={"dice": dice})
        trainer.train_dice(args.dice_steps)
    cfg = trainer.cfg
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)

    idx = rng.choice(len(data), size=min(args.samples, len(data)), replace=False)
    qpos = qvel = None  # the recorded simulator state, where the file has it
    with h5py.File(args.dataset, "r") as f:
        if "infos/qpos" in f and len(f["infos/qpos"]) == len(data):
            qpos, qvel = f["infos/qpos"][()][idx], f["infos/qvel"][()][idx]
    offline = penalties_and_error(trainer, data.observations[idx], data.actions[idx], qpos, qvel)

    buffer = rollout_rows(trainer, args.samples)
    obs, act, *_ = buffer.take(torch.randperm(len(buffer))[: args.samples])
    rollout = penalties_and_error(trainer, obs.numpy(), act.numpy())
    # The data's rows outside the offline sample (up to 100,000), so an offline row is not its own nearest.
    reference = rng.permutation(np.setdiff1d(np.arange(len(data)), idx))[:100_000]
    if not len(reference):  # the sample is the whole file: each offline row is then its own nearest
        reference = np.arange(len(data))
    offline["distance"], _ = nearest_data_row(trainer, data.observations[idx], data.actions[idx], reference)
    # On data rows the true ratio carries pi(a|s)/beta(a|s): a ratio estimate that knows the policy rises with it.
    with torch.no_grad():
        offline["policy_logp"] = trainer.sac.actor.log_prob(torch.as_tensor(data.observations[idx]),
                                                            torch.as_tensor(data.actions[idx])).numpy()
    rollout["distance"], nearest = nearest_data_row(trainer, obs.numpy(), act.numpy(), reference)
    # GradientDICE's objective reads tau only at data rows; a rollout's tau is the network's extrapolation. How much
    # of it is the ratio already at the nearest data row?
    at_nearest = penalties_and_error(trainer, data.observations[nearest], data.actions[nearest])
    if args.classifier_ratio:
        log_ratio = classifier_log_ratio(trainer, reference, args.samples)
        offline["classifier"] = log_ratio(data.observations[idx], data.actions[idx])
        rollout["classifier"] = log_ratio(obs.numpy(), act.numpy())

    groups = {"offline": offline, "model rollout": rollout}
    both = {k: np.concatenate([offline[k], rollout[k]]) for k in rollout}
    result = {"env": cfg.env, "run": args.run, "dataset": args.dataset, "samples": args.samples,
              "extra_dice_steps": args.dice_steps, "dice_batch": cfg.dice.batch_size,
              "dice_hidden": list(args.dice_hidden or cfg.dice.hidden), "fresh_dice": bool(args.dice_hidden),
              "dataset_attrs": {k: str(v) for k, v in data.attrs.items()},
              "correlations": {"offline": correlations(offline), "model_rollout": correlations(rollout),
                               "all": correlations(both)},
              "mean_error": {"offline": float(offline["error"].mean()),
                             "model_rollout": float(rollout["error"].mean())},
              # The ratio's normalisation on the data (about 1) and its spread, and on the rollouts.
              "tau": {group: {"mean": float(rows["tau"].mean()), "std": float(rows["tau"].std())}
                      for group, rows in groups.items()},
              "mean_distance": {"offline": float(offline["distance"].mean()),
                                "model_rollout": float(rollout["distance"].mean())},
              "rollout_vs_nearest_data_row": {
                  name: float(stats.spearmanr(rollout[name], at_nearest[name]).statistic)
                  for name in ("drop", "mopo", "error")}}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = args.stem or f"penalty_vs_error_{cfg.env}"
    (out / f"{stem}.json").write_text(json.dumps(result, indent=2))
    scatter(groups, out / f"{stem}.png")
    name = f"{cfg.env}-{cfg.task}" if cfg.task else cfg.env
    extra = f"; the ratio {args.dice_steps} steps more at batch {cfg.dice.batch_size}" if args.dice_steps else ""
    if args.dice_hidden:
        extra = (f"; a fresh {'-'.join(map(str, args.dice_hidden))} ratio trained {args.dice_steps} steps at batch "
                 f"{cfg.dice.batch_size} on the final policy")
    lines = [f"# Penalty vs true model error ({name}, {args.samples} offline + {args.samples} rollout samples{extra})",
             "",
             "| samples | penalty | Spearman | Pearson |", "|---|---|---|---|"]
    for group, corr in result["correlations"].items():
        for name in ("drop", "mopo"):
            lines.append(f"| {group} | {name} | {corr[name]['spearman']:.3f} | {corr[name]['pearson']:.3f} |")
    on_data, on_rollouts = result["tau"]["offline"], result["tau"]["model rollout"]
    lines += ["", f"tau (mean over the elites' estimators): on the data rows {on_data['mean']:.3f} ± "
              f"{on_data['std']:.3f} (mean ± sd over rows), on the rollouts {on_rollouts['mean']:.3f} ± "
              f"{on_rollouts['std']:.3f}."]
    lines += ["", "Spearman with the distance to the nearest data row (standardised (s, a); mean distance offline "
              f"{result['mean_distance']['offline']:.2f}, rollout {result['mean_distance']['model_rollout']:.2f}):",
              "", "| samples | DROP penalty | MOPO penalty | true error |", "|---|---|---|---|"]
    for group, corr in result["correlations"].items():
        d = corr["vs_distance"]
        lines.append(f"| {group} | {d['drop']:.3f} | {d['mopo']:.3f} | {d['error']:.3f} |")
    if args.classifier_ratio:
        lines += ["", "A classifier's log density ratio of the policy's model rollouts to the data (the ratio DROP "
                  "estimates, by a plain method), Spearman:", "",
                  "| samples | vs true error | vs distance | vs log pi(a\\|s) |", "|---|---|---|---|"]
        for group, corr in result["correlations"].items():
            logp = corr.get("vs_policy_logp", {}).get("classifier")
            cells = [f"{corr['classifier']['spearman']:.3f}", f"{corr['vs_distance']['classifier']:.3f}",
                     f"{logp:.3f}" if logp is not None else ""]
            lines.append(f"| {group} | " + " | ".join(cells) + " |")
    d = result["correlations"]["offline"]["vs_policy_logp"]
    lines += ["", "Spearman with the policy's log-likelihood of the data action, log pi(a|s), on the offline rows (the "
              "true ratio there carries pi(a|s) / beta(a|s)):", "", "| DROP penalty | MOPO penalty | true error |",
              "|---|---|---|", f"| {d['drop']:.3f} | {d['mopo']:.3f} | {d['error']:.3f} |"]
    d = result["rollout_vs_nearest_data_row"]
    lines += ["", "Spearman of each at a rollout's (s, a) with the same at its nearest data row (DICE's objective "
              "reads tau only at data rows; a rollout's is extrapolated):", "",
              "| DROP penalty | MOPO penalty | true error |", "|---|---|---|",
              f"| {d['drop']:.3f} | {d['mopo']:.3f} | {d['error']:.3f} |"]
    (out / f"{stem}.md").write_text("\n".join(lines) + f"\n\n![scatter]({stem}.png)\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
