"""Moving creep lags to the time constants the residual needs (`_lag_search`)."""

import math
from collections.abc import Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import piezojax as pj

from .._config.kinds import BlockKind
from .._config.model_config import all_fitted, attribute_getter
from .._config.table import TINY
from .._problem import Problem
from .plays import RELOCATE_GAIN, RESEED_MEMORY

# creep time constants searched after a fit (`relocated_lags`): LAG_GRID candidates log-spaced over
# [5 dt, the longest record] (fewer on long records, see RESEED_MEMORY); every set of as many as the creep has lags
# is scored when there are at most LAG_COMBINATIONS sets, else lags are swapped one at a time from the fitted ones
LAG_GRID, LAG_COMBINATIONS = 32, 20000


def _lag_search(plain, get, where: str, kind: BlockKind, dataset, fit_args: Mapping):
    r"""New time constants and gains for the creep lags of the fitted model `plain` (its block at `get`, at path
    `where`, of the creep kind `kind`), or `None`. Given the rest of the model, the output is linear in the lags'
    gains (`BlockKind.lag_gains`) — Kelvin–Voigt $c_j = 1/k_j$ (in parallel, $\delta = G[h + \sum_j c_j
    L_{\tau_j}[v]]$; in series, $\delta = G[(1 + \sum_j c_j L_{\tau_j})[h]]$), a lag creep's fractions
    ($(1 - \sum_j a_j + \sum_j a_j L_{\tau_j})[h]$) — so one linearisation in the gains of the fitted lags and of
    `LAG_GRID` candidate lags
    (log-spaced over $[5\,dt_{min}, T_{max}]$, at a negligible gain) gives the exact weighted sum of squares of any
    set of them with its gains refitted by linear least squares, the other parameters held. Every set of as many
    lags as the block has is scored (by single swaps from the fitted set when there are more than
    `LAG_COMBINATIONS`), keeping those whose gains come out positive (summing below `kind.max_total_gain`); the best is
    returned as `(gains, time_constants, moved)` (`moved`: lags not at a fitted time constant) when it lowers the
    sum of squares — the fit's, or the fitted lags' with their gains refitted where that is lower, so that what
    refitting the gains alone would gain does not count as a move — by more than `RELOCATE_GAIN` of it and more than
    $25\hat\sigma^2$ (a regressor of pure noise
    explains $\hat\sigma^2$; $\hat\sigma^2$ from what no combination of the lags explains)."""
    from itertools import combinations

    block = get(plain)
    name = kind.lag_gains
    leaf = getattr(block, name)
    tau = np.asarray(block.time_constants, float)
    m = tau.size
    c_now = np.asarray(kind.gains(np.asarray(leaf, float)), float)
    if m == 0 or not (np.all(np.isfinite(c_now)) and np.all(c_now > 0) and np.all(tau > 0)):
        return None
    dt = min(float(e.dt) for e in dataset)
    longest = max(e.n * float(e.dt) for e in dataset)
    # fewer candidates on long records: the lags' outputs (8 bytes per sample each) within RESEED_MEMORY, as the
    # plays' (measured on a 1e6-sample record: 34 lags raised the fit's peak from 1.7 to 2.9 GB, 16 to 1.87)
    samples = sum(e.n for e in dataset)
    grid = np.geomspace(5 * dt, longest, int(min(LAG_GRID, max(8, RESEED_MEMORY // (8 * samples) - m))))
    grid = grid[np.min(np.abs(np.log(grid[:, None] / tau[None, :])), axis=1) > 1e-3]
    # candidates at a negligible gain, within a bounded sum (a lag creep's fractions summing to nearly 1)
    room = kind.max_total_gain - float(np.sum(c_now))
    eps = 1e-9 * max(float(np.sum(c_now)), TINY) if not np.isfinite(room) else min(
        1e-9 * max(float(np.sum(c_now)), TINY), 0.5 * room / max(grid.size, 1))
    if not eps > 0:
        return None
    c0 = np.r_[c_now, np.full(grid.size, eps)]
    taus = np.r_[tau, grid]
    trial = eqx.tree_at(lambda b: (getattr(b, name), b.time_constants), block,
                        (jnp.asarray(kind.from_gains(c0), leaf.dtype), jnp.asarray(taus, block.time_constants.dtype)))
    problem = Problem(eqx.tree_at(get, plain, trial), dataset, predictor=fit_args.get("predictor"),
                      targets=fit_args.get("targets"), weights=fit_args.get("weights", "range"),
                      free=[f"{where}.{name}"], scales=np.ones(c0.size))
    res, g, h = (np.asarray(x, float) for x in problem.normal_equations(problem.u0))
    # from the parameter's values to the gains (elementwise): dr/dc = dr/dtheta dtheta/dc
    f = np.asarray(jax.jvp(kind.from_gains, (jnp.asarray(c0),), (jnp.ones(c0.size),))[1], float)
    g, h = g * f, h * np.outer(f, f)
    if not (np.all(np.isfinite(res)) and np.all(np.isfinite(g)) and np.all(np.isfinite(h))):
        return None
    # the sum of squares with every gain 0, and its gradient there: sse(c) = base + 2 gb.c + c'Hc, exactly
    base = float(res @ res) - 2 * float(g @ c0) + float(c0 @ h @ c0)
    gb = g - h @ c0
    d = np.sqrt(np.maximum(np.diag(h), TINY))
    hn = h / np.outer(d, d)

    def sse(sets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # per set (rows of column indices): sse, gains
        hs = hn[sets[:, :, None], sets[:, None, :]] + 1e-12 * np.eye(sets.shape[1])
        gs = (gb / d)[sets]
        with np.errstate(all="ignore"):
            y = -np.linalg.solve(hs, gs[..., None])[..., 0]
        out = base + np.einsum("si,si->s", gs, y)
        gains = y / d[sets]
        ok = np.all(gains > 0, axis=1) & (np.sum(gains, axis=1) < kind.max_total_gain) & np.isfinite(out)
        return np.where(ok, out, np.inf), gains

    fitted = np.arange(m)
    sse_now = base + 2 * float(gb[fitted] @ c_now) + float(c_now @ h[np.ix_(fitted, fitted)] @ c_now)
    refitted = float(sse(fitted[None])[0][0])  # the fitted lags with their gains refitted: not a move
    reference = min(sse_now, refitted) if np.isfinite(refitted) else sse_now
    if math.comb(c0.size, m) <= LAG_COMBINATIONS:
        sets = np.array(list(combinations(range(c0.size), m)))
        scores, gains = sse(sets)
        j = int(np.argmin(scores))
        best, best_sse, best_gains = sets[j], float(scores[j]), gains[j]
    else:  # swap one lag at a time, the best swap first, while one lowers the sum of squares
        best, best_sse, best_gains = fitted, sse_now, c_now
        for _ in range(4 * m):
            trials = np.array([np.r_[np.delete(best, p), q] for p in range(m) for q in range(c0.size)
                               if q not in best])
            scores, gains = sse(trials)
            j = int(np.argmin(scores))
            if not scores[j] < best_sse:
                break
            best, best_sse, best_gains = trials[j], float(scores[j]), gains[j]
    gn = gb / d
    unexplained = max(base - float(gn @ np.linalg.lstsq(hn, gn, rcond=None)[0]), 0.0)
    sigma2 = unexplained / max(problem.num_residuals - c0.size, 1)
    moved = int(np.sum(best >= m))
    if not moved or not reference - best_sse > max(RELOCATE_GAIN * reference, 25 * sigma2):
        return None
    order = np.argsort(taus[best])
    return best_gains[order], taus[best][order], moved


def relocated_lags(config, model, dataset, free, fit_args: Mapping) -> tuple[object, int] | None:
    r"""The fitted `model` with its creep lags moved to the time constants the residual needs (`_lag_search`,
    the other parameters held; for creep kinds with `BlockKind.lag_gains`: Kelvin–Voigt and lag creep),
    reparametrised as `build` returns it, and how many lags moved; `None` when the creep kind has no such lags,
    `free` does not fit both their gains and time constants, or no set of time constants on the search grid
    lowers the cost by more than `RELOCATE_GAIN` of it and than a regressor of pure noise would. `fit_args`: the
    `predictor`, `targets` and `weights` of the fit.

    A fit can end with its lags in the wrong basin: measured on `experiments.plant_study`'s Bouc–Wen draw 5
    (true lags 0.198 s and 1.65 s), both starts ended with one lag near 1.04 s carrying most of the creep and
    the other at 0.093 s with a sixth of the true gain; the search put them at 0.23 and 1.79 s (linear cost
    prediction 38 % lower) and the fit from there reached the truth's cost (training 1.00x the noise, from
    1.57x)."""
    if "creep" not in config.block_tables():
        return None
    kind = config.kind("creep")
    if kind.lag_gains is None:
        return None
    where = config.block_path("creep")
    if not all_fitted(where, (kind.lag_gains, "time_constants"), free):
        return None
    plain = pj.unwrap(model)
    get = attribute_getter(where.split("."))
    found = _lag_search(plain, get, where, kind, dataset, fit_args)
    if found is None:
        return None
    gains, taus, moved = found
    block = get(plain)
    leaf = getattr(block, kind.lag_gains)
    new = eqx.tree_at(lambda b: (getattr(b, kind.lag_gains), b.time_constants), block,
                      (jnp.asarray(kind.from_gains(gains), leaf.dtype),
                       jnp.asarray(taus, block.time_constants.dtype)))
    return config.constrain(eqx.tree_at(get, plain, new)), moved
