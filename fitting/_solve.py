"""`solve` and `fit`: a solver (`fitting._solver`) run from one or several starts, through levels of smoothing and
restarts past kinks, to a `FitResult`."""

import dataclasses
import os
import sys
import time
import warnings
from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import jax.tree_util as jtu
import lineax as lx
import numpy as np
import optimistix as optx

import piezojax as pj
from piezojax import PiezojaxValueError

from ._problem import Problem, matches, path_string
from ._results import FitResult, summarise
from ._solver import (
    AbstractNormalSolver,
    FitError,
    LevenbergMarquardt,
    Linearisation,
    TrustRegion,
    Verdict,
    as_progress_meter,
    iterate,
)
from ._stationarity import NOT_FINITE_NEARBY, descent_point, repair_point, stationarity_verdict


class PrecisionWarning(UserWarning):
    """A fit runs in single precision (JAX's 64-bit mode is off): see `solve`."""


def caller_level() -> int:
    """`stacklevel` for a warning issued by the caller of this function: the first frame outside `fitting`."""
    frame, level = sys._getframe(1), 1
    while frame is not None and frame.f_code.co_filename.startswith(_PACKAGE):
        frame, level = frame.f_back, level + 1
    return level


_PACKAGE = os.path.dirname(os.path.abspath(__file__)) + os.sep


def set_smoothing(model, smoothing: float):
    """`model` with the `smoothing` of every hysteresis block that has one set to `smoothing` (0 = exact).

    Works on reparametrised models; a model without smoothing is returned unchanged.
    """

    def is_h(x):
        # a field, not a wrapper's property (`pj.OutputPolynomial`): the map descends into the wrapped operator
        return isinstance(x, pj.AbstractHysteresis) and "smoothing" in {f.name for f in dataclasses.fields(x)}

    def replace(x):
        if is_h(x) and eqx.is_array(x.smoothing):
            return eqx.tree_at(lambda h: h.smoothing, x, jnp.asarray(smoothing, x.smoothing.dtype))
        return x

    return jtu.tree_map(replace, model, is_leaf=is_h)




def make_solver(method, rtol, atol, ftol, linear_solver) -> AbstractNormalSolver:
    if isinstance(method, AbstractNormalSolver):
        if linear_solver is not None:
            raise PiezojaxValueError("`linear_solver` is a setting of the built-in methods; with a solver instance as "
                                     "`method`, give it to that solver")
        return method
    if method == "levenberg_marquardt":
        descent = optx.DampedNewtonDescent(linear_solver=lx.Cholesky() if linear_solver is None else linear_solver)
        return LevenbergMarquardt(rtol=rtol, atol=atol, ftol=ftol, descent=descent)
    if method == "trust_region":
        return TrustRegion(rtol=rtol, atol=atol, ftol=ftol)
    raise PiezojaxValueError(f'`method` must be "levenberg_marquardt", "trust_region" or a '
                             f"fitting.AbstractNormalSolver, got {method!r}")


def _start_verdict(runs, n_levels) -> Verdict:
    """One start's verdict over its continuation levels: its first hard failure, else the last level's verdict
    (earlier levels may stop at max_steps without failing the fit; kink restarts come after the levels)."""
    for _, run in runs:
        if run.verdict.hard:
            return run.verdict
    if len(runs) < n_levels:
        # the levels stopped early without a hard failure of this start: another start was interrupted, which stops
        # them all; this one did not reach the exact model either (all are then ranked by cost alone)
        return Verdict("interrupted", "interrupted by the user (Ctrl-C) before the last smoothing level")
    return runs[-1][1].verdict


SETTLED_WINDOW = 50
"""Accepted steps over which `settled` measures what a fit stopped by `max_steps` still gained."""


def settled(verdict: Verdict, history, steps: int, m: int, p: int) -> Verdict:
    r"""A start stopped by `max_steps` (`verdict`, after `steps` steps; `history` its accepted costs, oldest first:
    the last `SETTLED_WINDOW + 1` or more, else it is returned unchanged) whose cost fell over its last `SETTLED_WINDOW`
    accepted steps by less than moving one parameter by one standard error changes it, $\hat\sigma^2/2 =
    \text{cost}/(m - p)$ (the data-resolution bound of `fitting._stationarity.kink_ftol`, without its 1e-5 floor),
    has converged in practice: another as many steps at that rate would change nothing the data can resolve. As
    after a kink restart that gains less than that, the verdict holds whatever the gradient test says (it is applied
    after it, and such a start is not restarted past kinks); the `levels` entry keeps the run's own reason.
    Measured on `experiments.plant_study`'s PI draw 1: a re-seeded fit at 1.00x the noise crawled on for 500 steps,
    its cost falling by 5e-6 of it in the last 60 (a nearly dead play's threshold, 36 ± 35 V, drifting), against a
    resolution of 3e-5; it ended "max_steps_reached" and `piezojax fit` exited 1. Other verdicts, and runs with
    fewer accepted steps, are returned unchanged. `fitting.fit_fleet` applies it to each actuator alike."""
    h = history
    if verdict.code != "max_steps_reached" or len(h) <= SETTLED_WINDOW:
        return verdict
    drop, resolution = h[-1 - SETTLED_WINDOW] - h[-1], h[-1] / max(m - p, 1)
    if not (np.isfinite(drop) and drop < resolution):
        return verdict
    return Verdict("successful", f"converged in practice: max_steps = {steps} reached while the cost fell by "
                                 f"{drop:.2e} over the last {SETTLED_WINDOW} accepted steps, less than moving one "
                                 f"parameter by one standard error changes it (cost/(m - p) = {resolution:.2e})")


def _linearisation(problem: Problem, run) -> Linearisation:
    """The run's linearisation at its last point, or a new one where the solver did not form it there."""
    if run.linearisation is not None:
        return run.linearisation
    r, g, h = problem.normal_equations(run.u)
    return Linearisation(r, 0.5 * jnp.sum(r**2), g, h)


def solve(
    problem: Problem,
    *,
    starts=None,
    smoothing: Sequence[float] | None = None,
    max_steps: int = 200,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    ftol: float = 1e-8,
    linear_solver: lx.AbstractLinearSolver | None = None,
    progress=True,
    throw: bool = False,
    gtol: float = 1e-2,
    kink_restarts: int = 5,
    method="levenberg_marquardt",
) -> FitResult:
    r"""Solve a `Problem` by Levenberg–Marquardt (`optimistix.LevenbergMarquardt`) from its initial model.

    The algorithm is `optx.LevenbergMarquardt`'s, assembled from its optimistix parts (`DampedNewtonDescent`,
    `ClassicalTrustRegion`) in normal-equation form (`fitting.LevenbergMarquardt`): at each accepted point the
    weighted residuals are linearised once into $g = J^\top r$ and $H = J^\top J$ (forward mode, `jacobian_chunk`
    experiments at a time, the $m \times p$ Jacobian never kept whole), and each trial solves
    $(H + \lambda I)\delta = -g$ in the scaled parameters $u = \theta/s$ of the problem (Cholesky by default). A
    rejected trial costs one simulation, not a Jacobian. Forming $H$ squares the condition number: with the default
    Jacobian-column scaling $\kappa(J)$ up to ≈ 1e6 is harmless in float64; the damping $\lambda I$ regularises the
    rest.

    **Arguments:**

    - `problem`: a `Problem`.
    - `starts`: optional multi-start: a sequence of models with the structure of the problem's model (e.g. cold
      starts, or perturbations of the initial model), fitted at once under `jax.vmap` (lockstep; each start keeps
      its own damping and verdict). The result is the start with the lowest final cost, with its verdict (a start
      that failed hard — non-finite, interrupted — only when all did); `result.starts` lists every start's cost and
      verdict (the reported start's after the stationarity test, as `result`). `None`: the problem's model.
      Memory and time per step grow with the number of starts (on XLA:CPU a stopped start is no longer
      linearised, so there a step costs what the running starts cost). At the last smoothing level a start stops
      early, `"outpaced"`, once another has converged at a lower cost, it has had twice the steps that one needed,
      and at the rate its cost fell over its last ten accepted steps it would not reach that cost within
      `max_steps` (where it would end above it anyway; see `fitting._solver.outpaced`).
    - `smoothing`: continuation levels for the hysteresis `smoothing` (e.g. `(0.1, 0.02, 0.0)`: relaxed, then
      exact operators; each level starts from the previous optimum). `None`: the model's own smoothing.
    - `max_steps`: steps per level (a start stopped by them whose cost fell by less than a one-standard-error change
      of one parameter over its last 50 accepted steps has converged in practice: `"successful"`, see `settled`);
      `rtol`, `atol`: optimistix's Cauchy termination tolerances on the parameters
      and the residuals; `ftol`: the fit also stops (converged) when the cost decreased by less than `ftol` relative
      per accepted step, on average over the last five (scipy's `ftol` test, averaged).
    - `linear_solver`: the lineax solver of the damped $p \times p$ system (default `lx.Cholesky()`).
    - `method`: `"levenberg_marquardt"` (default): `fitting.LevenbergMarquardt` as above. `"trust_region"`:
      `fitting.TrustRegion`, the algorithm of `scipy.optimize.least_squares(method="trf", x_scale="jac")` for an
      unbounded problem, from the same linearisations: a trust region of radius $\Delta$ in the parameters scaled
      by the running maximum of the Jacobian's column norms, the step $-(\hat H + \alpha I)^{-1}\hat g$ with
      $\alpha$ such that it reaches the radius (from the eigen-decomposition of the scaled $p \times p$ $\hat H$,
      Moré's iteration), the radius shrunk to a quarter of the step below a ratio (actual / predicted decrease) of
      0.25 and doubled above 0.75, any decrease accepted, and scipy's tests (relative cost decrease below `ftol`
      with a ratio above 0.25, or step below `rtol` relative). `linear_solver` is not used. On the calibration
      benchmark it needed about half the Jacobians of `"levenberg_marquardt"` (`experiments/bench_calibration.py`);
      both are local methods. Or a solver instance (a `fitting.AbstractNormalSolver`, e.g.
      `fitting.LevenbergMarquardt(search=optx.ClassicalTrustRegion(high_cutoff=0.9))`): then its own tolerances are
      used, not `rtol`, `atol`, `ftol`.
    - `progress`: `True` (default) prints step, cost, accepted steps and elapsed time on stderr
      (`fitting.TextProgressMeter`); `False` nothing; or a `fitting.AbstractProgressMeter` of your own.
    - `gtol`: a fit that stops with $\max_i|\cos(r, J_{:,i})| >$ `gtol` is probed along ± each parameter, the
      gradient and the Gauss–Newton step (see `FitResult`): a minimum at a kink of the piecewise smooth model is
      converged (`"converged_at_kink"`), a point where the cost still falls or the model is not finite nearby failed
      (`"not_stationary"`).
    - `kink_restarts`: where a start's steps stop although a probed direction lowers the cost (a joint step keeps
      crossing a kink of the exact operators), the fit moves to the lowest probed point and iterates again, at most
      this many times (0: never). Each restart costs about `4 p + 4` residual evaluations and a new iteration.
      When the last restart lowered the cost by less than `fitting._stationarity.kink_ftol` of it (1e-5, or
      $1/(m - p)$ when larger: less than a one-standard-error change of a parameter would), the cost no
      longer decreases in practice (the exact operators' kinks are dense: each step ends at the next one) and the
      fit is converged (`"converged_at_kink"`, with both numbers in the reason).
    - `throw`: raise `fitting.FitError` (a `pj.PiezojaxError`, holding the failed result) when the fit fails,
      instead of returning a failed result.

    **Returns:** a `FitResult`. A failed fit (max steps, stall, non-finite predictions, Ctrl-C) is returned with
    `success=False`, its `code` (a `fitting.RESULTS` name), `reason`, and the last *accepted* parameters — never NaN
    parameters. A trial step at which the model raises a runtime check (`eqx.error_if`, e.g. a parameter that
    underflowed to an invalid value) is a rejected trial of that start, like one with non-finite predictions: its
    step shrinks; the other starts of a multi-start batch step as usual.

    Not itself jit-able (a Python loop, so that progress and Ctrl-C work); each trial and each linearisation is one
    compiled call. A problem whose parameters are not float64 (JAX's 64-bit mode off) is fitted, with a
    `fitting.PrecisionWarning`.
    """
    levels = _levels(problem, smoothing, max_steps, kink_restarts)
    solver = make_solver(method, rtol, atol, ftol, linear_solver)
    meter = as_progress_meter(progress)
    u = _start_points(problem, starts)
    t0 = time.perf_counter()
    per_start, level, label = _run_levels(solver, problem, u, levels, max_steps=max_steps, meter=meter)
    # (`_start_verdict` calls a start interrupted whose levels stopped early)
    # past kinks: where a start's steps stopped although the cost still falls along a probed direction by more than
    # the gtol test allows (the exact operators are piecewise smooth, and a joint step can keep crossing a kink), go
    # to the lowest point along that direction and iterate again, at most `kink_restarts` times per start; a restart
    # is kept only if it converges at a lower cost
    interrupted = any(run.verdict.code == "interrupted" for runs_i in per_start for _, run in runs_i) or any(
        len(runs_i) < len(levels) for runs_i in per_start)
    kink_gain: list[float | None] = [None] * u.shape[0]  # relative decrease by the last restart (0: none)
    try:
        _past_kinks(solver, level, per_start, kink_gain, interrupted=interrupted, kink_restarts=kink_restarts,
                    max_steps=max_steps, meter=meter, gtol=gtol, label=label, last_level=levels[-1])
    except KeyboardInterrupt:
        pass  # a restart is only an attempt to improve: the points reached so far stand
    u = jnp.stack([runs_i[-1][1].u for runs_i in per_start])
    seconds = time.perf_counter() - t0
    verdicts = [_start_verdict(runs, len(levels)) for runs in per_start]
    costs = np.array([runs[-1][1].history[-1] for runs in per_start])
    order = np.lexsort(([not v.success for v in verdicts], np.where(np.isfinite(costs), costs, np.inf),
                        [v.hard for v in verdicts]))
    best = int(order[0])  # the lowest cost (a start stopped by max_steps below a converged one fits better)
    runs = per_start[best]
    history = [c for _, r in runs for c in r.history]
    try:
        lin = _linearisation(level, runs[-1][1])
        verdict = stationarity_verdict(level, u[best], lin, verdicts[best], initial_cost=history[0], gtol=gtol,
                                       kink_gain=kink_gain[best])
    except KeyboardInterrupt:
        # while the result's linearisation was formed: the point stands, without standard errors
        r = level.residuals(u[best])
        p = u.shape[1]
        lin = Linearisation(r, 0.5 * jnp.sum(r**2), jnp.full((p,), jnp.nan, r.dtype),
                            jnp.full((p, p), jnp.nan, r.dtype))
        verdict = Verdict("interrupted", "interrupted by the user (Ctrl-C) after the steps, while the standard "
                                         "errors were computed (not computed)")
    m, p = level.num_residuals, level.num_params
    verdict = settled(verdict, runs[-1][1].history, runs[-1][1].steps, m, p)
    table = None
    if starts is not None:
        verdicts = [settled(v, per_start[i][-1][1].history, per_start[i][-1][1].steps, m, p)
                    for i, v in enumerate(verdicts)]
        verdicts[best] = verdict
        table = [{"cost": float(costs[i]), "success": v.success, "code": v.code, "reason": v.reason,
                  "steps": sum(r.steps for _, r in per_start[i]), "best": i == best} for i, v in enumerate(verdicts)]
    result = summarise(
        level,
        u[best],
        lin,
        verdict,
        steps=sum(r.steps for _, r in runs),
        accepted=sum(r.accepted for _, r in runs),
        history=history,
        history_steps=[k + sum(q.steps for _, q in runs[:j]) for j, (_, r) in enumerate(runs) for k in r.history_steps],
        seconds=seconds,
        levels=[{"smoothing": s, "steps": r.steps, "cost": r.history[-1], "reason": r.verdict.reason} for s, r in runs],
        starts=table,
    )
    if throw and not result.success:
        raise FitError(result)
    return result


def _levels(problem: Problem, smoothing, max_steps, kink_restarts) -> list:
    """`solve`'s arguments checked; the continuation levels (`[None]`: the model's own smoothing)."""
    if isinstance(max_steps, bool) or not isinstance(max_steps, int | np.integer) or max_steps < 1:
        raise PiezojaxValueError(f"`max_steps` must be an integer >= 1, got {max_steps!r}")
    if isinstance(kink_restarts, bool) or not isinstance(kink_restarts, int | np.integer) or kink_restarts < 0:
        raise PiezojaxValueError(f"`kink_restarts` must be an integer >= 0, got {kink_restarts!r}")
    if smoothing is not None and (isinstance(smoothing, str | bytes) or np.ndim(smoothing) != 1):
        raise PiezojaxValueError(f"`smoothing` must be a sequence of continuation levels (e.g. (0.05, 0.0)) or None, "
                                 f"got {smoothing!r}")
    levels = [None] if smoothing is None else list(smoothing)
    if not levels:
        raise PiezojaxValueError("`smoothing` must list at least one level (or be None)")
    for s in levels:
        if s is not None and not (np.isfinite(s) and s >= 0):
            raise PiezojaxValueError(f"`smoothing` levels must be finite and >= 0, got {s}")
    if smoothing is not None:
        settings = [path_string(path) for path in pj.setting_key_paths(problem.model)]
        freed = [n for n in problem.parameter_names() if any(matches(n, st) for st in settings)]
        if freed:
            raise PiezojaxValueError(f"`smoothing` levels set {freed[0]!r}, which `free` also fits: fix it (leave it "
                                     "out of `free`) or give no levels")
    return levels


def _start_points(problem: Problem, starts) -> jnp.ndarray:
    """The scaled parameters of each start, shape `(starts, p)` (the problem's own start when `starts` is None)."""
    if starts is None:
        u = problem.u0[None]
    else:
        starts = list(starts)
        if not starts:
            raise PiezojaxValueError("`starts` must list at least one model (or be None: the problem's start)")
        u = jnp.stack([problem.u_of(m, name=f"starts[{i}]") for i, m in enumerate(starts)])
    if u.dtype != jnp.float64:
        warnings.warn(
            f"fitting in {u.dtype}: JAX's 64-bit mode is off, so the model, data and solver work in single precision "
            "(about 7 digits: costs and steps below ~1e-7 relative are rounding, standard errors unreliable). Call "
            "`jax.config.update('jax_enable_x64', True)` before creating models and data (the command line does); "
            "to fit in single precision on purpose, filter `fitting.PrecisionWarning`.",
            PrecisionWarning, stacklevel=caller_level())
    return u


def _run_levels(solver, problem: Problem, u, levels: list, *, max_steps: int, meter) -> tuple[list, Problem, str]:
    """`iterate` at each continuation level from the previous level's points: `(per_start, level, label)` with
    each start's `(smoothing, Run)` per level done, the problem at the last level run and its progress label. A
    Ctrl-C between two levels ends with the levels done (re-raised before the first)."""
    frozen = problem.frozen
    per_start: list[list] = [[] for _ in range(u.shape[0])]
    level, label = problem, ""
    try:
        for n_level, s in enumerate(levels):
            if s is not None:
                frozen = set_smoothing(frozen, s)
            label = f"[smoothing {s:g}] " if s is not None else ""
            next_level = problem.with_frozen(frozen)
            runs = iterate(solver, next_level.core, u, max_steps=max_steps, meter=meter, label=label,
                           outpace=n_level == len(levels) - 1)
            level = next_level
            for i, run in enumerate(runs):
                per_start[i].append((s, run))
            u = jnp.stack([run.u for run in runs])
            if any(run.verdict.code == "interrupted" for run in runs) or all(run.verdict.hard for run in runs):
                break
    except KeyboardInterrupt:  # between the steps of two levels: the levels done so far are the result
        if not per_start[0]:
            raise  # no step taken yet: nothing to return but the start
    return per_start, level, label


def _start_name(i: int, n: int) -> str:
    """How the progress lines of a multi-start fit name start `i` of `n` (nothing for a single start)."""
    return f"start {i + 1} of {n}, " if n > 1 else ""


def _past_kinks(solver, level, per_start, kink_gain, *, interrupted, kink_restarts, max_steps, meter, gtol, label,
                last_level) -> None:
    """The restarts past kinks of `solve`, appending each kept restart's run to its start's `per_start` list."""
    for i in range(len(per_start)):
        if interrupted or any(run.verdict.hard for _, run in per_start[i]):
            continue
        for _ in range(kink_restarts):
            last = per_start[i][-1][1]
            if not last.verdict.success:
                break
            lin = _linearisation(level, last)
            last.linearisation = lin
            nxt = descent_point(level, last.u, lin, gtol)  # None where it is stationary by the gtol test
            if nxt is None:
                break
            (run,) = iterate(solver, level.core, jnp.asarray(nxt, last.u.dtype)[None], max_steps=max_steps, meter=meter,
                             label=f"{label}[{_start_name(i, len(per_start))}past a kink] ")
            if run.verdict.code == "interrupted":
                interrupted = True
                break
            if not run.verdict.success:
                break  # inconclusive: keep the earlier point and its verdict
            if not run.history[-1] < last.history[-1]:
                kink_gain[i] = 0.0
                break
            kink_gain[i] = (last.history[-1] - run.history[-1]) / last.history[-1]
            per_start[i].append((last_level, run))
        if interrupted:
            break


def fit(
    model,
    dataset,
    *,
    predictor=None,
    targets=None,
    free=None,
    weights="range",
    scales="jacobian",
    jacobian_chunk=None,
    **solve_options,
) -> FitResult:
    """Calibrate `model` on `dataset` by weighted least squares: `solve(Problem(model, dataset, ...), ...)`.

    See `Problem` for `predictor`, `targets`, `free`, `weights`, `scales` and `solve` for the solver options.
    A fit that fails because the model is not finite at or next to where it stopped (a start whose Jacobian is not
    finite, a point whose probes found non-finite neighbours and no descent: `stuck_where_not_finite`) is repaired:
    that point is moved to a near point where the model is finite next to it (`fitting._stationarity.repair_point`)
    and fitted again from there, alone; the better of the two fits is returned (`throw` applies to it), with
    `result.repairs` saying what was moved and which was kept (or that nothing helped).

    ```python
    result = fitting.fit(actuator, dataset, free=["hysteresis", "dynamics"], smoothing=(0.05, 0.0))
    print(result.report())
    ```
    """
    options = dict(predictor=predictor, targets=targets, free=free, weights=weights, scales=scales,
                   jacobian_chunk=jacobian_chunk)
    problem = Problem(model, dataset, **options)
    throw = solve_options.pop("throw", False)
    result = solve(problem, **solve_options)
    if stuck_where_not_finite(result):
        result = _repaired(problem, result, dataset, options, solve_options)
    if throw and not result.success:
        raise FitError(result)
    return result


def _repaired(problem: Problem, result: FitResult, dataset, options: dict, solve_options: dict) -> FitResult:
    """`result`, a fit stuck where the model is not finite next to the point it stopped at, fitted again from that
    point moved (`repair_point`, probed at the smoothing level the fit stopped at): the better of the two fits (a
    success first, then the lower cost), with both fits' steps and time, and a note in `repairs`."""
    level = result.levels[-1]["smoothing"] if result.levels else None
    probed = problem if level is None else problem.with_frozen(set_smoothing(problem.frozen, level))
    repair = repair_point(probed, result.u)
    if repair is None:
        return result
    note = (f"the fit stopped at {'its start' if result.accepted_steps == 0 else 'a point'} ({result.code}): "
            + repair.describe())
    if repair.u is None:
        return dataclasses.replace(result, repairs=[note])
    moved = problem.params(jnp.asarray(repair.u, dtype=problem.u0.dtype))
    again = solve(Problem(moved, dataset, **options), **{**solve_options, "starts": None})
    better = (again.success, -again.cost) > (result.success, -result.cost) if np.isfinite(again.cost) else False
    note += (f"; fitted again from there ({again.code}, cost {again.cost:.4e}"
             + (", kept" if better else f", not kept: the first fit's {result.cost:.4e} stands") + ")")
    kept = again if better else result
    return dataclasses.replace(kept, repairs=[note], steps=result.steps + again.steps,
                               accepted_steps=result.accepted_steps + again.accepted_steps,
                               seconds=result.seconds + again.seconds)


def stuck_where_not_finite(result: FitResult) -> bool:
    """Whether a fit failed because the model is not finite at or next to the point it stopped at: the Jacobian at
    its start, or a probe next to its last point where no probe lowered the cost (`fit` then repairs that point)."""
    return not result.success and (result.code == "nonfinite_initial"
                                   or (result.code == "not_stationary" and NOT_FINITE_NEARBY in result.reason))
