"""Refinement rounds after a fit: hysteresis plays placed anew or re-seeded, creep lags moved, each round fitted
again from the last and kept only when it lowers the cost (`refine`); the kept result counts the whole run
(`whole_run`)."""

import dataclasses
from collections.abc import Callable

from .._solve import fit
from .._solver import HARD_FAILURES
from .lags import relocated_lags
from .plays import reseeded

# at most this many re-seeded fits after the first (each kept only when it lowers the cost), another only after one
# that lowered the cost by more than this fraction
RESEED_ROUNDS, RESEED_GAIN = 3, 1e-3


def _one_line(e: BaseException) -> str:
    return f"{type(e).__name__}: {' '.join(str(e).split())}"


def silent(message: str, *, warning: bool = False) -> None:
    del message, warning


def refine(config, result, dataset, free, fit_args: dict, *, log: Callable = silent,
           interrupted: Callable[[], bool] = lambda: False):
    """More fits from `result` with its hysteresis plays all placed anew where the residual needs them, or its dead
    elements re-seeded (`reseeded`: plays the fit left without weight, above the largest voltage, or on
    the threshold of another, placed where the residual needs them), or, when none is dead, one live element
    swapped where the residual needs it, and its creep lags moved where time constants elsewhere fit better
    (`relocated_lags`), each kept when its cost is lower; up to `RESEED_ROUNDS` rounds while the last
    was kept, lowered the cost by more than `RESEED_GAIN` and left elements dead, an element to swap or lags
    misplaced again (plays pulled onto one kink of the data's reversals can fall together in the re-seeded fit too).

    An interrupt (`KeyboardInterrupt`, or `interrupted()` true: one that was swallowed on its way) ends the rounds:
    the re-seeded fit's last accepted point is kept if its cost is lower, and the result returned has code
    `"interrupted"` (its reason names the verdict of the fit kept).

    **Arguments:**

    - `config`: the `ModelConfig` whose structure `result.model` has.
    - `result`: the first fit's `FitResult`; `dataset`, `free`, `fit_args`: what it was fitted with (`fitting.fit`'s
      keywords).
    - `log`: called with each progress line, and with `warning=True` for a warning.
    - `interrupted`: whether an interrupt arrived that no exception carried.

    **Returns:** the result kept and, for `result.json`, what was done (`None` when nothing was dead or misplaced;
    per round the plays re-seeded, `"elements"`, and the lags moved, `"lags"`; `"interrupted": True` when an
    interrupt ended it; `"error"` when a round raised: the fit so far is kept and the error reported as a warning).
    A re-seeded result kept reports the whole run (`whole_run`).
    """
    fits = [result]
    rounds, stopped_by_interrupt, failure = [], False, None
    try:
        while len(rounds) < RESEED_ROUNDS:
            again = reseeded(config, result.model, dataset, free, fit_args)
            model, moved = again if again is not None else (result.model, 0)
            try:  # a failure here must not discard the plays re-seeded above
                relocated = relocated_lags(config, model, dataset, free, fit_args)
            except KeyboardInterrupt:
                raise
            except Exception as e:  # noqa: BLE001 - an optional refinement; the fit so far stands
                relocated = None
                log(f"warning: moving the creep lags failed ({_one_line(e)}); they stay where the fit left them",
                    warning=True)
            model, lags = relocated if relocated is not None else (model, 0)
            if not moved and not lags:
                break
            what = [f"{moved} hysteresis element(s) re-seeded (placed anew, dead, coinciding, or a live one swapped)"
                    ] if moved else []
            what += [f"{lags} creep lag(s) moved to other time constants"] if lags else []
            log(f"{' and '.join(what)} where the residual needs them; fitting again")
            second = fit(model, dataset, **fit_args)
            fits.append(second)
            stopped = second.code == "interrupted"
            kept = (second.code not in HARD_FAILURES or stopped) and second.cost < result.cost
            previous = result
            if kept:
                result = second
            rounds.append({"elements": moved, "lags": lags, "cost_before": float(previous.cost),
                           "cost_after": float(second.cost), "steps": int(second.steps), "kept": bool(kept)})
            log(f"re-seeded fit{' (interrupted)' if stopped else ''}: cost {second.cost:.6e} against "
                f"{previous.cost:.6e}; {'kept' if kept else 'the earlier fit kept'}")
            stopped_by_interrupt = stopped
            if stopped or not kept or previous.cost - second.cost < RESEED_GAIN * previous.cost:
                break
    except KeyboardInterrupt:  # while placing the plays or compiling the new problem: the fits so far stand
        stopped_by_interrupt = True
    except Exception as e:  # noqa: BLE001 - a finished fit is never lost to its optional refinement
        failure = _one_line(e)
        log(f"warning: re-seeding the dead plays or moving the creep lags failed ({failure}); the fit so far is kept",
            warning=True)
    stopped_by_interrupt = stopped_by_interrupt or interrupted()
    if not rounds and not stopped_by_interrupt and failure is None:
        return result, None
    if result is not fits[0]:
        result = whole_run(result, fits)
    before = rounds[0]["cost_before"] if rounds else float(result.cost)
    info = {"elements": sum(r["elements"] for r in rounds), "lags": sum(r["lags"] for r in rounds),
            "cost_before": before, "cost_after": float(result.cost), "kept": any(r["kept"] for r in rounds),
            "rounds": rounds}
    if stopped_by_interrupt:
        info["interrupted"] = True
        if result.code != "interrupted":  # the run was interrupted, whatever the verdict of the fit kept
            result = dataclasses.replace(result, success=False, code="interrupted", reason=(
                f"interrupted while re-seeding dead plays or moving creep lags; the best fit so far ({result.code}: "
                f"{result.reason})"))
    if failure is not None:
        info["error"] = failure
    return result, info


def whole_run(result, fits: list):
    """`result`, one of `fits` (every fit `refine` ran, the first fit first), with the counts and the time of all
    of them, and the first fit's initial cost and starts (each marked `first_of`: how many fits ran), every fit's
    repairs; its history is that of the fits up to `result` (each started from the one before: a round follows
    only a kept one), one after the other (the cost jumps up where plays were re-seeded), counted in the steps of
    the fits before."""
    history, history_steps, offset = [], [], 0
    for f in fits[: next(i for i, f in enumerate(fits) if f is result) + 1]:
        history += list(f.history)
        history_steps += [offset + int(s) for s in f.history_steps]
        offset += int(f.steps)
    return dataclasses.replace(
        result, steps=sum(int(f.steps) for f in fits), accepted_steps=sum(int(f.accepted_steps) for f in fits),
        seconds=sum(float(f.seconds) for f in fits), initial_cost=fits[0].initial_cost,
        starts=[dict(st, first_of=len(fits)) for st in fits[0].starts] if fits[0].starts else fits[0].starts,
        repairs=[note for f in fits for note in f.repairs or ()] or None, history=history,
        history_steps=history_steps)
