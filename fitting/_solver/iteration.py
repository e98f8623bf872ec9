r"""One iteration of the solver, for every start of a batch at once: the compiled step that `iterate` (one
problem, one start or many) and `fitting.fit_fleet` (a batch of problems) both take.

A start's loop state is a `Carry`: its last accepted point, the linearisation there, the solver's state, the
bookkeeping of the loop's own stopping tests (`Bookkeeping`, whose `result` is a `RESULTS` item: `running` until it
stops) and its step count. `step` maps `iteration` over the batch: the solver's trial step (`solver.step`), its
convergence test, the loop's tests (`advance`), and the new state, a stopped start staying as it is. The problem is
shared by the starts (`iterate`) or one per row (`fit_fleet`); the model is evaluated at the trial point either for
its residuals alone, the linearisation at an accepted point then formed by the caller (`iterate`: a rejected trial
costs one simulation), or linearised there in the same step (`fit_fleet`: the steps are dispatched without waiting
for the host, and under `vmap` both branches of a choice would run anyway).
"""

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
from jaxtyping import Array, Bool, Float, Int

from .._problem import ProblemCore, over_starts
from .outcomes import RESULTS
from .solvers import AbstractNormalSolver, Linearisation, Trial
from .stopping import Bookkeeping, advance, begin

# ---------------------------------------------------------------------------------------------------- iteration


class Carry(eqx.Module):
    """One start's loop state (a leading axis of starts when stacked)."""

    y: Float[Array, " p"]  # the last accepted point (scaled parameters)
    lin: Linearisation  # the linearisation at `y` (its `g`, `h` at an earlier point until the caller relinearises)
    state: Any  # the solver's state
    book: Bookkeeping  # the loop's stopping tests
    steps: Int[Array, ""]  # iterations taken while running

    @property
    def running(self) -> Bool[Array, "..."]:
        return self.book.result == RESULTS.running


def linearise_one(core: ProblemCore, y) -> tuple[Linearisation, Bool[Array, ""]]:
    """The linearisation of one start at `y`, and whether its `g` and `h` are finite."""
    r, g, h = core.normal_equations(y)
    finite = jnp.all(jnp.isfinite(g)) & jnp.all(jnp.isfinite(h))
    return Linearisation(r, 0.5 * jnp.sum(r**2), g, h), finite


def start(solver: AbstractNormalSolver, y, lin: Linearisation, finite, *, window: int, keep: int = 0,
          padding=False) -> Carry:
    """The loop state of a start at `y` with its linearisation `lin` (`finite`: whether its `g`, `h` are); a
    `padding` row never runs."""
    book = begin(lin.cost, finite, window, keep)
    book = eqx.tree_at(lambda b: b.result, book, RESULTS.where(jnp.asarray(padding), RESULTS.padding, book.result))
    return Carry(y, lin, solver.init(y, lin), book, jnp.zeros((), jnp.int32))


def _select(pred, new, old):
    return jtu.tree_map(lambda a, b: jnp.where(pred, a, b), new, old)


def rejected(solver: AbstractNormalSolver, c: Carry, *, ftol, window: int, max_rejections: int) -> Carry:
    """`c` after a trial that did not count (the model refused the trial point, or its Jacobian there is not
    finite): a rejected trial — the start stays where it is, the solver's state as after a failed trial
    (`solver.refuse`), and a start that keeps meeting such points stalls (`max_rejections`)."""
    no = jnp.zeros((), bool)
    book = advance(c.book, cost=c.lin.cost, take=no, ok=~no, terminate=no, finite=~no, ftol=ftol, window=window,
                   max_rejections=max_rejections)
    running = c.running
    return Carry(c.y, c.lin, _select(running, solver.refuse(c.state), c.state), book,
                 c.steps + running.astype(jnp.int32))


def iteration(solver: AbstractNormalSolver, core: ProblemCore, c: Carry, refused, *, linearise: bool, window: int,
              max_rejections: int) -> tuple[Carry, Trial]:
    """One iteration of one start (a stopped one stays as it is): `(carry, trial)`. A `refused` start takes no
    trial (the model refused its trial point: `rejected`; `None`: none is). With `linearise`, the model is
    linearised at the trial point and an accepted start's `lin` is complete; without, only its residuals are
    evaluated and an accepted start's `g`, `h` are still those of its last point (the caller relinearises it, and
    sets `finite`)."""
    ftol = solver.ftol

    def evaluate(y):
        if linearise:
            lin, finite = linearise_one(core, y)
            return lin.r, (lin.g, lin.h, finite)
        return core.residuals(y), None

    running = c.running
    trial, new_state = solver.step(evaluate, c.y, c.lin, c.state, running if refused is None else running & ~refused)
    terminate = solver.terminate(c.y, c.lin, trial, new_state)
    g, h, finite = trial.aux if linearise else (c.lin.g, c.lin.h, jnp.asarray(True))
    take = trial.accept & trial.ok
    book = advance(c.book, cost=trial.cost, take=take, ok=trial.ok, terminate=terminate, finite=finite, ftol=ftol,
                   window=window, max_rejections=max_rejections)
    take = running & take
    lin = _select(take, Linearisation(trial.r, trial.cost, g, h), c.lin)
    state = _select(running, new_state, c.state)
    if linearise:
        state = _select(take, solver.relinearise(state, lin), state)
    out = Carry(jnp.where(take, trial.y, c.y), lin, state, book, c.steps + running.astype(jnp.int32))
    if refused is not None:
        out = _select(refused, rejected(solver, c, ftol=ftol, window=window, max_rejections=max_rejections), out)
        take = take & ~refused
    # the step itself stays inside (an output would change how XLA fuses y + step, e.g. into an FMA)
    return out, Trial(None, trial.y, None, trial.cost, take, trial.ok)


@eqx.filter_jit
def step(solver: AbstractNormalSolver, core: ProblemCore, carry: Carry, refused, *, rows=None, linearise: bool,
         window: int, max_rejections: int) -> tuple[Carry, Trial]:
    """`iteration` for every start of `carry` (leading axis): one compiled step. `rows` None: one problem `core`
    for every start (`iterate`); else one problem per row (`fit_fleet`): `rows` holds the arrays that differ by row
    (stacked on the leading axis) and `core` the rest, `eqx.combine(rows[i], core)` row `i`'s problem. `refused`:
    per start, whether the model refused its trial point, or `None` (none did)."""

    def one(row, c, refused):
        problem = core if row is None else eqx.combine(row, core)
        return iteration(solver, problem, c, refused, linearise=linearise, window=window,
                         max_rejections=max_rejections)

    axes = (None if rows is None else 0, 0, None if refused is None else 0)
    return over_starts(one, axes, carry.y.shape[0])(rows, carry, refused)


@eqx.filter_jit
def reject(solver: AbstractNormalSolver, before: Carry, after: Carry, mask, *, window: int, max_rejections: int
           ) -> Carry:
    """Per start: `rejected(before)` where `mask` (e.g. an accepted point whose Jacobian is not finite: the step
    undone), else `after`."""
    undone = jax.vmap(lambda c: rejected(solver, c, ftol=solver.ftol, window=window,
                                         max_rejections=max_rejections))(before)
    return select_rows(mask, undone, after)


def select_rows(mask, new, old):
    """Per start (leading axis): `new` where `mask`, else `old`."""
    return jtu.tree_map(lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - 1)), a, b), new, old)


@eqx.filter_jit
def relinearised(solver: AbstractNormalSolver, carry: Carry, g, h, mask) -> Carry:
    """Per start where `mask`: the linearisation's `g`, `h` replaced (formed at its new accepted point) and the
    solver's state updated (`solver.relinearise`)."""
    lin = select_rows(mask, Linearisation(carry.lin.r, carry.lin.cost, g, h), carry.lin)
    state = select_rows(mask, eqx.filter_vmap(solver.relinearise)(carry.state, lin), carry.state)
    return Carry(carry.y, lin, state, carry.book, carry.steps)


@eqx.filter_jit
def stop(carry: Carry, mask, item) -> Carry:
    """Per start where `mask`: its result set to `item` (e.g. `RESULTS.outpaced`)."""
    result = jax.vmap(lambda m, r: RESULTS.where(m, item, r))(mask, carry.book.result)
    return eqx.tree_at(lambda c: c.book.result, carry, result)
