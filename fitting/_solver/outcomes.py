"""How a fit ends, in one place: the results enumeration `RESULTS` with its messages (carried through the loop as
each start's state), and everything derived from it — the success and hard-failure sets, the code a result reports
(`result_code`), a start's `Verdict` with the numbers of its fit (`verdict_of`) — and `FitError`."""

from typing import NamedTuple

import equinox as eqx
import numpy as np

from piezojax import PiezojaxError

# ---------------------------------------------------------------------------------------------------- results


_MESSAGES = {
    "successful": "converged",
    "successful_flat": "converged: the accepted steps no longer lower the cost",
    "converged_at_kink": "converged at a kink of the piecewise smooth cost",
    "converged_zero_residual": "converged to a zero residual",
    "max_steps_reached": "the maximum number of steps was reached before convergence",
    "stalled": "no decrease of the cost in many consecutive trial steps (stalled or diverging)",
    "not_stationary": "stopped where the cost is not stationary",
    "outpaced": "stopped: another start converged at a lower cost that this one would not reach within max_steps",
    "interrupted": "interrupted by the user (Ctrl-C)",
    "nonfinite_initial": "the model's predictions or Jacobian are not finite at the initial parameters",
    "nonfinite": "the Jacobian is not finite at an accepted point",
    "linear_solve_failed": "the linear solve of a damped step failed",
    "running": "running: not stopped yet",
    "padding": "not a fit: a row that fills a fleet's last batch",
}

NAMES = tuple(_MESSAGES)
"""The names of the `RESULTS` items, in order."""

RESULTS = type(eqx.Enumeration)("RESULTS", (eqx.Enumeration,), {"__module__": __name__, **_MESSAGES, "__doc__": """\
How a fit ended (an `eqx.Enumeration`, as `optx.RESULTS`): `RESULTS[item]` is the message. `FitResult.code` is the
name of the item (`result_code`), `FitResult.reason` the message with the numbers of that fit.

The loop carries one item per start: `running` until the start stops, then why it stopped. `running` and `padding`
(a row that fills a fleet's last batch and never runs) are never a fit's code; `successful_flat` (the loop's own
convergence test) is reported as `successful`. The names in order: `NAMES`."""})


_REPORTED_AS = {"successful_flat": "successful"}
"""Items reported under another item's name (two tests of convergence, one code)."""

LOOP_ONLY = ("running", "padding")
"""Items that only the loop carries: never a fit's code."""

SUCCESSES = ("successful", "converged_at_kink", "converged_zero_residual")
"""The codes of a converged fit."""

HARD_FAILURES = ("interrupted", "nonfinite_initial", "nonfinite", "linear_solve_failed", "outpaced")
"""The codes after which a start is not continued (to the next smoothing level, or past a kink): the failures, and
a start of a multi-start fit that another outpaced (`iterate`)."""

CODES = tuple(dict.fromkeys(_REPORTED_AS.get(n, n) for n in NAMES if n not in LOOP_ONLY))
"""Every code a fit can report, in the order of `RESULTS`."""


def result_names(item) -> str | list[str]:
    """The name of a `RESULTS` item (`"running"`, `"successful_flat"`, ...); for a batch of items, the list of
    names."""
    values = np.asarray(item == RESULTS.successful)
    names = np.full(values.shape, "", dtype=object)
    for name in NAMES:
        names[np.asarray(item == getattr(RESULTS, name))] = name
    return str(names) if names.ndim == 0 else [str(n) for n in names]


def result_code(item) -> str | list[str]:
    """The code a fit reports for a `RESULTS` item (its name; `successful_flat` reports `"successful"`); for a batch
    of items, the list of codes."""
    names = result_names(item)
    return _REPORTED_AS.get(names, names) if isinstance(names, str) else [_REPORTED_AS.get(n, n) for n in names]


def result_message(code: str) -> str:
    """The message of the `RESULTS` item named `code`."""
    return RESULTS[getattr(RESULTS, code)]


class Verdict(NamedTuple):
    """A start's verdict: its code (a `RESULTS` name, see `result_code`) and the reason, with the numbers of that
    fit."""

    code: str
    reason: str

    @property
    def success(self) -> bool:
        return self.code in SUCCESSES

    @property
    def hard(self) -> bool:
        return self.code in HARD_FAILURES


def verdict_of(name: str, *, solver, window: int, since: int, max_steps: int, interrupted: bool = False,
               stalled_note: str = "") -> Verdict:
    """The `Verdict` of a start whose loop state ended as the `RESULTS` item `name` (`"running"`: it ran out of
    steps, or was `interrupted`); `since` its consecutive rejected trials; `stalled_note` is appended to a stall's
    reason."""
    if name == "successful":
        return Verdict("successful", solver.converged_reason)
    if name == "successful_flat":
        return Verdict("successful", f"converged (mean relative cost decrease per accepted step over the last "
                                     f"{window} below ftol = {float(solver.ftol):g})")
    if name == "stalled":
        return Verdict("stalled", f"no decrease of the cost in {since} consecutive trial steps (stalled or "
                                  f"diverging{stalled_note})")
    if name == "running":
        if interrupted:
            return Verdict("interrupted", result_message("interrupted"))
        return Verdict("max_steps_reached", f"max_steps = {max_steps} reached before convergence")
    if name in LOOP_ONLY or name not in NAMES:
        raise ValueError(f"no verdict for the loop state {name!r}")
    return Verdict(name, result_message(name))


class FitError(PiezojaxError, RuntimeError):
    """A fit run with `throw=True` failed: `str(error)` is the reason, `error.result` the failed `FitResult` (the
    last accepted parameters, never NaN), `error.code` its `RESULTS` name."""

    def __init__(self, result):
        super().__init__(f"fit failed: {result.reason}")
        self.result = result
        self.code = result.code

    def __reduce__(self):  # pickled and copied with its result (the default would call __init__ with the message)
        return type(self), (self.result,)
