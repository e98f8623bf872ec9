"""How a fit ends: the results enumeration with its messages, the success and hard-failure sets, a start's
`Verdict` and `FitError`."""

from typing import NamedTuple

import equinox as eqx
import numpy as np

from piezojax import PiezojaxError

# ---------------------------------------------------------------------------------------------------- results


class RESULTS(eqx.Enumeration):
    """How a fit ended (an `eqx.Enumeration`, as `optx.RESULTS`): `RESULTS[item]` is the message. `FitResult.code`
    is the item's name, `FitResult.reason` the message with the numbers of that fit."""

    successful = "converged"
    converged_at_kink = "converged at a kink of the piecewise smooth cost"
    converged_zero_residual = "converged to a zero residual"
    max_steps_reached = "the maximum number of steps was reached before convergence"
    stalled = "no decrease of the cost in many consecutive trial steps (stalled or diverging)"
    not_stationary = "stopped where the cost is not stationary"
    outpaced = "stopped: another start converged at a lower cost that this one would not reach within max_steps"
    interrupted = "interrupted by the user (Ctrl-C)"
    nonfinite_initial = "the model's predictions or Jacobian are not finite at the initial parameters"
    nonfinite = "the Jacobian is not finite at an accepted point"
    linear_solve_failed = "the linear solve of a damped step failed"


SUCCESSES = ("successful", "converged_at_kink", "converged_zero_residual")
"""The codes of a converged fit."""

HARD_FAILURES = ("interrupted", "nonfinite_initial", "nonfinite", "linear_solve_failed", "outpaced")
"""The codes after which a start is not continued (to the next smoothing level, or past a kink): the failures, and
a start of a multi-start fit that another outpaced (`iterate`)."""


def result_code(item) -> str:
    """The name of a `RESULTS` item (`"successful"`, ...); for a batch of items, the list of names."""
    names = {int(v._value): k for k, v in RESULTS._name_to_item.items()}
    values = np.asarray(item._value)
    return names[int(values)] if values.ndim == 0 else [names[int(v)] for v in values]


def result_message(code: str) -> str:
    """The message of the `RESULTS` item named `code`."""
    return RESULTS[getattr(RESULTS, code)]


class Verdict(NamedTuple):
    """A start's verdict: its `RESULTS` name and the reason, with the numbers of that fit."""

    code: str
    reason: str

    @property
    def success(self) -> bool:
        return self.code in SUCCESSES

    @property
    def hard(self) -> bool:
        return self.code in HARD_FAILURES


class FitError(PiezojaxError, RuntimeError):
    """A fit run with `throw=True` failed: `str(error)` is the reason, `error.result` the failed `FitResult` (the
    last accepted parameters, never NaN), `error.code` its `RESULTS` name."""

    def __init__(self, result):
        super().__init__(f"fit failed: {result.reason}")
        self.result = result
        self.code = result.code

    def __reduce__(self):  # pickled and copied with its result (the default would call __init__ with the message)
        return type(self), (self.result,)


