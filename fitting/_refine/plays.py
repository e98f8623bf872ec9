"""Re-seeding hysteresis plays: the plays' weights linearised together with candidates (`_PlayWeights`),
placed anew, swapped, or put where the residual needs them."""

from collections.abc import Mapping

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import piezojax as pj

from .._config.kinds import BlockKind
from .._config.model_config import all_fitted, attribute_getter
from .._config.table import DUPLICATE_THRESHOLD, TINY
from .._problem import Problem

RESEED_GRID, RESEED_MEMORY = 64, 2**27
# a move of plays or lags must lower the cost by more than this fraction of it
RELOCATE_GAIN = 1e-3


class _PlayWeights:
    r"""The fitted model's live plays (`thresholds`, `weights`) and candidate plays of weight 0 evenly on
    $(0, \max|v|)$ (at most `RESEED_GRID`, fewer on long records, see `RESEED_MEMORY`; less those within
    `DUPLICATE_THRESHOLD` of a live one), linearised together in their weights: $J^\top J$ and $J^\top r$ of the
    fit's weighted residual, formed as a fit's step forms them, with unit columns (so that no choice depends on the
    weights' scales). `decrease(t)` is what refitting the weights of the plays `t` (positions in `r`, the sorted
    thresholds) by linear least squares, the others held, takes off the sum of squares in the Gauss–Newton model
    (exact where the blocks after the hysteresis are linear), with the weights' changes; `live` and `candidates`
    are positions in `r`. `empty` when no candidate is left or the linearisation is not finite. With `stops`, the
    block is a sum of stops $\sum_i k_i S_{r_i}[v] = \sum_i k_i (v - P_{r_i}[v])$ (Maxwell slip; `weights` the
    $k_i$): it is linearised as the same operator in PI form (`as_prandtl_ishlinskii`: $w_0 = \sum k_i$, weights
    $-k_i$), and each stop's column is $w_0$'s less its play's."""

    def __init__(self, plain, get, where: str, dataset, fit_args: Mapping, thresholds, weights, vmax: float,
                 stops: bool = False):
        tol = DUPLICATE_THRESHOLD * vmax
        samples = sum(e.n for e in dataset)
        size = int(min(RESEED_GRID, max(8, RESEED_MEMORY // (8 * samples) - len(thresholds))))
        self.spacing = vmax / size
        grid = (np.arange(size) + 0.5) / size * vmax
        grid = grid[np.min(np.abs(grid[:, None] - np.asarray(thresholds)[None, :]), axis=1) > tol]
        self.empty = grid.size == 0
        if self.empty:
            return
        r = np.r_[np.asarray(thresholds, float), grid]
        w = np.r_[np.asarray(weights, float), np.zeros(grid.size)]
        order = np.argsort(r)
        self.r, self.w = r[order], w[order]
        block = get(plain)
        if stops:
            block = block.as_prandtl_ishlinskii(0.0)
        sign = -1.0 if stops else 1.0
        trial = eqx.tree_at(lambda b: (b.weights, b.thresholds), block,
                            (jnp.asarray(sign * self.w, block.weights.dtype),
                             jnp.asarray(self.r, block.thresholds.dtype)))
        free = [f"{where}.weights"] + ([f"{where}.w0"] if stops else [])
        problem = Problem(eqx.tree_at(get, plain, trial), dataset, predictor=fit_args.get("predictor"),
                          targets=fit_args.get("targets"), weights=fit_args.get("weights", "range"),
                          free=free, scales="value")
        res, g, h = (np.asarray(x, float) for x in problem.normal_equations(problem.u0))
        if not (np.all(np.isfinite(g)) and np.all(np.isfinite(h))):
            self.empty = True
            return
        scales = np.asarray(problem.scales, float)
        g, h = g / scales, h / np.outer(scales, scales)  # in the weights themselves
        if stops:  # each stop's column: w0's less its play's
            names = problem.parameter_names()
            i0 = names.index(f"{where}.w0")
            plays_at = [j for j in range(len(names)) if j != i0]
            t = np.zeros((len(plays_at), len(names)))
            t[:, i0], t[np.arange(len(plays_at)), plays_at] = 1.0, -1.0
            g, h = t @ g, t @ h @ t.T
        # unit columns: the choice does not depend on the weights' scales; a weight changes by step / d
        self.d = np.sqrt(np.maximum(np.diag(h), TINY))
        self.g, self.h = g / self.d, h / np.outer(self.d, self.d)
        self.sse = float(np.sum(np.square(res)))
        position = np.empty_like(order)
        position[order] = np.arange(order.size)
        self.live = list(position[: len(thresholds)])
        self.candidates = list(position[len(thresholds):])
        # a play must explain more than a regressor of pure noise would: 25 sigma^2 (5 sigma), sigma^2 estimated
        # from what no combination of the live and candidate plays explains
        unexplained = max(self.sse - self.decrease(list(range(order.size)))[0], 0.0)
        self.floor = 25.0 * unexplained / max(problem.num_residuals - order.size, 1)

    def nonnegative(self) -> np.ndarray:
        r"""The weights of every play of `r` (live and candidate) that minimise the sum of squares of the
        Gauss–Newton model subject to weights $\ge 0$ (non-negative least squares: most come out 0). In the unit
        columns' coordinates $y = d\,w$ the model is
        $\mathrm{sse} + 2g^\top(y - y_0) + (y - y_0)^\top H (y - y_0) = \|A y - b\|^2 + \mathrm{const}$ with
        $H = A^\top A$, $A = \Lambda^{1/2}V^\top$ from $H = V\Lambda V^\top$ (eigenvalues below $10^{-12}$ of the
        largest set to that: candidate columns can be nearly dependent) and $b = A y_0 - \Lambda^{-1/2}V^\top g$."""
        import scipy.optimize

        lam, vec = np.linalg.eigh(self.h)
        lam = np.maximum(lam, 1e-12 * max(float(lam[-1]), TINY))
        a = np.sqrt(lam)[:, None] * vec.T
        c = (vec.T @ self.g) / np.sqrt(lam)
        return scipy.optimize.nnls(a, a @ (self.w * self.d) - c, maxiter=50 * self.h.shape[0])[0] / self.d

    def decrease(self, t, without=None):
        """`without`: a play (not in `t`) whose weight is set to 0, the plays `t` refitted with it removed."""
        t = list(t)

        def refit(g):  # the steps of the plays `t` minimising the Gauss-Newton model with gradient `g`
            return -np.linalg.solve(self.h[np.ix_(t, t)] + 1e-10 * np.eye(len(t)), g) if t else np.zeros(0)

        if without is None:
            step = refit(self.g[t])
            return -float(self.g[t] @ step), step
        # the sum of squares |r + J delta|^2 = sse + 2 g.delta + delta.H.delta with delta_i = -a (play i's weight,
        # in the unit columns' coordinates, to 0), minimised over delta_t
        i = without
        assert i not in t
        a = self.w[i] * self.d[i]
        g = self.g[t] - a * self.h[t, i]
        step = refit(g)
        return 2 * a * float(self.g[i]) - a * a * float(self.h[i, i]) - float(g @ step), step


def _residual_thresholds(plain, get, where: str, dataset, fit_args: Mapping, thresholds, weights, n: int,
                         vmax: float) -> list[float]:
    r"""Up to `n` thresholds for freed plays, chosen where the fit's residual needs them: the live plays
    (`thresholds`, `weights`) and the candidate plays of `_PlayWeights` are linearised together in their weights,
    and candidates are chosen greedily, each the one whose weight, fitted jointly with the live and chosen ones by
    linear least squares, lowers the cost most while the new plays' weights come out positive (orthogonal matching
    pursuit on the normal equations). Fewer than `n` when fewer candidates would each lower the sum of squares by
    more than $25\hat\sigma^2$ (what a regressor of pure noise would explain, at 5 sigma; $\hat\sigma^2$ from the
    part of the residual that no combination of the live and candidate plays explains)."""
    lin = _PlayWeights(plain, get, where, dataset, fit_args, thresholds, weights, vmax)
    if lin.empty:
        return []
    live = lin.live
    chosen: list[int] = []
    for _ in range(n):
        base = lin.decrease(live + chosen)[0]  # `live` is never empty (`_reseed_plays`)
        best, best_gain = None, lin.floor
        for j in lin.candidates:
            if j in chosen:
                continue
            total, step = lin.decrease(live + chosen + [j])
            if np.all(step[len(live):] > 0) and total - base > best_gain:  # the new plays' weights all grow
                best, best_gain = j, total - base
        if best is None:
            break
        chosen.append(best)
    return [float(lin.r[j]) for j in chosen]


# a live play whose removal costs least is swapped: the SWAP_CANDIDATES cheapest to remove are tried
SWAP_CANDIDATES = 8


def _play_swap(plain, get, where: str, dataset, fit_args: Mapping, vmax: float, kind: BlockKind,
               lin: "_PlayWeights | None" = None):
    r"""The fitted model's plays with one moved where the residual needs it, or `None`: every live play none of
    whose neighbours is dead (`_reseed_plays` found none) can still sit in a worse basin than another threshold
    (measured on a numpy plant of 5 plays at 10-95 V fitted with 5 plays: true 45 and 70 V ended at 44 and 51 V,
    1.41x the noise in training and up to 1.96x held out, converged; with 8 plays the fit reached 1.0x). Given the
    thresholds, the output is linear in the weights (`_PlayWeights`): for each of the `SWAP_CANDIDATES` live plays
    whose removal costs least and each candidate threshold, the weights of the set with that play swapped for the
    candidate are refitted by linear least squares; the best set, with positive weights, is taken when it lowers
    the sum of squares below the live plays' own refit by more than `RELOCATE_GAIN` of it and than a regressor of
    pure noise would ($25\hat\sigma^2$). The swapped plays start at those refitted weights. The kind gives its
    elements as weighted plays or stops (`BlockKind.swap_form`; `None`: it swaps none) and builds the block back.
    `lin`: that linearisation when already formed (`_play_replace` forms the same one for plays)."""
    block = get(plain)
    form = kind.swap_form(block)
    if form is None:
        return None
    if lin is None:
        lin = _PlayWeights(plain, get, where, dataset, fit_args, np.asarray(form[1], float),
                           np.asarray(form[0], float), vmax, form[2])
    if lin.empty:
        return None
    live = lin.live
    base = lin.decrease(live)[0]
    loss = [base - lin.decrease([j for j in live if j != i], without=i)[0] for i in live]
    best, best_gain = None, max(RELOCATE_GAIN * (lin.sse - base), lin.floor)
    for i in [live[k] for k in np.argsort(loss)[:SWAP_CANDIDATES]]:
        kept = [j for j in live if j != i]
        for c in lin.candidates:
            total, step = lin.decrease(kept + [c], without=i)
            weights = lin.w[kept + [c]] + step / lin.d[kept + [c]]
            if np.all(weights > 0) and total - base > best_gain:
                best, best_gain = (kept + [c], weights), total - base
    if best is None:
        return None
    chosen, weights = best
    order = np.argsort(lin.r[chosen])
    return kind.from_swap_form(block, weights[order], lin.r[chosen][order])


def _play_clusters(r: np.ndarray, w: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray] | None:
    """`n` plays from the non-negative weights `w` of plays at the sorted thresholds `r`: from the plays of weight
    above 1 % of the largest (the `n` largest if fewer are), the two neighbours whose merging moves the least
    weighted spread (Ward's criterion, $\frac{w_a w_b}{w_a + w_b}(r_a - r_b)^2$) are merged into one play at their
    weighted mean threshold with their summed weight (a play's output is continuous in its threshold), until `n`
    are left. `None` when fewer than `n` plays have weight."""
    top = float(np.max(w, initial=0.0))
    on = np.flatnonzero(w > 1e-12 * max(top, 1e-300))
    if on.size < n:
        return None
    strong = on[w[on] >= 0.01 * top]
    on = strong if strong.size >= n else np.sort(on[np.argsort(w[on])[::-1][:n]])
    centres, weights = list(r[on].astype(float)), list(w[on].astype(float))
    while len(centres) > n:
        a, b, c = np.asarray(weights[:-1]), np.asarray(weights[1:]), np.diff(centres)
        k = int(np.argmin(a * b / (a + b) * c**2))
        m = weights[k] + weights[k + 1]
        centres[k:k + 2] = [(weights[k] * centres[k] + weights[k + 1] * centres[k + 1]) / m]
        weights[k:k + 2] = [m]
    return np.asarray(centres), np.asarray(weights)


def _play_replace(plain, get, where: str, dataset, fit_args: Mapping, vmax: float, kind: BlockKind):
    r"""The fitted model's plays all placed anew where the residual needs them, or `None`. A fit can end with its
    plays in another basin than the data's best, every play a little off, so that no single play gains by moving
    (`_play_swap` finds nothing): measured on `experiments.plant_study`'s draws with six plays between 2 and 48 V,
    fits ended with every threshold 3-4 V above the truth's (training 1.01x the noise, 342 sigma^2 above the
    truth's sum of squares), or with two plays merged and the others shifted (735 sigma^2 above). Given the other
    parameters, the output is linear in the weights (`_PlayWeights`), and non-negative least squares over the live
    and candidate plays (`_PlayWeights.nonnegative`) puts weight in groups around the plant's thresholds, which are
    merged into as many plays as the block has (`_play_clusters`). The set is taken when its weights,
    refitted by linear least squares at the new thresholds, come out positive and lower the sum of squares below
    the live plays' own refit by more than a regressor of pure noise would ($25\hat\sigma^2$: the set has as many
    parameters as the fitted one, so any significant decrease is worth the fit from it); the plays start at those
    weights. Plays (not stops: Maxwell slip keeps `_play_swap`). Returns `(block or None, the linearisation at the
    fitted plays or None)`, the second for `_play_swap`, which needs the same."""
    block = get(plain)
    form = kind.swap_form(block)
    if form is None or form[2]:
        return None, None
    w, r = np.asarray(form[0], float), np.asarray(form[1], float)
    lin = _PlayWeights(plain, get, where, dataset, fit_args, r, w, vmax)
    if lin.empty:
        return None, lin
    base = lin.sse - lin.decrease(lin.live)[0]
    found = _play_clusters(lin.r, lin.nonnegative(), r.size)
    if found is None:
        return None, lin
    r_new, w_new = found
    if np.all(np.abs(r_new - r) <= lin.spacing):  # every play where it was (to the candidates' resolution)
        return None, lin
    placed = kind.from_swap_form(block, w_new, r_new)
    new_form = kind.swap_form(placed)
    at = _PlayWeights(eqx.tree_at(get, plain, placed), get, where, dataset, fit_args, np.asarray(new_form[1], float),
                      np.asarray(new_form[0], float), vmax)
    if at.empty:
        return None, lin
    total, step = at.decrease(at.live)
    weights = at.w[at.live] + step / at.d[at.live]
    if not np.all(weights > 0) or base - (at.sse - total) <= lin.floor:
        return None, lin
    return kind.from_swap_form(block, weights, at.r[at.live]), lin




def reseeded(config, model, dataset, free, fit_args: Mapping | None = None) -> tuple[object, int] | None:
    """The fitted `model` with the hysteresis kind's dead elements re-seeded (`BlockKind.reseed`), reparametrised
    as `build` returns it, and how many moved; `None` when none is dead, the kind does not re-seed, or `free`
    does not fit both the weights and the thresholds of the hysteresis. With `fit_args` (the `predictor`,
    `targets` and `weights` of the fit) freed plays go where the residual needs them (`_residual_thresholds`),
    else to the widest gaps between the live thresholds; and when none is dead, one live element of a kind that
    swaps elements (`BlockKind.swap_form`: plays, Maxwell-slip elements) moves where the residual needs it if
    that lowers the cost (`_play_swap`). Before all of these, with `fit_args`, plays (not stops) may all be
    placed anew where the residual needs them (`_play_replace`); then `None` also means none moved."""
    kind = config.hysteresis_kind
    if "hysteresis" not in config.block_tables() or kind.empty or kind.element_parameters is None:
        return None
    where = config.block_path("hysteresis")
    if not all_fitted(where, kind.element_parameters, free):
        return None
    plain = pj.unwrap(model)
    get = attribute_getter(where.split("."))
    block = get(plain)
    vmax = max(float(np.max(np.abs(np.asarray(e.v_in)))) for e in dataset)
    place = None
    if fit_args is not None:
        def place(thresholds, weights, n):
            return _residual_thresholds(plain, get, where, dataset, fit_args, thresholds, weights, n, vmax)
    new, lin = (None, None) if fit_args is None else _play_replace(plain, get, where, dataset, fit_args, vmax,
                                                                   kind)
    if new is None:
        new = kind.reseed(config.hysteresis_options, block, vmax, place)
    if new is None and fit_args is not None:
        new = _play_swap(plain, get, where, dataset, fit_args, vmax, kind, lin)
    if new is None:
        return None
    before, after = kind.swap_form(block), kind.swap_form(new)
    old = np.asarray(before[1] if before else block.thresholds, float)
    now = np.asarray(after[1] if after else new.thresholds, float)
    moved = int(np.sum(np.min(np.abs(now[:, None] - old[None, :]), axis=1) > 1e-9 * vmax))
    return config.constrain(eqx.tree_at(get, plain, new)), moved
