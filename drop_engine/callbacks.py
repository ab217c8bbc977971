"""How a training run talks to its caller: progress, metrics, evaluations, checkpoints, and a stop flag.

The service's worker implements this against its database; the CLI draws a progress bar. Every method has a no-op
default so a caller overrides only what it needs.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Mapping, TextIO


class Callback:
    def on_start(self, resumed: tuple[int, int] | None) -> None:
        """Training begins, fresh (None) or from the checkpoint at (epoch, step); anything reported after that
        checkpoint by an earlier, lost run is superseded by what this run reports."""

    def on_progress(self, phase: str, epoch: int, step: int, total: int) -> None:
        """phase is 'dynamics' (its steps are epochs), 'behaviour_fit' (with sac.target_entropy='data'), 'train' or
        'export'; step counts within the phase, out of total."""

    def on_metrics(self, metrics: Mapping[str, float], step: int) -> None:
        """Named scalar metrics at a global SAC step (step 0 and negative for the dynamics phase)."""

    def on_dynamics(self, dynamics: Mapping[str, Any]) -> None:
        """The dynamics ensemble the run trains on, once fitted or fetched (and again on a resume): `cache_key`,
        `from_cache`, `cache_path` (None without a model cache) and the fit's report (`epochs`, `holdout_mse`,
        `elites`, `seconds`, `stopped_by`)."""

    def on_evaluation(self, epoch: int, mean_return: float, normalized_score: float) -> None:
        """An evaluation in the real env after `epoch` epochs."""

    def on_checkpoint(self, path: Path, epoch: int, step: int) -> None:
        """A checkpoint was written atomically at `path`."""

    def should_stop(self) -> bool:
        """Asked inside every phase, between batches, steps, row chunks or env steps, so it must be cheap. True stops
        the run within one of those: with a final checkpoint of the boundary before (a step, the epoch's start or the
        end of its SAC steps), or, in the dynamics phase, with none, as there is nothing to resume yet."""
        return False


class ProgressBar(Callback):
    """A tqdm bar over SAC steps showing the latest evaluation."""

    def __init__(self) -> None:
        self._bar = None
        self._phase = None

    def on_progress(self, phase: str, epoch: int, step: int, total: int) -> None:
        from tqdm import tqdm

        if phase != self._phase:
            self.close()
            self._phase = phase
            self._bar = tqdm(total=total or None, desc=phase, unit="epoch" if phase == "dynamics" else "step")
        self._bar.n = step
        self._bar.refresh()

    def on_dynamics(self, dynamics: Mapping[str, Any]) -> None:
        if dynamics.get("from_cache") and self._bar is not None:
            self._bar.set_description("dynamics (from the model cache)")

    def on_evaluation(self, epoch: int, mean_return: float, normalized_score: float) -> None:
        if self._bar is not None:
            self._bar.set_postfix(epoch=epoch, ret=f"{mean_return:.0f}", score=f"{normalized_score:.1f}")

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


class ProgressLine(Callback):
    """Plain progress lines for a log file (where tqdm's redrawn bars pile up): one when a phase or an epoch begins,
    at most one every `every_s` seconds within, and one per evaluation."""

    def __init__(self, stream: TextIO, every_s: float = 30.0):
        self.stream, self.every_s = stream, every_s
        self._key: tuple[str, int] | None = None
        self._last = 0.0

    def _print(self, text: str) -> None:
        print(text, file=self.stream, flush=True)
        self._last = time.monotonic()

    def on_progress(self, phase: str, epoch: int, step: int, total: int) -> None:
        key = (phase, epoch)
        if key == self._key and step != total and time.monotonic() - self._last < self.every_s:
            return
        self._key = key
        share = f" ({100 * step / total:.1f}%)" if total else ""
        of = f"/{total}" if total else ""  # a dynamics fit without an epoch cap (the paper preset) has no total
        where = f"epoch {epoch}, step {step}{of}" if phase == "train" else f"{step}{of}"
        self._print(f"{phase}: {where}{share}")

    def on_dynamics(self, dynamics: Mapping[str, Any]) -> None:
        if dynamics.get("from_cache"):
            self._print("dynamics: from the model cache")

    def on_evaluation(self, epoch: int, mean_return: float, normalized_score: float) -> None:
        self._print(f"evaluation: epoch {epoch}, return {mean_return:.1f}, score {normalized_score:.1f}")


def progress_reporter(enabled: bool, stream: TextIO) -> Callback:
    """A bar on a terminal, lines in a log file, or nothing."""
    if not enabled:
        return Callback()
    return ProgressBar() if stream.isatty() else ProgressLine(stream)


class CallbackList(Callback):
    """Several callbacks as one: every event goes to each, and any of them can ask to stop."""

    def __init__(self, *callbacks: Callback):
        self.callbacks = callbacks

    def on_start(self, resumed: tuple[int, int] | None) -> None:
        for cb in self.callbacks:
            cb.on_start(resumed)

    def on_progress(self, phase: str, epoch: int, step: int, total: int) -> None:
        for cb in self.callbacks:
            cb.on_progress(phase, epoch, step, total)

    def on_metrics(self, metrics: Mapping[str, float], step: int) -> None:
        for cb in self.callbacks:
            cb.on_metrics(metrics, step)

    def on_dynamics(self, dynamics: Mapping[str, Any]) -> None:
        for cb in self.callbacks:
            cb.on_dynamics(dynamics)

    def on_evaluation(self, epoch: int, mean_return: float, normalized_score: float) -> None:
        for cb in self.callbacks:
            cb.on_evaluation(epoch, mean_return, normalized_score)

    def on_checkpoint(self, path: Path, epoch: int, step: int) -> None:
        for cb in self.callbacks:
            cb.on_checkpoint(path, epoch, step)

    def should_stop(self) -> bool:
        return any(cb.should_stop() for cb in self.callbacks)
