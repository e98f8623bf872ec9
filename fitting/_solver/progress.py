"""Progress meters: what the loop reports after each step, to a terminal or nowhere."""

import abc
import dataclasses
import sys
from typing import Any, TextIO

import equinox as eqx
import numpy as np

from piezojax import PiezojaxValueError

# ---------------------------------------------------------------------------------------------------- progress


@dataclasses.dataclass(frozen=True)
class Progress:
    """What a progress meter is told after each step of `iterate`."""

    label: str  # e.g. "[smoothing 0.02] " (empty for a plain fit)
    step: int
    best_cost: float  # the lowest accepted cost over the starts
    accepted: int  # accepted steps of the first start
    running: int  # starts not yet finished
    starts: int
    seconds: float  # since the level began


class AbstractProgressMeter(eqx.Module):
    """Reports a fit's progress (as diffrax's progress meters): `init` when a level of the fit begins, `step` after
    every step, `close` at its end (also after Ctrl-C). Subclass it to log elsewhere (a notebook widget, a file)."""

    @abc.abstractmethod
    def init(self, label: str, starts: int) -> Any:
        """The meter's state at the start of a level."""

    @abc.abstractmethod
    def step(self, state: Any, progress: Progress) -> Any:
        """Report `progress`; returns the new state."""

    @abc.abstractmethod
    def close(self, state: Any) -> None:
        """The level ended."""


class NoProgressMeter(AbstractProgressMeter):
    """Reports nothing (`solve(..., progress=False)`)."""

    def init(self, label, starts):
        return None

    def step(self, state, progress):
        return state

    def close(self, state):
        return None


class TextProgressMeter(AbstractProgressMeter):
    """Step, (best) cost, accepted steps or running starts, and elapsed time, on `stream` (default: `sys.stderr` at
    the time of the fit).

    On a terminal, one live line rewritten in place after every step. Elsewhere (a log file, a pipe, a notebook's
    captured stream) one complete line per update: the first step, then at most one line every `interval` seconds,
    and the last step when the level ends — so a redirected log reads line by line instead of as one long line of
    carriage returns."""

    stream: TextIO | None = None
    interval: float = 2.0

    def _out(self):
        return sys.stderr if self.stream is None else self.stream

    def init(self, label, starts):
        try:
            live = bool(self._out().isatty())
        except (AttributeError, ValueError, OSError):  # no isatty, or a closed stream
            live = False
        return {"live": live, "printed_at": None, "pending": None}

    def step(self, state, progress):
        p = progress
        what = (f"cost {p.best_cost:.6e}  accepted {p.accepted:4d}" if p.starts == 1 else
                f"best cost {p.best_cost:.6e}  running {p.running}/{p.starts}")
        line = f"  {p.label}step {p.step:4d}  {what}  {p.seconds:7.1f} s"
        if state["live"]:
            print(f"\r{line}", end="", file=self._out(), flush=True)
            return state
        if state["printed_at"] is None or p.seconds - state["printed_at"] >= self.interval:
            print(line, file=self._out(), flush=True)
            return {**state, "printed_at": p.seconds, "pending": None}
        return {**state, "pending": line}

    def close(self, state):
        if state is None or state["live"]:
            print(file=self._out(), flush=True)
        elif state["pending"] is not None:
            print(state["pending"], file=self._out(), flush=True)


def as_progress_meter(progress) -> AbstractProgressMeter:
    """`True` → `TextProgressMeter()`, `False`/`None` → `NoProgressMeter()`, a meter → itself."""
    if isinstance(progress, AbstractProgressMeter):
        return progress
    if progress is None or isinstance(progress, bool | int | np.bool_ | np.integer):
        return TextProgressMeter() if progress else NoProgressMeter()
    raise PiezojaxValueError(f"`progress` must be True, False or a fitting.AbstractProgressMeter, got {progress!r}")


