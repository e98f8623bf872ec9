"""The hysteresis kinds: PI, play, Bouc–Wen, Maxwell slip, Preisach and none."""

import dataclasses
from collections.abc import Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import piezojax as pj
from piezojax.internal import columns_at_rows

from ..table import (
    DUPLICATE_THRESHOLD,
    MAX_ELEMENTS,
    MAX_LEVELS_PREISACH,
    MAX_PLAYS,
    MAX_SUBSTEPS,
    TINY,
    chord,
    f64,
    finite_number,
)
from .base import BlockKind, _NoBlock
from .options import HysteresisOptions


class NoHysteresis(_NoBlock):
    table, name, Options = "hysteresis", "none", HysteresisOptions


class _PlaySum(BlockKind):
    """A kind whose block is a sum of weighted plays (`weights`, `thresholds`): re-seeded and swapped as plays."""

    element_parameters = ("weights", "thresholds")

    def swap_form(self, block):
        return block.weights, block.thresholds, False

    def from_swap_form(self, block, weights, thresholds):
        return _with_plays(block, weights, thresholds)

    def reseed(self, o, block, max_input, place=None):
        r"""Dead plays — whose largest possible output on the data, $w_i(\max|v| - r_i)^+$ (a play from rest never
        leaves $[-(\max|v| - r), \max|v| - r]$), is below $10^{-3}$ of the operator's,
        $|w_0|\max|v| + \sum_i w_i(\max|v| - r_i)^+$: a negligible weight, a threshold at or above $\max|v|$ (the
        play never moves), or one just below it (a heavy play that moves by millivolts, measured on the independent
        plant: a weight of 20 nm/V at 99.97 V of 100) — and plays whose thresholds coincide (closer than
        `DUPLICATE_THRESHOLD` of $\max|v|$: the fit pulled them onto one kink of the data; they act as one, so the
        heaviest keeps their summed weight and the others are freed) are moved to new thresholds at 1 % of the live
        plays' mean weight (small, so the re-seeded model starts where the fit ended, and not zero, so the play's
        threshold has a gradient). `place(thresholds, weights, n)` chooses the new thresholds (the command line:
        where the residual needs them, `ModelConfig.reseeded`); without it, or for the plays it leaves, each goes
        in turn to the middle of the widest gap between the thresholds on $[0, \max|v|]$."""
        return _reseed_plays(block, max_input, place)


class PrandtlIshlinskiiKind(_PlaySum):
    """`pj.PrandtlIshlinskii`: `plays` (≤ 100), `weights`, `thresholds`, `w0`, `smoothing`. Start:
    `fitting.cold_start_actuator` in its family, else `pj.pi_cold_start` on the quasi-static output."""

    table, name = "hysteresis", "prandtl_ishlinskii"

    @dataclasses.dataclass(frozen=True, kw_only=True)
    class Options(HysteresisOptions):
        plays: int
        smoothing: float
        weights: np.ndarray | None = None
        thresholds: np.ndarray | None = None
        w0: float | None = None

    def parse(self, t, raw):
        n, (w, r) = t.sized_vectors("plays", 10, MAX_PLAYS, {"weights": dict(positive=True),
                                                          "thresholds": dict(positive=True, ascending=True)})
        return self.Options(smoothing=t.number("smoothing", 0.0, nonnegative=True), plays=n, weights=w,
                            thresholds=r, w0=t.number("w0", None, positive=True))

    def parameters(self, o):
        return ("weights", "thresholds", "w0")

    def placeholder(self, o):
        n = o.plays
        return {"weights": np.full(n, 0.1), "thresholds": np.arange(1.0, n + 1), "w0": 1.0}

    def start(self, o, data):
        recs = data.records()
        pi = pj.pi_cold_start([v for v, _, _ in recs], [y for _, y, _ in recs], o.plays)
        w = np.asarray(pi.weights)
        top = max(float(np.max(np.abs(np.r_[w, float(pi.w0)]))), TINY)
        # dead plays revived at 1e-3 of the largest weight: a zero weight is a flat spot of the Positive map
        return {"weights": np.maximum(w, 1e-3 * top), "thresholds": np.asarray(pi.thresholds),
                "w0": max(float(pi.w0), 1e-3 * top)}

    def build(self, o, v, config):
        return pj.PrandtlIshlinskii(f64(v["weights"]), f64(v["thresholds"]), w0=f64(v["w0"]),
                                    smoothing=f64(o.smoothing))

    def constraints(self, o):
        return {"weights": pj.Positive, "w0": pj.Positive, "thresholds": pj.OrderedPositive}

    def cold_start_args(self, o, config):
        return {"n_plays": o.plays}

    def from_cold_start(self, o, block):
        return {"weights": np.asarray(block.weights), "thresholds": np.asarray(block.thresholds),
                "w0": float(block.w0)}


class PlayKind(_PlaySum):
    r"""Weighted play (backlash) operators without a linear term, $y = \sum_i w_i P_{r_i}[v]$ (`pj.PrandtlIshlinskii`
    with $w_0 = 0$): `plays` (≤ 100, default 1: one backlash), `weights`, `thresholds`, `smoothing`. Start: the
    weights by non-negative least squares on the play outputs for thresholds $c\max|v|\,i/n$, $i = 1 \dots n$, the
    scale $c$ the best of 0.02 to 0.9."""

    table, name = "hysteresis", "play"

    @dataclasses.dataclass(frozen=True, kw_only=True)
    class Options(HysteresisOptions):
        plays: int
        smoothing: float
        weights: np.ndarray | None = None
        thresholds: np.ndarray | None = None

    def parse(self, t, raw):
        n, (w, r) = t.sized_vectors("plays", 1, MAX_PLAYS, {"weights": dict(positive=True),
                                                         "thresholds": dict(positive=True, ascending=True)})
        return self.Options(smoothing=t.number("smoothing", 0.0, nonnegative=True), plays=n, weights=w,
                            thresholds=r)

    def parameters(self, o):
        return ("weights", "thresholds")

    def placeholder(self, o):
        n = o.plays
        return {"weights": np.full(n, 0.1), "thresholds": np.arange(1.0, n + 1)}

    def start(self, o, data):
        import scipy.optimize

        n, recs = o.plays, data.records()
        y = data.sampled_outputs()
        sign = 1.0 if data.static_gain() >= 0 else -1.0
        best = None
        for c in np.geomspace(0.02, 0.9, 10):
            r = c * data.max_input() * np.arange(1, n + 1) / n
            play = pj.PlayOperator(jnp.asarray(r))
            a = data.sampled([np.asarray(play(jnp.asarray(v))).reshape(v.size, n) for v, _, _ in recs])
            a = np.column_stack([a, np.ones(a.shape[0]), -np.ones(a.shape[0])])  # a free offset
            w, res = scipy.optimize.nnls(a, sign * y)
            if best is None or res < best[0]:
                best = (res, w[:n], r)
        _, w, r = best
        w = np.maximum(w, 1e-3 * max(float(w.max()), TINY))
        return {"weights": w, "thresholds": r}

    def build(self, o, v, config):
        return pj.PrandtlIshlinskii(f64(v["weights"]), f64(v["thresholds"]), w0=f64(0.0),
                                    smoothing=f64(o.smoothing))

    def constraints(self, o):
        return {"weights": pj.Positive, "thresholds": pj.OrderedPositive}


def _with_plays(block, weights, thresholds):
    return eqx.tree_at(lambda b: (b.weights, b.thresholds), block,
                       (jnp.asarray(weights, block.weights.dtype), jnp.asarray(thresholds, block.thresholds.dtype)))


def _reseed_plays(block, max_input: float, place=None):
    """`block` with its dead and coinciding plays moved (see `_PlaySum.reseed`), or `None`. `place(
    thresholds, weights, n)`, when given, proposes up to `n` thresholds for the freed plays from the live ones
    (`ModelConfig.reseeded`: where the residual needs them); the rest go to the widest gaps."""
    w, r = np.asarray(block.weights, float), np.asarray(block.thresholds, float)
    reach = np.abs(w) * np.maximum(max_input - r, 0.0)
    total = float(np.sum(reach)) + abs(float(block.w0)) * max_input
    dead = reach < 1e-3 * max(total, TINY)
    # plays that share a threshold act as one (their weights add): the heaviest keeps the sum, the others are free
    w = w.copy()
    tol = DUPLICATE_THRESHOLD * max_input
    live = np.flatnonzero(~dead)
    live = live[np.argsort(r[live], kind="stable")]
    groups: list[list[int]] = []
    for i in live:  # each group spans at most `tol` from its lowest threshold
        if groups and r[i] - r[groups[-1][0]] <= tol:
            groups[-1].append(i)
        else:
            groups.append([i])
    for group in map(np.asarray, groups):
        if group.size > 1:
            keep = group[np.argmax(np.abs(w[group]))]
            w[keep] = np.sum(w[group])
            dead[group[group != keep]] = True
    if not dead.any() or dead.all() or not max_input > 0:
        return None
    live_r, live_w, n_free = r[~dead], w[~dead], int(dead.sum())
    proposed: list[float] = []
    for x in [] if place is None else place(live_r, live_w, n_free):  # only thresholds where a new play can act
        x = float(x)
        if (len(proposed) < n_free and np.isfinite(x) and 0 < x < max_input
                and all(abs(x - y) > tol for y in [*live_r, *proposed])):
            proposed.append(x)
    new_r = list(live_r) + proposed
    for _ in range(n_free - len(proposed)):
        pts = np.r_[0.0, np.sort(new_r), max_input]
        i = int(np.argmax(np.diff(pts)))
        new_r.append(0.5 * (pts[i] + pts[i + 1]))
    new_w = np.r_[live_w, np.full(n_free, 0.01 * float(np.mean(live_w)))]
    order = np.argsort(new_r)
    return eqx.tree_at(lambda b: (b.weights, b.thresholds), block,
                       (jnp.asarray(new_w[order], block.weights.dtype),
                        jnp.asarray(np.asarray(new_r)[order], block.thresholds.dtype)))


class BoucWenKind(BlockKind):
    """`pj.BoucWen`: `A`, `beta`, `gamma`, `n`, `d`, `method`, `substeps`, `smoothing`."""

    table, name = "hysteresis", "bouc_wen"

    @dataclasses.dataclass(frozen=True, kw_only=True)
    class Options(HysteresisOptions):
        smoothing: float
        A: float | None = None
        beta: float | None = None
        gamma: float | None = None
        n: float | None = None
        d: float | None = None
        method: str
        substeps: int

    def parse(self, t, raw):
        smoothing = t.number("smoothing", 0.0, nonnegative=True)
        A, beta = t.number("A", None, positive=True), t.number("beta", None, positive=True)
        gamma, n, d = t.number("gamma", None), t.number("n", None, positive=True), t.number("d", None)
        method = t.string("method", ("closed_form", "rk4"))
        substeps = t.integer("substeps", 8, minimum=1, maximum=MAX_SUBSTEPS)
        if method == "closed_form" and n not in (None, 1.0):
            raise t.error(f"method 'closed_form' needs n = 1, got n = {n}", "method")
        if method == "closed_form" and smoothing != 0:
            raise t.error("method 'closed_form' needs smoothing = 0 (use method = 'rk4')", "method")
        if method is None:
            levels = raw.get("fit", {}).get("smoothing") if isinstance(raw.get("fit"), Mapping) else None
            smooth = smoothing != 0 or (isinstance(levels, list) and any(
                finite_number(s) and s != 0 for s in levels))
            method = "closed_form" if (n in (None, 1.0) and not smooth) else "rk4"
        return self.Options(smoothing=smoothing, A=A, beta=beta, gamma=gamma, n=n, d=d, method=method,
                            substeps=substeps)

    def parameters(self, o):
        return ("A", "beta", "gamma", "n", "d")

    def required(self, o):
        return ("A", "beta", "gamma", "d")

    def placeholder(self, o):
        return {"A": 0.1, "beta": 0.01, "gamma": 0.01, "n": 1.0, "d": 1.0}

    def start(self, o, data):
        r"""For $n = 1$ and $z = A\hat z$, $d\hat z = dv - \beta|dv|\hat z - \gamma\,dv|\hat z|$ does not depend
        on $A$, and $y = d\,v - A\hat z$ is linear in $(d, A)$: a grid of $(\beta, \gamma/\beta)$ (saturation
        after 0.1 to 30 times the voltage span; $\gamma/\beta$ from -0.8 to 0.9, inside the bounded class), each
        with $(d, A)$ and an offset by linear least squares; the best with $A > 0$."""
        recs = data.records()
        span = max(float(np.ptp(v)) for v, _, _ in recs) or data.max_input()
        betas, ratios = np.geomspace(0.1, 30.0, 12) / span, np.linspace(-0.8, 0.9, 8)
        bb, rr = (x.ravel() for x in np.meshgrid(betas, ratios))
        zs = [_bouc_wen_grid(jnp.asarray(bb), jnp.asarray(bb * rr), v, k) for (v, _, _), k in zip(recs, data.rows())]
        v_all, y_all = data.sampled_inputs(), data.sampled_outputs()
        best, best_err = None, np.inf
        for i in range(bb.size):
            z = np.concatenate([zz[i] for zz in zs])
            a = np.column_stack([v_all, -z, np.ones_like(v_all)])
            coef, *_ = np.linalg.lstsq(a, y_all, rcond=None)
            err = float(np.sum((y_all - a @ coef) ** 2))
            if coef[1] > 0 and np.isfinite(err) and err < best_err:
                best, best_err = (float(coef[1]), bb[i], bb[i] * rr[i], float(coef[0])), err
        if best is None:  # no loop in the data: a nearly linear element
            d = chord(v_all, y_all)
            best = (max(1e-3 * abs(d), TINY), 1.0 / span, 0.0, d)
        A, beta, gamma, d = best
        return {"A": A, "beta": beta, "gamma": gamma, "n": 1.0, "d": d}

    def optional_start(self, o, data):
        return self.placeholder(o)  # n = 1, the usual Bouc–Wen choice

    def build(self, o, v, config):
        return pj.BoucWen(f64(v["A"]), f64(v["beta"]), f64(v["gamma"]), f64(v["n"]), f64(v["d"]),
                          smoothing=f64(o.smoothing), method=o.method, substeps=o.substeps)

    def constraints(self, o):
        return {"A": pj.Positive, "beta": pj.Positive, "n": pj.Positive}

    def default_free(self, o, config):
        # the exponent has no effect in the closed form (n = 1)
        return ("A", "beta", "gamma", "d") + (("n",) if o.method == "rk4" else ())

    def cost(self, o):
        return max(1, o.substeps // 4)


def _bouc_wen_grid(beta, gamma, v, rows, block: int = 2**16) -> np.ndarray:
    r"""$\hat z$ of a unit-$A$ Bouc–Wen operator ($n = 1$, closed form) for each `(beta, gamma)` pair, at the
    samples `rows` of `v` (a slice or sorted indices): shape `(pairs, rows)`. All pairs are stepped together over
    `block` samples at a time, so that only one block of every pair's output is held: the whole record at once
    was the start's memory peak (96 pairs on a 1e6-sample record: 768 MB)."""
    v = np.asarray(v, float)
    n = v.size
    block = max(1, min(block, n))
    # the last block padded to the block's length (one compiled shape; its padded samples are never kept)
    vp = np.concatenate([v, np.full(-n % block, v[-1])])
    keep = np.arange(n)[rows]
    state = _bouc_wen_init(beta, gamma)
    out = []
    for i in range(0, n, block):
        state, z = _bouc_wen_block(beta, gamma, state, jnp.asarray(vp[i : i + block]))
        sel = keep[(keep >= i) & (keep < i + block)] - i
        out.append(np.asarray(z)[:, sel])
    return np.concatenate(out, axis=1)


def _unit_bouc_wen(beta, gamma):
    return pj.BoucWen(1.0, beta, gamma, output="z")


@jax.jit
def _bouc_wen_init(beta, gamma):
    return jax.vmap(lambda b, g: _unit_bouc_wen(b, g).init())(beta, gamma)


@jax.jit
def _bouc_wen_block(beta, gamma, state, v):
    return jax.vmap(lambda b, g, s: _unit_bouc_wen(b, g).scan(v, s))(beta, gamma, state)


class MaxwellSlipKind(BlockKind):
    """`pj.MaxwellSlip`: `elements` (≤ 100), `stiffness`, `breakaway`, `smoothing`. Start: non-negative least
    squares of the stiffnesses on a uniform grid of slip thresholds up to 1.2 max|v|."""

    table, name = "hysteresis", "maxwell_slip"
    element_parameters = ("stiffness", "breakaway")

    @dataclasses.dataclass(frozen=True, kw_only=True)
    class Options(HysteresisOptions):
        elements: int
        smoothing: float
        stiffness: np.ndarray | None = None
        breakaway: np.ndarray | None = None

    def parse(self, t, raw):
        n, (k, f) = t.sized_vectors("elements", 8, MAX_ELEMENTS, {"stiffness": dict(positive=True),
                                                               "breakaway": dict(positive=True)})
        return self.Options(smoothing=t.number("smoothing", 0.0, nonnegative=True), elements=n, stiffness=k,
                            breakaway=f)

    def parameters(self, o):
        return ("stiffness", "breakaway")

    def placeholder(self, o):
        n = o.elements
        return {"stiffness": np.ones(n), "breakaway": np.arange(1.0, n + 1)}

    def start(self, o, data):
        import scipy.optimize

        n, recs = o.elements, data.records()
        # thresholds up to 1.2 max|v|: the widest elements stay elastic (the linear part of the response)
        r = 1.2 * data.max_input() * np.arange(1, n + 1) / n
        play = pj.PlayOperator(jnp.asarray(r))
        a = data.sampled([v[:, None] - np.asarray(play(jnp.asarray(v))) for v, _, _ in recs])
        y = data.sampled_outputs()
        sign = 1.0 if data.static_gain() >= 0 else -1.0
        k, _ = scipy.optimize.nnls(a, sign * y)
        k = np.maximum(k, 1e-3 * max(float(k.max()), TINY))
        return {"stiffness": k, "breakaway": k * r}

    def build(self, o, v, config):
        return pj.MaxwellSlip(f64(v["stiffness"]), f64(v["breakaway"]), smoothing=f64(o.smoothing))

    def constraints(self, o):
        return {"stiffness": pj.Positive, "breakaway": pj.Positive}

    def swap_form(self, block):
        """The elements as stops: stiffness $k_i$ and slip threshold $r_i = f_i/k_i$ (`MaxwellSlip.thresholds`)."""
        return block.stiffness, block.thresholds, True

    def from_swap_form(self, block, weights, thresholds):
        k = jnp.asarray(weights, block.stiffness.dtype)
        return eqx.tree_at(lambda b: (b.stiffness, b.breakaway), block,
                           (k, k * jnp.asarray(thresholds, block.breakaway.dtype)))


class PreisachKind(BlockKind):
    r"""`pj.Preisach.uniform`: `levels` (≤ 30) of a uniform triangular relay grid on `range = [v_min, v_max]`
    (default ±1.05 max|v| of the data), relay weights `mu` (fitted), `smoothing` (relay switching width in volts;
    0 = exact, whose weights still enter linearly). Start: the weights by ridge-regularised linear least squares
    on the relay outputs (the output is linear in them). The switching values stay fixed at the grid."""

    table, name = "hysteresis", "preisach"

    @dataclasses.dataclass(frozen=True, kw_only=True)
    class Options(HysteresisOptions):
        levels: int
        range: tuple[float, float] | None = None
        mu: np.ndarray | None = None
        smoothing: float

    def parse(self, t, raw):
        n = t.integer("levels", 8, minimum=1, maximum=MAX_LEVELS_PREISACH)
        rng = t.vector("range", 2, ascending=True)
        mu = t.vector("mu", n * (n + 1) // 2)
        return self.Options(levels=n, range=None if rng is None else (float(rng[0]), float(rng[1])), mu=mu,
                            smoothing=t.number("smoothing", 0.0, nonnegative=True))

    def parameters(self, o):
        return ("mu", "range")

    def required(self, o):
        return ("mu", "range")

    def placeholder(self, o):
        n = o.levels
        return {"mu": np.zeros(n * (n + 1) // 2), "range": (-1.0, 1.0)}

    def data_derived(self, o, config):
        return ("range",)

    def derived_value(self, o, key, block):
        # `Preisach.uniform` puts the relays at the centres of n x n cells of side h on [v_min, v_max]: the largest
        # alpha is v_max - h/2, the smallest beta v_min + h/2 (one level: any range with that centre)
        n = o.levels
        top, bottom = float(np.max(np.asarray(block.alpha))), float(np.min(np.asarray(block.beta)))
        h = (top - bottom) / (n - 1) if n > 1 else 1.0
        return [bottom - h / 2, top + h / 2]

    def start(self, o, data):
        vmax = 1.05 * data.max_input()
        rng = o.range if o.range is not None else (-vmax, vmax)
        ones = pj.Preisach.uniform(rng[0], rng[1], o.levels, smoothing=o.smoothing)
        eye = jnp.eye(ones.mu.shape[0])
        # the relays' outputs a few at a time (all 55 relays of 10 levels on a 1e6-sample record: a 1.25 GB start)
        cols = np.concatenate([columns_at_rows(lambda j, e, vj=jnp.asarray(v): _relay_outputs(ones, eye[j:e], vj).T,
                                               eye.shape[0], v.size, k)
                               for (v, _, _), k in zip(data.records(), data.rows())])
        y = data.sampled_outputs()
        lam = 1e-8 * float(np.sum(cols**2)) / max(cols.shape[1], 1)
        mu = np.linalg.solve(cols.T @ cols + lam * np.eye(cols.shape[1]), cols.T @ y)
        return {"mu": mu, "range": rng}

    def build(self, o, v, config):
        rng = v["range"]
        return pj.Preisach.uniform(float(rng[0]), float(rng[1]), o.levels, mu=f64(v["mu"]),
                                   smoothing=f64(o.smoothing))

    def constraints(self, o):
        return {}

    def default_free(self, o, config):
        return ("mu",)


@eqx.filter_jit
def _relay_outputs(ones, masks, v):
    """The output of each single relay of the Preisach operator `ones` (one row of `masks` as its `mu`) over `v`."""
    return jax.vmap(lambda m: eqx.tree_at(lambda p: p.mu, ones, m)(v))(masks)
