r"""Cold-start initialisation of a composed actuator from data alone (no prior guess of the parameters).

The model is the parallel Hammerstein chain of `pj.Actuator`,
$\delta = G(s)\big[w_0 V + \sum_i w_i P_{r_i}[V] + \sum_j c_j L_{\tau_j}[V]\big]$ with play operators $P_r$,
Kelvin–Voigt creep lags $L_\tau = 1/(1 + \tau s)$ of gains $c_j = 1/k_j$, and a DC-normalised $G$ ($G(0) = 1$).
For fixed thresholds $r_i$, time constants $\tau_j$ and dynamics $G$ the displacement is *linear* in
$(w_0, w_i, c_j)$, and for a fixed drive $u = \mathcal{H}[V] + \mathcal{C}[V]$ the sampled $G$ is a linear ARX
recursion. The cold start alternates these linear problems; everything here runs once, on concrete NumPy data of
data-dependent size, so it is plain NumPy/SciPy (not jit-able, not differentiable, on purpose).
"""

import jax
import jax.numpy as jnp
import numpy as np
import scipy  # submodules (signal, optimize, linalg) load on first use: importing them costs about a second

import piezojax as pj
from piezojax import PiezojaxValueError
from piezojax.internal import MAX_ROWS, check_max_rows, contiguous_runs, lag_columns, nnls_gram, row_subset

from ._data import Dataset

# ----------------------------------------------------------------------------------------------------------------
# linear building blocks (NumPy mirrors of the models' exact ZOH recursions)


@jax.jit
def _play(thresholds, v):
    return pj.PlayOperator(thresholds)(v)


def _play_columns(v: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """`(N, n)` play outputs $P_{r_i}[v]$ from the demagnetised state, by the library's own operator (compiled once
    per shape)."""
    if thresholds.size == 0:
        return np.zeros((v.size, 0))
    return np.asarray(_play(jnp.asarray(thresholds), jnp.asarray(v)), dtype=float)


def filter_pairs(x: np.ndarray, dt: float, omega: np.ndarray, zeta: np.ndarray) -> np.ndarray:
    r"""Apply the DC-normalised cascade $\prod_i \omega_i^2/(s^2 + 2\zeta_i\omega_i s + \omega_i^2)$ along axis 0,
    from rest, exactly as `StableTransferFunction(1.0, omega, zeta).simulate` (ZOH of the *whole* cascade — not of
    each section, whose inputs are not piecewise constant): its realisation is discretised by
    `scipy.signal.cont2discrete` and run as second-order sections."""
    a, b, c, d = (np.asarray(m, float) for m in pj.StableTransferFunction(1.0, omega=omega, zeta=zeta).state_space())
    ad, bd, cd, _, _ = scipy.signal.cont2discrete((a, b[:, None], c[None, :], np.zeros((1, 1))), dt, method="zoh")
    # strictly proper (D = 0): y_k = sum_{i >= 1} b_i u_{k-i}; the one-sample delay is applied explicitly, since a
    # rounded ~1e-17 leading numerator coefficient would otherwise become a huge spurious zero
    num, den = scipy.signal.ss2tf(ad, bd, cd, np.zeros((1, 1)))
    num = np.ravel(num)[1:]
    sos = scipy.signal.zpk2sos(np.roots(num), np.roots(den), num[0])
    y = scipy.signal.sosfilt(sos, x, axis=0)
    return np.concatenate([np.zeros_like(y[:1]), y[:-1]], axis=0)


def _clusters(weights: np.ndarray, grid: np.ndarray, n: int, rel: float, log: bool) -> np.ndarray:
    """Points of a dense non-negative fit reduced to `n`: runs of active grid points; while there are more than `n`,
    the lightest run (total weight) is merged into its nearest neighbour; each run's weight-averaged position
    (geometric when `log`).
    Fewer than `n` runs: the missing points are spread log-uniformly over the grid's free range."""
    pos = np.log(grid) if log else grid
    runs = contiguous_runs(weights > rel * max(weights.max(initial=0.0), np.finfo(float).tiny))

    def centre(c):
        w = weights[c]
        return float(np.sum(w * pos[c]) / np.sum(w))

    while len(runs) > n:
        # the lightest run joins its nearest neighbour (merging by smallest gap instead would fuse two real,
        # heavy clusters and keep a light spurious one, e.g. a play at the top of the grid fitting peak residue)
        j = int(np.argmin([np.sum(weights[c]) for c in runs]))
        left = centre(runs[j]) - centre(runs[j - 1]) if j > 0 else np.inf
        right = centre(runs[j + 1]) - centre(runs[j]) if j + 1 < len(runs) else np.inf
        k = j - 1 if left <= right else j + 1
        lo, hi = min(j, k), max(j, k)
        runs[lo : hi + 1] = [runs[lo] + runs[hi]]
    points = [centre(c) for c in runs]
    while len(points) < n:  # split the widest free interval
        edges = [pos[0]] + sorted(points) + [pos[-1]]
        j = int(np.argmax(np.diff(edges)))
        points.append(0.5 * (edges[j] + edges[j + 1]))
    points = np.sort(np.asarray(points))
    return np.exp(points) if log else points


# ----------------------------------------------------------------------------------------------------------------
# dynamics: ARX with a spectral fallback


def _arx_lstsq(records, order: int, den: np.ndarray | None, max_rows: int | None = None):
    r"""One equation-error least squares (rows $k \ge n$; at most `max_rows` of them, the same fixed random subset
    on every call), on $y$, $u$ prefiltered by $1/A(z)$ when `den` is given."""
    rows, rhs = [], []
    usable = [(u, y) for u, y, _ in records if y.size > order + 1]
    keep = row_subset([y.size - order for _, y in usable], max_rows)
    for (u, y), k in zip(usable, keep):
        if den is not None:
            u, y = scipy.signal.lfilter([1.0], den, u), scipy.signal.lfilter([1.0], den, y)
        k = np.arange(order, y.size)[k]
        rows.append(np.column_stack([-y[k - i] for i in range(1, order + 1)] + [u[k - i] for i in range(1, order + 1)]))
        rhs.append(y[k])
    if not rows:
        return None
    a = np.concatenate(rows)
    scale = np.sqrt(np.einsum("ij,ij->j", a, a))
    scale = np.where(scale > 0, scale, 1.0)
    an = a / scale
    gram = np.einsum("ij,ik->jk", an, an)
    coef = np.linalg.lstsq(gram, np.einsum("ij,i->j", an, np.concatenate(rhs)), rcond=None)[0] / scale
    return np.concatenate([[1.0], coef[:order]])


def _arx_pairs(records, order: int, iterations: int = 20, max_rows: int | None = None):
    r"""Discrete denominator by ARX least squares, $y_k = -\sum_{i=1}^{n} a_i y_{k-i} + \sum_{i=1}^{n} b_i
    u_{k-i} + e_k$, pooled over the records of one step `dt` (rows $k \ge n$), refined by Steiglitz–McBride
    iterations (the same least squares on $y$, $u$ prefiltered by $1/\hat A(z)$ of the previous estimate): plain
    equation-error ARX is biased by output noise — badly at high sampling rates, where $y_{k-1}$, $y_{k-2}$ are
    nearly collinear (measured here: $\zeta$ 0.30 for a true 0.10) — and the iteration converges to the
    output-error estimate for white noise. Then the continuous poles $s = \ln z/dt$ of $z^n + a_1 z^{n-1} + \dots
    + a_n$: a complex pair gives $\omega = |s|$, $\zeta = -\mathrm{Re}\,s/|s|$. Returns `(omega, zeta)` of the
    `order/2` pole pairs, or `None` when a pole is unstable ($|z| \ge 1$), on the negative real axis (no
    continuous-time equivalent), or the real poles cannot be paired. `max_rows`: see `_arx_lstsq`."""
    dt = records[0][2]

    def stable(den):
        return den is not None and np.all(np.isfinite(den)) and np.all(np.abs(np.roots(den)) < 1.0)

    den = _arx_lstsq(records, order, None, max_rows)
    if not stable(den):
        return None
    for _ in range(iterations):
        new = _arx_lstsq(records, order, den, max_rows)
        if not stable(new):
            break
        done = np.max(np.abs(new - den)) < 1e-10
        den = new
        if done:
            break
    z = np.roots(den)
    if np.any((np.abs(z.imag) < 1e-12) & (z.real <= 0)):
        return None
    s = np.log(z.astype(complex)) / dt
    upper = s[s.imag > 1e-12 * np.abs(s)]
    real = np.sort(s[np.abs(s.imag) <= 1e-12 * np.abs(s)].real)
    omega = list(np.abs(upper))
    zeta = list(-upper.real / np.abs(upper))
    if real.size % 2:
        return None
    for p, q in zip(real[0::2], real[1::2]):  # two real poles = one overdamped pair (zeta >= 1)
        w = np.sqrt(p * q)
        omega.append(w)
        zeta.append(-(p + q) / (2 * w))
    if not all(np.isfinite(omega)) or not all(np.isfinite(zeta)) or min(zeta, default=1.0) <= 0:
        return None
    order_idx = np.argsort(omega)
    return np.asarray(omega)[order_idx], np.asarray(zeta)[order_idx]


def _spectral_pairs(records, order: int):
    r"""Fallback: the empirical frequency response $\hat H(f) = \hat S_{uy}(f)/\hat S_{uu}(f)$ (Welch, pooled over
    records); the resonance $\omega = 2\pi f_{peak}$ at the largest $|\hat H|$ above the lowest bins, among the
    bins where the input power exceeds $10^{-4}$ of its peak, and
    $\zeta$ from the peak height, $|H(\omega)| = 1/(2\zeta)$ for a DC-normalised pair, clipped to $[0.02, 1]$.
    Extra pairs (order > 2) are placed one and two octaves above."""
    dt = records[0][2]
    num = den = 0.0
    f = None
    for u, y, _ in records:
        nper = min(1024, u.size)
        if nper < 16:
            continue
        f, puy = scipy.signal.csd(u, y, fs=1 / dt, nperseg=nper)
        _, puu = scipy.signal.welch(u, fs=1 / dt, nperseg=nper)
        num = num + puy
        den = den + puu
    if f is None:
        return np.full(order // 2, 0.25 * np.pi / dt), np.full(order // 2, 0.5)
    h = np.abs(num) / np.maximum(np.abs(den), np.finfo(float).tiny)
    # only bins the input excites (elsewhere the ratio is noise over nothing)
    h = np.where(np.abs(den) > 1e-4 * np.max(np.abs(den)), h, 0.0)
    dc = float(np.median(h[1:4])) if h.size > 4 else 1.0
    k = 4 + int(np.argmax(h[4:])) if h.size > 5 else h.size - 1
    peak = h[k] / max(dc, np.finfo(float).tiny)
    w = 2 * np.pi * f[k]
    z = float(np.clip(1 / (2 * max(peak, 1e-12)), 0.02, 1.0))
    omega = w * 2.0 ** np.arange(order // 2)
    return omega, np.full(order // 2, z)


def _highpassed(records, cutoff: float):
    """Each record's `u` and `y` through the same 2nd-order Butterworth high-pass (`cutoff` in Hz), forward and
    backward (zero phase). Filtering input and output by one LTI filter leaves the dynamics between them unchanged,
    and removes what the drive estimate gets wrong at low frequency (hysteresis and creep misfit, a sensor offset),
    which otherwise dominates the regression and hides a resonance that only rings after steps."""
    out = []
    for u, y, dt in records:
        nyq = 0.5 / dt
        if not 0 < cutoff < 0.5 * nyq or u.size < 32:
            continue
        sos = scipy.signal.butter(2, cutoff / nyq, btype="highpass", output="sos")
        out.append((scipy.signal.sosfiltfilt(sos, u), scipy.signal.sosfiltfilt(sos, y), dt))
    return out


def dynamics_candidates(records, order: int, max_rows: int | None = None) -> list[tuple[str, np.ndarray, np.ndarray]]:
    r"""Candidate `(label, omega, zeta)` for the dynamics from the drive/output records of one step: the ARX of
    `_arx_pairs` on the raw records and on records high-passed at $f_s/1000$, $f_s/200$ and $f_s/50$ (see
    `_highpassed`), then the spectral peak (`_spectral_pairs`). A candidate that fails (an unstable or
    non-physical estimate) is left out; the caller keeps the one that explains the data best. Each regression uses
    at most `max_rows` rows."""
    dt = records[0][2]
    out = []
    for label, recs in [("ARX", records)] + [
        (f"ARX above {frac / dt:.3g} Hz", _highpassed(records, frac / dt)) for frac in (1e-3, 5e-3, 2e-2)
    ]:
        if not recs:
            continue
        try:
            pairs = _arx_pairs(recs, order, max_rows=max_rows)
        except (np.linalg.LinAlgError, ValueError):
            pairs = None
        if pairs is not None:
            out.append((label, *pairs))
    out.append(("spectral peak", *_spectral_pairs(records, order)))
    return out


# ----------------------------------------------------------------------------------------------------------------


def _records(dataset):

    if not isinstance(dataset, Dataset):
        dataset = Dataset(list(dataset))
    recs = []
    for exp in dataset:
        if exp.has("displacement"):
            recs.append((np.asarray(exp.v_in, float), np.asarray(exp.channels["displacement"], float), float(exp.dt)))
    if not recs:
        raise PiezojaxValueError(
            "`dataset` has no experiment with a `displacement` channel: nothing to initialise from"
        )
    return recs


def _design(v: np.ndarray, dt: float, thresholds: np.ndarray, taus: np.ndarray) -> np.ndarray:
    """Design matrix `[v, P_r[v], L_tau[v]]` of one record, shape `(N, 1 + n + m)`, filled in place (the plays 16 at
    a time, and not copied: the compact design of `cold_start_actuator`; its dense grid is a `_LazyDesign`)."""
    n = thresholds.size
    out = np.empty((v.size, 1 + n + taus.size))
    out[:, 0] = v
    for j in range(0, n, 16):
        out[:, 1 + j : 1 + min(n, j + 16)] = _play_columns(v, thresholds[j : j + 16])
    out[:, 1 + n :] = lag_columns(v, dt, taus)
    return out


class _LazyDesign:
    """`_design(v, dt, thresholds, taus)` never held whole: its columns are made again each time they are asked for,
    `v`, then 16 plays at a time, then 16 lags at a time (`blocks`). For the dense grid of `cold_start_actuator`, whose
    design on a 1e6-sample record (97 columns: 776 MB) was the start's largest array; it is read once per
    dynamics iteration, and making it again costs ~2.6 s per read there."""

    def __init__(self, v: np.ndarray, dt: float, thresholds: np.ndarray, taus: np.ndarray):
        self.v, self.dt, self.thresholds, self.taus = v, dt, thresholds, taus

    def blocks(self):
        yield self.v[:, None]
        for j in range(0, self.thresholds.size, 16):
            yield _play_columns(self.v, self.thresholds[j : j + 16])
        for j in range(0, self.taus.size, 16):
            yield lag_columns(self.v, self.dt, self.taus[j : j + 16])


def _through(designs, recs, omega, zeta, rows) -> np.ndarray:
    """Every record's design columns (an array, or a `_LazyDesign`) passed through the dynamics (if identified;
    whole records, a few columns at a time), at the least-squares rows `rows` (`row_subset`), stacked over
    records."""
    out = []
    for a, (_, _, dt), keep in zip(designs, recs, rows):
        blocks = a.blocks() if isinstance(a, _LazyDesign) else (a[:, j : j + 16] for j in range(0, a.shape[1], 16))
        out.append(np.concatenate([(x if omega is None else filter_pairs(x, dt, omega, zeta))[keep]
                                   for x in blocks], axis=1))
    return np.concatenate(out)


def _strictly_ascending(x: np.ndarray, spacing: float) -> np.ndarray:
    """Sorted, at least `spacing/4` above 0 and strictly ascending (ties broken by a tiny offset)."""
    x = np.maximum.accumulate(np.maximum(np.sort(x), 0.25 * spacing))
    return x + 1e-6 * spacing * np.arange(x.size)


def cold_start_actuator(
    dataset,
    n_plays: int,
    creep_order: int,
    dynamics_order: int = 2,
    *,
    structure: str = "parallel",
    creep: str = "kelvin_voigt",
    grid_factor: int = 8,
    tau_range: tuple[float, float] | None = None,
    iterations: int = 2,
    min_weight_fraction: float = 1e-3,
    constrained: bool = True,
    max_rows: int | None = MAX_ROWS,
):
    r"""Initial `pj.Actuator` (PI hysteresis + Kelvin–Voigt creep + stable dynamics) from displacement data alone.

    The model is $\delta = G(s)\big[w_0 V + \sum_{i=1}^{n} w_i P_{r_i}[V] + \sum_{j=1}^{m} L_{\tau_j}[V]/k_j\big]$
    (`structure="parallel"`, `KelvinVoigtCreep(k, tau, k0=None)`, `StableTransferFunction(1.0, omega, zeta)` with
    unit DC gain, so the static scale sits in the hysteresis and the creep gains), or, with `structure="series"`,
    $\delta = G(s)\big[(1 + \sum_j c_j L_{\tau_j})[H[V]]\big]$ (`KelvinVoigtCreep(1/c, tau, k0=1)`: the creep
    acts on the hysteresis output, its gains $c_j$ dimensionless; with `creep="lag"` the same response as
    `pj.LagCreep`, fractions $c_j/(1 + \sum c)$ and the hysteresis scaled by $1 + \sum c$). Every least squares
    below has a free constant (a sensor offset). Steps:

    1. **Dense linear fit.** Non-negative least squares of the displacement on
       $G[V], G[P_{\rho_1}[V]], \dots, G[P_{\rho_{gn}}[V]], G[L_{t_1}[V]], \dots, G[L_{t_{gm}}[V]]$ over all
       records: a threshold grid $\rho$ on $(0, \max|V|)$ and a log-spaced time-constant grid $t$ over
       `tau_range` (default $[5\,dt_{min}, T_{max}/2]$, $T_{max}$ the longest record), with $G$ the current
       dynamics estimate ($G = 1$ on the first pass). For fixed $r$, $\tau$ and $G$ the displacement is linear in
       $w_0, w_i \ge 0$ and the creep gains $c_j = 1/k_j \ge 0$ ($G$ is linear, so
       $G[\sum_i w_i P_{r_i}[V]] = \sum_i w_i G[P_{r_i}[V]]$).
    2. **Thresholds and time constants** by clustering the dense gains (as `pj.pi_cold_start` does, on the
       $G$-filtered columns and with the creep columns in the same solve): runs of active grid points; while there
       are more than `n_plays` (`creep_order`), the lightest run joins its nearest neighbour; each run gives its
       gain-weighted mean position (geometric mean for $\tau$).
    3. **Gains** $w_0, w_i, c_j$ by one non-negative least squares with those $r_i$, $\tau_j$ (through $G$).
       In series the model is bilinear in $(w, c)$: alternating non-negative least squares from the parallel
       gains (`_series_gains`).
    4. **Dynamics** by ARX least squares of $\delta$ on the drive $u = \hat{\mathcal H}[V] + \hat{\mathcal C}[V]$,
       $\delta_k = -\sum_{i \le n_G} a_i\delta_{k-i} + \sum_{i \le n_G} b_i u_{k-i}$ (the ZOH-sampled all-pole
       $G$ is strictly proper), pooled over the records of the most common $dt$ and refined by Steiglitz–McBride
       iterations (the same regression on data prefiltered by $1/\hat A(z)$, which removes the output-noise bias
       of plain ARX); the discrete poles $z$ map to $s = \ln z/dt$, a complex pair to $\omega = |s|$,
       $\zeta = -\mathrm{Re}\,s/|s|$, two real poles $p, q < 0$ to $\omega = \sqrt{pq}$,
       $\zeta = -(p + q)/(2\omega) \ge 1$. **Fallback** when a pole is unstable or on the negative real axis: the
       peak of the empirical frequency response $S_{uy}/S_{uu}$ (Welch), with $\zeta = 1/(2|H|_{peak})$ clipped to
       $[0.02, 1]$. The same regression also runs on drive and displacement high-passed at $f_s/1000$,
       $f_s/200$ and $f_s/50$ (one LTI filter on both leaves $G$ unchanged and removes the low-frequency misfit of
       the drive, which otherwise hides a resonance that only rings after steps); of these candidates the one
       whose $G$ explains the displacement best is kept.
    5. Steps 1–4 are repeated `iterations` times with the new $G$ (the first pass, without dynamics, mistakes
       resonant ringing for creep and hysteresis; the ARX of step 4 still finds the resonance from that rough
       drive), then step 3 once more with the final $G$.

    The result is wrapped for `fitting.fit`: `weights`, `w0`, creep `stiffnesses`, `time_constants` and dynamics
    `omega`, `zeta` as `pj.Positive`, `thresholds` as `pj.OrderedPositive` (with `constrained=False`, the plain
    model). Free everything but the dynamics' `gain` (fixed at 1: it duplicates the overall scale), e.g.
    `free=["hysteresis.weights", "hysteresis.thresholds", "hysteresis.w0", "creep", "dynamics.omega",
    "dynamics.zeta"]`.

    Only the sampled ZOH convention of `pj.Actuator.simulate` (the fitting default) is mirrored. Plain NumPy/SciPy:
    not jit-able or differentiable (it runs once, before the fit).

    **Arguments:**

    - `dataset`: a `fitting.Dataset` (or a sequence of `fitting.Experiment`); the experiments with a `displacement`
      channel are used.
    - `n_plays`: number of play operators ($\ge 1$).
    - `creep_order`: number of Kelvin–Voigt lags ($\ge 0$; 0: no creep block).
    - `dynamics_order`: order of $G$, even ($\ge 0$; 0: no dynamics block).
    - `structure`: `"parallel"` (creep driven by the voltage, beside the hysteresis) or `"series"` (after it).
    - `creep`: `"kelvin_voigt"` or `"lag"` (`pj.LagCreep`, series only).
    - `grid_factor`: dense grid sizes are `grid_factor` times the number of plays / lags.
    - `tau_range`: `(tau_min, tau_max)` of the time-constant grid [s].
    - `iterations`: further passes of steps 1–4 through the identified dynamics.
    - `min_weight_fraction`: dense gains below this fraction of the largest count as zero when clustering.
    - `constrained`: return the reparametrised model (default) or the plain one.
    - `max_rows`: every least squares above uses at most this many samples (default 200000), a fixed random subset
      of each record's when the records are longer; the plays, lags and filters still run over whole records (they
      carry the history). A 1e6-sample record starts in seconds and a few hundred MB; `None`: every sample.

    **Returns:** a `pj.Actuator`, reparametrised (`constrained=True`: pass it to `fitting.fit`; simulate
    `pj.unwrap(init)`).

    ```python
    init = fitting.cold_start_actuator(dataset, n_plays=6, creep_order=2)
    free = ["hysteresis.weights", "hysteresis.thresholds", "hysteresis.w0", "creep", "dynamics.omega",
            "dynamics.zeta"]
    result = fitting.fit(init, dataset, free=free, weights="noise")
    ```
    """
    _check_orders(n_plays, creep_order, dynamics_order, structure, creep, iterations, grid_factor)
    check_max_rows(max_rows)
    recs = _records(dataset)
    vmax = max(float(np.max(np.abs(v))) for v, _, _ in recs)
    if not vmax > 0:
        raise PiezojaxValueError("`dataset`: every `v_in` is identically zero, nothing can be identified")
    dt_min = min(dt for _, _, dt in recs)
    t_max = max(v.size * dt for v, _, dt in recs)
    if tau_range is None:
        tau_range = (5 * dt_min, 0.5 * t_max)
    tau_lo, tau_hi = (float(x) for x in tau_range)
    if not (0 < tau_lo < tau_hi and np.isfinite(tau_hi)):
        raise PiezojaxValueError(f"`tau_range` must be (tau_min, tau_max) with 0 < tau_min < tau_max, got {tau_range}")

    npairs = dynamics_order // 2
    series = structure == "series" and creep_order > 0
    dt_counts: dict[float, int] = {}
    for v, _, dt in recs:
        dt_counts[dt] = dt_counts.get(dt, 0) + v.size
    dt_arx = max(dt_counts, key=dt_counts.get)
    is_arx = [dt == dt_arx for _, _, dt in recs]
    rows = row_subset([y.size for _, y, _ in recs], max_rows)
    y_all = np.concatenate([y[k] for (_, y, _), k in zip(recs, rows)])

    # dense design: a threshold grid on (0, max|V|) and a log-spaced time-constant grid
    n_grid = grid_factor * n_plays
    r_grid = vmax * np.arange(1, n_grid + 1) / (n_grid + 1)
    tau_grid = np.geomspace(tau_lo, tau_hi, grid_factor * creep_order) if creep_order else np.zeros(0)
    dense_raw = [_LazyDesign(v, dt, r_grid, tau_grid) for v, _, dt in recs]

    def gains(raw, omega, zeta):
        return _nnls_offset(_through(raw, recs, omega, zeta, rows), y_all)

    def compact_gains(compact_raw, taus, omega, zeta):
        """`(w, c)` of the compact design: parallel least squares, then the series gains from it."""
        coef = gains(compact_raw, omega, zeta)
        w, c = coef[: 1 + n_plays], coef[1 + n_plays :]
        if series:
            w, c = _series_gains(compact_raw, recs, rows, y_all, taus, omega, zeta, w, c, n_plays)
        return w, c

    omega = zeta = None
    for it in range(1 + (iterations if npairs else 0)):
        # 1.-2. dense non-negative fit through the current dynamics, clustered into thresholds and time constants
        dense = gains(dense_raw, omega, zeta)
        thresholds = _clusters(dense[1 : 1 + n_grid], r_grid, n_plays, min_weight_fraction, log=False)
        thresholds = _strictly_ascending(thresholds, r_grid[0])
        c_dense = dense[1 + n_grid :]
        taus = _clusters(c_dense, tau_grid, creep_order, min_weight_fraction, log=True) if creep_order else tau_grid
        # 3. the compact linear fit (parallel), then the series gains from it
        compact_raw = [_design(v, dt, thresholds, taus) for v, _, dt in recs]
        w, c = compact_gains(compact_raw, taus, omega, zeta)
        if not npairs:
            break
        # 4. the dynamics from the drive u = H[V] + C[V] (parallel) or (1 + C)[H[V]] (series): the candidate that
        # explains the displacement best
        drives = [_drive(a, dt, taus, w, c, series, n_plays) for a, (_, _, dt) in zip(compact_raw, recs)]
        pairs = [(u, y, dt) for u, (_, y, dt), ok in zip(drives, recs, is_arx) if ok]
        omega, zeta = _best_dynamics(dynamics_candidates(pairs, dynamics_order, max_rows), drives, recs, rows,
                                     y_all)
    if npairs:  # 5. final gains through the final dynamics
        w, c = compact_gains(compact_raw, taus, omega, zeta)

    return _actuator(w, c, thresholds, taus, omega, zeta, recs=recs, vmax=vmax, creep=creep if creep_order else None,
                     series=series, constrained=constrained)


def _check_orders(n_plays, creep_order, dynamics_order, structure, creep, iterations, grid_factor) -> None:
    """`cold_start_actuator`'s structural arguments checked."""
    for name, value, low in (
        ("n_plays", n_plays, 1),
        ("creep_order", creep_order, 0),
        ("dynamics_order", dynamics_order, 0),
    ):
        if not isinstance(value, int | np.integer) or isinstance(value, bool) or value < low:
            raise PiezojaxValueError(f"`{name}` must be an integer >= {low}, got {value!r}")
    if dynamics_order % 2:
        raise PiezojaxValueError(
            f"`dynamics_order` must be even (pole pairs; two real poles are an overdamped pair), got {dynamics_order}"
        )
    if structure not in ("parallel", "series"):
        raise PiezojaxValueError(f"`structure` must be 'parallel' or 'series', got {structure!r}")
    if creep not in ("kelvin_voigt", "lag"):
        raise PiezojaxValueError(f"`creep` must be 'kelvin_voigt' or 'lag', got {creep!r}")
    if creep == "lag" and structure != "series":
        raise PiezojaxValueError("`creep='lag'` is DC-normalised: it needs `structure='series'`")
    if not (isinstance(iterations, int) and iterations >= 0):
        raise PiezojaxValueError(f"`iterations` must be an integer >= 0, got {iterations!r}")
    if not (isinstance(grid_factor, int) and grid_factor >= 1):
        raise PiezojaxValueError(f"`grid_factor` must be an integer >= 1, got {grid_factor!r}")


def _actuator(w, c, thresholds, taus, omega, zeta, *, recs, vmax: float, creep: str | None, series: bool,
              constrained: bool):
    """The `pj.Actuator` of `cold_start_actuator` from its identified gains (`w`: `[w0, w_1..n]`, `c`: creep gains),
    thresholds, time constants and dynamics (`omega` None: no dynamics block; `creep` None: no creep block),
    reparametrised unless `constrained` is False."""
    creep_order, npairs = (0 if creep is None else len(taus)), omega is not None
    # strictly positive gains, so that the Positive reparametrisation can start from them; the floor is relative to
    # the data's own scale (|y| per volt), so that a fit that put no weight on the hysteresis still gives finite
    # creep stiffnesses (their inverses)
    scale = max(float(np.max(np.abs(y))) for _, y, _ in recs) / vmax
    top = max(float(np.max(w)), 1e-6 * scale, np.finfo(float).tiny)
    w0 = max(float(w[0]), 1e-3 * top)
    weights = np.maximum(w[1:], 1e-3 * top)
    if creep_order:
        # series gains are dimensionless (relative to the instantaneous response), parallel ones in output/volt
        c = np.maximum(c, 1e-3 * max(float(np.max(c)), 1e-3 * (1.0 if series else top)))

    f64 = lambda x: jnp.asarray(x, jnp.float64)  # noqa: E731
    if creep == "lag":
        # (1 + sum c_j L_j) h = (1 - sum a_j + sum a_j L_j)(1 + sum c) h with a_j = c_j / (1 + sum c)
        total = 1.0 + float(np.sum(c))
        w0, weights = w0 * total, weights * total
        creep_block = pj.LagCreep(f64(c / total), f64(taus))
    elif creep_order:
        creep_block = pj.KelvinVoigtCreep(f64(1.0 / c), f64(taus), k0=f64(1.0) if series else None)
    else:
        creep_block = None
    hyst = pj.PrandtlIshlinskii(f64(weights), f64(thresholds), w0=f64(w0))
    dyn = pj.StableTransferFunction(f64(1.0), omega=f64(omega), zeta=f64(zeta)) if npairs else None
    model = pj.Actuator(hyst, creep_block, dyn, structure="series" if series else "parallel")
    if not constrained:
        return model
    model = pj.constrain(model, lambda m: m.hysteresis.weights, pj.Positive)
    model = pj.constrain(model, lambda m: m.hysteresis.w0, pj.Positive)
    model = pj.constrain(model, lambda m: m.hysteresis.thresholds, pj.OrderedPositive)
    if creep == "lag":
        model = pj.constrain(model, lambda m: m.creep.fractions, pj.Fractions)
        model = pj.constrain(model, lambda m: m.creep.time_constants, pj.Positive)
    elif creep_order:
        model = pj.constrain(model, lambda m: m.creep.stiffnesses, pj.Positive)
        model = pj.constrain(model, lambda m: m.creep.time_constants, pj.Positive)
    if npairs:
        model = pj.constrain(model, lambda m: m.dynamics.omega, pj.Positive)
        model = pj.constrain(model, lambda m: m.dynamics.zeta, pj.Positive)
    return model


def _nnls_offset(a: np.ndarray, y: np.ndarray) -> np.ndarray:
    """`nnls_gram` with a free constant (a sensor offset, either sign) beside the non-negative columns, eliminated by
    removing every column's mean and the data's; returns the columns' coefficients."""
    return nnls_gram(a - np.mean(a, axis=0), y - np.mean(y))


def _drive(design: np.ndarray, dt: float, taus: np.ndarray, w: np.ndarray, c: np.ndarray, series: bool,
           n_plays: int) -> np.ndarray:
    """The input of the dynamics for one record: $H[V] + \\sum_j c_j L_j[V]$ (parallel) or
    $(1 + \\sum_j c_j L_j)[H[V]]$ (series), `design` its `[V, P_r[V], L_tau[V]]` columns."""
    h = design[:, : 1 + n_plays] @ w
    if not series:
        return h + design[:, 1 + n_plays :] @ c
    return h + lag_columns(h, dt, taus) @ c


def _series_gains(compact_raw, recs, rows, y_all, taus, omega, zeta, w, c, n_plays, sweeps: int = 4):
    r"""Hysteresis weights $w$ and dimensionless series creep gains $c_j$ of
    $\delta = G\big[(1 + \sum_j c_j L_{\tau_j})[H_w[V]]\big]$, bilinear in $(w, c)$: alternating non-negative
    least squares, $w$ for fixed $c$ (the columns $(1 + \sum c_j L_j)[P_{r_i}[V]]$), then $(a, a c)$ for fixed
    $w$ (the columns $H_w[V]$, $L_j[H_w[V]]$; $a$ rescales $w$). It starts from the parallel fit's
    $w$ and $c_j = c^{par}_j / g$, $g$ the chord slope of $H_w[V]$ against $V$ (the creep on $V$ read as creep on
    $H \approx g V$)."""
    hyst = [a[:, : 1 + n_plays] for a in compact_raw]
    v_all = np.concatenate([a[:, 0] for a in compact_raw])
    h_all = np.concatenate([h @ w for h in hyst])
    g = float(np.dot(v_all, h_all) / max(np.dot(v_all, v_all), np.finfo(float).tiny))
    c = np.maximum(c / g, 0.0) if g > 0 else np.full(taus.size, 0.05)
    # the lags of each design column do not change between sweeps
    lags = [[lag_columns(h[:, i], dt, taus) for i in range(h.shape[1])] for h, (_, _, dt) in zip(hyst, recs)]
    for _ in range(sweeps):
        cols = [h + np.stack([lag @ c for lag in lag_h], axis=1) for h, lag_h in zip(hyst, lags)]
        w_new = _nnls_offset(_through(cols, recs, omega, zeta, rows), y_all)
        if not np.any(w_new > 0):
            break
        w = w_new
        hs = [h @ w for h in hyst]
        cols = [np.column_stack([hh, lag_columns(hh, dt, taus)]) for hh, (_, _, dt) in zip(hs, recs)]
        coef = _nnls_offset(_through(cols, recs, omega, zeta, rows), y_all)
        if not coef[0] > 0:
            break
        w, c = w * coef[0], coef[1:] / coef[0]
    return w, c


def _best_dynamics(candidates, drives, recs, rows, y_all):
    """The candidate `(omega, zeta)` whose dynamics, applied to the drive (with a free scale and offset), leave the
    smallest residual of the displacement."""
    best, best_err = None, np.inf
    for _, omega, zeta in candidates:
        try:
            out = _through([u[:, None] for u in drives], recs, omega, zeta, rows)[:, 0]
        except (np.linalg.LinAlgError, ValueError):
            continue
        a = np.column_stack([out, np.ones_like(out)])
        coef = np.linalg.lstsq(a, y_all, rcond=None)[0]
        err = float(np.sum((y_all - a @ coef) ** 2))
        if np.isfinite(err) and err < best_err:
            best, best_err = (omega, zeta), err
    return best if best is not None else candidates[-1][1:]


def cold_start_free(model) -> list[str]:
    """The parameter paths to free when fitting a `cold_start_actuator` model: everything but the dynamics' DC
    gain (it duplicates the overall scale of hysteresis and creep) and the hysteresis smoothing."""
    paths = ["hysteresis.weights", "hysteresis.thresholds", "hysteresis.w0"]
    m = pj.unwrap(model)
    if m.creep is not None:
        paths += ["creep.stiffnesses", "creep.time_constants"]
    if m.dynamics is not None:
        paths += ["dynamics.omega", "dynamics.zeta"]
    return paths
