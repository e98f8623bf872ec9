"""Levenberg–Marquardt over a `Problem`: stepped from Python (progress, Ctrl-C, failure reasons), with continuation."""

import dataclasses
import functools
import sys
import time
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import lineax as lx
import numpy as np
import optimistix as optx

import piezojax as pj
from piezojax._checks import PiezojaxValueError

from ._problem import Problem, _linearise
from ._results import FitResult, summarise


def set_smoothing(model, smoothing: float):
    """`model` with the `smoothing` of every hysteresis block that has one set to `smoothing` (0 = exact).

    Works on reparametrised models; a model without smoothing is returned unchanged.
    """

    def is_h(x):
        return isinstance(x, pj.AbstractHysteresis) and hasattr(x, "smoothing")

    def replace(x):
        if is_h(x) and eqx.is_array(x.smoothing):
            return eqx.tree_at(lambda h: h.smoothing, x, jnp.asarray(smoothing, x.smoothing.dtype))
        return x

    return jtu.tree_map(replace, model, is_leaf=is_h)


@dataclasses.dataclass
class _Run:
    u: jax.Array
    steps: int
    accepted: int
    history: list
    history_steps: list
    success: bool
    reason: str
    code: str


@functools.lru_cache(maxsize=16)
def _parts(linear_solver) -> tuple[optx.DampedNewtonDescent, optx.ClassicalTrustRegion]:
    # one object per setting, so that compiled steps are found again in the cache
    return optx.DampedNewtonDescent(linear_solver=linear_solver), optx.ClassicalTrustRegion()


def _trial_one(descent, search, core, y, r, cost, g, h, step_size, search_state, rtol, atol, active):
    """One Levenberg–Marquardt trial: the damped Gauss–Newton step from the linearisation `(g, h)` at `y`, the cost
    at the trial point, and the trust-region verdict (optimistix's `DampedNewtonDescent` and `ClassicalTrustRegion`,
    the two halves of `optx.LevenbergMarquardt`)."""
    f_info = optx.FunctionInfo.EvalGradHessian(cost, g, lx.MatrixLinearOperator(h, lx.positive_semidefinite_tag))
    descent_state = descent.query(y, f_info, descent.init(y, f_info))
    delta, result = descent.step(step_size, descent_state)
    # a finished start (e.g. non-finite at its start) stays where it is: its model is never evaluated elsewhere
    delta = jnp.where(active, delta, 0.0)
    y_eval = y + delta
    r_eval = core.residuals(y_eval)
    cost_eval = 0.5 * jnp.sum(r_eval**2)
    step_size, accept, _, search_state = search.step(
        jnp.array(False), y, y_eval, f_info, optx.FunctionInfo.Eval(cost_eval), search_state
    )
    accept = accept & jnp.isfinite(cost_eval)
    # optimistix's Cauchy test (`cauchy_termination`, max norm) on the step and the change of the residuals
    y_small = jnp.max(jnp.abs(delta) / (atol + rtol * jnp.abs(y_eval))) < 1
    f_small = jnp.max(jnp.abs(r_eval - r) / (atol + rtol * jnp.abs(r_eval))) < 1
    return (y_eval, r_eval, cost_eval, accept, step_size, search_state, accept & y_small & f_small,
            result == optx.RESULTS.successful)


@eqx.filter_jit
def _trial(descent, search, core, y, r, cost, g, h, step_size, search_state, rtol, atol, active):
    """`_trial_one` for every start (leading axis of `y`, `r`, `cost`, `g`, `h`, `step_size`, `search_state`,
    `active`)."""
    batched = eqx.filter_vmap(_trial_one, in_axes=(None, None, None, 0, 0, 0, 0, 0, 0, 0, None, None, 0))
    return batched(descent, search, core, y, r, cost, g, h, step_size, search_state, rtol, atol, active)


@jax.jit
def _where(mask, new, old):
    """Per start (leading axis): `new` where `mask`, else `old`, for arrays and pytrees of arrays (one compiled
    call for the whole pytree)."""
    return jtu.tree_map(lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - 1)), a, b), new, old)


def _levenberg_marquardt(u0, core, *, rtol, atol, ftol, max_steps, linear_solver, progress,
                         label="", max_rejections=40, window=5) -> list[_Run]:
    r"""Levenberg–Marquardt in normal-equation form from every start in `u0` (shape `(starts, p)`) at once, stepped
    from Python.

    The algorithm is `optx.LevenbergMarquardt`'s — damped Newton descent $(H + \lambda I)\delta = -g$ with the
    Gauss–Newton $H = J^\top J$, $g = J^\top r$, and the classical trust-region update of $\lambda$ — built from its
    optimistix parts, with two differences that matter for long records: the model is linearised only at accepted
    points (a rejected trial costs one simulation, not a Jacobian), and the linearisation is $(g, H)$, accumulated
    over chunks of experiments (`ProblemCore.normal_equations`), never the $m \times p$ Jacobian. The starts run
    in lockstep under `vmap` (a finished start is frozen); each has its own damping, history and verdict."""
    descent, search = _parts(linear_solver)
    n_starts = u0.shape[0]
    y = u0
    r, cost, g, h, finite = _linearise(core, y)
    cost_np, finite_np = np.asarray(cost), np.asarray(finite)
    histories = [[float(c)] for c in cost_np]
    history_steps = [[0] for _ in range(n_starts)]
    steps, accepted, since = np.zeros(n_starts, int), np.zeros(n_starts, int), np.zeros(n_starts, int)
    verdicts: list = [None] * n_starts
    for i in range(n_starts):
        if not np.isfinite(cost_np[i]):
            verdicts[i] = (False, "the model's predictions are not finite at the initial parameters",
                           "nonfinite_initial")
        elif not finite_np[i]:
            verdicts[i] = (False, "the Jacobian is not finite at the initial parameters", "nonfinite_initial")
    active = np.array([v is None for v in verdicts])
    state = search.init(u0[0], None)
    search_state = jtu.tree_map(lambda x: jnp.broadcast_to(x, (n_starts,) + jnp.shape(x)), state)
    step_size = jnp.ones((n_starts,), u0.dtype)
    rtol, atol = jnp.asarray(rtol, u0.dtype), jnp.asarray(atol, u0.dtype)
    t0 = time.perf_counter()
    try:
        for k in range(1, max_steps + 1):
            if not active.any():
                break
            out = _trial(descent, search, core, y, r, cost, g, h, step_size, search_state, rtol, atol,
                         jnp.asarray(active))
            y_eval, r_eval, cost_eval, accept, new_step_size, new_search_state, terminate, ok = out
            accept_np, terminate_np, ok_np = np.asarray(accept), np.asarray(terminate), np.asarray(ok)
            cost_eval_np = np.asarray(cost_eval)
            take = active & accept_np & ok_np
            relinearise = np.zeros(n_starts, bool)
            for i in np.flatnonzero(active):
                steps[i] = k
                if not ok_np[i]:
                    verdicts[i] = (False, "the linear solve of a damped step failed", "linear_solve_failed")
                elif take[i]:
                    accepted[i], since[i] = accepted[i] + 1, 0
                    hist = histories[i]
                    hist.append(float(cost_eval_np[i]))
                    history_steps[i].append(k)
                    if terminate_np[i]:
                        verdicts[i] = (True, "converged (relative change below rtol/atol)", "successful")
                    # accepted steps that no longer lower the cost (parameters drifting along a flat valley, e.g.
                    # the threshold of a play whose weight is zero) end the fit too
                    elif len(hist) > window and hist[-window - 1] - hist[-1] <= ftol * window * hist[-1]:
                        verdicts[i] = (True, f"converged (mean relative cost decrease per accepted step over the "
                                             f"last {window} below ftol = {ftol:g})", "successful")
                    else:
                        relinearise[i] = True
                else:
                    since[i] += 1
                    if since[i] >= max_rejections:
                        verdicts[i] = (False, f"no decrease of the cost in {since[i]} consecutive trial steps "
                                              "(stalled or diverging)", "stalled")
            y, r, cost = _where(take, (y_eval, r_eval, cost_eval), (y, r, cost))
            step_size, search_state = _where(active, (new_step_size, new_search_state), (step_size, search_state))
            active = np.array([v is None for v in verdicts])
            if relinearise.any():
                _, _, g_new, h_new, finite = _linearise(core, y)
                g, h = _where(relinearise, (g_new, h_new), (g, h))
                for i in np.flatnonzero(relinearise & ~np.asarray(finite)):
                    verdicts[i] = (False, "the Jacobian is not finite at an accepted point", "nonfinite")
                active = np.array([v is None for v in verdicts])
            if progress:
                best = min(hh[-1] for hh in histories)
                what = (f"cost {best:.6e}  accepted {accepted[0]:4d}" if n_starts == 1 else
                        f"best cost {best:.6e}  running {int(active.sum())}/{n_starts}")
                print(f"\r  {label}step {k:4d}  {what}  {time.perf_counter() - t0:7.1f} s", end="", file=sys.stderr,
                      flush=True)
    except KeyboardInterrupt:
        for i in np.flatnonzero(active):
            verdicts[i] = (False, "interrupted by the user (Ctrl-C)", "interrupted")
    if progress:
        print(file=sys.stderr)
    runs = []
    for i in range(n_starts):
        success, reason, code = verdicts[i] or (
            False, f"max_steps = {max_steps} reached before convergence", "max_steps_reached")
        runs.append(_Run(y[i], int(steps[i]), int(accepted[i]), histories[i], history_steps[i], success, reason,
                         code))
    return runs


# failures after which a start is not continued to the next smoothing level
_HARD = ("interrupted", "nonfinite_initial", "nonfinite", "linear_solve_failed")


def _start_verdict(runs, n_levels):
    """`(success, reason, code)` of one start over its continuation levels: its first hard failure, else the last
    level's verdict (earlier levels may stop at max_steps without failing the fit)."""
    for _, run in runs:
        if not run.success and run.code in _HARD:
            return False, run.reason, run.code
    last = runs[-1][1]
    return last.success and len(runs) == n_levels, last.reason, last.code


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
    progress: bool = True,
    throw: bool = False,
    gtol: float = 1e-2,
) -> FitResult:
    r"""Solve a `Problem` by Levenberg–Marquardt (`optimistix.LevenbergMarquardt`) from its initial model.

    The algorithm is `optx.LevenbergMarquardt`'s, assembled from its optimistix parts (`DampedNewtonDescent`,
    `ClassicalTrustRegion`) in normal-equation form: at each accepted point the weighted residuals are linearised
    once into $g = J^\top r$ and $H = J^\top J$ (forward mode, `jacobian_chunk` experiments at a time, the
    $m \times p$ Jacobian never kept whole), and each trial solves $(H + \lambda I)\delta = -g$ in the scaled
    parameters $u = \theta/s$ of the problem (Cholesky by default). A rejected trial costs one simulation, not a
    Jacobian. Forming $H$ squares the condition number: with the default Jacobian-column scaling $\kappa(J)$ up
    to ≈ 1e6 is harmless in float64; the damping $\lambda I$ regularises the rest.

    **Arguments:**

    - `problem`: a `Problem`.
    - `starts`: optional multi-start: a sequence of models with the structure of the problem's model (e.g. cold
      starts, or perturbations of the initial model), fitted at once under `jax.vmap` (lockstep; each start keeps
      its own damping and verdict). The result is the start with the lowest final cost among those that converged
      (among all if none did); `result.starts` lists every start's cost and verdict. `None`: the problem's model.
      Memory and time per step grow with the number of starts.
    - `smoothing`: continuation levels for the hysteresis `smoothing` (e.g. `(0.1, 0.02, 0.0)`: relaxed, then
      exact operators; each level starts from the previous optimum). `None`: the model's own smoothing.
    - `max_steps`: Levenberg–Marquardt steps per level; `rtol`, `atol`: optimistix's Cauchy termination tolerances
      on the parameters and the residuals; `ftol`: the fit also stops (converged) when the cost decreased by less than
      `ftol` relative per accepted step, on average over the last five (scipy's `ftol` test, averaged).
    - `linear_solver`: the lineax solver of the damped $p \times p$ system (default `lx.Cholesky()`).
    - `progress`: print step, cost, accepted steps and elapsed time on stderr.
    - `gtol`: a fit that stops with $\max_i|\cos(r, J_{:,i})| >$ `gtol` (not a stationary point: e.g. the trust
      region shrank to nothing around non-finite predictions) is reported as failed (`"not_stationary"`).
    - `throw`: raise `RuntimeError` with the reason when the fit fails, instead of returning a failed result.

    **Returns:** a `FitResult`. A failed fit (max steps, stall, non-finite predictions, Ctrl-C) is returned with
    `success=False`, its `reason`, and the last *accepted* parameters — never NaN parameters.

    Not itself jit-able (a Python loop, so that progress and Ctrl-C work); each trial and each linearisation is one
    compiled call.
    """
    if linear_solver is None:
        linear_solver = lx.Cholesky()
    if max_steps < 1:
        raise PiezojaxValueError(f"`max_steps` must be >= 1, got {max_steps}")
    levels = [None] if smoothing is None else list(smoothing)
    if not levels:
        raise PiezojaxValueError("`smoothing` must list at least one level (or be None)")
    for s in levels:
        if s is not None and not (np.isfinite(s) and s >= 0):
            raise PiezojaxValueError(f"`smoothing` levels must be finite and >= 0, got {s}")
    if starts is None:
        u = problem.u0[None]
    else:
        starts = list(starts)
        if not starts:
            raise PiezojaxValueError("`starts` must list at least one model (or be None: the problem's start)")
        u = jnp.stack([problem.u_of(m, name=f"starts[{i}]") for i, m in enumerate(starts)])
    t0 = time.perf_counter()
    frozen = problem.frozen
    per_start: list[list] = [[] for _ in range(u.shape[0])]
    for s in levels:
        if s is not None:
            frozen = set_smoothing(frozen, s)
        label = f"[smoothing {s:g}] " if s is not None else ""
        level = problem.with_frozen(frozen)
        runs = _levenberg_marquardt(u, level.core, rtol=rtol, atol=atol, ftol=ftol, max_steps=max_steps,
                                    linear_solver=linear_solver, progress=progress, label=label)
        for i, run in enumerate(runs):
            per_start[i].append((s, run))
        u = jnp.stack([run.u for run in runs])
        if any(run.code == "interrupted" for run in runs) or all(run.code in _HARD for run in runs):
            break
    seconds = time.perf_counter() - t0
    verdicts = [_start_verdict(runs, len(levels)) for runs in per_start]
    costs = np.array([runs[-1][1].history[-1] for runs in per_start])
    order = np.lexsort((np.where(np.isfinite(costs), costs, np.inf), [not v[0] for v in verdicts]))
    best = int(order[0])  # the lowest cost among the successful starts (among all if none succeeded)
    runs = per_start[best]
    success, reason, code = verdicts[best]
    result = summarise(
        level,
        u[best],
        success=success,
        reason=reason,
        code=code,
        steps=sum(r.steps for _, r in runs),
        accepted=sum(r.accepted for _, r in runs),
        history=[c for _, r in runs for c in r.history],
        history_steps=[k + sum(q.steps for _, q in runs[:j]) for j, (_, r) in enumerate(runs) for k in r.history_steps],
        seconds=seconds,
        levels=[{"smoothing": s, "steps": r.steps, "cost": r.history[-1], "reason": r.reason} for s, r in runs],
        gtol=gtol,
    )
    if starts is not None:
        result.starts = [
            {"cost": float(costs[i]), "success": v[0], "code": v[2], "reason": v[1],
             "steps": sum(r.steps for _, r in per_start[i]), "best": i == best}
            for i, v in enumerate(verdicts)
        ]
    if throw and not result.success:
        raise RuntimeError(f"fit failed: {result.reason}")
    return result


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

    ```python
    result = fitting.fit(actuator, dataset, free=["hysteresis", "dynamics"], smoothing=(0.05, 0.0))
    print(result.report())
    ```
    """
    problem = Problem(model, dataset, predictor=predictor, targets=targets, free=free, weights=weights, scales=scales,
                      jacobian_chunk=jacobian_chunk)
    return solve(problem, **solve_options)
