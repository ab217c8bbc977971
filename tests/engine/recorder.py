"""A callback that records everything a run reports and can ask it to stop from inside a chosen function."""
import inspect
import sys
from collections import Counter, defaultdict

from drop_engine.callbacks import Callback


def _code(fn):
    return inspect.unwrap(fn).__code__


class Recorder(Callback):
    """Records everything, and counts the asks to stop made from inside each function (`asked_in`); with `stop_in`,
    asks to stop from the ask after the first `after` of those made inside that function on."""

    def __init__(self, stop_in=None, after: int = 0):
        self.metrics, self.evaluations, self.checkpoints, self.phases, self.progress = [], [], [], set(), None
        self.steps = defaultdict(list)  # phase -> every (step, total) reported in it
        self.asks, self.stop_in, self.after, self.stopping, self.starts = Counter(), stop_in, after, False, []
        self.dynamics = []

    def asked_in(self, fn) -> int:
        return self.asks[_code(fn)]

    def on_start(self, resumed):
        self.starts.append(resumed)

    def on_progress(self, phase, epoch, step, total):
        self.phases.add(phase)
        self.steps[phase].append((step, total))
        self.progress = (epoch, step)

    def on_metrics(self, metrics, step):
        self.metrics.append((step, dict(metrics)))

    def on_dynamics(self, dynamics):
        self.dynamics.append(dict(dynamics))

    def on_evaluation(self, epoch, mean_return, normalized_score):
        self.evaluations.append((epoch, mean_return, normalized_score))

    def on_checkpoint(self, path, epoch, step):
        self.checkpoints.append(path)

    def should_stop(self):
        frame = sys._getframe(1)
        while frame is not None:
            self.asks[frame.f_code] += 1
            frame = frame.f_back
        self.stopping = self.stopping or (self.stop_in is not None and self.asked_in(self.stop_in) > self.after)
        return self.stopping
