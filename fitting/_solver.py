r"""The least-squares solvers, as optimistix splits them: a small abstract solver (`init` / `step` / `terminate`),
each concrete solver a *descent* (the step from a linearisation) and a *search* (whether to take it, and the next
step size or radius); a results enumeration with messages; a pluggable progress meter; the loop's own stopping
tests (`advance`: flat cost, stall, non-finite Jacobian; shared with `fit_fleet`) and one verdict per stopping code
(`verdict_of`); and `iterate`, the loop that runs a solver from several starts at once.

Everything works in normal-equation form: a linearisation at an accepted point is $(r, \tfrac12\|r\|^2, g, H)$ with
$g = J^\top r$ and $H = J^\top J$ (`Problem.normal_equations`: forward mode, a chunk of experiments at a time, the
$m \times p$ Jacobian never kept), and a rejected trial costs one simulation, not a Jacobian.

The multi-start bookkeeping above one level of continuation (levels of smoothing, restarts past kinks, the choice
of the best start, the report) is `fitting.solve`'s.
"""

import abc
import dataclasses
import sys
import time
from collections.abc import Callable
from typing import Any, ClassVar, NamedTuple, TextIO

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from piezojax._checks import PiezojaxError, PiezojaxValueError
from piezojax._dtypes import matmul

from ._problem import ProblemCore, linearise, model_error, over_starts

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


# ---------------------------------------------------------------------------------------------------- solvers


class Linearisation(eqx.Module):
    r"""The model linearised at a point: weighted residuals `r`, `cost` $= \tfrac12\|r\|^2$, $g = J^\top r$,
    $H = J^\top J$ (one start; `iterate` stacks starts on a leading axis)."""

    r: Float[Array, " m"]
    cost: Float[Array, ""]
    g: Float[Array, " p"]
    h: Float[Array, "p p"]


class Trial(eqx.Module):
    """A solver's trial step: the step and the trial point `y` (the point plus the step), its residuals and cost,
    whether the search accepts it, and whether the linear algebra of the step succeeded."""

    step: Float[Array, " p"]
    y: Float[Array, " p"]
    r: Float[Array, " m"]
    cost: Float[Array, ""]
    accept: Bool[Array, ""]
    ok: Bool[Array, ""]


class AbstractNormalSolver(eqx.Module):
    r"""A least-squares solver on normal equations, in optimistix's split (`optx.AbstractLeastSquaresSolver`,
    stepped from the outside so that each start of a batch keeps its own state):

    - `init(y, lin)`: the solver's state at the start `y` with its linearisation `lin`;
    - `step(residuals, y, lin, state, active)`: a trial step from the linearisation and the residuals at the trial
      point (`residuals(y)`: the weighted residual vector); a start that is not `active` stays where it is;
    - `terminate(y, lin, trial, state)`: whether the trial met the solver's convergence test;
    - `relinearise(state, lin)`: the state after the model is linearised again at an accepted point;
    - `refuse(state)`: the state after the model refused the trial point (a runtime check), as after a failed trial.

    All five are pure JAX, for one start (`iterate` maps them over the starts).
    """

    rtol: eqx.AbstractVar[Any]
    atol: eqx.AbstractVar[Any]
    ftol: eqx.AbstractVar[Any]
    converged_reason: eqx.AbstractClassVar[str]

    @abc.abstractmethod
    def init(self, y: Array, lin: Linearisation) -> Any: ...

    @abc.abstractmethod
    def step(self, residuals: Callable[[Array], Array], y: Array, lin: Linearisation, state: Any,
             active: Bool[Array, ""]) -> tuple[Trial, Any]: ...

    @abc.abstractmethod
    def terminate(self, y: Array, lin: Linearisation, trial: Trial, state: Any) -> Bool[Array, ""]: ...

    @abc.abstractmethod
    def relinearise(self, state: Any, lin: Linearisation) -> Any: ...

    @abc.abstractmethod
    def refuse(self, state: Any) -> Any: ...


def _tolerance(x):
    # a NumPy float64 scalar: an array leaf (a new value is not a new compilation), cast to the parameters' dtype
    # where the steps and the loop's flat-cost test (`advance`, in the costs' dtype) use it
    return np.asarray(x, np.float64)


class LevenbergMarquardt(AbstractNormalSolver):
    r"""`optx.LevenbergMarquardt`'s algorithm in normal-equation form, from its own optimistix parts: the descent
    `optx.DampedNewtonDescent` solves $(H + \lambda I)\delta = -g$ (`linear_solver`, Cholesky by default) and the
    search `optx.ClassicalTrustRegion` updates the step size $1/\lambda$ from the ratio of actual to predicted
    decrease; optimistix's Cauchy test (`rtol`, `atol` on the step and the change of the residuals) ends it. The
    difference that matters for long records: the model is linearised only at accepted points.

    ```python
    fitting.solve(problem, method=fitting.LevenbergMarquardt(rtol=1e-10, atol=1e-12))
    ```
    """

    rtol: Array = eqx.field(converter=_tolerance, default=1e-8)
    atol: Array = eqx.field(converter=_tolerance, default=1e-10)
    ftol: Array = eqx.field(converter=_tolerance, default=1e-8)
    descent: optx.DampedNewtonDescent = optx.DampedNewtonDescent(linear_solver=lx.Cholesky())
    search: optx.ClassicalTrustRegion = optx.ClassicalTrustRegion()
    converged_reason: ClassVar[str] = "converged (relative change below rtol/atol)"

    def init(self, y, lin):
        # the state is (step size, search state); the first step size is optimistix's (1, i.e. lambda = 1)
        return jnp.ones((), y.dtype), self.search.init(y, None)

    def _f_info(self, lin):
        return optx.FunctionInfo.EvalGradHessian(
            lin.cost, lin.g, lx.MatrixLinearOperator(lin.h, lx.positive_semidefinite_tag))

    def step(self, residuals, y, lin, state, active):
        step_size, search_state = state
        f_info = self._f_info(lin)
        descent_state = self.descent.query(y, f_info, self.descent.init(y, f_info))
        delta, result = self.descent.step(step_size, descent_state)
        # a finished start (e.g. non-finite at its start) stays where it is: its model is never evaluated elsewhere
        delta = jnp.where(active, delta, 0.0)
        y_eval = y + delta
        r_eval = residuals(y_eval)
        cost_eval = 0.5 * jnp.sum(r_eval**2)
        step_size, accept, _, search_state = self.search.step(
            jnp.array(False), y, y_eval, f_info, optx.FunctionInfo.Eval(cost_eval), search_state)
        accept = accept & jnp.isfinite(cost_eval)
        trial = Trial(delta, y_eval, r_eval, cost_eval, accept, result == optx.RESULTS.successful)
        return trial, (step_size, search_state)

    def terminate(self, y, lin, trial, state):
        # optimistix's Cauchy test (`cauchy_termination`, max norm) on the step and the change of the residuals
        rtol, atol = jnp.asarray(self.rtol, y.dtype), jnp.asarray(self.atol, y.dtype)
        y_small = jnp.max(jnp.abs(trial.step) / (atol + rtol * jnp.abs(trial.y))) < 1
        f_small = jnp.max(jnp.abs(trial.r - lin.r) / (atol + rtol * jnp.abs(trial.r))) < 1
        return trial.accept & y_small & f_small

    def relinearise(self, state, lin):
        return state

    def refuse(self, state):
        # as after a rejected trial: `ClassicalTrustRegion`'s low_constant (the state holds step sizes)
        return jtu.tree_map(lambda x: self.search.low_constant * x, state)


def _column_norms(h):
    r"""$\|J_{:,j}\|$ from $H = J^\top J$; zero columns count as 1 (scipy's `x_scale="jac"`)."""
    norms = jnp.sqrt(jnp.clip(jnp.diagonal(h, axis1=-2, axis2=-1), 0.0, None))
    return jnp.where(norms > 0, norms, 1.0)


class TrustRegionDescent(eqx.Module):
    r"""The descent of scipy's TRF for an unbounded problem, in normal-equation form: in the variables scaled by
    $d = 1/$`scale_inv` (the running maximum of the Jacobian's column norms), the Gauss–Newton step if it lies within
    the radius $\Delta$, else $-(\hat H + \alpha I)^{-1}\hat g$ with $\|p\| = \Delta$ (scipy's
    `solve_lsq_trust_region`, from the eigen-decomposition of the $p \times p$ $\hat H = D H D$ instead of the SVD
    of $\hat J$; Moré's Newton iteration on $\alpha$, relative tolerance 1 %)."""

    max_iter: int = eqx.field(static=True, default=10)
    rtol: float = eqx.field(static=True, default=0.01)

    def subproblem(self, lam, vecs, suf, delta, alpha, m):
        r"""From $s_i^2 = $ `lam` (descending), $V$ = `vecs`, $V^\top\hat g$ = `suf`: `(p, alpha)`."""
        s = jnp.sqrt(lam)
        full_rank = s[-1] > jnp.finfo(lam.dtype).eps * m * s[0]
        lam_safe = jnp.where(lam > 0, lam, 1.0)
        p_gn = -matmul(vecs, suf / lam_safe)
        take_gn = full_rank & (jnp.linalg.norm(p_gn) <= delta)

        def phi_and_derivative(a):
            denom = lam + a
            p_norm = jnp.linalg.norm(suf / denom)
            return p_norm - delta, -jnp.sum(suf**2 / denom**3) / p_norm

        upper = jnp.linalg.norm(suf) / delta
        phi0, dphi0 = phi_and_derivative(jnp.where(full_rank, 0.0, 1.0))
        lower = jnp.where(full_rank, -phi0 / dphi0, 0.0)
        alpha = jnp.where(~full_rank & (alpha == 0), jnp.maximum(0.001 * upper, jnp.sqrt(lower * upper)), alpha)

        def body(_, carry):
            a, lo, hi, done = carry
            a_reset = jnp.where((a < lo) | (a > hi), jnp.maximum(0.001 * hi, jnp.sqrt(lo * hi)), a)
            phi, dphi = phi_and_derivative(a_reset)
            hi_new = jnp.where(phi < 0, a_reset, hi)
            ratio = phi / dphi
            lo_new = jnp.maximum(lo, a_reset - ratio)
            a_new = a_reset - (phi + delta) * ratio / delta
            keep = lambda new, old: jnp.where(done, old, new)  # noqa: E731
            return keep(a_new, a), keep(lo_new, lo), keep(hi_new, hi), done | (jnp.abs(phi) < self.rtol * delta)

        alpha, *_ = jax.lax.fori_loop(0, self.max_iter, body, (alpha, lower, upper, jnp.array(False)))
        p = -matmul(vecs, suf / (lam + alpha))
        p = p * (delta / jnp.linalg.norm(p))
        return jnp.where(take_gn, p_gn, p), jnp.where(take_gn, 0.0, alpha)

    def step(self, radius, scale_inv, alpha, lin, m):
        r"""`(step, scaled step, alpha, predicted decrease)` from the linearisation `lin` ($m$ residuals)."""
        d = 1.0 / scale_inv
        hh = lin.h * d[:, None] * d[None, :]
        gh = lin.g * d
        lam, vecs = jnp.linalg.eigh(hh)
        lam, vecs = jnp.clip(lam[::-1], 0.0, None), vecs[:, ::-1]
        step_h, alpha = self.subproblem(lam, vecs, matmul(vecs.T, gh), radius, alpha, m)
        predicted = -(0.5 * matmul(step_h, matmul(hh, step_h)) + matmul(gh, step_h))
        return step_h, alpha, predicted, d


class RadiusSearch(eqx.Module):
    r"""The search of scipy's TRF: the ratio $\rho$ of actual to predicted decrease; the radius shrunk to
    `shrink` × the (scaled) step below $\rho$ = `low`, doubled above `high` when the step reached the radius; any
    decrease accepted."""

    low: float = eqx.field(static=True, default=0.25)
    high: float = eqx.field(static=True, default=0.75)
    shrink: float = eqx.field(static=True, default=0.25)

    def ratio(self, predicted, actual):
        return jnp.where(predicted > 0, actual / jnp.where(predicted > 0, predicted, 1.0),
                         jnp.where((predicted == 0) & (actual == 0), 1.0, 0.0))

    def step(self, radius, ratio, step_norm, finite):
        """The next radius."""
        new = jnp.where(ratio < self.low, self.shrink * step_norm,
                        jnp.where((ratio > self.high) & (step_norm > 0.95 * radius), 2.0 * radius, radius))
        return jnp.where(finite, new, self.shrink * step_norm)


class _TrustRegionState(eqx.Module):
    scale_inv: Array  # running maximum of the Jacobian's column norms
    radius: Array
    alpha: Array  # the last Levenberg–Marquardt parameter of the subproblem (its next starting guess)
    ratio: Array  # actual / predicted decrease of the last trial
    actual: Array  # actual decrease of the last trial


class TrustRegion(AbstractNormalSolver):
    r"""The algorithm of `scipy.optimize.least_squares(method="trf", x_scale="jac")` for an unbounded problem, from
    the same linearisations as `LevenbergMarquardt`: the descent `TrustRegionDescent` (the trust-region step in the
    variables scaled by the running maximum of the Jacobian's column norms), the search `RadiusSearch` (the radius
    from the ratio of actual to predicted decrease), and scipy's tests: relative cost decrease below `ftol` with a
    ratio above 0.25, or a step below `rtol` relative (scipy's `xtol`). `atol` is not used."""

    rtol: Array = eqx.field(converter=_tolerance, default=1e-8)
    atol: Array = eqx.field(converter=_tolerance, default=1e-10)
    ftol: Array = eqx.field(converter=_tolerance, default=1e-8)
    descent: TrustRegionDescent = TrustRegionDescent()
    search: RadiusSearch = RadiusSearch()
    converged_reason: ClassVar[str] = (
        "converged (scipy's ftol/xtol test: relative cost decrease below ftol or step below rtol)")

    def init(self, y, lin):
        scale_inv = _column_norms(lin.h)
        radius = jnp.linalg.norm(y * scale_inv)
        zero = jnp.zeros((), y.dtype)
        return _TrustRegionState(scale_inv, jnp.where(radius > 0, radius, 1.0), zero, zero, zero)

    def step(self, residuals, y, lin, state, active):
        step_h, alpha, predicted, d = self.descent.step(state.radius, state.scale_inv, state.alpha, lin,
                                                        lin.r.shape[0])
        step_h = jnp.where(active, step_h, 0.0)
        step = d * step_h
        y_eval = y + step
        r_eval = residuals(y_eval)
        cost_eval = 0.5 * jnp.sum(r_eval**2)
        finite = jnp.isfinite(cost_eval)
        actual = lin.cost - cost_eval
        ratio = self.search.ratio(predicted, actual)
        radius = self.search.step(state.radius, ratio, jnp.linalg.norm(step_h), finite)
        radius = jnp.where(active, radius, state.radius)
        alpha = alpha * state.radius / radius
        trial = Trial(step, y_eval, r_eval, cost_eval, finite & (actual > 0), jnp.all(jnp.isfinite(step)))
        return trial, _TrustRegionState(state.scale_inv, radius, alpha, ratio, actual)

    def terminate(self, y, lin, trial, state):
        ftol, xtol = jnp.asarray(self.ftol, y.dtype), jnp.asarray(self.rtol, y.dtype)
        ftol_ok = (state.actual < ftol * lin.cost) & (state.ratio > self.search.low)
        xtol_ok = jnp.linalg.norm(trial.step) < xtol * (xtol + jnp.linalg.norm(y))
        return jnp.isfinite(trial.cost) & (ftol_ok | xtol_ok)

    def relinearise(self, state, lin):
        # scipy's running maximum of the column norms, at each new linearisation
        return eqx.tree_at(lambda s: s.scale_inv, state, jnp.maximum(state.scale_inv, _column_norms(lin.h)))

    def refuse(self, state):
        # as after a non-finite trial: the radius shrinks (scipy: to a quarter of the step; here of the radius)
        return eqx.tree_at(lambda s: (s.radius, s.alpha), state,
                           (self.search.shrink * state.radius, state.alpha / self.search.shrink))


# ---------------------------------------------------------------------------------------------------- stopping

# How a start stands after a step, as a traced int: running, or why it stopped. The solver's own test and the
# loop's flat-cost test are two ways to converge with different reasons; `PADDING` marks a fleet's filler rows.
# `OUTPACED`: a start of a multi-start batch stopped by `iterate` (`outpaced`).
RUNNING, CONVERGED, CONVERGED_FLAT, STALLED, LINEAR_SOLVE_FAILED, NONFINITE, NONFINITE_INITIAL, PADDING, OUTPACED = (
    range(9))

# accepted steps over which `outpaced` measures a running start's rate of decrease
OUTPACE_WINDOW = 10


class Bookkeeping(eqx.Module):
    """One start's state for the loop's own stopping tests, beside the solver's `terminate` (a leading axis of
    starts when stacked). `iterate` and `fit_fleet` both advance it with `advance`, so the two loops stop alike."""

    accepted: Int[Array, ""]  # accepted steps
    since: Int[Array, ""]  # consecutive rejected trials
    recent: Float[Array, " window_plus_1"]  # the last `window + 1` accepted costs, oldest first (the first repeated)
    code: Int[Array, ""]  # `RUNNING` or why the start stopped


def begin(cost, finite, window: int) -> Bookkeeping:
    """The bookkeeping of a start whose linearisation at its initial point has `cost` (and is `finite`)."""
    zero = jnp.zeros((), jnp.int32)
    code = jnp.where(jnp.isfinite(cost) & finite, RUNNING, NONFINITE_INITIAL).astype(jnp.int32)
    return Bookkeeping(zero, zero, jnp.full((window + 1,), cost), code)


def advance(book: Bookkeeping, *, cost, take, ok, terminate, finite, ftol, window: int, max_rejections: int
            ) -> Bookkeeping:
    r"""One step of a running start (a stopped one stays as it is): `take` whether its trial was accepted (at a
    trial cost `cost`), `ok` whether the linear solve succeeded, `terminate` the solver's own test, `finite` whether
    the Jacobian at the new point is finite (`True` where not known yet).

    The start ends, in this order: `LINEAR_SOLVE_FAILED`; `CONVERGED` (the solver's test); `CONVERGED_FLAT` when its
    accepted steps no longer lower the cost (the mean relative decrease over the last `window` accepted steps below
    `ftol`: parameters drifting along a flat valley); `NONFINITE` (the Jacobian at the accepted point); `STALLED`
    after `max_rejections` consecutive rejected trials."""
    active = book.code == RUNNING
    take = active & take
    accepted = book.accepted + take.astype(jnp.int32)
    recent = jnp.where(take, jnp.concatenate([book.recent[1:], jnp.asarray(cost, book.recent.dtype)[None]]),
                       book.recent)
    since = jnp.where(take, 0, book.since + active.astype(jnp.int32))
    ftol = jnp.asarray(ftol, recent.dtype)
    flat = take & (accepted >= window) & (recent[0] - recent[-1] <= ftol * window * recent[-1])
    code = jnp.select(
        [~active, ~ok, terminate, flat, take & ~finite, ~take & (since >= max_rejections)],
        [book.code, LINEAR_SOLVE_FAILED, CONVERGED, CONVERGED_FLAT, NONFINITE, STALLED],
        RUNNING,
    ).astype(jnp.int32)
    return Bookkeeping(accepted, since, recent, code)


def outpaced(histories, history_steps, codes, steps, step: int, max_steps: int, window: int = OUTPACE_WINDOW
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
    the steps they were taken at (its initial cost at step 0); `codes`: the starts' bookkeeping codes after `step`;
    `steps`: the step at which each start stopped (the current one for those running)."""
    done = [j for j in range(len(codes)) if codes[j] in (CONVERGED, CONVERGED_FLAT)]
    if not done:
        return {}
    winner = min(done, key=lambda j: histories[j][-1])
    target, k_star = histories[winner][-1], int(steps[winner])
    if step < 2 * k_star or step >= max_steps:  # at the last step a running start ends `max_steps_reached` anyway
        return {}
    out = {}
    for i in np.flatnonzero(np.asarray(codes) == RUNNING):
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


def verdict_of(code: int, *, solver, window: int, since: int, max_steps: int, interrupted: bool = False,
               stalled_note: str = "") -> Verdict:
    """The `Verdict` of a start whose bookkeeping ended with `code` (`RUNNING`: it ran out of steps, or was
    interrupted); `since` its consecutive rejected trials; `stalled_note` is appended to a stall's reason."""
    if code == CONVERGED:
        return Verdict("successful", solver.converged_reason)
    if code == CONVERGED_FLAT:
        return Verdict("successful", f"converged (mean relative cost decrease per accepted step over the last "
                                     f"{window} below ftol = {float(solver.ftol):g})")
    if code == STALLED:
        return Verdict("stalled", f"no decrease of the cost in {since} consecutive trial steps (stalled or "
                                  f"diverging{stalled_note})")
    if code == NONFINITE:
        return Verdict("nonfinite", "the Jacobian is not finite at an accepted point")
    if code == NONFINITE_INITIAL:
        return Verdict("nonfinite_initial", result_message("nonfinite_initial"))
    if code == LINEAR_SOLVE_FAILED:
        return Verdict("linear_solve_failed", result_message("linear_solve_failed"))
    if code == RUNNING:
        if interrupted:
            return Verdict("interrupted", result_message("interrupted"))
        return Verdict("max_steps_reached", f"max_steps = {max_steps} reached before convergence")
    raise ValueError(f"no verdict for the bookkeeping code {code}")


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
    verdicts: list = [None] * n_starts
    for i in range(n_starts):
        if not np.isfinite(cost_np[i]):
            why = model_error(core, y[i])
            verdicts[i] = Verdict("nonfinite_initial", "the model's predictions are not finite at the initial "
                                                       "parameters" + (f" ({why})" if why else ""))
        elif not finite_np[i]:
            verdicts[i] = Verdict("nonfinite_initial", "the Jacobian is not finite at the initial parameters")
    active = np.asarray(book.code) == RUNNING
    state = _init(solver, y, lin)
    meter_state = meter.init(label, n_starts)
    t0 = time.perf_counter()
    model_errors = [""] * n_starts  # per start, the last runtime check the model raised at its trial point
    try:
        for k in range(1, max_steps + 1):
            if not active.any():
                break
            refused = np.zeros(n_starts, bool)
            try:
                out = _step(solver, core, y, lin, state, jnp.asarray(active))
                jax.block_until_ready(out)
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
    runs = []
    for i in range(n_starts):
        verdict = verdicts[i] or verdict_of(RUNNING, solver=solver, window=window, since=0, max_steps=max_steps)
        lin_i = jtu.tree_map(lambda x: x[i], lin) if fresh[i] else None
        accepted = len(histories[i]) - 1
        runs.append(Run(y[i], int(steps[i]), accepted, histories[i], history_steps[i], verdict, lin_i))
    return runs
