"""`iterate`: the host loop that runs a solver from several starts at once (progress, Ctrl-C, refused trials)."""

import dataclasses
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array

from .._problem import ProblemCore, linearise, model_error, over_starts
from .outcomes import Verdict
from .progress import AbstractProgressMeter, Progress
from .solvers import AbstractNormalSolver, Linearisation, Trial
from .stopping import OUTPACED, RUNNING, STALLED, advance, begin, outpaced, verdict_of

# ---------------------------------------------------------------------------------------------------- the loop


@eqx.filter_jit
def _init(solver, y, lin):
    return eqx.filter_vmap(solver.init)(y, lin)


@eqx.filter_jit
def _step(solver, core: ProblemCore, y, lin, state, active):
    """`solver.step` and `solver.terminate` for every start (leading axis of all but `solver`, `core`)."""

    def one(y, lin, state, active):
        trial, new_state = solver.step(core.residuals, y, lin, state, active)
        terminate = solver.terminate(y, lin, trial, new_state)
        # the step itself stays inside (an output would change how XLA fuses y + step, e.g. into an FMA)
        return eqx.tree_at(lambda t: t.step, trial, None), new_state, terminate

    return over_starts(one, (0, 0, 0, 0), y.shape[0])(y, lin, state, active)


@eqx.filter_jit
def _relinearise(solver, state, lin, mask):
    new = eqx.filter_vmap(solver.relinearise)(state, lin)
    return _select(mask, new, state)


@eqx.filter_jit
def _refuse(solver, state, new_state, mask):
    """`solver.refuse(state)` where `mask` (the starts whose trial the model refused), `new_state` elsewhere."""
    return _select(mask, eqx.filter_vmap(solver.refuse)(state), new_state)


def _select(mask, new, old):
    return jtu.tree_map(lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - 1)), a, b), new, old)


@jax.jit
def _where(mask, new, old):
    """Per start (leading axis): `new` where `mask`, else `old` (one compiled call for a whole pytree)."""
    return _select(mask, new, old)


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


def _refused_trials(solver, core, y, lin, state, active) -> np.ndarray:
    """Which active starts' trial points the model refuses (its runtime checks raise): each start's trial alone."""
    refused = np.zeros(y.shape[0], bool)
    for i in np.flatnonzero(active):
        one = jtu.tree_map(lambda x: x[i : i + 1], (y, lin, state))
        try:
            jax.block_until_ready(_step(solver, core, *one, jnp.ones((1,), bool)))
        except eqx.EquinoxRuntimeError:
            refused[i] = True
    return refused


@eqx.filter_jit
def _begin(cost, finite, window):
    return jax.vmap(lambda c, f: begin(c, f, window))(cost, finite)


@eqx.filter_jit
def _advance(book, cost, take, ok, terminate, ftol, window, max_rejections):
    def one(book, cost, take, ok, terminate):
        return advance(book, cost=cost, take=take, ok=ok, terminate=terminate, finite=jnp.asarray(True), ftol=ftol,
                       window=window, max_rejections=max_rejections)

    return jax.vmap(one)(book, cost, take, ok, terminate)


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


def _trials(solver, core: ProblemCore, y, lin: Linearisation, state, active: np.ndarray):
    """One batched `_step` of the active starts, as `((trial, new_state, terminate), refused, message)`: `refused`
    marks the starts whose trial point the model refused (its runtime check raised, `message` its first line; the
    others are stepped as usual, a refused start stays at its point)."""
    n_starts = y.shape[0]
    refused = np.zeros(n_starts, bool)
    try:
        out = _step(solver, core, y, lin, state, jnp.asarray(active))
        jax.block_until_ready(out)
        return out, refused, ""
    except eqx.EquinoxRuntimeError as e:
        # the model refused a trial point (a runtime check, e.g. a stiffness that underflowed to 0): find
        # which starts' trials it refuses and step the others as usual
        message = str(e).strip().splitlines()[0]
    refused = _refused_trials(solver, core, y, lin, state, active) if n_starts > 1 else active.copy()
    if not refused.any():  # raised only batched: every active start's trial counts as refused
        refused = active.copy()
    out = None
    if (active & ~refused).any():
        try:  # the others' trials, batched as usual (a refused start stays at its point)
            out = _step(solver, core, y, lin, state, jnp.asarray(active & ~refused))
            jax.block_until_ready(out)
        except eqx.EquinoxRuntimeError:
            refused = active.copy()
            out = None
    if out is None:  # no trial taken: every start stays where it is
        no = jnp.zeros((n_starts,), bool)
        out = Trial(None, y, lin.r, lin.cost, no, ~no), state, no
    return out, refused, message


def _runs(y, lin: Linearisation, steps, histories, history_steps, verdicts, fresh, *, solver, window: int,
          max_steps: int) -> list["Run"]:
    """Each start's `Run` at the end of `iterate` (a start without a verdict ran out of steps)."""
    runs = []
    for i in range(y.shape[0]):
        verdict = verdicts[i] or verdict_of(RUNNING, solver=solver, window=window, since=0, max_steps=max_steps)
        lin_i = jtu.tree_map(lambda x: x[i], lin) if fresh[i] else None
        accepted = len(histories[i]) - 1
        runs.append(Run(y[i], int(steps[i]), accepted, histories[i], history_steps[i], verdict, lin_i))
    return runs


def iterate(solver: AbstractNormalSolver, core: ProblemCore, u0, *, max_steps: int,
            meter: AbstractProgressMeter, label: str = "", max_rejections: int = 40, window: int = 5,
            outpace: bool = True) -> list[Run]:
    r"""Run `solver` from every start in `u0` (shape `(starts, p)`) at once, stepped from Python (progress meter,
    Ctrl-C): the starts run in lockstep (their trials under `vmap`; their linearisations one at a time on
    XLA:CPU, see `_linearise_starts`), a finished start is frozen, and each has its own state, history and
    verdict.

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
    failed; it now goes on). (`fit_fleet` still ends such an actuator as `nonfinite`.)
    """
    n_starts = u0.shape[0]
    ftol = jnp.asarray(float(solver.ftol))
    y = u0
    r, cost, g, h, finite = _linearise_starts(core, y, np.ones(n_starts, bool), None)
    lin = Linearisation(r, cost, g, h)
    book = _begin(cost, finite, window)
    cost_np, finite_np = np.asarray(cost), np.asarray(finite)
    histories = [[float(c)] for c in cost_np]
    history_steps = [[0] for _ in range(n_starts)]
    steps = np.zeros(n_starts, int)
    fresh = np.ones(n_starts, bool)  # whether `lin` is at the start's current point
    verdicts = _initial_verdicts(core, y, cost_np, finite_np)
    active = np.asarray(book.code) == RUNNING
    state = _init(solver, y, lin)
    meter_state = meter.init(label, n_starts)
    t0 = time.perf_counter()
    model_errors = [""] * n_starts  # per start, the last runtime check the model raised at its trial point
    try:
        for k in range(1, max_steps + 1):
            if not active.any():
                break
            out, refused, message = _trials(solver, core, y, lin, state, active)
            for i in np.flatnonzero(refused):
                model_errors[i] = message
            trial, new_state, terminate = out
            if refused.any():
                new_state = _refuse(solver, state, new_state, jnp.asarray(refused))
            # a refused trial: a rejected one (the linear solve did not fail)
            kept = jnp.asarray(~refused)
            ok = trial.ok | ~kept
            take_j = trial.accept & ok & kept
            book_before, fresh_before = book, fresh.copy()
            book = _advance(book, trial.cost, take_j, ok, terminate & kept, ftol, window, max_rejections)
            codes, take = np.asarray(book.code), active & np.asarray(take_j)
            cost_eval_np = np.asarray(trial.cost)
            for i in np.flatnonzero(active):
                steps[i] = k
                if take[i]:
                    fresh[i] = False
                    histories[i].append(float(cost_eval_np[i]))
                    history_steps[i].append(k)
                if codes[i] == STALLED and not model_errors[i] and not np.isfinite(cost_eval_np[i]):
                    model_errors[i] = model_error(core, trial.y[i])  # a refusal traced as NaN
            y_before, lin_before, state_before = y, lin, state
            y, lin_r, lin_cost = _where(jnp.asarray(take), (trial.y, trial.r, trial.cost), (y, lin.r, lin.cost))
            lin = Linearisation(lin_r, lin_cost, lin.g, lin.h)
            state = _where(jnp.asarray(active), new_state, state)
            relinearise = take & (codes == RUNNING)
            if relinearise.any():
                _, _, g, h, finite = _linearise_starts(core, y, relinearise, lin)
                undo = relinearise & ~np.asarray(finite)
                if undo.any():
                    # derivatives not finite at the new point (e.g. a weakly determined time constant stepped to
                    # 1e-249 s, where d exp(-dt/tau)/d tau is 0 * inf): the step is undone and counted as a refused
                    # trial, so that the next one is shorter; a start that keeps meeting such points stalls
                    # (`max_rejections`)
                    u = jnp.asarray(undo)
                    book = _advance(book_before, trial.cost, take_j & ~u, ok, terminate & kept & ~u, ftol, window,
                                    max_rejections)
                    codes = np.asarray(book.code)
                    y, lin_r, lin_cost = _where(u, (y_before, lin_before.r, lin_before.cost), (y, lin.r, lin.cost))
                    g, h = _where(u, (lin_before.g, lin_before.h), (g, h))
                    state = _refuse(solver, state_before, state, u)
                    for i in np.flatnonzero(undo):
                        histories[i].pop()
                        history_steps[i].pop()
                        fresh[i] = fresh_before[i]
                    relinearise = relinearise & ~undo
                lin = Linearisation(lin_r, lin_cost, g, h)
                state = _relinearise(solver, state, lin, jnp.asarray(relinearise))
                fresh |= relinearise
            ended = np.flatnonzero(active & (codes != RUNNING))
            since = np.asarray(book.since) if ended.size else None
            for i in ended:
                why = f"; last model error: {model_errors[i]}" if model_errors[i] else ""
                verdicts[i] = verdict_of(int(codes[i]), solver=solver, window=window, since=int(since[i]),
                                         max_steps=max_steps, stalled_note=why)
            if n_starts > 1 and outpace:
                beaten = outpaced(histories, history_steps, codes, steps, k, max_steps)
                for i, reason in beaten.items():
                    verdicts[i] = Verdict("outpaced", reason)
                if beaten:
                    mask = np.isin(np.arange(n_starts), list(beaten))
                    book = eqx.tree_at(lambda b: b.code, book, jnp.where(jnp.asarray(mask), OUTPACED, book.code))
                    codes = np.asarray(book.code)
            active = codes == RUNNING
            best = min(hh[-1] for hh in histories)
            meter_state = meter.step(meter_state, Progress(label, k, best, len(histories[0]) - 1, int(active.sum()),
                                                           n_starts, time.perf_counter() - t0))
    except KeyboardInterrupt:
        for i in np.flatnonzero(active):
            verdicts[i] = verdict_of(RUNNING, solver=solver, window=window, since=0, max_steps=max_steps,
                                     interrupted=True)
    finally:
        meter.close(meter_state)
    return _runs(y, lin, steps, histories, history_steps, verdicts, fresh, solver=solver, window=window,
                 max_steps=max_steps)
