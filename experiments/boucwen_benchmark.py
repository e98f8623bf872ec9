r"""Grey-box identification of the Bouc–Wen hysteretic benchmark (Noël & Schoukens) from `train.h5`.

Data: `experiments/data/boucwen_benchmark/train.h5` ("Hysteretic benchmark with a dynamic nonlinearity", J.P. Noël &
M. Schoukens, 4TU.ResearchData doi 10.4121/12967592; this realisation from github.com/forgi86/dynonet, MIT). Group
`multisine`: `u` (force, N), `y` (displacement, m), `fs` = 750 Hz; 5 periods × 8192 samples of one random-phase
multisine (5–150 Hz, 50 N RMS), simulated from rest at sample 0, with measurement noise.

Model (the equations are known, the parameters are not):

$$m\ddot y + c\dot y + k y + z = u,\qquad
  \dot z = \alpha\dot y - \beta\left(\gamma|\dot y|\,|z|^{\nu-1}z + \delta\,\dot y\,|z|^{\nu}\right).$$

Parametrisation: $\theta = (\log m/m_0, \log c/c_0, \log k/k_0, \log\alpha/\alpha_0, g, d)$ with $m, c, k, \alpha > 0$
by the exponential, $\beta\gamma = \beta_0 g$ and $\beta\delta = \beta_0 d$ signed. $\beta$ only ever appears
multiplied by $\gamma$ or $\delta$, so $(\beta, \gamma, \delta)$ is not identifiable, only the two products are: $\beta$
is fixed at a positive data scale $\beta_0 = 1/\mathrm{rms}(y)$ and $(\gamma, \delta)$ carry the fit. $\nu = 1$ by
default, the usual Bouc–Wen choice (the $z$ equation is then piecewise linear in $z$, and $\nu$ trades off against
$\beta$ over the range of $|z|$ the data visit); `--free-nu` adds $\log\nu$ as a seventh parameter (start 1) in a
third stage. Measured: it moves $\nu$ to 0.99999996 in 2 LM steps and leaves every RMSE unchanged to 4 digits.
$|z|^\nu$ uses `safe_abs_pow` (finite derivatives at $z = 0$).

Which samples (0-based, period $p$ = samples $8192p \dots 8192p + 8191$):

- fit: periods 1–3 (samples 8192–32767). The input is periodic and the system is in its periodic steady state after
  period 0 (the transient from rest at sample 0 decays as $e^{-c t / 2m}$ and faster), so the least-squares cost over
  the three periods equals, up to a constant, three times the cost against their average $\bar y$; the fit uses
  $\bar y$ (8192 residuals instead of 24576).
- validation: period 4 (samples 32768–40959), never used in the fit. It has the same input as the fitted periods and
  differs only by its noise, so its floor is the noise level; the synthetic sine sweep (`--make-test`) checks a
  different input.
- reported train/validation RMSE: one simulation from rest at sample 0 through all 5 periods, scored on the
  samples above (period 0, the start-up transient, is reported too).
- noise level: RMS of (period 2 − period 3) / √2, 7.46e-6 m; an RMSE at that level is all a model can reach.

Initialisation (no nominal values): (1) a linear model $m\ddot y + c\dot y + k_\ell y = u$ by least squares in the
frequency domain on the excited bins of $\bar y$ and $u$ ($\hat U = (k_\ell - m\omega^2 + jc\omega)\bar Y$, i.e.
derivatives of the band-limited interpolant); (2) the linear stiffness is split between $k$ and $\alpha$, the
hysteresis scale $\beta_0\gamma$ is of the order $1/\mathrm{rms}(y)$ (where $\beta|z| \approx \alpha$, the loop
bends), $\delta = 0$, and the viscous damping is a fraction of $c_\ell$ (the linear fit lumps the hysteretic
dissipation into $c$): a grid of 3 × 3 × 2 such guesses is simulated and the one with the smallest stage-1 cost kept.

Fit: optimistix Levenberg–Marquardt on the output (simulation) error, Jacobians by `jax.jacfwd`.

1. stage 1: RK4 with 4 sub-steps per sample, from rest 2048 samples before period 1, scored on its first 4096
   samples (against $\bar y$);
2. stage 2: RK4 with 8 sub-steps, from rest at sample 0 (one whole period of warm-up, as the data), scored on the
   whole steady period against $\bar y$.

`--quick` (tests): stage 1 from rest 1024 samples before period 1, scored on 2048; stage 2 with 4 sub-steps and at
most 8 LM steps; the evaluation then also uses 4 sub-steps.

Simulator: `piezojax._nonlinear.fixed_step` (classical RK4 in one `lax.scan`, the input at the stage times from the
band-limited periodic interpolant of the multisine period; `periodic=False` zero-pads a transient record first).
Checked against `pj.BoucWenOscillator.simulate(..., hold="periodic")` (diffrax Tsit5, adaptive) at the nominal
parameters: on the first 3000 train samples (`rtol=1e-11`) max / RMS difference 1.6e-6 / 2.6e-7 m with 4 sub-steps,
2.7e-7 / 6.1e-8 m with 8; on a steady synthetic multisine period (`rtol=1e-8`) 1.4e-6 / 2.7e-7 m (4), 5.9e-7 /
7.3e-8 m (8), 1.3e-7 / 1.6e-8 m (16): about second order, because the vector field has kinks at $\dot y = 0$ and
$z = 0$. The data noise is 7.3e-6 m RMS. One Jacobian (6 parameters, 16384 samples) takes 0.06 s with 4 sub-steps
and 0.15 s with 8 (2-core CPU); most of the fit's time is compiling the optimistix solves (~10 s each).

`--test PATH` (HDF5, groups `multisine` and/or `sinesweep`, each with `u`, `y` and optionally `fs`):
`multisine` is one steady-state period, simulated from rest for `--ms-periods` periods (default 3) and scored on the
last; `sinesweep` is simulated from rest (zero-padded band-limited input). RMSE = $\sqrt{\mathrm{mean}((\hat y -
y)^2)}$ in m, printed and saved as `{"multisine_rmse": .., "sinesweep_rmse": ..}` in `test_rmse.json` (null for a
missing group). `--make-test PATH` writes a synthetic test file in that layout: a new random-phase multisine period
(5–150 Hz, 50 N RMS) and a tapered 40 N linear sine sweep (5–150 Hz), simulated with the nominal benchmark
parameters by diffrax (adaptive Tsit5, `rtol=1e-8`, a different integrator from the fit's), plus Gaussian noise; the
noise-free outputs are stored as `y_clean`. The official files were made differently (the benchmark's MATLAB
example: Newmark integration at 20 × 750 Hz, then FIR decimation of y), so scores on them also contain that
difference; on `train.h5` it is below the noise (the nominal model leaves 7.36e-6 m against 7.46e-6 m noise).

Run: `python -m experiments.boucwen_benchmark [--test PATH] [--out results/boucwen_benchmark] [--quick]`.
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parent / "data" / "boucwen_benchmark" / "train.h5"
PERIOD = 8192
FIT_PERIODS = (1, 2, 3)  # 0-based; samples 8192..32767
VAL_PERIOD = 4  # samples 32768..40959
NOMINAL = {"m": 2.0, "c": 10.0, "k": 5e4, "alpha": 5e4, "beta": 1e3, "gamma": 0.8, "delta": -1.1, "nu": 1.0}
NOISE_DEFAULT = 7.3e-6  # m, the train data's noise level (RMS of half the period-to-period difference)


class BenchmarkFileError(ValueError):
    """A data or test file that does not have the benchmark layout."""


# ----------------------------------------------------------------------------------------------------------------
# Files.


def read_group(path, group: str, required: bool = True) -> dict | None:
    """Read `group/u`, `group/y` (and `group/fs` if present) of an HDF5 file as 1-D float64 arrays.

    **Returns:** dict with `u`, `y`, `fs` (None if absent) and `y_clean` (if present), or None when the group is
    absent and not `required`. Raises `BenchmarkFileError` with a one-line message otherwise.
    """
    import h5py

    path = Path(path)
    if not path.is_file():
        raise BenchmarkFileError(f"{path}: file not found")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise BenchmarkFileError(f"{path}: not a readable HDF5 file ({e})") from None
    with f:
        if group not in f:
            if required:
                raise BenchmarkFileError(f"{path}: no group '{group}' (found: {sorted(f.keys())})")
            return None
        g = f[group]
        out = {}
        for name in ("u", "y"):
            if name not in g:
                raise BenchmarkFileError(f"{path}: group '{group}' has no dataset '{name}' (found: {sorted(g.keys())})")
            out[name] = np.asarray(g[name], dtype=np.float64).ravel()
        out["fs"] = float(np.asarray(g["fs"]).ravel()[0]) if "fs" in g else None
        if "y_clean" in g:
            out["y_clean"] = np.asarray(g["y_clean"], dtype=np.float64).ravel()
    n = out["u"].shape[0]
    if n == 0:
        raise BenchmarkFileError(f"{path}: '{group}/u' is empty")
    for name in ("y", "y_clean"):
        if name in out and out[name].shape[0] != n:
            raise BenchmarkFileError(
                f"{path}: '{group}/{name}' has {out[name].shape[0]} samples but '{group}/u' has {n}"
            )
    for name in ("u", "y", "y_clean"):
        if name in out and not np.all(np.isfinite(out[name])):
            raise BenchmarkFileError(f"{path}: '{group}/{name}' contains NaN or infinite values")
    if out["fs"] is not None and not (np.isfinite(out["fs"]) and out["fs"] > 0):
        raise BenchmarkFileError(f"{path}: '{group}/fs' must be a positive number, got {out['fs']}")
    return out


def load_train(path=DATA) -> dict:
    """The training record: `u`, `y` (5 × 8192 samples) and `fs`."""
    d = read_group(path, "multisine")
    if d["u"].shape[0] != 5 * PERIOD:
        raise BenchmarkFileError(f"{path}: expected 5 x {PERIOD} samples in 'multisine', got {d['u'].shape[0]}")
    if d["fs"] is None:
        raise BenchmarkFileError(f"{path}: group 'multisine' has no dataset 'fs'")
    return d


def load_test(path) -> dict:
    """The `multisine` and `sinesweep` groups of a test file (each optional, at least one required)."""
    out = {g: read_group(path, g, required=False) for g in ("multisine", "sinesweep")}
    if out["multisine"] is None and out["sinesweep"] is None:
        import h5py

        with h5py.File(path, "r") as f:
            found = sorted(f.keys())
        raise BenchmarkFileError(f"{path}: neither group 'multisine' nor 'sinesweep' found (found: {found})")
    return out


def noise_level(y: np.ndarray) -> float:
    """Noise RMS from two steady periods with the same input: RMS of their difference / sqrt(2) (periods 2, 3)."""
    a, b = y[2 * PERIOD : 3 * PERIOD], y[3 * PERIOD : 4 * PERIOD]
    return float(np.sqrt(np.mean((a - b) ** 2) / 2))


# ----------------------------------------------------------------------------------------------------------------
# Linear initialisation (numpy only).


def linear_fit(u: np.ndarray, y: np.ndarray, fs: float) -> dict:
    r"""$m\ddot y + c\dot y + k y = u$ by least squares on the excited frequency bins of one period.

    $U_\ell = (k - m\omega_\ell^2 + j c\,\omega_\ell) Y_\ell$ for the bins where $|U_\ell| > 10^{-3}\max|U|$,
    real and imaginary parts stacked.

    **Returns:** dict with `m`, `c`, `k`, the natural frequency `f_n` (Hz) and the excited band (Hz).
    """
    n = u.shape[0]
    U, Y = np.fft.rfft(u), np.fft.rfft(y)
    freqs = np.fft.rfftfreq(n, 1 / fs)
    exc = np.abs(U) > 1e-3 * np.abs(U).max()
    exc[0] = False
    w, Ue, Ye = 2 * np.pi * freqs[exc], U[exc], Y[exc]
    a = np.concatenate(
        [
            np.column_stack([-(w**2) * Ye.real, -w * Ye.imag, Ye.real]),
            np.column_stack([-(w**2) * Ye.imag, w * Ye.real, Ye.imag]),
        ]
    )
    b = np.concatenate([Ue.real, Ue.imag])
    m, c, k = np.linalg.lstsq(a, b, rcond=None)[0]
    return {
        "m": float(m),
        "c": float(c),
        "k": float(k),
        "f_n": float(np.sqrt(abs(k / m)) / (2 * np.pi)),
        "band_hz": [float(freqs[exc].min()), float(freqs[exc].max())],
    }


# ----------------------------------------------------------------------------------------------------------------
# JAX part (imported lazily so that `enable_fast_cpu_scans` runs before any JAX computation).


def _jax():
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import optimistix as optx

    import piezojax as pj

    return eqx, jax, jnp, optx, pj


class Parametrisation:
    r"""$\theta \mapsto$ `pj.BoucWenOscillator`: log-multipliers of $m, c, k, \alpha$ about a start, $\beta$ fixed at
    `beta0`, $\gamma = \theta_4$, $\delta = \theta_5$, $\nu = e^{\theta_6}$ if `free_nu` else 1."""

    def __init__(self, m0, c0, k0, a0, beta0, free_nu=False):
        self.scale = np.array([m0, c0, k0, a0], dtype=np.float64)
        self.beta0 = float(beta0)
        self.free_nu = free_nu

    def model(self, theta):
        eqx, jax, jnp, optx, pj = _jax()
        pos = jnp.asarray(self.scale) * jnp.exp(theta[:4])
        nu = jnp.exp(theta[6]) if self.free_nu else jnp.ones((), theta.dtype)
        return pj.BoucWenOscillator(
            m=pos[0], c=pos[1], k=pos[2], alpha=pos[3], beta=jnp.asarray(self.beta0, theta.dtype),
            gamma=theta[4], delta=theta[5], nu=nu,
        )

    def values(self, theta) -> dict:
        """Physical values as floats (with the identifiable products beta*gamma and beta*delta)."""
        theta = np.asarray(theta, dtype=np.float64)
        pos = self.scale * np.exp(theta[:4])
        d = {"m": pos[0], "c": pos[1], "k": pos[2], "alpha": pos[3], "beta": self.beta0, "gamma": theta[4],
             "delta": theta[5], "nu": float(np.exp(theta[6])) if self.free_nu else 1.0}
        d["beta*gamma"] = self.beta0 * theta[4]
        d["beta*delta"] = self.beta0 * theta[5]
        return {k: float(v) for k, v in d.items()}

    def with_free_nu(self, theta):
        """The same model with nu free (start 1): a new parametrisation and theta."""
        eqx, jax, jnp, optx, pj = _jax()
        p = Parametrisation(*self.scale, self.beta0, free_nu=True)
        th = jnp.concatenate([theta[:6], jnp.zeros(1, theta.dtype)])
        return p, th


def _vector_field(x, u_t, model):
    return model.vector_field(None, x, u_t)


def simulate(model, table, dt, repeat=1, start=None):
    """Displacement from rest over `repeat` passes of the stage-input table (optionally from row `start`)."""
    eqx, jax, jnp, optx, pj = _jax()
    from piezojax._nonlinear.fixed_step import rk4_scan

    if start is not None:
        table = table[start]
    _, states = rk4_scan(_vector_field, jnp.zeros(3, table.dtype), table, dt, model, repeat=repeat)
    return states[:, 0]


def lm_fit(residuals, theta, max_steps, label, tol=1e-7):
    """optimistix Levenberg–Marquardt (forward-mode Jacobians); prints the RMS residual before and after."""
    eqx, jax, jnp, optx, pj = _jax()
    res = jax.jit(residuals)
    r0 = np.asarray(res(theta))
    t0 = time.perf_counter()
    solver = optx.LevenbergMarquardt(rtol=tol, atol=tol)
    sol = optx.least_squares(lambda th, _: res(th), solver, theta, max_steps=max_steps, throw=False)
    r1 = np.asarray(res(sol.value))
    steps = int(sol.stats["num_steps"])
    ok = bool(sol.result == optx.RESULTS.successful)
    elapsed = time.perf_counter() - t0
    print(
        f"  [{label}] LM: RMS residual {np.sqrt(np.mean(r0**2)):.3e} -> {np.sqrt(np.mean(r1**2)):.3e} m in "
        f"{steps} steps, {elapsed:.1f} s ({'converged' if ok else 'stopped at max_steps or failed'})",
        flush=True,
    )
    return sol.value, {"lm_steps": steps, "converged": ok, "seconds": elapsed,
                       "rms_before": float(np.sqrt(np.mean(r0**2))), "rms_after": float(np.sqrt(np.mean(r1**2)))}


def fit(data: dict, settings: dict) -> tuple:
    """Linear start, grid of hysteresis guesses, LM stage 1 (short window) and stage 2 (whole period)."""
    eqx, jax, jnp, optx, pj = _jax()
    from piezojax._nonlinear.fixed_step import stage_inputs

    u, y, fs = data["u"], data["y"], data["fs"]
    dt = 1.0 / fs
    u_period = u[:PERIOD]
    y_avg = np.mean([y[p * PERIOD : (p + 1) * PERIOD] for p in FIT_PERIODS], axis=0)
    info = {}
    t0 = time.perf_counter()
    lin = linear_fit(u_period, y_avg, fs)
    info["linear"] = lin
    print(
        f"linear start (frequency-domain LS on {lin['band_hz'][0]:.1f}-{lin['band_hz'][1]:.1f} Hz): "
        f"m = {lin['m']:.4g} kg, c = {lin['c']:.4g} N s/m, k = {lin['k']:.4g} N/m, f_n = {lin['f_n']:.2f} Hz",
        flush=True,
    )
    m_l, c_l, k_l = abs(lin["m"]), abs(lin["c"]), abs(lin["k"])
    y_rms = float(np.sqrt(np.mean(y_avg**2)))
    beta0 = 1.0 / y_rms
    par = Parametrisation(m_l, c_l, k_l / 2, k_l / 2, beta0)

    uj = jnp.asarray(u_period)
    yj = jnp.asarray(y_avg)
    # Stage 1: from rest `warm1` samples before the period start, scored on the first `win1` samples.
    s1, warm1, win1 = settings["substeps1"], settings["warm1"], settings["win1"]
    table1 = stage_inputs(uj, dt, s1)
    rows1 = jnp.asarray(np.arange(-warm1, win1) % PERIOD)

    def resid1(theta):
        yhat = simulate(par.model(theta), table1, dt, start=rows1)[warm1:]
        r = yhat - yj[:win1]
        return jnp.where(jnp.isfinite(r), r, 1.0)

    # Grid of physics-free guesses: split of the linear stiffness, hysteresis scale, viscous fraction.
    cost1 = jax.jit(lambda th: jnp.sqrt(jnp.mean(resid1(th) ** 2)))
    best = None
    for split in (0.25, 0.5, 0.75):
        for scale in (0.3, 1.0, 3.0):
            for cfrac in (0.1, 0.5):
                th = jnp.array([0.0, np.log(cfrac), np.log(2 * (1 - split)), np.log(2 * split), scale, 0.0])
                cst = float(cost1(th))
                if np.isfinite(cst) and (best is None or cst < best[0]):
                    best = (cst, th, (split, scale, cfrac))
    theta = best[1]
    info["grid_best"] = {"alpha_fraction_of_k_lin": best[2][0], "beta_gamma_times_rms_y": best[2][1],
                         "c_fraction_of_c_lin": best[2][2], "rms": best[0]}
    print(
        f"  start: alpha = {best[2][0]:.2f} k_lin, beta*gamma = {best[2][1]:.1f}/rms(y), c = {best[2][2]:.1f} c_lin, "
        f"delta = 0; stage-1 RMS {best[0]:.3e} m ({time.perf_counter() - t0:.1f} s)",
        flush=True,
    )
    info["start"] = par.values(theta)
    theta, info["stage1"] = lm_fit(resid1, theta, settings["steps1"],
                                   f"stage 1: RK4 x{s1}, warm-up {warm1}, window {win1}")

    # Stage 2: from rest at sample 0, one period of warm-up, the whole steady period scored.
    s2 = settings["substeps2"]
    table2 = stage_inputs(uj, dt, s2)

    def make_resid2(p):
        def resid2(theta):
            r = simulate(p.model(theta), table2, dt, repeat=2)[PERIOD:] - yj
            return jnp.where(jnp.isfinite(r), r, 1.0)
        return resid2

    theta, info["stage2"] = lm_fit(make_resid2(par), theta, settings["steps2"],
                                   f"stage 2: RK4 x{s2}, from rest at sample 0, period 1-3 average")
    if settings["free_nu"]:
        par, theta = par.with_free_nu(theta)
        theta, info["stage3_free_nu"] = lm_fit(make_resid2(par), theta, settings["steps2"], "stage 3: nu free")
    info["fit_seconds"] = time.perf_counter() - t0
    return par, theta, table2, info


# ----------------------------------------------------------------------------------------------------------------
# Evaluation.


def rmse(a, b) -> float:
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


def evaluate_train(model, data, substeps):
    """One simulation from rest through the 5 periods; RMSE on period 0, the fit periods and the validation period."""
    eqx, jax, jnp, optx, pj = _jax()
    from piezojax._nonlinear.fixed_step import stage_inputs

    dt = 1.0 / data["fs"]
    table = stage_inputs(jnp.asarray(data["u"][:PERIOD]), dt, substeps)
    pred = np.asarray(jax.jit(simulate, static_argnums=(2, 3))(model, table, dt, 5))
    y = data["y"]
    fit_sl = slice(FIT_PERIODS[0] * PERIOD, (FIT_PERIODS[-1] + 1) * PERIOD)
    val_sl = slice(VAL_PERIOD * PERIOD, (VAL_PERIOD + 1) * PERIOD)
    return pred, {
        "period0_transient_rmse": rmse(pred[:PERIOD], y[:PERIOD]),
        "train_rmse": rmse(pred[fit_sl], y[fit_sl]),
        "validation_rmse": rmse(pred[val_sl], y[val_sl]),
        "train_samples": f"{fit_sl.start}..{fit_sl.stop - 1}",
        "validation_samples": f"{val_sl.start}..{val_sl.stop - 1}",
    }


def simulate_multisine(model, u, fs, substeps, periods):
    """Steady-state response to a periodic input: `periods` periods from rest; the last one, and the RMS change
    from the one before (how far transients have died)."""
    eqx, jax, jnp, optx, pj = _jax()
    from piezojax._nonlinear.fixed_step import stage_inputs

    n = u.shape[0]
    table = stage_inputs(jnp.asarray(u), 1.0 / fs, substeps)
    y = np.asarray(jax.jit(simulate, static_argnums=(2, 3))(model, table, 1.0 / fs, periods))
    return y[-n:], rmse(y[-n:], y[-2 * n : -n]) if periods > 1 else float("nan")


def simulate_transient(model, u, fs, substeps):
    """Response from rest to a non-periodic record (band-limited interpolant of the zero-padded samples)."""
    eqx, jax, jnp, optx, pj = _jax()
    from piezojax._nonlinear.fixed_step import stage_inputs

    table = stage_inputs(jnp.asarray(u), 1.0 / fs, substeps, periodic=False)
    return np.asarray(jax.jit(simulate, static_argnums=(2, 3))(model, table, 1.0 / fs, 1))


def evaluate_test(model, test, fs_default, substeps, ms_periods):
    """RMSE on the groups of a test file; also against `y_clean` where the file has it."""
    scores, extra, preds = {"multisine_rmse": None, "sinesweep_rmse": None}, {}, {}
    g = test["multisine"]
    if g is not None:
        fs = g["fs"] or fs_default
        pred, settle = simulate_multisine(model, g["u"], fs, substeps, ms_periods)
        scores["multisine_rmse"] = rmse(pred, g["y"])
        extra["multisine_last_period_change_rms"] = settle
        if "y_clean" in g:
            extra["multisine_rmse_vs_clean"] = rmse(pred, g["y_clean"])
        preds["multisine"] = pred
    g = test["sinesweep"]
    if g is not None:
        fs = g["fs"] or fs_default
        pred = simulate_transient(model, g["u"], fs, substeps)
        scores["sinesweep_rmse"] = rmse(pred, g["y"])
        if "y_clean" in g:
            extra["sinesweep_rmse_vs_clean"] = rmse(pred, g["y_clean"])
        preds["sinesweep"] = pred
    return scores, extra, preds


# ----------------------------------------------------------------------------------------------------------------
# Synthetic test file.


def multisine_period(n, fs, f_lo=5.0, f_hi=150.0, rms=50.0, seed=0):
    """One period of a random-phase multisine with flat amplitude on the bins in [f_lo, f_hi] (as the benchmark's)."""
    rng = np.random.default_rng(seed)
    spec = np.zeros(n // 2 + 1, dtype=complex)
    freqs = np.fft.rfftfreq(n, 1 / fs)
    lines = (freqs >= f_lo) & (freqs <= f_hi)
    spec[lines] = np.exp(2j * np.pi * rng.random(lines.sum()))
    u = np.fft.irfft(spec, n)
    return rms * u / np.std(u)


def sine_sweep(n, fs, f_lo=5.0, f_hi=150.0, amplitude=40.0, taper_s=0.5):
    """Linear sine sweep from f_lo to f_hi over n samples, with half-cosine fade in/out of `taper_s` seconds."""
    t = np.arange(n) / fs
    duration = n / fs
    phase = 2 * np.pi * (f_lo * t + (f_hi - f_lo) * t**2 / (2 * duration))
    w = np.ones(n)
    nt = min(int(taper_s * fs), n // 2)
    ramp = 0.5 * (1 - np.cos(np.pi * np.arange(nt) / nt))
    w[:nt], w[n - nt :] = ramp, ramp[::-1]
    return amplitude * w * np.sin(phase)


def make_synthetic_test(path, *, fs=750.0, sweep_samples=20000, noise=NOISE_DEFAULT, seed=1, rtol=1e-8):
    """Write a test file in the benchmark layout from the nominal parameters (see the module docstring).

    **Returns:** dict with the noise-free outputs' RMS and the generation time.
    """
    import h5py

    eqx, jax, jnp, optx, pj = _jax()
    from fitting._io import atomic_file

    t0 = time.perf_counter()
    dt = 1.0 / fs
    bw = pj.BoucWenOscillator(**NOMINAL)
    rng = np.random.default_rng(seed + 1000)
    u_ms = multisine_period(PERIOD, fs, seed=seed)
    # two periods from rest (the interpolant of the doubled record is the same periodic signal); keep the second
    y2 = bw.simulate(jnp.asarray(np.tile(u_ms, 2)), dt, hold="periodic", rtol=rtol)
    y_ms = np.asarray(y2)[PERIOD:]
    u_sw = sine_sweep(sweep_samples, fs)
    pad = max(1024, sweep_samples // 8)  # the same zero padding as the scoring simulator's default
    u_pad = jnp.asarray(np.concatenate([u_sw, np.zeros(pad)]))
    y_sw = np.asarray(bw.simulate(u_pad, dt, hold="periodic", rtol=rtol, num_samples=sweep_samples))
    with atomic_file(path) as tmp, h5py.File(tmp, "w") as f:
        for name, uu, yy in (("multisine", u_ms, y_ms), ("sinesweep", u_sw, y_sw)):
            g = f.create_group(name)
            g["u"] = uu[:, None]
            g["y"] = (yy + noise * rng.standard_normal(yy.shape))[:, None]
            g["y_clean"] = yy[:, None]
            g["fs"] = np.array([fs])
        f.attrs["source"] = "synthetic: nominal Bouc-Wen benchmark parameters, diffrax Tsit5 adaptive, plus noise"
        f.attrs["noise_rms_m"] = noise
    return {"seconds": time.perf_counter() - t0, "multisine_y_rms": float(np.std(y_ms)),
            "sinesweep_y_rms": float(np.std(y_sw))}


# ----------------------------------------------------------------------------------------------------------------
# Output.


def save_figure(path, data, pred, test=None, test_preds=None):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fitting._io import atomic_file

    fs = data["fs"]
    sl = slice(VAL_PERIOD * PERIOD, (VAL_PERIOD + 1) * PERIOD)
    t = np.arange(sl.start, sl.stop) / fs
    rows = 2 + (2 if test_preds else 0)
    fig, axes = plt.subplots(rows, 1, figsize=(11, 2.4 * rows))
    zoom = slice(0, int(2 * fs))  # the first 2 s, where the curves can be told apart
    axes[0].plot(t[zoom], 1e3 * data["y"][sl][zoom], ".", ms=2.5, color="0.3", label="data (validation period 4)")
    axes[0].plot(t[zoom], 1e3 * pred[sl][zoom], color="C3", lw=0.7, label="model (simulated from rest at t = 0)")
    axes[0].set_ylabel("y (mm), first 2 s")
    axes[0].legend(fontsize=7, loc="upper right")
    axes[1].plot(t, 1e6 * (data["y"][sl] - pred[sl]), color="C0", lw=0.4)
    axes[1].set_ylabel("validation\nresidual (µm)")
    axes[1].set_xlabel("time (s)")
    if test_preds:
        i = 2
        for name in ("multisine", "sinesweep"):
            if name not in test_preds:
                continue
            g = test[name]
            tt = np.arange(g["u"].shape[0]) / (g["fs"] or fs)
            axes[i].plot(tt, 1e6 * (g["y"] - test_preds[name]), color="C2", lw=0.4)
            axes[i].set_ylabel(f"{name}\nresidual (µm)")
            i += 1
        axes[-1].set_xlabel("time (s)")
    fig.tight_layout()
    with atomic_file(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def write_json(path, obj):
    from fitting._io import atomic_write_bytes

    atomic_write_bytes(path, (json.dumps(obj, indent=2) + "\n").encode())


def format_parameters(start: dict, fitted: dict) -> str:
    lines = [f"{'parameter':<11} {'start':>12} {'fitted':>12} {'nominal':>12}"]
    nominal = dict(NOMINAL)
    nominal["beta*gamma"] = NOMINAL["beta"] * NOMINAL["gamma"]
    nominal["beta*delta"] = NOMINAL["beta"] * NOMINAL["delta"]
    for name in ("m", "c", "k", "alpha", "beta*gamma", "beta*delta", "nu"):
        lines.append(f"{name:<11} {start[name]:>12.5g} {fitted[name]:>12.5g} {nominal[name]:>12.5g}")
    lines.append("(beta alone is not identifiable: only beta*gamma and beta*delta enter the equations; "
                 "nominal values for information only, never used)")
    return "\n".join(lines)


def main(argv=None):
    """Command-line entry point; returns the report dict."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(DATA), help="train.h5 of the benchmark")
    parser.add_argument("--test", default=None, help="test file (HDF5 groups multisine and/or sinesweep)")
    parser.add_argument("--out", default="results/boucwen_benchmark", help="output folder")
    parser.add_argument("--quick", action="store_true", help="fewer LM steps and 4 RK4 sub-steps (tests)")
    parser.add_argument("--free-nu", action="store_true", help="also fit nu (stage 3)")
    parser.add_argument("--ms-periods", type=int, default=3, help="periods simulated for the multisine test")
    parser.add_argument("--make-test", default=None, metavar="PATH",
                        help="write a synthetic test file (nominal parameters + noise) to PATH and exit")
    parser.add_argument("--sweep-samples", type=int, default=20000, help="sine sweep length for --make-test")
    parser.add_argument("--noise", type=float, default=NOISE_DEFAULT, help="noise RMS (m) for --make-test")
    args = parser.parse_args(argv)
    if args.ms_periods < 2:
        raise SystemExit("error: --ms-periods must be at least 2")

    import piezojax as pj

    pj.enable_fast_cpu_scans()
    import jax

    jax.config.update("jax_enable_x64", True)
    start = time.perf_counter()

    if args.make_test is not None:
        out = make_synthetic_test(args.make_test, sweep_samples=args.sweep_samples, noise=args.noise)
        print(f"wrote {args.make_test}: multisine period {PERIOD} samples, sine sweep {args.sweep_samples} samples, "
              f"noise {args.noise:.2e} m ({out['seconds']:.1f} s)")
        return out

    try:
        test = load_test(args.test) if args.test is not None else None
        data = load_train(args.data)
    except BenchmarkFileError as e:
        raise SystemExit(f"error: {e}") from None

    if args.quick:
        settings = {"substeps1": 4, "warm1": 1024, "win1": 2048, "steps1": 60, "substeps2": 4, "steps2": 8}
    else:
        settings = {"substeps1": 4, "warm1": 2048, "win1": 4096, "steps1": 60, "substeps2": 8, "steps2": 40}
    settings["free_nu"] = bool(args.free_nu)
    noise = noise_level(data["y"])
    print(f"train.h5: {data['u'].shape[0]} samples at {data['fs']:.0f} Hz; noise level {noise:.3e} m "
          f"(periods 2 vs 3); settings {settings}", flush=True)

    par, theta, _, info = fit(data, settings)
    fitted = par.values(theta)
    model = par.model(jax.numpy.asarray(theta))
    pred, metrics = evaluate_train(model, data, settings["substeps2"])
    metrics["noise_level"] = noise
    print(f"\ntrain RMSE (samples {metrics['train_samples']}): {metrics['train_rmse']:.4e} m")
    print(f"validation RMSE (samples {metrics['validation_samples']}): {metrics['validation_rmse']:.4e} m")
    print(f"period 0 (start-up transient from rest): {metrics['period0_transient_rmse']:.4e} m; "
          f"noise level {noise:.4e} m")
    table = format_parameters(info["start"], fitted)
    print("\n" + table)

    scores, extra, test_preds = None, {}, {}
    if test is not None:
        scores, extra, test_preds = evaluate_test(model, test, data["fs"], settings["substeps2"], args.ms_periods)
        print(f"\ntest file {args.test}:")
        for key, val in scores.items():
            print(f"  {key}: {'absent' if val is None else f'{val:.4e} m'}")
        for key, val in extra.items():
            print(f"  ({key}: {val:.4e} m)")
    elapsed = time.perf_counter() - start

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    report = {
        "data": str(args.data),
        "fit_samples": "periods 1-3 (samples 8192..32767), averaged into one steady period",
        "validation_samples": metrics["validation_samples"],
        "quick": bool(args.quick),
        "settings": settings,
        "metrics": metrics,
        "parameters": fitted,
        "nominal_parameters_for_information": NOMINAL,
        "fit_info": info,
        "test_file": args.test,
        "test": scores,
        "test_extra": extra,
        "run_seconds": elapsed,
    }
    write_json(out / "metrics.json", report)
    if scores is not None:
        write_json(out / "test_rmse.json", scores)
    save_figure(out / "validation.png", data, pred, test, test_preds)
    print(f"\nrun time {elapsed:.1f} s; results in {out}")
    return report


if __name__ == "__main__":
    main(sys.argv[1:])
