"""Is a fit's end point a minimum? MINPACK's gradient test, and for the piecewise smooth models (the exact hysteresis
operators) one-sided probes of the cost; the point past a kink that `fitting.solve` restarts from."""

import dataclasses
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._problem import lost_columns
from ._solver import Linearisation, Verdict

KINK_FTOL = 1e-5
"""A fit whose last restart past a kink (`solve`'s `kink_restarts`) lowered the cost by less than this fraction of
it no longer decreases in practice: it is converged (`"converged_at_kink"`) whatever the probed slopes."""


def kink_ftol(m: int, p: int) -> float:
    r"""The relative cost decrease below which a restart past a kink counts as no decrease: `KINK_FTOL`, or, when
    larger, $1/(m - p)$ — moving one parameter by one standard error changes the cost
    $\tfrac12\sum r^2$ by $\hat\sigma^2/2 = \text{cost}/(m - p)$, so a smaller gain is below what the data can
    resolve."""
    return max(KINK_FTOL, 1.0 / max(m - p, 1))


def descent_point(problem, u, lin: Linearisation, gtol: float = 1e-2):
    """A point of lower cost than `u` past a kink that stopped the steps: from the lowest-cost probe of
    `_probe_descent`, the step along its direction doubled while the cost keeps falling; `None` when `u` passes the
    gtol test (or its linearisation `lin` is not finite: nothing to follow) or no probe lowers the cost."""
    r, jtr, jtj = (np.asarray(x) for x in (lin.r, lin.g, lin.h))
    if not np.all(np.isfinite(jtr)) or max_gradient_cosine(r, jtr, jtj) <= gtol:
        return None  # stationary by MINPACK's gtol test
    cost = 0.5 * float(np.sum(r**2))
    if not np.isfinite(cost):
        return None
    slope, _, best = _probe_descent(problem, u, cost, r, jtr, jtj)
    if best is None or slope >= -gtol:
        return None  # no probe lowers the cost by more than the gtol test allows
    # a line search along the best probed direction: double the step while the cost keeps falling
    e, step, c = best
    u = np.asarray(u, dtype=float)
    limit = max(1.0, float(np.max(np.abs(u))))  # at most a unit change of the largest scaled parameter
    while 2 * step <= limit:
        c2 = _probe_cost(problem, u + 2 * step * e)
        if not (np.isfinite(c2) and c2 < c):
            break
        step, c = 2 * step, c2
    return u + step * e


def _probe_cost(problem, u) -> float:
    """The cost at `u`; `inf` where the predictions are not finite or the model's runtime checks fail."""
    try:
        rr = np.asarray(problem.residuals(jnp.asarray(u, dtype=problem.u0.dtype)))
    except eqx.EquinoxRuntimeError:
        return np.inf
    c = 0.5 * float(np.sum(rr**2))
    return c if np.isfinite(c) else np.inf


def _probe_descent(problem, u, cost, r, jtr, jtj) -> tuple[float, bool, Any]:
    r"""The subgradient form of the gtol test, for a fit that stops where the cost is not differentiable.

    For directions $e$ (± each scaled parameter, the negative gradient, the Gauss–Newton step) and steps $h$ of
    1e-7 and 1e-5 of max(1, |u|): the one-sided slope $(c(u + h e) - c(u))/h$, in the units of the gtol test,
    $\|r\|\,\|J e\|$ (for a smooth cost it is the cosine between $r$ and $J e$, the quantity the gtol test bounds).
    Returns the smallest (steepest descent, negative) of them, whether a step gave non-finite residuals, and the
    probe of lowest cost if it is below `cost` (`(direction, step, cost)`; else `None`)."""
    u = np.asarray(u, dtype=float)
    jtj = np.asarray(jtj, dtype=float)
    p = u.size
    directions = [np.eye(p)[i] * sgn for i in range(p) for sgn in (1.0, -1.0)]
    g = -np.asarray(jtr, dtype=float)
    if np.any(g):
        directions.append(g / np.max(np.abs(g)))
    gn = np.linalg.lstsq(jtj, g, rcond=1e-12)[0]
    if np.all(np.isfinite(gn)) and np.any(gn):
        directions.append(gn / np.max(np.abs(gn)))
    size = max(1.0, float(np.max(np.abs(u)))) if p else 1.0
    rnorm = float(np.sqrt(np.sum(np.asarray(r, dtype=float) ** 2)))
    slope, nonfinite, best, best_cost = np.inf, False, None, cost
    for h in (1e-7, 1e-5):
        for e in directions:
            scale = rnorm * np.sqrt(max(float(e @ jtj @ e), 0.0))
            if not scale > 0:
                continue  # a direction the residuals do not depend on
            c = _probe_cost(problem, u + h * size * e)
            if np.isfinite(c):
                slope = min(slope, (c - cost) / (h * size) / scale)
                if c < best_cost:
                    best, best_cost = (e, h * size, c), c
            else:
                nonfinite = True
    return slope, nonfinite, best


def max_gradient_cosine(r, jtr, jtj) -> float:
    """MINPACK's gtol quantity: the largest |cos| between the residual and a Jacobian column (0 for a zero residual
    or no parameters). A column whose squared norm is below 1e-30 of the largest (`fitting._problem.lost_columns`)
    counts as zero (cosine 0, as MINPACK skips zero columns): there $J^\top J$'s diagonal has lost its digits
    (measured: a resonance's damping driven to 3e-199 on a record that never excites it gave a cosine of inf)."""

    r, jtr, jtj = (np.asarray(x) for x in (r, jtr, jtj))
    diag = np.clip(np.diag(jtj), 0.0, None)
    # a column is dropped only for being tiny next to the largest finite one; a non-finite one keeps its NaN or inf
    lost = lost_columns(diag)
    col_norms = np.sqrt(diag)
    rnorm = np.sqrt(np.sum(r**2))
    with np.errstate(invalid="ignore", divide="ignore"):
        cosines = np.where(lost, np.where(np.isnan(jtr), np.nan, 0.0), np.abs(jtr) / (col_norms * rnorm))
    if not (cosines.size and rnorm > 0):
        return 0.0
    return float(np.nanmax(cosines)) if np.any(~np.isnan(cosines)) else float("nan")  # nan: no Jacobian




def stationarity_verdict(problem, u, lin: Linearisation, verdict: Verdict, *, initial_cost: float, gtol: float = 1e-2,
                         kink_gain: float | None = None) -> Verdict:
    r"""The final verdict of a fit the solver ended at `u` with `verdict`, from MINPACK's first-order test: where
    the largest cosine between the residual and a Jacobian column (from `lin`, the linearisation at `u`) exceeds
    `gtol`, a converged fit is checked: rounding-level residuals are `"converged_zero_residual"`; a point where the
    cost rises along every probed direction (`_probe_descent`) is a minimum at a kink, `"converged_at_kink"`, as is
    one whose last restart past a kink gained less than `kink_ftol` (`kink_gain`); anything else failed,
    `"not_stationary"`. Other verdicts are returned unchanged."""
    r, jtr, jtj = (np.asarray(x) for x in (lin.r, lin.g, lin.h))
    m, p = problem.num_residuals, problem.num_params
    cost = 0.5 * float(np.sum(r**2))
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(jtr)) and np.all(np.isfinite(jtj))):
        return verdict  # no test without a finite linearisation (the result reports its errors as not computed)
    gradient_cosine = max_gradient_cosine(r, jtr, jtj)
    if not verdict.success or not gradient_cosine > gtol:
        return verdict
    if cost <= (1e4 * np.finfo(float).eps) ** 2 * initial_cost:
        # the residuals are rounding noise: their direction, hence the cosine, means nothing
        return Verdict("converged_zero_residual",
                       f"converged to a zero residual (cost {cost:.3e}, {cost / initial_cost:.1e} of the start's: the "
                       f"gradient test max |cos(r, J_i)| = {gradient_cosine:.2e} is rounding noise there)")
    slope, nonfinite, _ = _probe_descent(problem, u, cost, r, jtr, jtj)
    if slope >= -gtol and not nonfinite:
        # the one-sided slopes of the cost along every probed direction pass the gtol test: a minimum where the cost
        # is not differentiable (the exact operators are piecewise smooth), where the gradient (one side's
        # derivative) cannot
        return Verdict("converged_at_kink",
                       f"converged at a kink of the cost (max |cos(r, J_i)| = {gradient_cosine:.2e} > gtol = "
                       f"{gtol:g} from one side's derivative, but the cost rises along ± each parameter, the "
                       f"gradient and the Gauss–Newton direction: steepest one-sided slope {slope:+.1e} in gtol's "
                       "units: the cost is not differentiable there, as at a kink of an exact, piecewise smooth "
                       "operator, or its curvature outweighs the computed gradient over the smallest probed step)")
    if kink_gain is not None and kink_gain < kink_ftol(m, p) and not nonfinite:
        return Verdict("converged_at_kink",
                       f"converged: the cost no longer decreases (the last restart past a kink lowered it by "
                       f"{kink_gain:.1e} of it, below {kink_ftol(m, p):.1e}: less than moving one parameter by "
                       f"one standard error changes it), although it still falls along a probed "
                       f"direction at a one-sided slope of {slope:+.1e} in gtol's units (gtol = {gtol:g}): the "
                       "kinks of the exact, piecewise smooth model stop every step within a short distance")
    why = (f"the cost falls along a probed direction (slope {slope:+.1e} in gtol's units)"
           if slope < -gtol else NOT_FINITE_NEARBY)
    return Verdict("not_stationary",
                   f"stopped where the cost is not stationary (max |cos(r, J_i)| = {gradient_cosine:.2e} > "
                   f"gtol = {gtol:g}; {why}): the trust region shrank without a decrease")


NOT_FINITE_NEARBY = "the model is not finite next to this point"
"""The reason `stationarity_verdict` gives for a point the fit cannot leave because its neighbours' predictions are
not finite (`repair_point` moves such a point)."""

REPAIR_STEPS = tuple(10.0**k for k in range(-8, 1))
"""The moves `repair_point` tries for one scaled parameter, relative to max(1, |u_j|)."""

_NEIGHBOUR = 1e-7
"""The relative distance at which `repair_point` probes a scaled parameter's two neighbours."""


@dataclasses.dataclass(frozen=True)
class Repair:
    """What `repair_point` did: `u`, the moved scaled parameters (`None`: no move made the point finite next to
    it), `moved`, per moved parameter its name and physical value before and after, and `why`, what was not
    finite."""

    u: Any
    moved: tuple[tuple[str, float, float], ...]
    why: str

    def describe(self) -> str:
        """One sentence for the report."""
        if self.u is None and not self.moved and self.why.startswith("the model's predictions are not finite"):
            return f"{self.why}: left as it was"
        if self.u is None:
            return (f"{self.why}, and no move of one parameter (by up to max(1, |u|) in the solver's scaled units) "
                    "made it finite: left as it was")
        moves = ", ".join(f"{n} from {a:.6g} to {b:.6g}" for n, a, b in self.moved)
        return f"{self.why}: moved {moves}"


def repair_point(problem, u) -> Repair | None:
    r"""Move a point where the model is not finite next to it (a start whose Jacobian is not finite, a fit stopped by
    non-finite neighbours) to a near point where it is; `None` when it is finite next to it already.

    First, each scaled parameter $u_j$ one of whose neighbours $u_j \pm 10^{-7}\max(1, |u_j|)$ gives non-finite
    residuals (the point lies on the edge of the region where the model is defined: a square root at zero, a bound
    reached by an unconstrained parameter) is moved alone (`_move`: the step of `REPAIR_STEPS`, times
    $\max(1, |u_j|)$, to either side, of lowest cost among those after which the residuals there and at both its
    neighbours are finite). Then, while the linearisation (`problem.normal_equations`) is not finite although every
    neighbour is (a derivative infinite at the point: forward mode then spreads NaN to every column, so the columns
    do not say which parameter it is), each parameter is tried alone at the smallest step, to either side, until one
    gives a finite linearisation (at most 2p linearisations). A point whose own residuals are not finite is not
    repaired here (`u` `None`)."""
    u = np.asarray(u, dtype=float)
    names = problem.parameter_names()
    if not np.isfinite(_probe_cost(problem, u)):
        return Repair(None, (), "the model's predictions are not finite at the point")
    edge = [j for j in range(u.size) if not _finite_neighbours(problem, u, j)]
    new, moved = u.copy(), list(edge)
    for j in edge:
        new = _move(problem, new, j)
        if new is None:
            return Repair(None, (), _why(names, edge))
    if not _finite_linearisation(problem, new):
        found = None
        for j in range(u.size):
            for s in (1.0, -1.0):
                v = new + s * REPAIR_STEPS[0] * max(1.0, abs(float(new[j]))) * np.eye(u.size)[j]
                if np.isfinite(_probe_cost(problem, v)) and _finite_linearisation(problem, v):
                    found = (j, v)
                    break
            if found:
                break
        if found is None:
            return Repair(None, (), _why(names, edge))
        if found[0] not in moved:
            moved.append(found[0])
        new = found[1]
    if not moved:
        return None
    before = np.asarray(problem.physical(jnp.asarray(u, dtype=problem.u0.dtype)))
    after = np.asarray(problem.physical(jnp.asarray(new, dtype=problem.u0.dtype)))
    return Repair(new, tuple((names[j], float(before[j]), float(after[j])) for j in moved), _why(names, edge))


def _why(names, along) -> str:
    if not along:
        return "the model's Jacobian is not finite at the point"
    return "the model is not finite next to the point (along " + ", ".join(names[j] for j in along) + ")"


def _finite_linearisation(problem, u) -> bool:
    try:
        r, g, h = (np.asarray(x) for x in problem.normal_equations(jnp.asarray(u, dtype=problem.u0.dtype)))
    except eqx.EquinoxRuntimeError:
        return False
    return bool(np.all(np.isfinite(r)) and np.all(np.isfinite(g)) and np.all(np.isfinite(h)))


def _finite_neighbours(problem, u, j: int) -> bool:
    h = _NEIGHBOUR * max(1.0, abs(float(u[j])))
    return all(np.isfinite(_probe_cost(problem, u + s * h * np.eye(u.size)[j])) for s in (1.0, -1.0))


def _move(problem, u, j: int):
    """`u` with its `j`-th entry moved, to either side, by the step of `REPAIR_STEPS` (times max(1, |u_j|)) of lowest
    cost among those after which the model is finite at and next to it along `j`, else `None`. (The lowest cost, not
    the smallest move: next to the edge of the model's domain its derivative is nearly infinite, and the solver's
    Jacobian scaling, fixed at the start, would be made there: measured on a square root started at zero, 105 steps
    from a move of 1e-7 against 9 from 0.1.)"""
    e = np.eye(u.size)[j]
    size = max(1.0, abs(float(u[j])))
    found = []
    for step in REPAIR_STEPS:
        for s in (1.0, -1.0):
            v = u + s * step * size * e
            c = _probe_cost(problem, v)
            if np.isfinite(c) and _finite_neighbours(problem, v, j):
                found.append((c, s * step))
    return u + min(found)[1] * size * e if found else None
