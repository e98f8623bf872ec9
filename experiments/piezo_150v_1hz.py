r"""Fit hysteresis + linear dynamics to a measured piezoelectric actuator (±150 V, 1 Hz sine).

Data: `experiments/data/piezo_150V_1Hz/hysteresis_v_150_1hz.csv` (A. Chandra et al., "Discovery of sparse hysteresis
models for piezoelectric materials", Appl. Phys. Lett. 2023, doi 10.1063/5.0146134; github.com/chandratue/
SmartHysteresis, MIT). 5 kHz for 10 s; the voltage is 0 until t = 3.257 s and then jumps to −87 V, the start of a
±150 V, 1 Hz sine; the displacement rings at ≈ 1 kHz for ≈ 20 ms after that jump.

Model: one `pj.Actuator` per hysteresis family, built from library blocks only (no model class of its own),

$$x = b + G(0)\,u_r + G(s)\big[u - u_r\big],\qquad u = \mathcal{L}\big[P(\mathcal{H}[v])\big],\qquad
P(h) = h + s_h\Big(a_2 \frac{h^2}{s_h^2} + a_3 \frac{h^3}{s_h^3}\Big),$$

$$\mathcal{L}(s) = (1 - \alpha) + \frac{\alpha}{\tau s + 1},\qquad
G(s) = \frac{\omega_m^2}{\omega_z^2}\frac{s^2 + 2\zeta_z\omega_z s + \omega_z^2}{s^2 + 2\zeta_m\omega_m s + \omega_m^2}
\frac{\omega^2}{s^2 + 2\zeta\omega s + \omega^2}\qquad (G(0) = 1),$$

that is `pj.Actuator(pj.OutputPolynomial(H, [a2, a3], scale=20.0), pj.LagCreep([α], [τ]),
pj.StableTransferFunction(1.0, omega=[ω_m, ω], zeta=[ζ_m, ζ], zero_omega=[ω_z], zero_zeta=[ζ_z]),
structure="series", offset=b, prehistory=u_p)` (µm and V throughout), with $u_r$ the drive's remanent value after
the prehistory (see `pj.Actuator`), and

- Prandtl–Ishlinskii: $\mathcal{H}$ = `pj.PrandtlIshlinskii` (weights, thresholds, $w_0$ > 0);
- Bouc–Wen: $\mathcal{H}$ = `pj.BoucWen` ($y = d v - z$, closed form, $n = 1$);
- Maxwell slip: $\mathcal{H}[v] = c\,v - M[v]$ with $M$ = `pj.MaxwellSlip` (stiffness, breakaway): the
  displacement follows the voltage less the voltage held by the slip elements (paper 003's $V_p = V_{in} - V_H$ with
  $x \propto V_p$, here driven by $v$ instead of the charge, which is not measured). No library block puts a linear
  term and an operator of opposite signs in one hysteresis slot, so this family uses `structure="parallel"`, whose
  drive is $\mathcal{H}[v] + \mathcal{C}[v]$: `pj.Actuator(pj.MaxwellSlip(k, f), pj.LinearCreep(
  pj.StableTransferFunction(-c)), pj.StableTransferFunction(-1.0, poles=[-1/τ], zeros=[-1/((1 - α) τ)], omega=...,
  zeta=..., zero_omega=..., zero_zeta=...), structure="parallel", ...)`: the creep slot is the static linear path
  $-c\,v$, and the dynamics (DC gain $-1$) carries the lag $\mathcal{L}$ as a real pole and zero, so
  $x = b + G\,\mathcal{L}\,[c\,v - M[v]]$. It has no output polynomial (on $M$ alone, which is all that slot could
  shape, it fitted worse). As a map $v \to c\,v - M[v]$ this is a PI operator with $w_0 = c - \sum k_i$ and weights
  $k_i$, so it is close to the PI model by construction.

Why each piece (read from the data):

- Prehistory $u_p$ and offset $b$: the sensor reads −1.68 µm at rest while the steady loop is centred at −0.07 µm,
  so the actuator is remanent at t = 0. The hysteresis starts demagnetised and is driven $0 \to u_p \to 0$ (one
  fitted scalar for its remanent state), the creep and dynamics start settled; the model then runs on the whole
  record from t = 0, so the virgin jump to −87 V and the first loading are modelled, not cut away.
- Output polynomial ($a_2$, $a_3$, $s_h$ = 20 µm): the measured loop is slightly asymmetric (peaks +19.42 µm,
  troughs −19.52 µm), which the odd-symmetric operators cannot produce.
- Lag ($\alpha$, $\tau$): the steady 1 Hz loop lags by the equivalent of ≈ 5 ms, but the step at 3.257 s reaches
  −10 µm within one sample, so a plain first-order lag is wrong at the step; a fraction $\alpha$ responding with
  time constant $\tau$ fits both.
- Low-frequency pole pair with a zero pair ("mode": $\omega_m$, $\zeta_m$, $\omega_z$, $\zeta_z$; left out with
  `--no-mode`): the stage-1 residual has a cycle-to-cycle repeatable part at the low odd harmonics of the drive.
  For PI and Bouc–Wen the fit makes it a heavily damped pair near 3 Hz ($\zeta_m$ ≈ 0.4–0.7) with its zeros ≈ 6 %
  higher: a second, slower share of the response (≈ 11 %, the high-frequency gain $\omega_m^2/\omega_z^2$ being
  ≈ 0.89) settling over tens of ms, next to the fast lag.
- Resonance ($\omega$, $\zeta$): the step at 3.257 s rings at ≈ 950 Hz for ≈ 20 ms.

Fit: three `fitting.fit` calls per family (Levenberg–Marquardt; constraints by reparametrisation: `pj.Positive`,
`pj.OrderedPositive`, `pj.Fractions`, `pj.Bounded`), each freeing parameters by path (`free_stage1`), the later ones
starting from the reparametrised result (`FitResult.params`) of the one before:

1. Hysteresis, output polynomial, lag, offset and prehistory on the training data (t < 7 s) decimated to 1 kHz
   (`--quick`: 250 Hz), without pole pairs. The decimation is anti-aliased (`decimate`): the voltage at the centre
   of each block of 5 samples and the displacement averaged over the block, the blocks aligned so that one starts
   at the voltage jump. The block mean has its first zero at 1 kHz and attenuates the ≈ 950 Hz ringing about 18×;
   every fifth sample alone would alias it to ≈ 50 Hz, and those few samples would dominate the fit. (The
   previous version of this experiment left the 30 ms after the jump out of this stage instead; `fitting.Problem`
   has no per-sample weights or masks, so the ringing is filtered out rather than left out.) Starts from data
   only: PI by `pj.pi_cold_start`; Maxwell slip by non-negative least squares of $(c, k)$ on a uniform threshold
   grid; Bouc–Wen from the loop's half-width at v = 0 ($z_{\max}$) and a linear least squares for $d$ over a few
   $A$; $u_p$ and $b$ by a small grid; $\alpha = 0.5$, $\tau = 10$ ms, $a_2 = a_3 = 0$.
2. (unless `--no-mode`) The mode added at the stage-1 residual's spectral peak in 3–40 Hz, $\zeta_m = 0.5$,
   starting cancelled by its zero pair (so the stage starts from stage 1's fit); everything of stage 1 and the
   mode, on the same data.
3. The pole pairs (and the mode's zeros) on the full-rate (5 kHz) training data from 10 ms before the jump,
   everything else fixed (v = 0 before the jump and the model starts settled, so this slice is simulated exactly
   from the model's initial state); the resonance starts at the FFT peak above 200 Hz of the residual in the 30 ms
   after the jump with $\zeta = 0.05$ (`--quick` skips this stage and keeps that start).

Evaluation on the full-rate data: the whole record is predicted from t = 0 (`fitting.predict`), train = t < 7 s
(also reported without the 30 ms after the jump), test = 7 s ≤ t ≤ 10 s. RMSE in µm and NRMSE = RMSE / (max − min
of the measured test displacement). Measured on 2 cores (test RMSE; the sensor's noise is ≈ 0.05 µm): PI 0.0579,
Bouc–Wen 0.0614, Maxwell slip 0.0626 µm in 80–110 s; with `--no-mode` 0.0621, 0.0634, 0.0629 µm in ≈ 65 s.

Run: `python -m experiments.piezo_150v_1hz [--out results/piezo_150v_1hz] [--quick] [--no-mode]`. The output
folder is written atomically and replaces only an earlier output of this experiment; Ctrl-C stops it with exit
status 130, writing nothing.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from experiments._command import existing_file, output_folder, positive_int, run, stop_if_interrupted, writing

KIND = "experiments.piezo_150v_1hz"  # what the output folder's marker records
OUT = "results/piezo_150v_1hz"
DATA = Path(__file__).resolve().parent / "data" / "piezo_150V_1Hz" / "hysteresis_v_150_1hz.csv"
T_SPLIT = 7.0  # train: t < 7 s, test: t >= 7 s
RING_WINDOW = 0.03  # s after the voltage jump: the ringing (reported apart; its spectrum starts the resonance)
POLY_SCALE = 20.0  # µm: scale of the output polynomial's argument
DECIMATE = 5  # 5 kHz -> 1 kHz for stages 1-2 (20, i.e. 250 Hz, with --quick)
FAMILIES = ("PI", "BW", "MS")


def load_data(path: Path = DATA) -> dict:
    """Read the CSV (`[empty index, t in s, displacement in µm, voltage in V]`, no header) into numpy arrays.

    **Returns:** dict with `t`, `x` (µm), `v` (V), `dt` (s, the mean step; checked uniform to 1e-6 relative) and
    `t_jump` (the first sample with nonzero voltage).
    """
    from piezojax import PiezojaxValueError

    path = Path(path)
    if not path.exists():
        raise PiezojaxValueError(f"data file not found: {path}")
    try:
        d = np.genfromtxt(path, delimiter=",")
    except ValueError as e:  # rows of different lengths
        raise PiezojaxValueError(f"{path}: not a CSV of 4 comma-separated fields per row "
                                 f"({str(e).strip().splitlines()[-1].strip()})") from None
    if d.ndim != 2 or d.shape[1] != 4 or d.shape[0] < 2:
        raise PiezojaxValueError(f"{path}: expected rows of 4 comma-separated fields, got shape {d.shape}")
    t, x, v = d[:, 1], d[:, 2], d[:, 3]
    for name, col in (("time", t), ("displacement", x), ("voltage", v)):
        if not np.all(np.isfinite(col)):
            raise PiezojaxValueError(f"{path}: column `{name}` contains NaN or infinite values")
    steps = np.diff(t)
    dt = (t[-1] - t[0]) / (len(t) - 1)
    if not dt > 0 or np.max(np.abs(steps - dt)) > 1e-3 * dt:
        raise PiezojaxValueError(f"{path}: column `time` is not uniformly sampled")
    jump = int(np.argmax(v != 0))
    return {"t": t, "x": x, "v": v, "dt": dt, "t_jump": float(t[jump])}


# ----------------------------------------------------------------------------------------------------------------
# JAX part (imported lazily so that `enable_fast_cpu_scans` runs before any JAX computation).


def _jax_modules():
    import equinox as eqx
    import jax.numpy as jnp

    import fitting
    import piezojax as pj

    return eqx, jnp, pj, fitting


def _f64(a):
    _, jnp, _, _ = _jax_modules()
    return jnp.asarray(a, jnp.float64)


def decimate(record, factor: int, t_jump: float):
    """The record at `1/factor` of its rate, anti-aliased: blocks of `factor` samples, one starting at the voltage
    jump; per block the voltage at its centre and the displacement averaged over it (a `fitting.Experiment`)."""
    _, _, _, fitting = _jax_modules()
    t, v, x = record.t, record.v_in, record["displacement"]
    first = int(np.searchsorted(t, t_jump - 1e-6 * record.dt)) % factor
    blocks = (record.n - first) // factor
    x_mean = x[first : first + blocks * factor].reshape(blocks, factor).mean(axis=1)
    centre = slice(first + factor // 2, first + blocks * factor, factor)
    return fitting.Experiment.from_arrays(
        t=t[centre], v_in=v[centre], displacement=x_mean, name=f"{record.name}, 1/{factor} rate"
    )


# ----------------------------------------------------------------------------------------------------------------
# The models, from library blocks.


def build_model(family, hysteresis, *, c=0.0, lag=(0.5, 0.01), offset=0.0, prehistory=0.0):
    r"""The `pj.Actuator` of the module docstring for one family, without pole pairs (see `with_pairs`) and with the
    output polynomial at zero.

    **Arguments:**

    - `family`: `"PI"`, `"BW"` or `"MS"`; `hysteresis`: the operator $\mathcal{H}$ (for `"MS"` the
      `pj.MaxwellSlip` $M$) and `c` the linear coefficient of `"MS"`.
    - `lag`: $(\alpha, \tau)$; `offset` $b$ [µm]; `prehistory` $u_p$ [V].
    """
    _, _, pj, _ = _jax_modules()
    f64 = _f64
    alpha, tau = lag
    if family == "MS":
        # the lag as the dynamics' real pole and zero: (1 - alpha) + alpha / (tau s + 1) = (s - z) / (s - p) p / z
        lag_tf = pj.StableTransferFunction(f64(-1.0), poles=f64([-1 / tau]), zeros=f64([-1 / ((1 - alpha) * tau)]))
        linear = pj.LinearCreep(pj.StableTransferFunction(f64(-c)))
        return pj.Actuator(hysteresis, linear, lag_tf, structure="parallel", offset=f64(offset),
                           prehistory=f64(prehistory))
    h = pj.OutputPolynomial(hysteresis, f64([0.0, 0.0]), f64(POLY_SCALE))
    return pj.Actuator(h, pj.LagCreep(f64([alpha]), f64([tau])), None, structure="series", offset=f64(offset),
                       prehistory=f64(prehistory))


def lag_of(model, family) -> tuple[float, float]:
    r"""$(\alpha, \tau)$ of a model from `build_model`."""
    if family == "MS":
        p, z = float(model.dynamics.poles[0]), float(model.dynamics.zeros[0])
        return 1 - p / z, -1 / p
    return float(model.creep.fractions[0]), float(model.creep.time_constants[0])


def constrained(model, family):
    """`model` (from `build_model`, without pole pairs) with its constrained parameters wrapped for fitting."""
    _, _, pj, _ = _jax_modules()
    c = pj.constrain
    p = model
    if family == "PI":
        p = c(p, lambda m: m.hysteresis.hysteresis.w0, pj.Positive)
        p = c(p, lambda m: m.hysteresis.hysteresis.weights, pj.Positive)
        p = c(p, lambda m: m.hysteresis.hysteresis.thresholds, pj.OrderedPositive)
    elif family == "BW":
        p = c(p, lambda m: m.hysteresis.hysteresis.A, pj.Positive)
        p = c(p, lambda m: m.hysteresis.hysteresis.beta, pj.Positive)
        p = c(p, lambda m: m.hysteresis.hysteresis.d, pj.Positive)
        # gamma stays unconstrained: the data decide its sign
    elif family == "MS":
        p = c(p, lambda m: m.hysteresis.stiffness, pj.Positive)
        p = c(p, lambda m: m.hysteresis.breakaway, pj.Positive)
    else:
        raise ValueError(f"`family` must be one of {FAMILIES}, got {family!r}")
    if family == "MS":  # the lag's pole: a time constant between 0.1 ms and 10 s
        return c(p, lambda m: m.dynamics.poles, lambda x: pj.Bounded.from_value(x, -1e4, -0.1))
    p = c(p, lambda m: m.creep.fractions, pj.Fractions)
    return c(p, lambda m: m.creep.time_constants, pj.Positive)


def with_pairs(params, family, pairs, zero_pair=None):
    """The reparametrised model `params` with the dynamics' pole pairs (and the mode's zero pair) set, their
    positive parameters wrapped; everything else, wrappers included, is kept (so a parameter that an earlier stage
    drove to the edge of its constraint, e.g. a play weight to 0, carries over as it is)."""
    eqx, _, pj, _ = _jax_modules()
    f64 = _f64
    tf = {"omega": f64([w for w, _ in pairs]), "zeta": f64([z for _, z in pairs])}
    if zero_pair is not None:
        tf.update(zero_omega=f64([zero_pair[0]]), zero_zeta=f64([zero_pair[1]]))
    if family == "MS":  # keep the lag's pole (wrapped) and zero
        old = params.dynamics
        lag = {"poles": pj.unwrap(old.poles), "zeros": old.zeros}
        dynamics = pj.StableTransferFunction(old.gain, **tf, **lag)
        dynamics = eqx.tree_at(lambda d: d.poles, dynamics, old.poles)
    else:
        dynamics = pj.StableTransferFunction(f64(1.0), **tf)
    dynamics = pj.constrain(dynamics, lambda d: d.omega, pj.Positive)
    dynamics = pj.constrain(dynamics, lambda d: d.zeta, pj.Positive)
    if zero_pair is not None:
        dynamics = pj.constrain(dynamics, lambda d: d.zero_omega, pj.Positive)
    return eqx.tree_at(lambda m: m.dynamics, params, dynamics, is_leaf=lambda x: x is None)


HYSTERESIS_PARAMETERS = {
    "PI": ("weights", "thresholds", "w0"),
    "BW": ("A", "beta", "gamma", "d"),
    "MS": ("stiffness", "breakaway"),
}


def free_stage1(family) -> list[str]:
    """Parameter paths of stage 1: hysteresis, output polynomial, lag, offset, prehistory."""
    if family == "MS":
        free = [f"hysteresis.{name}" for name in HYSTERESIS_PARAMETERS[family]]
        return free + ["offset", "prehistory", "creep.system.gain", "dynamics.poles", "dynamics.zeros"]
    free = [f"hysteresis.hysteresis.{name}" for name in HYSTERESIS_PARAMETERS[family]]
    return free + ["hysteresis.coefficients", "offset", "prehistory", "creep.fractions", "creep.time_constants"]


DYNAMICS_PAIRS = ["dynamics.omega", "dynamics.zeta"]
MODE_ZEROS = ["dynamics.zero_omega", "dynamics.zero_zeta"]


# ----------------------------------------------------------------------------------------------------------------
# Initialisation from data (no knowledge of the answer).


def _loop_features(v, x):
    """Chord slope, intercept and loop half-width at v = 0 of the steady cycles passed in."""
    a, b = np.polyfit(v, x, 1)
    dv = np.gradient(v)
    near0 = np.abs(v) < 0.05 * np.max(np.abs(v))
    up = np.mean(x[near0 & (dv > 0)])
    down = np.mean(x[near0 & (dv < 0)])
    return a, b, 0.5 * abs(down - up)


def init_pi(v, x, n_plays):
    """`pj.pi_cold_start` on the excited part of the training data, centred on the mean steady displacement."""
    _, _, pj, _ = _jax_modules()
    return pj.pi_cold_start(np.asarray(v), np.asarray(x), n_plays)


def _stop_columns(v, r):
    """Stop operator outputs $S_{r_i}[v]$ (one column per threshold), demagnetised start."""
    _, jnp, pj, _ = _jax_modules()
    return np.asarray(pj.StopOperator(jnp.asarray(r))(jnp.asarray(v)))


def init_maxwell(v, x, n_elements):
    r"""Maxwell slip $x = c v - \sum_i k_i S_{r_i}[v]$: thresholds uniform on $(0, \max|v|)$, $(c, k)$ by NNLS.

    **Returns:** `(c, pj.MaxwellSlip(k, k r))`."""
    import scipy.optimize

    _, jnp, pj, _ = _jax_modules()
    vmax = float(np.max(np.abs(v)))
    r = vmax * np.arange(1, n_elements + 1) / (n_elements + 1)
    # x = c v - S k  ->  columns [v, -S]; c >= 0 and k >= 0.
    coef, _ = scipy.optimize.nnls(np.column_stack([v, -_stop_columns(v, r)]), x)
    c, k = coef[0], coef[1:]
    k = np.maximum(k, 1e-3 * max(k.max(), 1e-9))
    return float(c), pj.MaxwellSlip(_f64(k), _f64(k * r))


def init_bouc_wen(v, x, steady):
    r"""Bouc–Wen $y = d v - z$, $n = 1$, $\beta = \gamma$: $z_{\max}$ from the loop half-width at v = 0, then for a
    few $A$ the best $d$ by linear least squares; keep the best."""
    _, jnp, pj, _ = _jax_modules()
    a, _, half = _loop_features(v[steady], x[steady])
    z_max = 1.2 * half
    vj = jnp.asarray(v)
    best = None
    for ratio in (0.1, 0.2, 0.35, 0.5, 0.7):
        A = ratio * a
        beta = A / (2 * z_max)
        z = np.asarray(pj.BoucWen(A, beta, beta, output="z")(vj))
        design = np.column_stack([v, np.ones_like(v)])
        coef = np.linalg.lstsq(design, x + z, rcond=None)[0]
        cost = float(np.sum((design @ coef - z - x) ** 2))
        if best is None or cost < best[0]:
            best = (cost, A, beta, coef[0])
    _, A, beta, d = best
    return pj.BoucWen(_f64(A), _f64(beta), _f64(beta), d=_f64(d))


def initial_model(family, low, t_jump, n):
    """Stage 1's start from the decimated training record `low`: the operator on the excited part (centred), then
    the prehistory voltage and the offset by a small grid (one compiled simulation for all candidates)."""
    _, _, _, fitting = _jax_modules()
    ts, xs, vs = low.t, low["displacement"], low.v_in
    excited = ts >= t_jump + RING_WINDOW
    centre = float(np.mean(xs[ts > t_jump + 0.8]))
    ve, xe = vs[excited], xs[excited] - centre
    c = 0.0
    if family == "PI":
        h = init_pi(ve, xe, n)
    elif family == "MS":
        c, h = init_maxwell(ve, xe, n)
    else:
        h = init_bouc_wen(ve, xe, ts[excited] > t_jump + 0.8)
    vmax = float(np.max(np.abs(vs)))
    best = None
    for u_p in vmax * np.array([-1.0, -0.7, -0.4, -0.2, 0.2, 0.4, 0.7, 1.0]):
        model = build_model(family, h, c=c, prehistory=u_p)
        y = fitting.predict(model, low)["displacement"]
        b = float(np.mean(xs - y))
        cost = float(np.mean((xs - y - b) ** 2))
        if best is None or cost < best[0]:
            best = (cost, u_p, b)
    cost, u_p, b = best
    return build_model(family, h, c=c, prehistory=u_p, offset=b), float(np.sqrt(cost))


# ----------------------------------------------------------------------------------------------------------------
# Fitting.


def run_fit(params, experiments, free, max_steps, label):
    """One `fitting.fit` of the reparametrised model `params` (displacement in µm, unit weight) over the paths
    `free`; prints the RMS before and after.

    **Returns:** `(fitted params, fitted model, info dict)`.
    """
    _, _, _, fitting = _jax_modules()
    result = fitting.fit(params, experiments, free=free, weights={"displacement": 1.0}, max_steps=max_steps,
                         progress=False)
    stop_if_interrupted(result)
    rms0 = float(np.sqrt(2 * result.initial_cost / result.num_residuals))
    rms1 = float(np.sqrt(2 * result.cost / result.num_residuals))
    verdict = "converged" if result.success else result.reason.split("(")[0].split(":")[0].strip()
    print(f"  [{label}] rms {rms0:.4f} -> {rms1:.4f} µm in {result.steps} steps, {result.seconds:.1f} s ({verdict})",
          flush=True)
    info = {"steps": result.steps, "success": result.success, "code": result.code, "rms_um": rms1,
            "seconds": result.seconds, "parameters": result.num_params}
    return result.params, result.model, info


def _peak(signal, dt, low, high, n_fft=None):
    """Frequency [Hz] of the largest FFT magnitude of `signal` within (low, high)."""
    n = len(signal) if n_fft is None else n_fft
    freqs = np.fft.rfftfreq(n, dt)
    band = (freqs > low) & (freqs < high)
    spectrum = np.abs(np.fft.rfft(signal, n))
    return float(freqs[band][np.argmax(spectrum[band])])


def fit_family(family, record, data, settings):
    """Stages 1, 2 (mode) and 3 (dynamics at full rate) of the module docstring for one hysteresis family."""
    _, _, pj, fitting = _jax_modules()
    t, x, dt, t_jump = data["t"], data["x"], data["dt"], data["t_jump"]
    t0 = time.perf_counter()
    train = record.slice(None, T_SPLIT, name="train")
    low = decimate(train, settings["decimate"], t_jump)
    print(f"{family}: initialising from data", flush=True)
    model, rms = initial_model(family, low, t_jump, settings["n_elements"])
    print(f"  [{family}] start: prehistory {float(model.prehistory):.0f} V, offset {float(model.offset):.3f} µm, "
          f"rms {rms:.4f} µm ({time.perf_counter() - t0:.1f} s)", flush=True)
    rate = f"{1 / low.dt:.0f} Hz"
    free = free_stage1(family)
    params, model, info1 = run_fit(constrained(model, family), [low], free, settings["max_steps"],
                                   f"{family} stage 1, {rate}")

    pairs, zero_pair, info2, mode_start = [], None, None, None
    if settings["mode"]:
        # the mode at the stage-1 residual's spectral peak in 3-40 Hz (steady cycles), starting cancelled by its
        # zeros (G = 1: the stage starts from stage 1's fit)
        y = fitting.predict(model, low)["displacement"]
        steady = low.t > t_jump + 0.8
        resid = (low["displacement"] - y)[steady]
        mode_start = _peak(resid * np.hanning(resid.size), low.dt, 3.0, 40.0)
        print(f"  [{family}] mode start: {mode_start:.1f} Hz (stage-1 residual peak in 3-40 Hz)", flush=True)
        w_m = 2 * np.pi * mode_start
        pairs, zero_pair = [(w_m, 0.5)], (w_m, 0.5)
        params = with_pairs(params, family, pairs, zero_pair)
        params, model, info2 = run_fit(params, [low], free + DYNAMICS_PAIRS + MODE_ZEROS, settings["max_steps"],
                                       f"{family} stage 2, +mode, {rate}")
        dyn = model.dynamics
        pairs = [(float(dyn.omega[0]), float(dyn.zeta[0]))]
        zero_pair = (float(dyn.zero_omega[0]), float(dyn.zero_zeta[0]))

    # Stage 3: the resonance from the full-rate residual just after the jump, then the dynamics at full rate
    resid = x - fitting.predict(model, record)["displacement"]
    seg = resid[(t >= t_jump) & (t < t_jump + RING_WINDOW)]
    peak = _peak(seg - seg.mean(), dt, 200.0, np.inf, n_fft=4096)
    print(f"  [{family}] resonance start: {peak:.0f} Hz (FFT peak above 200 Hz of the residual after the jump)",
          flush=True)
    params = with_pairs(params, family, pairs + [(2 * np.pi * peak, 0.05)], zero_pair)
    model, info3 = pj.unwrap(params), None
    if settings["max_steps_dynamics"] > 0:
        after = record.slice(t_jump - 0.01, T_SPLIT, name="after the jump")
        free3 = DYNAMICS_PAIRS + (MODE_ZEROS if zero_pair is not None else [])
        _, model, info3 = run_fit(params, [after], free3, settings["max_steps_dynamics"],
                                  f"{family} stage 3, dynamics, {1 / dt:.0f} Hz")
    elapsed = time.perf_counter() - t0
    print(f"  [{family}] fitted in {elapsed:.1f} s", flush=True)
    return model, {
        "stage1": info1,
        "stage2_mode": info2,
        "stage3_dynamics": info3,
        "fit_seconds": elapsed,
        "mode_start_hz": mode_start,
        "resonance_start_hz": peak,
    }


def evaluate(model, record, data):
    """Full-rate prediction from t = 0 and errors on train (t < 7 s), train without the ringing window, and test."""
    _, _, _, fitting = _jax_modules()
    t, x = data["t"], data["x"]
    pred = fitting.predict(model, record)["displacement"]
    test = t >= T_SPLIT
    train = ~test
    ring = (t >= data["t_jump"]) & (t < data["t_jump"] + RING_WINDOW)
    test_range = float(np.ptp(x[test]))
    out = {}
    for name, mask in (("train", train), ("train_no_ring", train & ~ring), ("test", test)):
        rmse = float(np.sqrt(np.mean((pred[mask] - x[mask]) ** 2)))
        out[f"{name}_rmse_um"] = rmse
        out[f"{name}_nrmse"] = rmse / test_range
    out["test_max_abs_error_um"] = float(np.max(np.abs(pred[test] - x[test])))
    return pred, out


def describe(model, family):
    """Fitted parameters as plain floats/lists for the JSON report."""
    alpha, tau = lag_of(model, family)
    dyn = model.dynamics
    has_mode = dyn.zero_omega.shape[0] > 0
    h = model.hysteresis if family == "MS" else model.hysteresis.hysteresis
    d = {
        "offset_um": float(model.offset),
        "prehistory_voltage_V": float(model.prehistory),
        "lag_time_constant_s": tau,
        "lag_fraction": alpha,
        "resonance_hz": float(dyn.omega[-1] / (2 * np.pi)),
        "resonance_zeta": float(dyn.zeta[-1]),
        "mode_hz": float(dyn.omega[0] / (2 * np.pi)) if has_mode else None,
        "mode_zeta": float(dyn.zeta[0]) if has_mode else None,
        "mode_zero_hz": float(dyn.zero_omega[0] / (2 * np.pi)) if has_mode else None,
        "mode_zero_zeta": float(dyn.zero_zeta[0]) if has_mode else None,
        "output_polynomial": None if family == "MS" else np.asarray(model.hysteresis.coefficients).tolist(),
    }
    if family == "PI":
        d.update(w0=float(h.w0), weights=np.asarray(h.weights).tolist(), thresholds_V=np.asarray(h.thresholds).tolist())
    elif family == "BW":
        d.update(A=float(h.A), beta=float(h.beta), gamma=float(h.gamma), d=float(h.d))
    else:
        d.update(c=-float(model.creep.system.gain), stiffness=np.asarray(h.stiffness).tolist(),
                 breakaway=np.asarray(h.breakaway).tolist())
    return d


def save_figures(folder, data, preds):
    """Loops (v–x, measured vs model, test cycles) and time series with residuals."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t, x, v = data["t"], data["x"], data["v"]
    test = t >= T_SPLIT
    fig, axes = plt.subplots(1, len(preds), figsize=(5 * len(preds), 4.5), squeeze=False)
    for ax, (name, pred) in zip(axes[0], preds.items()):
        ax.plot(v[test], x[test], ".", ms=1, color="0.6", label="measured (test, 7–10 s)")
        ax.plot(v[test], pred[test], "-", lw=1, color="C3", label=f"{name} model")
        ax.plot(v[t < T_SPLIT], pred[t < T_SPLIT], "-", lw=0.5, color="C0", alpha=0.6, label=f"{name} model, train")
        ax.set_xlabel("voltage (V)")
        ax.set_ylabel("displacement (µm)")
        ax.set_title(name)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(folder / "loops.png", dpi=120)
    plt.close(fig)

    fig, axes = plt.subplots(1 + len(preds), 1, figsize=(11, 2.2 * (1 + len(preds))), sharex=True)
    axes[0].plot(t, x, color="0.5", lw=0.6, label="measured")
    for i, (name, pred) in enumerate(preds.items()):
        axes[0].plot(t, pred, lw=0.6, color=f"C{i}", label=name)
        axes[i + 1].plot(t, x - pred, lw=0.4, color=f"C{i}")
        axes[i + 1].set_ylabel(f"{name} resid. (µm)")
        axes[i + 1].set_ylim(-0.5, 0.5)
        axes[i + 1].axvline(T_SPLIT, color="k", ls="--", lw=0.8)
    axes[0].axvline(T_SPLIT, color="k", ls="--", lw=0.8)
    axes[0].set_ylabel("displacement (µm)")
    axes[0].legend(fontsize=7, ncol=4)
    axes[-1].set_xlabel("time (s); dashed: train | test split")
    fig.tight_layout()
    fig.savefig(folder / "time_series.png", dpi=120)
    plt.close(fig)


def format_table(metrics):
    """A plain-text table of the errors per model."""
    head = (
        f"{'model':<6} {'train RMSE µm':>14} {'train NRMSE':>12} {'train* RMSE µm':>15} "
        f"{'test RMSE µm':>13} {'test NRMSE':>11} {'test max µm':>12}"
    )
    lines = [head, "-" * len(head)]
    for name, m in metrics.items():
        lines.append(
            f"{name:<6} {m['train_rmse_um']:>14.4f} {100 * m['train_nrmse']:>11.3f}% "
            f"{m['train_no_ring_rmse_um']:>15.4f} "
            f"{m['test_rmse_um']:>13.4f} {100 * m['test_nrmse']:>10.3f}% {m['test_max_abs_error_um']:>12.3f}"
        )
    lines.append(
        f"train: 0 <= t < {T_SPLIT} s (train*: without the {1000 * RING_WINDOW:.0f} ms after the voltage jump); "
        f"test: {T_SPLIT} <= t <= 10 s; 5 kHz; NRMSE = RMSE / range of the measured test displacement"
    )
    return "\n".join(lines)


def main(argv=None):
    """Command-line entry point; returns the metrics dict."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=OUT, help=f"output folder (default {OUT}); an earlier output of this "
                        "experiment is replaced whole, any other folder is refused")
    parser.add_argument("--data", type=existing_file, default=DATA, help="the CSV file")
    parser.add_argument("--quick", action="store_true",
                        help="5 elements, 15 steps per stage, 250 Hz, no full-rate stage: for tests")
    parser.add_argument("--n-elements", type=positive_int, default=None,
                        help="plays / slip elements (default 16, quick 5)")
    parser.add_argument("--no-mode", dest="mode", action="store_false",
                        help="leave the low-frequency mode out of G(s) (no stage 2)")
    parser.add_argument("--models", default=",".join(FAMILIES), help="comma-separated subset of PI,BW,MS")
    args = parser.parse_args(argv)
    families = [f.strip() for f in args.models.split(",") if f.strip()]
    unknown = [f for f in families if f not in FAMILIES]
    if unknown or not families:
        parser.error(f"--models: {'unknown model ' + repr(unknown[0]) if unknown else 'no model'} (choose from "
                     f"{', '.join(FAMILIES)})")

    import piezojax as pj

    pj.enable_fast_cpu_scans()
    import jax

    jax.config.update("jax_enable_x64", True)
    pj.enable_compilation_cache()  # compiled programs kept for the next run ($PIEZOJAX_CACHE_DIR)
    import fitting

    out = output_folder(args.out, KIND, default=OUT)  # before any long work
    start = time.perf_counter()
    if args.quick:
        settings = {"n_elements": 5, "max_steps": 15, "max_steps_dynamics": 0, "decimate": 20}
    else:
        settings = {"n_elements": 16, "max_steps": 200, "max_steps_dynamics": 100, "decimate": DECIMATE}
    settings["mode"] = bool(args.mode)
    if args.n_elements is not None:
        settings["n_elements"] = args.n_elements
    data = load_data(args.data)
    record = fitting.Experiment.from_arrays(v_in=data["v"], t=data["t"], displacement=data["x"], name="piezo 150 V")
    print(
        f"data: {len(data['t'])} samples, dt = {data['dt'] * 1e3:.4f} ms, voltage jump at t = {data['t_jump']:.4f} s; "
        f"settings {settings}",
        flush=True,
    )
    metrics, params, preds, infos = {}, {}, {}, {}
    for family in families:
        model, info = fit_family(family, record, data, settings)
        pred, m = evaluate(model, record, data)
        metrics[family], params[family], preds[family], infos[family] = m, describe(model, family), pred, info
        print(f"  [{family}] test RMSE {m['test_rmse_um']:.4f} µm, NRMSE {100 * m['test_nrmse']:.3f} %", flush=True)
    table = format_table(metrics)
    elapsed = time.perf_counter() - start

    report = {
        "data": str(args.data),
        "train": f"0 <= t < {T_SPLIT} s",
        "test": f"{T_SPLIT} <= t <= 10 s",
        "settings": settings,
        "quick": bool(args.quick),
        "metrics": metrics,
        "parameters": params,
        "fit_info": infos,
        "run_seconds": elapsed,
    }
    with writing(out, KIND) as tmp:
        fitting.files.save_json(tmp / "metrics.json", report)
        (tmp / "table.txt").write_text(table + "\n")
        np.savez_compressed(tmp / "predictions.npz", t=data["t"], x=data["x"], v=data["v"], **preds)
        save_figures(tmp, data, preds)
    print()
    print(table)
    print(f"\nrun time {elapsed:.1f} s; results in {out}")
    return metrics


if __name__ == "__main__":
    sys.exit(run(main, "python -m experiments.piezo_150v_1hz"))
