"""The loop's own stopping tests (`advance`: flat cost, stall, non-finite Jacobian; one for `iterate` and
`fit_fleet`) and the outpacing of slow starts (`outpaced`). A start's state is a `RESULTS` item (`running` until it
stops)."""


import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .outcomes import RESULTS

# ---------------------------------------------------------------------------------------------------- stopping

# accepted steps over which `outpaced` measures a running start's rate of decrease
OUTPACE_WINDOW = 10


class Bookkeeping(eqx.Module):
    """One start's state for the loop's own stopping tests, beside the solver's `terminate` (a leading axis of
    starts when stacked). `iterate` and `fit_fleet` both advance it with `advance`, so the two loops stop alike."""

    accepted: Int[Array, ""]  # accepted steps
    since: Int[Array, ""]  # consecutive rejected trials
    recent: Float[Array, " keep_plus_1"]  # the last accepted costs, oldest first (the initial one repeated)
    result: RESULTS  # `running`, or why the start stopped


def begin(cost, finite, window: int, keep: int = 0) -> Bookkeeping:
    """The bookkeeping of a start whose linearisation at its initial point has `cost` (and is `finite`); it keeps
    the last `max(window, keep) + 1` accepted costs."""
    zero = jnp.zeros((), jnp.int32)
    result = RESULTS.where(jnp.isfinite(cost) & finite, RESULTS.running, RESULTS.nonfinite_initial)
    return Bookkeeping(zero, zero, jnp.full((max(window, keep) + 1,), cost), result)


def _first(cases, default):
    """The item of the first true condition of `cases` (`(condition, item)` pairs), else `default`."""
    out = default
    for condition, item in reversed(cases):
        out = RESULTS.where(condition, item, out)
    return out


def advance(book: Bookkeeping, *, cost, take, ok, terminate, finite, ftol, window: int, max_rejections: int
            ) -> Bookkeeping:
    r"""One step of a running start (a stopped one stays as it is): `take` whether its trial was accepted (at a
    trial cost `cost`), `ok` whether the linear solve succeeded, `terminate` the solver's own test, `finite` whether
    the Jacobian at the new point is finite (`True` where not known yet).

    The start ends, in this order: `linear_solve_failed`; `successful` (the solver's test); `successful_flat` when
    its accepted steps no longer lower the cost (the mean relative decrease over the last `window` accepted steps
    below `ftol`: parameters drifting along a flat valley); `nonfinite` (the Jacobian at the accepted point);
    `stalled` after `max_rejections` consecutive rejected trials."""
    active = book.result == RESULTS.running
    take = active & take
    accepted = book.accepted + take.astype(jnp.int32)
    recent = jnp.where(take, jnp.concatenate([book.recent[1:], jnp.asarray(cost, book.recent.dtype)[None]]),
                       book.recent)
    since = jnp.where(take, 0, book.since + active.astype(jnp.int32))
    ftol = jnp.asarray(ftol, recent.dtype)
    flat = take & (accepted >= window) & (recent[-1 - window] - recent[-1] <= ftol * window * recent[-1])
    result = _first([(~active, book.result), (~ok, RESULTS.linear_solve_failed), (terminate, RESULTS.successful),
                     (flat, RESULTS.successful_flat), (take & ~finite, RESULTS.nonfinite),
                     (~take & (since >= max_rejections), RESULTS.stalled)], RESULTS.running)
    return Bookkeeping(accepted, since, recent, result)


def outpaced(histories, history_steps, names, steps, step: int, max_steps: int, window: int = OUTPACE_WINDOW
             ) -> dict[int, str]:
    r"""The running starts of a multi-start batch that another has outpaced, each with the reason: a start has
    converged (the solver's test or the flat-cost one) after $k^*$ steps at a cost $c^*$ below this start's $c$;
    this start has had twice as many steps, $2k^*$; and at the rate its cost fell over its last `window` accepted
    steps, $\rho = \ln(c_{-w}/c)$ per step taken since (rejected trials included), it would need $\ln(c/c^*)/\rho$
    more steps to reach $c^*$: more than the `max_steps - step` left, where it would stop above $c^*$ anyway.
    The projection alone is not safe: a start can crawl along a plateau and then drop into a lower basin (measured
    on `experiments.plant_study`'s Bouc–Wen draw 8: one start converged after 117 steps, when the other was at 3.6
    times its cost and falling by 0.1 % a step; 40 steps later it was below it, and it converged 1.3 % lower), so
    every start gets twice the winner's steps first. `histories`, `history_steps`: each start's accepted costs and
    the steps they were taken at (its initial cost at step 0); `names`: the names of the starts' `RESULTS` after
    `step`; `steps`: the step at which each start stopped (the current one for those running)."""
    done = [j for j in range(len(names)) if names[j] in ("successful", "successful_flat")]
    if not done:
        return {}
    winner = min(done, key=lambda j: histories[j][-1])
    target, k_star = histories[winner][-1], int(steps[winner])
    if step < 2 * k_star or step >= max_steps:  # at the last step a running start ends `max_steps_reached` anyway
        return {}
    out = {}
    for i in np.flatnonzero(np.asarray(names) == "running"):
        h, hs = histories[i], history_steps[i]
        c = h[-1]
        if not c > target or len(h) <= window:
            continue
        rate = float(np.log(h[-1 - window] / c)) / max(step - hs[-1 - window], 1)
        need = float(np.log(c / target)) / rate if rate > 0 else np.inf
        left = max_steps - step
        if need > left:
            out[int(i)] = (f"stopped after {step} steps: another start converged at cost {target:.6e} after "
                           f"{k_star}; at the rate of its last {window} accepted steps this one (cost {c:.6e}) would "
                           "need " + (f"about {need:.0f} more steps" if np.isfinite(need) else "indefinitely many "
                                      "steps") + f" to reach it, more than the {left} left of max_steps = {max_steps}")
    return out
