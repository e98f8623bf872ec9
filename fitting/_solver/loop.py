"""`iterate`: the host loop that runs a solver from several starts at once (progress, Ctrl-C, refused trials)."""

import dataclasses
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array

from .._problem import ProblemCore, linearise, model_error
from .iteration import Carry, reject, relinearised, select_rows, start, step, stop
from .outcomes import RESULTS, Verdict, result_names, verdict_of
from .progress import AbstractProgressMeter, Progress
from .solvers import AbstractNormalSolver, Linearisation, Trial
from .stopping import outpaced

# ---------------------------------------------------------------------------------------------------- the loop


_where = jax.jit(select_rows)  # one compiled call for a whole pytree


@eqx.filter_jit
def _start(solver, y, lin, finite, window):
    return eqx.filter_vmap(lambda y, lin, finite: start(solver, y, lin, finite, window=window))(y, lin, finite)


@dataclasses.dataclass
class Run:
    """One start's run of `iterate`: the last accepted point `u`, counts, accepted costs and the step of each, and
    its verdict."""

    u: Array
    steps: int
    accepted: int
    history: list
    history_steps: list
    verdict: Verdict
    linearisation: Linearisation | None = None  # at `u`, when the last accepted point was linearised


def _refused_trials(solver, core, carry: Carry, running: np.ndarray, window: int, max_rejections: int
                    ) -> np.ndarray:
    """Which running starts' trial points the model refuses (its runtime checks raise): each start's trial alone."""
    refused = np.zeros(running.shape[0], bool)
    for i in np.flatnonzero(running):
        one = jtu.tree_map(lambda x: x[i : i + 1], carry)
        try:
            jax.block_until_ready(step(solver, core, one, jnp.zeros((1,), bool), linearise=False,
                                       window=window, max_rejections=max_rejections))
        except eqx.EquinoxRuntimeError:
            refused[i] = True
    return refused


def _linearise_starts(core: ProblemCore, y, which: np.ndarray, lin: Linearisation | None):
    """`linearise` at the starts `which` (a boolean mask over the rows of `y`) as `(r, cost, g, h, finite)`; `g`
    and `h` of the other rows are `lin`'s and their `finite` is True (their `r` and `cost` are not to be used: the
    caller keeps its own). `lin` None: the first linearisation, of every start (`which` all True).

    On XLA:CPU one start at a time, through the single-start program: measured faster than vmapping the starts
    (the 150 V record's 29-parameter actuator, 35000 samples: 48 ms for one start alone, 156 ms for two vmapped,
    391 ms for four), a finished start's linearisation costs nothing, and a multi-start fit compiles the same
    linearisation as a single start. Elsewhere (accelerators) batched over every start."""
    n = y.shape[0]
    if n == 1 or jax.default_backend() != "cpu":
        r, cost, g, h, finite = linearise(core, y)
        if lin is None or which.all():
            return r, cost, g, h, finite
        mask = jnp.asarray(which)
        g, h = _where(mask, (g, h), (lin.g, lin.h))
        return r, cost, g, h, finite | ~mask
    rows = [linearise(core, y[i : i + 1]) if which[i] else None for i in range(n)]
    if lin is None:
        return tuple(jnp.concatenate(parts) for parts in zip(*rows))
    fill = (lin.r, lin.cost, lin.g, lin.h, jnp.ones((n,), bool))
    return tuple(
        jnp.concatenate([row[k] if row is not None else fill[k][i : i + 1] for i, row in enumerate(rows)])
        for k in range(5)
    )


def _initial_verdicts(core: ProblemCore, y, cost: np.ndarray, finite: np.ndarray) -> list:
    """Per start, the verdict `nonfinite_initial` where its first linearisation is not finite, else None."""
    verdicts: list = [None] * y.shape[0]
    for i in range(y.shape[0]):
        if not np.isfinite(cost[i]):
            why = model_error(core, y[i])
            verdicts[i] = Verdict("nonfinite_initial", "the model's predictions are not finite at the initial "
                                                       "parameters" + (f" ({why})" if why else ""))
        elif not finite[i]:
            verdicts[i] = Verdict("nonfinite_initial", "the Jacobian is not finite at the initial parameters")
    return verdicts


def _trials(solver, core: ProblemCore, carry: Carry, running: np.ndarray, window: int, max_rejections: int):
    """One batched `step` of the running starts, as `(carry, trial, refused, message)`: `refused` marks the starts
    whose trial point the model refused (its runtime check raised, `message` its first line): they take a rejected
    trial (`rejected`), the others are stepped as usual."""
    n_starts = running.shape[0]
    kw = dict(linearise=False, window=window, max_rejections=max_rejections)
    try:
        out = step(solver, core, carry, jnp.zeros((n_starts,), bool), **kw)
        jax.block_until_ready(out)
        return *out, np.zeros(n_starts, bool), ""
    except eqx.EquinoxRuntimeError as e:
        # the model refused a trial point (a runtime check, e.g. a stiffness that underflowed to 0): find
        # which starts' trials it refuses and step the others as usual
        message = str(e).strip().splitlines()[0]
    refused = _refused_trials(solver, core, carry, running, window, max_rejections) if n_starts > 1 else running.copy()
    if not refused.any():  # raised only batched: every running start's trial counts as refused
        refused = running.copy()
    if not (running & ~refused).any():
        return (*_no_trial(solver, carry, refused, window, max_rejections), refused, message)
    try:
        out = step(solver, core, carry, jnp.asarray(refused), **kw)
        jax.block_until_ready(out)
    except eqx.EquinoxRuntimeError:  # no trial taken: every running start's trial counts as refused
        refused = running.copy()
        out = _no_trial(solver, carry, refused, window, max_rejections)
    return *out, refused, message


def _no_trial(solver, carry: Carry, refused: np.ndarray, window: int, max_rejections: int) -> tuple[Carry, Trial]:
    """Every start where `refused` takes a rejected trial (`rejected`), without evaluating the model."""
    no = jnp.zeros((refused.shape[0],), bool)
    return (reject(solver, carry, carry, jnp.asarray(refused), window=window, max_rejections=max_rejections),
            Trial(None, carry.y, None, carry.lin.cost, no, ~no))


def _runs(carry: Carry, histories, history_steps, verdicts, fresh, *, solver, window: int, max_steps: int
          ) -> list["Run"]:
    """Each start's `Run` at the end of `iterate` (a start without a verdict ran out of steps)."""
    runs = []
    steps = np.asarray(carry.steps)
    for i in range(carry.y.shape[0]):
        verdict = verdicts[i] or verdict_of("running", solver=solver, window=window, since=0, max_steps=max_steps)
        lin_i = jtu.tree_map(lambda x: x[i], carry.lin) if fresh[i] else None
        accepted = len(histories[i]) - 1
        runs.append(Run(carry.y[i], int(steps[i]), accepted, histories[i], history_steps[i], verdict, lin_i))
    return runs


def iterate(solver: AbstractNormalSolver, core: ProblemCore, u0, *, max_steps: int,
            meter: AbstractProgressMeter, label: str = "", max_rejections: int = 40, window: int = 5,
            outpace: bool = True) -> list[Run]:
    r"""Run `solver` from every start in `u0` (shape `(starts, p)`) at once, stepped from Python (progress meter,
    Ctrl-C): the starts run in lockstep (their trials in one compiled `step`, as `fit_fleet`'s; their
    linearisations one at a time on XLA:CPU, see `_linearise_starts`), a finished start is frozen, and each has its
    own state, history and verdict.

    Besides the solver's own test (`terminate`), a start ends by the loop's tests (`advance`): converged when its
    accepted steps no longer lower the cost (mean relative decrease over the last `window` below the solver's
    `ftol`: parameters drifting along a flat valley); `stalled` after `max_rejections` consecutive rejected trials;
    `max_steps_reached`; `interrupted` on Ctrl-C (the last accepted point is kept); `outpaced` when another start has
    converged at a cost this one would not reach within `max_steps` (`outpaced`; only with `outpace`: `solve` tests
    it at the last smoothing level alone, since a start stopped earlier would be fitted again at the next level).
    A trial point the model refuses
    is a failed trial of that start only: the others take their step as usual. `piezojax`'s own checks are traced
    as NaN refusals (a non-finite trial); an `eqx.error_if` in a user's model raises for the whole batch, so it is
    caught and the starts' trials are run one by one to find the refused ones. An accepted point whose Jacobian is
    not finite is undone the same way, as a refused trial (measured: a Preisach + creep fit of a 1e6-sample record
    stepped a weakly determined time constant to 1e-249 s, where its derivative is 0 * inf, and ended there as
    failed; it now goes on). (`fit_fleet` ends such an actuator as `nonfinite`.)
    """
    n_starts = u0.shape[0]
    kw = dict(window=window, max_rejections=max_rejections)
    r, cost, g, h, finite = _linearise_starts(core, u0, np.ones(n_starts, bool), None)
    carry = _start(solver, u0, Linearisation(r, cost, g, h), finite, window)
    histories = [[float(c)] for c in np.asarray(cost)]
    history_steps = [[0] for _ in range(n_starts)]
    fresh = np.ones(n_starts, bool)  # whether `carry.lin` is complete at the start's current point
    verdicts = _initial_verdicts(core, u0, np.asarray(cost), np.asarray(finite))
    running = np.asarray(carry.running)
    meter_state = meter.init(label, n_starts)
    t0 = time.perf_counter()
    model_errors = [""] * n_starts  # per start, the last runtime check the model raised at its trial point
    pending = None  # during an iteration: the state before it, restored if Ctrl-C arrives before it is complete
    try:
        for k in range(1, max_steps + 1):
            if not running.any():
                break
            before, fresh_before = carry, fresh.copy()
            pending = (before, fresh_before, k)
            carry, trial, refused, message = _trials(solver, core, carry, running, window, max_rejections)
            for i in np.flatnonzero(refused):
                model_errors[i] = message
            names = result_names(carry.book.result)
            take, cost_eval = np.asarray(trial.accept), np.asarray(trial.cost)
            for i in np.flatnonzero(take):
                fresh[i] = False
                histories[i].append(float(cost_eval[i]))
                history_steps[i].append(k)
            for i in np.flatnonzero(running):
                if names[i] == "stalled" and not model_errors[i] and not np.isfinite(cost_eval[i]):
                    model_errors[i] = model_error(core, trial.y[i])  # a refusal traced as NaN
            relinearise = take & (np.asarray(names) == "running")
            if relinearise.any():
                _, _, g, h, finite = _linearise_starts(core, carry.y, relinearise, carry.lin)
                undo = relinearise & ~np.asarray(finite)
                if undo.any():
                    # derivatives not finite at the new point (e.g. a weakly determined time constant stepped to
                    # 1e-249 s, where d exp(-dt/tau)/d tau is 0 * inf): the step is undone and counted as a refused
                    # trial, so that the next one is shorter; a start that keeps meeting such points stalls
                    # (`max_rejections`)
                    carry = reject(solver, before, carry, jnp.asarray(undo), **kw)
                    names = result_names(carry.book.result)
                    for i in np.flatnonzero(undo):
                        histories[i].pop()
                        history_steps[i].pop()
                        fresh[i] = fresh_before[i]
                    relinearise = relinearise & ~undo
                carry = relinearised(solver, carry, g, h, jnp.asarray(relinearise))
                fresh |= relinearise
            ended = np.flatnonzero(running & (np.asarray(names) != "running"))
            since = np.asarray(carry.book.since) if ended.size else None
            for i in ended:
                why = f"; last model error: {model_errors[i]}" if model_errors[i] else ""
                verdicts[i] = verdict_of(names[i], solver=solver, window=window, since=int(since[i]),
                                         max_steps=max_steps, stalled_note=why)
            if n_starts > 1 and outpace:
                beaten = outpaced(histories, history_steps, names, np.asarray(carry.steps), k, max_steps)
                for i, reason in beaten.items():
                    verdicts[i] = Verdict("outpaced", reason)
                if beaten:
                    carry = stop(carry, jnp.asarray(np.isin(np.arange(n_starts), list(beaten))), RESULTS.outpaced)
            running = np.asarray(carry.running)
            pending = None
            best = min(hh[-1] for hh in histories)
            meter_state = meter.step(meter_state, Progress(label, k, best, len(histories[0]) - 1, int(running.sum()),
                                                           n_starts, time.perf_counter() - t0))
    except KeyboardInterrupt:
        if pending is not None:  # the interrupted iteration is undone: each start at its last complete point
            carry, fresh, k = pending
            for hs, steps_of in zip(histories, history_steps):
                while steps_of[-1] == k:
                    hs.pop()
                    steps_of.pop()
            running = np.asarray(carry.running)
        for i in np.flatnonzero(running):
            verdicts[i] = verdict_of("running", solver=solver, window=window, since=0, max_steps=max_steps,
                                     interrupted=True)
    finally:
        meter.close(meter_state)
    return _runs(carry, histories, history_steps, verdicts, fresh, solver=solver, window=window, max_steps=max_steps)
