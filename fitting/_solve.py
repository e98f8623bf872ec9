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

from ._problem import Problem, _linearise, _over_starts
from ._results import FitResult, descent_point, summarise


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
    batched = _over_starts(_trial_one, (None, None, None, 0, 0, 0, 0, 0, 0, 0, None, None, 0), y.shape[0])
    return batched(descent, search, core, y, r, cost, g, h, step_size, search_state, rtol, atol, active)


def _column_norms(h):
    r"""$\|J_{:,j}\|$ from $H = J^\top J$ (leading axes batched); zero columns count as 1 (scipy's `x_scale="jac"`)."""
    norms = jnp.sqrt(jnp.clip(jnp.diagonal(h, axis1=-2, axis2=-1), 0.0, None))
    return jnp.where(norms > 0, norms, 1.0)


def _tr_subproblem(lam, vecs, suf, delta, alpha, m, max_iter=10, rtol=0.01):
    r"""scipy's `solve_lsq_trust_region` from the eigen-decomposition of $\hat H = \hat J^\top \hat J$ instead of the
    SVD of $\hat J$ ($s_i^2 = $ `lam` descending, $V$ = `vecs`, $s \odot U^\top r = V^\top \hat g$ = `suf`): the
    Gauss–Newton step if it is inside the radius `delta`, else the step $-(\hat H + \alpha I)^{-1}\hat g$ with
    $\|p\| = \Delta$ (Moré's Newton iteration on $\alpha$ from `alpha`, relative tolerance 1 %). **Returns:**
    `(p, alpha)`."""
    s = jnp.sqrt(lam)
    full_rank = s[-1] > jnp.finfo(lam.dtype).eps * m * s[0]
    lam_safe = jnp.where(lam > 0, lam, 1.0)
    p_gn = -vecs @ (suf / lam_safe)
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
        return keep(a_new, a), keep(lo_new, lo), keep(hi_new, hi), done | (jnp.abs(phi) < rtol * delta)

    alpha, *_ = jax.lax.fori_loop(0, max_iter, body, (alpha, lower, upper, jnp.array(False)))
    p = -vecs @ (suf / (lam + alpha))
    p = p * (delta / jnp.linalg.norm(p))
    return jnp.where(take_gn, p_gn, p), jnp.where(take_gn, 0.0, alpha)


def _tr_trial_one(core, y, r, cost, g, h, state, active, ftol, xtol):
    """One trial of scipy's `least_squares(method="trf", x_scale="jac")` for an unbounded problem, in normal-equation
    form: the trust-region step in the variables scaled by the running maximum of the Jacobian's column norms, the
    cost there, the radius update and scipy's `ftol`/`xtol` tests."""
    scale_inv, delta, alpha = state
    d = 1.0 / scale_inv
    hh = h * d[:, None] * d[None, :]
    gh = g * d
    lam, vecs = jnp.linalg.eigh(hh)
    lam, vecs = jnp.clip(lam[::-1], 0.0, None), vecs[:, ::-1]
    step_h, alpha = _tr_subproblem(lam, vecs, vecs.T @ gh, delta, alpha, r.shape[0])
    step_h = jnp.where(active, step_h, 0.0)
    step = d * step_h
    y_eval = y + step
    r_eval = core.residuals(y_eval)
    cost_eval = 0.5 * jnp.sum(r_eval**2)
    finite = jnp.isfinite(cost_eval)
    predicted = -(0.5 * step_h @ hh @ step_h + gh @ step_h)
    actual = cost - cost_eval
    ratio = jnp.where(predicted > 0, actual / jnp.where(predicted > 0, predicted, 1.0),
                      jnp.where((predicted == 0) & (actual == 0), 1.0, 0.0))
    step_h_norm = jnp.linalg.norm(step_h)
    new_delta = jnp.where(ratio < 0.25, 0.25 * step_h_norm,
                          jnp.where((ratio > 0.75) & (step_h_norm > 0.95 * delta), 2.0 * delta, delta))
    new_delta = jnp.where(finite, new_delta, 0.25 * step_h_norm)
    new_delta = jnp.where(active, new_delta, delta)
    alpha = alpha * delta / new_delta
    ftol_ok = (actual < ftol * cost) & (ratio > 0.25)
    xtol_ok = jnp.linalg.norm(step) < xtol * (xtol + jnp.linalg.norm(y))
    accept = finite & (actual > 0)
    return (y_eval, r_eval, cost_eval, accept, (scale_inv, new_delta, alpha), finite & (ftol_ok | xtol_ok),
            jnp.all(jnp.isfinite(step)))


@eqx.filter_jit
def _tr_trial(core, y, r, cost, g, h, state, active, ftol, xtol):
    """`_tr_trial_one` for every start (leading axis of everything but `core`, `ftol`, `xtol`)."""
    batched = _over_starts(_tr_trial_one, (None, 0, 0, 0, 0, 0, 0, 0, None, None), y.shape[0])
    return batched(core, y, r, cost, g, h, state, active, ftol, xtol)


@jax.jit
def _tr_init(u, h):
    scale_inv = _column_norms(h)
    delta = jnp.linalg.norm(u * scale_inv, axis=1)
    return scale_inv, jnp.where(delta > 0, delta, 1.0), jnp.zeros_like(delta)


@jax.jit
def _tr_rescale(state, h, mask):
    # scipy's running maximum of the column norms, at each new linearisation
    scale_inv, delta, alpha = state
    new = jnp.maximum(scale_inv, _column_norms(h))
    return jnp.where(mask[:, None], new, scale_inv), delta, alpha


@jax.jit
def _where(mask, new, old):
    """Per start (leading axis): `new` where `mask`, else `old`, for arrays and pytrees of arrays (one compiled
    call for the whole pytree)."""
    return jtu.tree_map(lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - 1)), a, b), new, old)


def _iterate(u0, core, *, rtol, atol, ftol, max_steps, linear_solver, progress,
                         label="", max_rejections=40, window=5, method="levenberg_marquardt") -> list[_Run]:
    r"""Levenberg–Marquardt or the trust-region method, in normal-equation form, from every start in `u0` (shape
    `(starts, p)`) at once, stepped from Python.

    `method="levenberg_marquardt"`: `optx.LevenbergMarquardt`'s algorithm — damped Newton descent
    $(H + \lambda I)\delta = -g$ with the Gauss–Newton $H = J^\top J$, $g = J^\top r$, and the classical
    trust-region update of $\lambda$ — built from its optimistix parts, with two differences that matter for long
    records: the model is linearised only at accepted points (a rejected trial costs one simulation, not a Jacobian),
    and the linearisation is $(g, H)$, accumulated over chunks of experiments (`ProblemCore.normal_equations`), never
    the $m \times p$ Jacobian. `method="trust_region"`: scipy's `least_squares(method="trf", x_scale="jac")` for
    an unbounded problem (`_tr_trial_one`), from the same linearisations. The starts run in lockstep under `vmap` (a
    finished start is frozen); each has its own damping, history and verdict."""
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
    rtol, atol = jnp.asarray(rtol, u0.dtype), jnp.asarray(atol, u0.dtype)
    if method == "trust_region":
        state = _tr_init(y, h)
        converged = "converged (scipy's ftol/xtol test: relative cost decrease below ftol or step below rtol)"
        ftol_arr = jnp.asarray(ftol, u0.dtype)

        def trial(y, r, cost, g, h, state, active):
            return _tr_trial(core, y, r, cost, g, h, state, active, ftol_arr, rtol)

        def shrink(state):  # as after a non-finite trial: a quarter of the radius
            scale_inv, delta, alpha = state
            return scale_inv, 0.25 * delta, 4.0 * alpha
    else:
        descent, search = _parts(linear_solver)
        state = (jnp.ones((n_starts,), u0.dtype),
                 jtu.tree_map(lambda x: jnp.broadcast_to(x, (n_starts,) + jnp.shape(x)), search.init(u0[0], None)))
        converged = "converged (relative change below rtol/atol)"

        def trial(y, r, cost, g, h, state, active):
            out = _trial(descent, search, core, y, r, cost, g, h, *state, rtol, atol, active)
            y_eval, r_eval, cost_eval, accept, step_size, search_state, terminate, ok = out
            return y_eval, r_eval, cost_eval, accept, (step_size, search_state), terminate, ok

        def shrink(state):  # as after a rejected trial: `ClassicalTrustRegion`'s low_constant (the state is step sizes)
            return jtu.tree_map(lambda x: search.low_constant * x, state)

    t0 = time.perf_counter()
    model_error = ""
    try:
        for k in range(1, max_steps + 1):
            if not active.any():
                break
            try:
                y_eval, r_eval, cost_eval, accept, new_state, terminate, ok = trial(y, r, cost, g, h, state,
                                                                                    jnp.asarray(active))
                accept_np, terminate_np, ok_np = np.asarray(accept), np.asarray(terminate), np.asarray(ok)
                cost_eval_np = np.asarray(cost_eval)
            except eqx.EquinoxRuntimeError as e:
                # the model refused the trial parameters (a runtime check, e.g. a stiffness that underflowed to 0):
                # a failed trial like a non-finite one, the step shrunk (every start, as they were evaluated at once)
                model_error = str(e).strip().splitlines()[0]
                y_eval, r_eval, cost_eval, new_state = y, r, cost, shrink(state)
                accept_np, terminate_np = np.zeros(n_starts, bool), np.zeros(n_starts, bool)
                ok_np, cost_eval_np = np.ones(n_starts, bool), np.asarray(cost)
            take = active & accept_np & ok_np
            relinearise = np.zeros(n_starts, bool)
            for i in np.flatnonzero(active):
                steps[i] = k
                if not ok_np[i]:
                    verdicts[i] = (False, "the linear solve of a damped step failed", "linear_solve_failed")
                    continue
                if take[i]:
                    accepted[i], since[i] = accepted[i] + 1, 0
                    hist = histories[i]
                    hist.append(float(cost_eval_np[i]))
                    history_steps[i].append(k)
                else:
                    since[i] += 1
                if terminate_np[i]:
                    verdicts[i] = (True, converged, "successful")
                elif take[i]:
                    # accepted steps that no longer lower the cost (parameters drifting along a flat valley, e.g.
                    # the threshold of a play whose weight is zero) end the fit too
                    if len(hist) > window and hist[-window - 1] - hist[-1] <= ftol * window * hist[-1]:
                        verdicts[i] = (True, f"converged (mean relative cost decrease per accepted step over the "
                                             f"last {window} below ftol = {ftol:g})", "successful")
                    else:
                        relinearise[i] = True
                elif since[i] >= max_rejections:
                    why = f"; last model error: {model_error}" if model_error else ""
                    verdicts[i] = (False, f"no decrease of the cost in {since[i]} consecutive trial steps "
                                          f"(stalled or diverging{why})", "stalled")
            y, r, cost = _where(take, (y_eval, r_eval, cost_eval), (y, r, cost))
            state = _where(active, new_state, state)
            active = np.array([v is None for v in verdicts])
            if relinearise.any():
                _, _, g_new, h_new, finite = _linearise(core, y)
                g, h = _where(relinearise, (g_new, h_new), (g, h))
                if method == "trust_region":
                    state = _tr_rescale(state, h, relinearise)
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
    return last.success and len(runs) >= n_levels, last.reason, last.code  # (kink restarts come after the levels)


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
    kink_restarts: int = 5,
    method: str = "levenberg_marquardt",
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
      its own damping and verdict). The result is the start with the lowest final cost, with its verdict (a start
      that failed hard — non-finite, interrupted — only when all did); `result.starts` lists every start's cost and
      verdict. `None`: the problem's model.
      Memory and time per step grow with the number of starts.
    - `smoothing`: continuation levels for the hysteresis `smoothing` (e.g. `(0.1, 0.02, 0.0)`: relaxed, then
      exact operators; each level starts from the previous optimum). `None`: the model's own smoothing.
    - `max_steps`: Levenberg–Marquardt steps per level; `rtol`, `atol`: optimistix's Cauchy termination tolerances
      on the parameters and the residuals; `ftol`: the fit also stops (converged) when the cost decreased by less than
      `ftol` relative per accepted step, on average over the last five (scipy's `ftol` test, averaged).
    - `linear_solver`: the lineax solver of the damped $p \times p$ system (default `lx.Cholesky()`).
    - `method`: `"levenberg_marquardt"` (default): optimistix's algorithm as above. `"trust_region"`: the
      algorithm of `scipy.optimize.least_squares(method="trf", x_scale="jac")` for an unbounded problem, from the
      same linearisations: a trust region of radius $\Delta$ in the parameters scaled by the running maximum of the
      Jacobian's column norms, the step $-(\hat H + \alpha I)^{-1}\hat g$ with $\alpha$ such that it reaches the
      radius (from the eigen-decomposition of the scaled $p \times p$ $\hat H$, Moré's iteration), the radius
      shrunk to a quarter of the step below a ratio (actual / predicted decrease) of 0.25 and doubled above 0.75,
      any decrease accepted, and scipy's tests (relative cost decrease below `ftol` with a ratio above 0.25, or step
      below `rtol` relative). `linear_solver` is not used. On the calibration benchmark it needed about half the
      Jacobians of `"levenberg_marquardt"` (`experiments/bench_calibration.py`); both are local methods.
    - `progress`: print step, cost, accepted steps and elapsed time on stderr.
    - `gtol`: a fit that stops with $\max_i|\cos(r, J_{:,i})| >$ `gtol` is probed along ± each parameter, the
      gradient and the Gauss–Newton step (see `FitResult`): a minimum at a kink of the piecewise smooth model is
      converged (`"converged_at_kink"`), a point where the cost still falls or the model is not finite nearby failed
      (`"not_stationary"`).
    - `kink_restarts`: where a start's steps stop although a probed direction lowers the cost (a joint step keeps
      crossing a kink of the exact operators), the fit moves to the lowest probed point and iterates again, at most
      this many times (0: never). Each restart costs about `4 p + 4` residual evaluations and a new iteration.
      When the last restart lowered the cost by less than `fitting._results.kink_ftol` of it (1e-5, or
      $1/(m - p)$ when larger: less than a one-standard-error change of a parameter would), the cost no
      longer decreases in practice (the exact operators' kinks are dense: each step ends at the next one) and the
      fit is converged (`"converged_at_kink"`, with both numbers in the reason).
    - `throw`: raise `RuntimeError` with the reason when the fit fails, instead of returning a failed result.

    **Returns:** a `FitResult`. A failed fit (max steps, stall, non-finite predictions, Ctrl-C) is returned with
    `success=False`, its `reason`, and the last *accepted* parameters — never NaN parameters. A trial step at which
    the model raises a runtime check (`eqx.error_if`, e.g. a parameter that underflowed to an invalid value) is a
    rejected trial, like one with non-finite predictions: the step shrinks (for every start of a multi-start batch).

    Not itself jit-able (a Python loop, so that progress and Ctrl-C work); each trial and each linearisation is one
    compiled call.
    """
    if linear_solver is None:
        linear_solver = lx.Cholesky()
    if isinstance(max_steps, bool) or not isinstance(max_steps, int | np.integer) or max_steps < 1:
        raise PiezojaxValueError(f"`max_steps` must be an integer >= 1, got {max_steps!r}")
    if isinstance(kink_restarts, bool) or not isinstance(kink_restarts, int | np.integer) or kink_restarts < 0:
        raise PiezojaxValueError(f"`kink_restarts` must be an integer >= 0, got {kink_restarts!r}")
    if method not in ("levenberg_marquardt", "trust_region"):
        raise PiezojaxValueError(f'`method` must be "levenberg_marquardt" or "trust_region", got {method!r}')
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
        runs = _iterate(u, level.core, rtol=rtol, atol=atol, ftol=ftol, max_steps=max_steps,
                                    linear_solver=linear_solver, progress=progress, label=label, method=method)
        for i, run in enumerate(runs):
            per_start[i].append((s, run))
        u = jnp.stack([run.u for run in runs])
        if any(run.code == "interrupted" for run in runs) or all(run.code in _HARD for run in runs):
            break
    # past kinks: where a start's steps stopped although the cost still falls along a probed direction by more than
    # the gtol test allows (the exact operators are piecewise smooth, and a joint step can keep crossing a kink), go
    # to the lowest point along that direction and iterate again, at most `kink_restarts` times per start; a restart
    # is kept only if it converges at a lower cost
    interrupted = any(run.code == "interrupted" for runs_i in per_start for _, run in runs_i)
    kink_gain: list[float | None] = [None] * u.shape[0]  # relative decrease by the last restart (0: none)
    for i in range(u.shape[0]):
        if interrupted or any(run.code in _HARD for _, run in per_start[i]):
            continue
        for _ in range(kink_restarts):
            last = per_start[i][-1][1]
            if not last.success:
                break
            nxt = descent_point(level, u[i], gtol)  # None where u[i] is stationary by the gtol test
            if nxt is None:
                break
            (run,) = _iterate(jnp.asarray(nxt, u.dtype)[None], level.core, rtol=rtol, atol=atol, ftol=ftol,
                              max_steps=max_steps, linear_solver=linear_solver, progress=progress,
                              label=f"{label}[past a kink] ", method=method)
            if run.code == "interrupted":
                interrupted = True
                break
            if not run.success:
                break  # inconclusive: keep the earlier point and its verdict
            if not run.history[-1] < last.history[-1]:
                kink_gain[i] = 0.0
                break
            kink_gain[i] = (last.history[-1] - run.history[-1]) / last.history[-1]
            per_start[i].append((levels[-1], run))
            u = u.at[i].set(run.u)
        if interrupted:
            break
    seconds = time.perf_counter() - t0
    verdicts = [_start_verdict(runs, len(levels)) for runs in per_start]
    costs = np.array([runs[-1][1].history[-1] for runs in per_start])
    hard = [v[2] in _HARD for v in verdicts]
    order = np.lexsort(([not v[0] for v in verdicts], np.where(np.isfinite(costs), costs, np.inf), hard))
    best = int(order[0])  # the lowest cost (a start stopped by max_steps below a converged one fits better)
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
        kink_gain=kink_gain[best],
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
