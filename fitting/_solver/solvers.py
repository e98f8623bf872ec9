"""The solvers as optimistix splits them: an abstract normal-equation solver (`init` / `step` / `terminate`) and the
concrete ones, each a *descent* (the step from a linearisation) and a *search* (whether to take it, and the next
step size or radius)."""

import abc
from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float

from piezojax.internal import matmul

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
    whether the search accepts it, whether the linear algebra of the step succeeded, and what the evaluation of the
    trial point returned besides the residuals (`aux`: e.g. the linearisation there)."""

    step: Float[Array, " p"]
    y: Float[Array, " p"]
    r: Float[Array, " m"]
    cost: Float[Array, ""]
    accept: Bool[Array, ""]
    ok: Bool[Array, ""]
    aux: Any = None


class AbstractNormalSolver(eqx.Module):
    r"""A least-squares solver on normal equations, in optimistix's split (`optx.AbstractLeastSquaresSolver`,
    stepped from the outside so that each start of a batch keeps its own state):

    - `init(y, lin)`: the solver's state at the start `y` with its linearisation `lin`;
    - `step(fn, y, lin, state, active)`: a trial step from the linearisation and the residuals at the trial point
      (`fn(y)` is `(r, aux)`, the weighted residual vector and anything else the caller evaluates there, returned
      as the trial's `aux`, as optimistix's `has_aux`); a start that is not `active` stays where it is;
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
    def step(self, fn: Callable[[Array], tuple[Array, Any]], y: Array, lin: Linearisation, state: Any,
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

    def step(self, fn, y, lin, state, active):
        step_size, search_state = state
        f_info = self._f_info(lin)
        descent_state = self.descent.query(y, f_info, self.descent.init(y, f_info))
        delta, result = self.descent.step(step_size, descent_state)
        # a finished start (e.g. non-finite at its start) stays where it is: its model is never evaluated elsewhere
        delta = jnp.where(active, delta, 0.0)
        y_eval = y + delta
        r_eval, aux = fn(y_eval)
        cost_eval = 0.5 * jnp.sum(r_eval**2)
        step_size, accept, _, search_state = self.search.step(
            jnp.array(False), y, y_eval, f_info, optx.FunctionInfo.Eval(cost_eval), search_state)
        accept = accept & jnp.isfinite(cost_eval)
        trial = Trial(delta, y_eval, r_eval, cost_eval, accept, result == optx.RESULTS.successful, aux)
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

    def step(self, fn, y, lin, state, active):
        step_h, alpha, predicted, d = self.descent.step(state.radius, state.scale_inv, state.alpha, lin,
                                                        lin.r.shape[0])
        step_h = jnp.where(active, step_h, 0.0)
        step = d * step_h
        y_eval = y + step
        r_eval, aux = fn(y_eval)
        cost_eval = 0.5 * jnp.sum(r_eval**2)
        finite = jnp.isfinite(cost_eval)
        actual = lin.cost - cost_eval
        ratio = self.search.ratio(predicted, actual)
        radius = self.search.step(state.radius, ratio, jnp.linalg.norm(step_h), finite)
        radius = jnp.where(active, radius, state.radius)
        alpha = alpha * state.radius / radius
        trial = Trial(step, y_eval, r_eval, cost_eval, finite & (actual > 0), jnp.all(jnp.isfinite(step)), aux)
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


