"""Stopping a long phase part-way. The phase asks the caller's stop flag between small units of work (batches, steps,
row chunks, env steps) and raises `Stopped`; whoever owns the phase's state catches it where that state is whole again
(the trainer: at a step or an epoch boundary) and drops the partial work, so a stop takes effect within one unit."""
from __future__ import annotations

from typing import Callable

StopFlag = Callable[[], bool]


class Stopped(Exception):
    """The caller asked to stop; raised from inside a phase, whose partial work is then discarded."""


def never() -> bool:
    return False


def check(should_stop: StopFlag) -> None:
    """Raise `Stopped` if the caller asks to stop now."""
    if should_stop():
        raise Stopped
