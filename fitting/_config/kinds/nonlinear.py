"""Whole-model kinds of the `[model]` table: nonlinear models that are not built from the actuator's blocks.

- `bouc_wen_oscillator`: `pj.BoucWenOscillator`, the hysteretic benchmark's force-driven oscillator (`v_in` is the
  force, `displacement` the output; rename the benchmark's `u`, `y` with `[data] columns`).
- `electromechanical`: `pj.ElectromechanicalActuator`, paper 003's lumped electromechanical actuator with Maxwell-slip
  voltage hysteresis (`displacement` and `charge` from `v_in`).

Each declares its keys, the parameters a simulation needs, data-driven starts for the others, constraints and the
default free set, as every `ModelKind` (`fitting/_config/kinds/models.py`).
"""

import functools
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy

import piezojax as pj
from piezojax import PiezojaxValueError
from piezojax.internal import MAX_ROWS, nnls_gram, row_subset

from ..._initialise import dynamics_candidates, filter_pairs
from ..._predict import ExperimentArrays, Predictor, as_arrays, run_predictor
from ..table import MAX_ELEMENTS, MAX_SUBSTEPS, TINY, StartWarning, chord, f64
from .models import ModelKind

MAX_COUPLING_DEGREE = 4


def _resonance(dataset, output: str) -> tuple[float, float, float]:
    r"""`(omega, zeta, gain)` of the second-order response from `v_in` to `output` (`_resonance_of`). Raises
    `PiezojaxValueError` when no experiment has the output."""
    recs = [(np.asarray(e.v_in, float), np.asarray(e[output], float), e.dt) for e in dataset if e.has(output)]
    if not recs:
        raise PiezojaxValueError(f"data-driven initial values need data files with a {output!r} column (or give "
                                 "every parameter value explicitly in the configuration)")
    return _resonance_of(recs)


def _resonance_of(recs) -> tuple[float, float, float]:
    r"""`(omega, zeta, gain)` of a second-order response from the `(input, output, dt)` records (those of the
    smallest step): each candidate of `fitting.cold_start_actuator`'s resonance estimate (ARX on the raw and
    high-passed records, the spectral peak), with the static gain by least squares through the DC-normalised
    filter; the candidate with the smallest residual. Without a candidate, a well-damped mode at a fifth of the
    Nyquist frequency."""
    dt = min(r[2] for r in recs)
    recs = [r for r in recs if r[2] == dt]
    best = None
    for _, omega, zeta in dynamics_candidates(recs, 2, MAX_ROWS):
        if omega.size != 1 or not (np.isfinite(omega[0]) and np.isfinite(zeta[0])):
            continue
        u = np.concatenate([filter_pairs(v, dt, omega, zeta) for v, _, _ in recs])
        y = np.concatenate([np.asarray(y) - np.mean(y) for _, y, _ in recs])
        u = u - np.mean(u)
        g = chord(u, y)
        err = float(np.sum((y - g * u) ** 2))
        if np.isfinite(err) and g != 0 and (best is None or err < best[3]):
            best = (float(omega[0]), float(zeta[0]), g, err)
    if best is None:  # no resonance found: a well-damped mode at a fifth of the Nyquist frequency
        v = np.concatenate([r[0] for r in recs])
        y = np.concatenate([r[1] for r in recs])
        return 0.2 * np.pi / dt, 0.7, chord(v, y)
    return best[:3]


# ------------------------------------------------------------------------------------------ Bouc–Wen oscillator


_BW_NAMES = ("m", "c", "k", "alpha", "beta", "gamma", "delta", "nu")


@functools.cache
def bouc_wen_oscillator_predictor(hold: str = "linear", substeps: int = 4) -> Predictor:
    """Predictor for a `pj.BoucWenOscillator`: `displacement` from the force `v_in`, from rest, with fixed steps
    (`substeps` per sample: RK4 with the band-limited input for `hold="periodic"`, Tsit5 otherwise), so that the
    Jacobian is that of one fixed discretisation."""

    def fn(model, data):
        if hold == "periodic":
            y = model.simulate(data.v_in, data.dt, hold="periodic", method="rk4", substeps=substeps)
        else:
            y = model.simulate(data.v_in, data.dt, hold=hold, rtol=None, substeps=substeps)
        return {"displacement": y}

    return Predictor(fn, ("displacement",))


class BoucWenOscillatorKind(ModelKind):
    r"""`pj.BoucWenOscillator` (`[model] kind = "bouc_wen_oscillator"`): $m\ddot y + c\dot y + ky + z = u$,
    $\dot z = \alpha\dot y - \beta(\gamma|\dot y||z|^{\nu-1}z + \delta\dot y|z|^\nu)$, driven by the force in `v_in`
    (N), predicting `displacement` (m). Keys: the parameters `m`, `c`, `k`, `alpha`, `beta`, `gamma`, `delta`, `nu`
    (each optional: the rest start from the data), `hold` (`"linear"` default, `"zoh"`, or `"periodic"` for a
    record that is one period of a multisine) and `substeps` (fixed steps per sample, default 4).

    Start: the resonance $\omega$, $\zeta$ and static compliance $1/(k + \alpha)$ of the small-signal response
    (the resonance estimate of `fitting.cold_start_actuator`), split $k = \alpha = (k + \alpha)/2$, $m = (k +
    \alpha)/\omega^2$, $c = 2\zeta\omega m$; $\nu = 1$, $\beta$ such that $\gamma = 1$ saturates $z$ at half the
    largest force, and $\delta$ the best of $\{1, 0, -0.5, -1.4\}$ by simulated error. $\beta$ only enters through
    $\beta\gamma$ and $\beta\delta$ and $\nu$ is usually 1: both are fixed by default (`[fit] free` frees them)."""

    input_unit = "N"  # v_in is the force
    table, name = "model", "bouc_wen_oscillator"
    keys = _BW_NAMES + ("hold", "substeps")
    blocks = ()

    def parse(self, t, raw, source):
        o = {k: t.number(k, None, positive=k in ("m", "nu")) for k in _BW_NAMES}
        o["hold"] = t.string("hold", ("linear", "zoh", "periodic"), "linear")
        o["substeps"] = t.integer("substeps", 4, minimum=1, maximum=MAX_SUBSTEPS)
        return o

    def outputs(self, config):
        return ("displacement",)

    def predictor(self, config):
        o = config.model_options
        return bouc_wen_oscillator_predictor(o["hold"], o["substeps"])

    def records(self, config, dataset):
        return []

    def cost(self, config):
        return config.model_options["substeps"]

    def missing(self, config):
        return [f"[model] {k}" for k in _BW_NAMES if k != "nu" and config.model_options[k] is None]

    def _start(self, config, data) -> dict:
        o = config.model_options
        if data is None:
            return dict(zip(_BW_NAMES, (2.0, 10.0, 5e4, 5e4, 1e3, 0.8, -1.1, 1.0)))
        omega, zeta, gain = _resonance(data.dataset, "displacement")
        k_eff = 1.0 / abs(gain) if o["k"] is None or o["alpha"] is None else o["k"] + o["alpha"]
        k = o["k"] if o["k"] is not None else (0.5 * k_eff if o["alpha"] is None else max(k_eff - o["alpha"], TINY))
        alpha = o["alpha"] if o["alpha"] is not None else max(k_eff - k, 1e-3 * k_eff)
        m = o["m"] if o["m"] is not None else (k + alpha) / omega**2
        umax = max(float(np.max(np.abs(e.v_in))) for e in data.dataset)
        return {"m": m, "c": 2 * zeta * np.sqrt((k + alpha) * m), "k": k, "alpha": alpha,
                "beta": alpha / (0.5 * max(umax, TINY)), "gamma": 1.0, "delta": 0.0, "nu": 1.0}

    def build(self, config, blocks, data):
        o = config.model_options
        v = self._start(config, data) | {k: x for k, x in o.items() if k in _BW_NAMES and x is not None}
        return pj.BoucWenOscillator(**{k: f64(v[k]) for k in _BW_NAMES})

    def constraints(self, config):
        return {"m": pj.Positive, "c": pj.Positive, "k": pj.Positive, "alpha": pj.Positive}

    def default_free(self, config):
        return ("m", "c", "k", "alpha", "gamma", "delta")

    def start_state(self, config, model, dataset):
        """$\\delta$ (when the file gives none): the best of a few values, by the simulated error."""
        if config.model_options["delta"] is not None:
            return model
        recs = [e for e in dataset if e.has("displacement")]
        if not recs:
            return model
        pred = self.predictor(config)
        gamma = float(model.gamma)
        cands = [eqx.tree_at(lambda s: s.delta, model, jnp.asarray(r * gamma, model.delta.dtype))
                 for r in (1.0, 0.0, -0.5, -1.4)]
        return min(cands, key=lambda m: _error(pred, m, recs))


def _error(pred, model, experiments) -> float:
    total = 0.0
    for e in experiments:
        data = as_arrays([e], pred.inputs, model.m.dtype)
        y = np.asarray(e["displacement"])
        err = np.asarray(run_predictor(pred, model, data)["displacement"]) - y
        total += float(np.sum((err / max(float(np.ptp(y)), TINY)) ** 2))
    return total if np.isfinite(total) else np.inf


# ------------------------------------------------------------------------------------------ electromechanical


@functools.cache
def electromechanical_predictor(hold: str = "linear", substeps: int = 8) -> Predictor:
    """Predictor for a `pj.ElectromechanicalActuator`: `displacement` (m) and `charge` (C) from `v_in`, from rest."""

    def fn(model, data):
        out = model.simulate(data.v_in, data.dt, hold=hold, substeps=substeps)
        return {"displacement": out["x"], "charge": out["q"]}

    return Predictor(fn, ("displacement", "charge"))


def _stops(v: np.ndarray, widths: np.ndarray) -> np.ndarray:
    """Stop operators $S_\\rho[v]$ (clip of the input increments to $\\pm\\rho$), one column per width."""
    return np.asarray(_stop(jnp.asarray(widths), jnp.asarray(v)))


@jax.jit
def _stop(widths, v):
    return pj.StopOperator(widths)(v)


STOP_FIT_SAMPLES = 40000


def _stop_fit(signals: list, targets: list, n: int) -> tuple[np.ndarray, np.ndarray] | None:
    r"""`(widths, coefficients)` of $y = c_0 s + \sum_j c_j S_{\rho_j}[s] + \text{offset}$ over records (`signals` $s$
    and `targets` $y$, one array each per record), $c \ge 0$, `n` stop operators $S_{\rho_j}$ (`coefficients`: $c_0, c_1
    \dots c_n$), on the first `STOP_FIT_SAMPLES` samples in all; `None` when $s$ is zero. For given widths the
    coefficients are a non-negative least squares (the offset free in sign); the widths start at the `n` heaviest of a
    geometric grid (0.5–80 % of $\max|s|$, four per element) or spread geometrically over three ranges, each start is
    refined by `scipy.optimize.least_squares` on their logarithms (the coefficients projected out; the widths bounded by
    $\max|s|$: a wider stop is the signal itself, collinear with the first column), and the smallest residual is kept
    (the problem has local minima: measured, a spread start found the truth's basin where the grid's heaviest widths
    left one element dead)."""
    # the first `STOP_FIT_SAMPLES` samples in all (each record from rest, so a prefix is exact): every evaluation
    # runs the stops over the whole signal (measured: 20 s for 4 elements on 1e5 samples without this limit)
    per = max(STOP_FIT_SAMPLES // len(signals), 2)
    signals, targets = [np.asarray(x)[:per] for x in signals], [np.asarray(t)[:per] for t in targets]
    top = float(max(np.max(np.abs(x)) for x in signals))
    if not (np.isfinite(top) and top > 0):
        return None
    rows = row_subset([x.size for x in signals], MAX_ROWS)
    y = np.concatenate([np.asarray(t)[keep] for t, keep in zip(targets, rows)])

    def coefficients(log_widths):
        a = np.concatenate([np.column_stack([x, _stops(x, np.exp(log_widths)) if n else np.zeros((x.size, 0)),
                                             np.ones_like(x), -np.ones_like(x)])[keep]
                            for x, keep in zip(signals, rows)])
        return a, nnls_gram(a, y)

    def residual(log_widths):
        a, c = coefficients(log_widths)
        return a @ c - y

    widths = np.zeros(0)
    if n:
        grid = top * np.geomspace(0.005, 0.8, 4 * n)
        _, c = coefficients(np.log(grid))
        starts = [np.sort(grid[np.argsort(-c[1 : 1 + grid.size], kind="stable")[:n]])] + [
            top * np.geomspace(lo, hi, n) for lo, hi in ((0.01, 0.8), (0.02, 0.5), (0.05, 0.3))]
        best = None
        for w0 in starts:
            fit = scipy.optimize.least_squares(residual, np.log(w0), diff_step=1e-3, max_nfev=20 + 10 * n,
                                               bounds=(np.log(1e-4 * top), np.log(top)))
            cost = float(np.sum(fit.fun**2))
            if np.all(np.isfinite(fit.x)) and np.isfinite(cost) and (best is None or cost < best[0]):
                best = (cost, np.sort(np.exp(fit.x)))
        widths = best[1] if best is not None else starts[0]
    _, c = coefficients(np.log(widths))
    return widths, c[: n + 1]


def _live(c: np.ndarray) -> np.ndarray:
    r"""The elements' coefficients $c_1 \dots c_n$ of `_stop_fit`, a dead one (0) raised to 1e-3 of the largest."""
    return np.maximum(c[1:], 1e-3 * max(float(np.max(c[1:], initial=0.0)), c[0]))


def _electromechanical_from_charge(recs, m: float, n: int, capacitance: float | None = None) -> dict | None:
    r"""Start of the electromechanical model from records `(v_in, displacement, charge, dt)` that measure both
    outputs (those of the smallest step); `None` where it finds no physical model ($C \le 0$ or $k \le 0$).
    A given `capacitance` replaces the estimate of $C$ in $T$ and $k$.

    With $V_p = (q - Tx)/C$ the mechanics read $m\ddot x + b\dot x + (k + T^2/C)x = (T/C)q$: displacement
    follows the measured charge through a linear resonance, free of the hysteresis (which acts between $V_{in}$
    and $q$), so `_resonance_of` on $(q, x)$ gives $\omega_q^2 = (k + T^2/C)/m$, $\zeta_q$ and the gain
    $g = (T/C)/(m\omega_q^2)$. Then $V_{in} = V_p + V_H(q)$ is, exactly and at every sample,
    $V_{in} + (T/C)x = q/C + \sum_j S_{\rho_j}[q]/C_j$: element $j$ (`clip(s + dq/C_j, ±v_j)`) is a stop operator of
    the charge of width $\rho_j = C_j v_j$, scaled by $1/C_j$: `_stop_fit` gives $1/C$, the $1/C_j$ and the widths.
    Measured on a numpy plant (four elements, 0.1 % noise): the voltage-driven start had left the fit "converged"
    at 13.5× the charge noise; this one starts it at 1.3× the fitted cost, and the fit reaches the noise
    (0.98–1.03×) in 30 steps."""
    omega, zeta, g = _resonance_of([(q, x, dt) for _, x, q, dt in recs])
    k_q = m * omega**2
    alpha = g * k_q  # T / C
    if not (np.isfinite(alpha) and alpha != 0):
        return None
    fit = _stop_fit([q for _, _, q, _ in recs], [v + alpha * x for v, x, _, _ in recs], n)
    if fit is None or not fit[1][0] > 0:
        return None
    widths, c = fit
    cap = 1.0 / c[0] if capacitance is None else capacitance
    t = alpha * cap
    k = k_q - alpha * t
    if not (np.isfinite(k) and k > 0 and np.isfinite(t)):
        return None
    inv = _live(c)
    return {"b": 2 * zeta * omega * m, "k": k, "capacitance": cap, "t_em": t,
            "element_capacitances": 1.0 / inv, "breakaway_voltages": widths * inv}


def _electromechanical_from_displacement(recs, m: float, n: int, capacitance: float, predictor, substeps: int,
                                         samples: int = 20000) -> dict | None:
    r"""Start of the electromechanical model from records `(v_in, displacement, dt)` (those of the smallest step) and a
    known `capacitance` $C$; `None` where it finds none. Quasi-statically $V_p = (k/T)x$ and $q = \beta x$, $\beta =
    Ck/T + T$, so $V_{in} = (k/T)x + V_H(\beta x)$: a stop-operator model of the displacement (`_stop_fit`: $V_{in} = a
    x + \sum_j c_j S_{r_j}[x]$, $a = k/T$, $c_j = \beta/C_j$, $r_j = C_j v_j/\beta$) fixes everything but $T$ and the
    damping. These two, which set the resonance $\omega_0^2 = aT/m$ and $\zeta$, are chosen by simulating the whole
    model (`predictor`, batched) for 16 resonances from $f_s/500$ to $f_s/4$ and five $\zeta$ from 0.02 to 0.5 (those
    the `substeps` integrate stably), on `samples // len(recs)` samples of each record from where its drive first moves:
    the smallest squared error. (The linear ARX of the voltage-driven start cannot see this resonance: the sticking
    elements stiffen the small-signal response, so it moves with the amplitude.) Measured on a numpy plant (four
    elements, 0.1 % noise, no charge): the voltage-driven start had left the fit at 4.8× the noise; this one has the
    resonance 0.6 % off, and the fit reaches 1.15× (1.25× on a held-out record)."""
    v_all = [r[0] for r in recs]
    sign = 1.0 if chord(np.concatenate(v_all), np.concatenate([r[1] for r in recs])) >= 0 else -1.0
    x_all = [sign * r[1] for r in recs]
    fit = _stop_fit(x_all, v_all, n)
    if fit is None or not fit[1][0] > 0:
        return None
    widths, c = fit
    a, cj = float(c[0]), _live(c)
    dt = recs[0][2]
    omega = np.repeat(2 * np.pi * np.geomspace(0.002, 0.25, 16) / dt, 5)
    zeta = np.tile([0.02, 0.05, 0.1, 0.2, 0.5], 16)
    # only what the fixed steps integrate stably, h (sqrt(k/m) + b/m) <= 3 (the simulation refuses the rest)
    keep = omega * (1 + 2 * zeta) * dt / substeps <= 2.9
    omega, zeta = omega[keep], zeta[keep]
    t_em = sign * m * omega**2 / a
    k = a * np.abs(t_em)
    beta = capacitance * a + np.abs(t_em)
    cands = {"b": 2 * zeta * np.sqrt(k * m), "k": k, "t_em": t_em, "element_capacitances": beta[:, None] / cj,
             "breakaway_voltages": np.broadcast_to(widths * cj, (k.size, n))}
    # each record's window starts where its drive first moves (at rest before: exact), all of one length (one
    # compilation; a shorter record is padded with its last input and its error masked)
    per = max(samples // len(recs), 2)
    sim = _batched_simulation(predictor, float(m), float(capacitance), float(dt), n)
    err = np.zeros(k.size)
    for v, x, _ in recs:
        moved = np.flatnonzero(v != v[0])
        i0 = max(int(moved[0]) - 1, 0) if v[0] == 0 and moved.size else 0
        v, x = v[i0 : i0 + per], x[i0 : i0 + per]
        drive = np.concatenate([v, np.full(per - v.size, v[-1])])
        out = np.asarray(sim(*(jnp.asarray(np.asarray(cands[key], float)) for key in _EM_SCAN), jnp.asarray(drive)))
        err += np.sum((out[:, : x.size] - x) ** 2, axis=1)
    err = np.where(np.isfinite(err), err, np.inf)
    if not np.isfinite(np.min(err)) or np.max(err[np.isfinite(err)]) - np.min(err) <= 1e-12 * np.min(err):
        return None  # no candidate, or the records cannot tell them apart
    i = int(np.argmin(err))
    return {key: np.asarray(cands[key])[i] for key in _EM_SCAN} | {"capacitance": capacitance}


_EM_SCAN = ("b", "k", "t_em", "element_capacitances", "breakaway_voltages")


def _optional_start(start, *args) -> dict | None:
    """`start(*args)`, or `None` where it fails on the records (the caller falls back to the next start; an
    interrupt still stops the fit)."""
    try:
        out = start(*args)
    except (PiezojaxValueError, ValueError, ArithmeticError, np.linalg.LinAlgError, RuntimeError):
        return None
    if out is None or not all(np.all(np.isfinite(np.asarray(v, float))) for v in out.values()):
        return None
    return out


@functools.cache
def _batched_simulation(predictor, m: float, capacitance: float, dt: float, n: int):
    """The displacement of `predictor` for a batch of electromechanical models (the `_EM_SCAN` values, one row
    each), compiled once per record length."""
    def one(b, k, t_em, caps, volts, v):
        model = pj.ElectromechanicalActuator(m, b, k, capacitance, t_em[None], caps, volts)
        data = ExperimentArrays(t=jnp.arange(v.size, dtype=v.dtype) * dt, dt=jnp.asarray(dt, v.dtype), v_in=v,
                                channels={})
        return predictor.fn(model, data)["displacement"]

    return jax.jit(jax.vmap(one, in_axes=(0, 0, 0, 0, 0, None)))


class ElectromechanicalKind(ModelKind):
    r"""`pj.ElectromechanicalActuator` (`[model] kind = "electromechanical"`, paper 003): $V_{in} = V_H + V_p$,
    $q = C V_p + T_{em}x$, $m\ddot x + b\dot x + kx = T_{em}V_p$, $V_H$ a Maxwell slip of $q$. Predicts
    `displacement` and `charge` from `v_in`. Keys: `m` (required: with the displacement alone only the ratios of $m$,
    $b$, $k$, $T_{em}$ are identifiable), `b`, `k`, `capacitance` (required unless a data file has a `charge`
    column), `t_em` (ascending polynomial coefficients of $T_{em}(V_{in})$, or `coupling_degree`, default 0),
    `elements` (Maxwell-slip elements, default 4) with `element_capacitances` and `breakaway_voltages`, `hold`
    (`"linear"` or `"zoh"`) and `substeps` (fixed Tsit5 steps per sample, default 8; explicit steps need
    $h(\sqrt{k/m} + b/m) \le 3$).

    Start: from records that measure the charge as well, `_electromechanical_from_charge` (the mechanics from the
    charge-to-displacement resonance, which the hysteresis does not touch, then the elements from the exact
    relation $V_{in} + (T/C)x = q/C + V_H(q)$). From the displacement alone with `capacitance` given,
    `_electromechanical_from_displacement` (stop operators of the displacement, the resonance chosen by simulation).
    Otherwise, or where those find no physical model: to first order the charge follows the voltage,
    $dq \approx C_e\,dV_p$ with $C_e = C + T^2/k$, so
    element $j$ is $a_j S_{\rho_j}[V_{in}]$ in volts (a stop operator, $a_j = C_e/C_j$, $\rho_j = v_j/a_j$) and
    $x \approx \frac{T}{k} F(s)\bigl[V_{in} - \sum_j a_j S_{\rho_j}[V_{in}]\bigr]$, $F$ the DC-normalised resonance:
    linear in $(T/k, Ta_j/k) \ge 0$ for each candidate resonance of `fitting.cold_start_actuator`'s estimate,
    solved by non-negative least squares on widths $\rho_j$ from 0.005 to 0.8 $\max|V_{in}|$ (four per element;
    the `elements` widths with the largest weights are kept and solved again); the candidate with the smallest
    residual gives $k = m\omega^2$, $b = 2\zeta\omega m$, $T$ and the elements; with the charge measured,
    $C$ is the slope of $q - Tx$ against $V_p$. Fitted by default: `b`, `k`, `t_em`, the elements, and `capacitance`
    when the charge is a target."""

    table, name = "model", "electromechanical"
    keys = ("m", "b", "k", "capacitance", "t_em", "coupling_degree", "elements", "element_capacitances",
            "breakaway_voltages", "hold", "substeps")
    blocks = ()

    def parse(self, t, raw, source):
        if "m" not in t.data:
            raise t.error("missing (the moving mass: with the displacement alone only the ratios of m, b, k and "
                          "t_em are identifiable)", "m")
        t_em = t.vector("t_em", None)
        degree = t.integer("coupling_degree", None, minimum=0, maximum=MAX_COUPLING_DEGREE)
        if t_em is not None and degree is not None and degree != t_em.size - 1:
            raise t.error(f"has {t_em.size} coefficients, so coupling_degree = {t_em.size - 1}; got {degree}",
                          "coupling_degree")
        n, (caps, volts) = t.sized_vectors("elements", 4, MAX_ELEMENTS, {"element_capacitances": dict(positive=True),
                                                                       "breakaway_voltages": dict(positive=True)},
                                           minimum=0)
        return {"m": t.number("m", positive=True), "b": t.number("b", None, nonnegative=True),
                "k": t.number("k", None, positive=True), "capacitance": t.number("capacitance", None, positive=True),
                "t_em": t_em, "degree": degree if degree is not None else (0 if t_em is None else t_em.size - 1),
                "elements": n, "element_capacitances": caps, "breakaway_voltages": volts,
                "hold": t.string("hold", ("linear", "zoh"), "linear"),
                "substeps": t.integer("substeps", 8, minimum=1, maximum=MAX_SUBSTEPS)}

    def outputs(self, config):
        return ("displacement", "charge")

    def predictor(self, config):
        o = config.model_options
        return electromechanical_predictor(o["hold"], o["substeps"])

    def records(self, config, dataset):
        return []

    def cost(self, config):
        return 2 * config.model_options["substeps"]  # Tsit5: six stages, each with the charge solve

    def missing(self, config):
        o = config.model_options
        return [f"[model] {k}" for k in self.missing_keys(o) if o[k] is None]

    def _placeholder(self, o) -> dict:
        n = o["elements"]
        return {"b": 1.0, "k": 1e6, "capacitance": 1e-6, "t_em": np.r_[1.0, np.zeros(o["degree"])],
                "element_capacitances": np.full(n, 1e-5), "breakaway_voltages": np.arange(1.0, n + 1)}

    def _start(self, config, data) -> dict:
        o = config.model_options
        if data is None or all(o[k] is not None for k in self.missing_keys(o)):
            return self._placeholder(o)
        n = o["elements"]
        both = [(np.asarray(e.v_in, float), np.asarray(e["displacement"], float), np.asarray(e["charge"], float),
                 e.dt) for e in data.dataset if e.has("displacement") and e.has("charge")]
        if both:
            dt = min(r[3] for r in both)
            start = _optional_start(_electromechanical_from_charge, [r for r in both if r[3] == dt], o["m"], n,
                                    o["capacitance"])
            if start is not None:
                return start | {"t_em": np.r_[start["t_em"], np.zeros(o["degree"])]}
        recs = [(np.asarray(e.v_in, float), np.asarray(e["displacement"], float), e.dt)
                for e in data.dataset if e.has("displacement")]
        if not recs:
            raise PiezojaxValueError("data-driven initial values need data files with a 'displacement' column (or "
                                     "give every parameter value explicitly in the configuration)")
        dt = min(r[2] for r in recs)
        recs = [r for r in recs if r[2] == dt]
        if o["capacitance"] is not None:
            start = _optional_start(_electromechanical_from_displacement, recs, o["m"], n, o["capacitance"],
                                    self.predictor(config), o["substeps"])
            if start is not None:
                return start | {"t_em": np.r_[start["t_em"], np.zeros(o["degree"])]}
        v = np.concatenate([r[0] for r in recs])
        x = np.concatenate([r[1] for r in recs])
        # candidate element widths from 0.5 % to 80 % of the largest voltage (geometric: narrow elements shape the
        # reversals), four per element; the n that carry the most weight are kept
        grid = float(np.max(np.abs(v))) * np.geomspace(0.005, 0.8, 4 * n) if n else np.zeros(0)
        sign = 1.0 if chord(v, x) >= 0 else -1.0

        def solve(widths, omega, zeta):
            # x = (T/k) F(s)[V - sum_j a_j S_j[V]]: coefficients >= 0 by NNLS (with a free offset)
            drives = [np.column_stack([r[0], -_stops(r[0], widths)]) if widths.size else r[0][:, None]
                      for r in recs]
            cols = np.concatenate([filter_pairs(d, dt, omega, zeta) for d in drives])
            cols = np.column_stack([cols, np.ones(cols.shape[0]), -np.ones(cols.shape[0])])
            coef, res = scipy.optimize.nnls(cols, sign * x)
            return coef[: widths.size + 1], res

        # each candidate resonance of the cold start's estimate; the one with the smallest residual
        cands = [(w, z) for _, w, z in dynamics_candidates(recs, 2, MAX_ROWS) if w.size == 1]
        best = None
        for omega, zeta in cands + [(np.array([0.2 * np.pi / dt]), np.array([0.7]))]:
            coef, res = solve(grid, omega, zeta)
            if coef[0] > 0 and np.isfinite(res) and (best is None or res < best[0]):
                best = (res, omega, zeta, coef)
        if best is None:  # a heuristic that fails on usable data: the placeholder, and the fit may still get there
            return self._start_failed(o, "no loading curve in the displacement (zero or unrelated to v_in)")
        _, omega, zeta, coef = best
        widths = np.sort(grid[np.argsort(-coef[1:], kind="stable")[:n]])
        coef, _ = solve(widths, omega, zeta)
        omega, zeta = float(omega[0]), float(zeta[0])
        m = o["m"]
        k = o["k"] if o["k"] is not None else m * omega**2
        b = o["b"] if o["b"] is not None else 2 * zeta * np.sqrt(k * m)
        t = sign * float(coef[0]) * k if o["t_em"] is None else float(o["t_em"][0])
        a = np.asarray(coef[1:]) / coef[0]
        a = np.maximum(a, 1e-3 * max(float(np.max(a, initial=0.0)), 1e-3))
        cap = o["capacitance"]
        charged = [e for e in data.dataset if e.has("charge") and e.has("displacement")]
        if cap is None and charged:  # q - T x = C V_p, V_p = V - sum_j a_j S_j[V] to first order
            vp = np.concatenate([np.asarray(e.v_in, float) - (_stops(np.asarray(e.v_in, float), widths) @ a if n
                                                              else 0.0) for e in charged])
            rest = np.concatenate([np.asarray(e["charge"], float) - t * np.asarray(e["displacement"], float)
                                   for e in charged])
            cap = chord(vp, rest)
            cap = cap if cap > 0 else chord(vp, rest + t * np.concatenate([np.asarray(e["displacement"], float)
                                                                           for e in charged]))
        if cap is None:
            raise PiezojaxValueError(f"{config.source}: [model] capacitance: give it explicitly, or fit on data "
                                     "files with a 'charge' column")
        if not cap > 0:  # the charge does not rise with the voltage: no estimate, the fit starts from 1 uF
            warnings.warn(f"[model] electromechanical: the capacitance estimated from the charge is {cap:.3g} F (the "
                          "charge does not rise with v_in); starting from the placeholder 1e-6 F", StartWarning,
                          stacklevel=2)
            cap = float(self._placeholder(o)["capacitance"])
        # element j moves with the charge, dq = (C + T^2/k) dV_p quasi-statically: C_j = (C + T^2/k)/a_j
        c_eff = cap + t**2 / k
        return {"b": b, "k": k, "capacitance": cap, "t_em": np.r_[t, np.zeros(o["degree"])],
                "element_capacitances": c_eff / a, "breakaway_voltages": a * widths}

    def _start_failed(self, o, why: str) -> dict:
        """The placeholder values with a `StartWarning` saying `why` the data-driven start found none (a start must
        not end the run)."""
        warnings.warn(f"[model] electromechanical: the data-driven start failed ({why}); starting from the "
                      "placeholder values", StartWarning, stacklevel=3)
        return self._placeholder(o)

    @staticmethod
    def missing_keys(o) -> tuple[str, ...]:
        return ("b", "k", "capacitance", "t_em") + (
            ("element_capacitances", "breakaway_voltages") if o["elements"] else ())

    def build(self, config, blocks, data):
        o = config.model_options
        v = self._start(config, data) | {k: o[k] for k in self.missing_keys(o) if o[k] is not None}
        empty = np.zeros(0)
        return pj.ElectromechanicalActuator(
            f64(o["m"]), f64(v["b"]), f64(v["k"]), f64(v["capacitance"]), f64(v["t_em"]),
            f64(v["element_capacitances"] if o["elements"] else empty),
            f64(v["breakaway_voltages"] if o["elements"] else empty))

    def constraints(self, config):
        return {"b": pj.Positive, "k": pj.Positive, "capacitance": pj.Positive} | (
            {"element_capacitances": pj.Positive, "breakaway_voltages": pj.Positive}
            if config.model_options["elements"] else {})

    def default_free(self, config):
        return ("b", "k", "t_em", "capacitance") + (
            ("element_capacitances", "breakaway_voltages") if config.model_options["elements"] else ())

    def fit_free(self, config, free, targets):
        if targets is not None and "charge" not in targets:
            # without the charge, C is nearly redundant with the element capacitances (only the ratio C/C_j and the
            # small term T x / C of the charge separate them)
            free = [p for p in free if p != "capacitance"]
        return free
