r"""Grey-box identification of the Bouc–Wen hysteretic benchmark (Noël & Schoukens) from `train.h5`.

Data: `experiments/data/boucwen_benchmark/train.h5` ("Hysteretic benchmark with a dynamic nonlinearity", J.P. Noël &
M. Schoukens, 4TU.ResearchData doi 10.4121/12967592; this realisation from github.com/forgi86/dynonet, MIT). Group
`multisine`: `u` (force, N), `y` (displacement, m), `fs` = 750 Hz; 5 periods × 8192 samples of one random-phase
multisine (5–150 Hz, 50 N RMS), simulated from rest at sample 0, with measurement noise.

Model: `pj.BoucWenOscillator` (the equations are known, the parameters are not),

$$m\ddot y + c\dot y + k y + z = u,\qquad
  \dot z = \alpha\dot y - \beta\left(\gamma|\dot y|\,|z|^{\nu-1}z + \delta\,\dot y\,|z|^{\nu}\right),$$

with $m, c, k, \alpha$ wrapped by `pj.constrain(..., pj.Positive)` and free; $\gamma$ and $\delta$ free and signed;
$\beta$ and $\nu$ frozen (left out of `free`). $\beta$ only ever appears multiplied by $\gamma$ or $\delta$, so
$(\beta, \gamma, \delta)$ is not identifiable, only the two products are: $\beta$ is fixed at a positive data scale
$\beta_0 = 1/\mathrm{rms}(y)$ and $(\gamma, \delta)$ carry the fit. $\nu = 1$ by default, the usual Bouc–Wen choice
(the $z$ equation is then piecewise linear in $z$, and $\nu$ trades off against $\beta$ over the range of $|z|$ the
data visit); `--free-nu` wraps $\nu$ in `pj.Positive` and frees it (start 1) in a third stage.

Simulation: `pj.BoucWenOscillator.simulate(u, dt, hold="periodic", method="rk4", substeps=S)`: classical RK4, $S$
steps per sample in one `lax.scan`, with the input at the stage times from the band-limited periodic interpolant of
the samples. The fit's predictor (`periodic_response`, a `fitting.Predictor`) drives the model from rest with the
record's input repeated periodically, starting `warmup` samples before the record's first sample, and returns the
record's samples. At the nominal parameters the RK4 response differs from adaptive diffrax Tsit5 (`rtol=1e-8`, the
integrator of `--make-test`) on a steady multisine period by 2.7e-7 m RMS with 4 sub-steps and 7.3e-8 m with 8
(about second order: the vector field has kinks at $\dot y = 0$ and $z = 0$), against 7.3e-6 m of data noise.

Which samples (0-based, period $p$ = samples $8192p \dots 8192p + 8191$):

- fit: periods 1–3 (samples 8192–32767). The input is periodic and the system is in its periodic steady state after
  period 0 (the transient from rest at sample 0 decays as $e^{-c t / 2m}$ and faster), so the least-squares cost over
  the three periods equals, up to a constant, three times the cost against their average $\bar y$; the fit uses
  $\bar y$ (one `fitting.Experiment` of 8192 samples: `v_in` = the force period, `displacement` = $\bar y$).
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
dissipation into $c$): a grid of 3 × 3 × 2 such models is scored by the stage-1 `fitting.Problem`'s residuals and
the one with the smallest cost is the start.

Fit: `fitting.fit` (Levenberg–Marquardt in normal-equation form, forward-mode Jacobians, Jacobian-column scaling of
the free parameters), output (simulation) error, in stages, each from the previous one's `params`:

1. stage 1: RK4 with 4 sub-steps, from rest 2048 samples before the period, the whole period scored against
   $\bar y$;
2. stage 2: RK4 with 8 sub-steps, from rest one whole period before (as the data: period 0 is the warm-up), the
   whole steady period scored against $\bar y$;
3. (`--free-nu`) stage 2 with $\nu$ free as well.

`--quick` (tests): stage 1 from rest 1024 samples before the period; stage 2 with 4 sub-steps and at most 8 LM
steps; the evaluation then also uses 4 sub-steps.

Measured (full run, synthetic test file of `--make-test` with its defaults): train / validation RMSE 7.4017e-6 /
7.2892e-6 m (noise level 7.46e-6 m); test multisine 7.3061e-6 m, sine sweep 7.2202e-6 m (against the noise-free
outputs: 2.66e-7 and 1.20e-7 m); $m, c, k, \alpha, \beta\gamma, \beta\delta$ within 0.4 % of the nominal values;
stage 1 converges in 15 steps, stage 2 in 11; 10–15 s in all on a shared 2-core CPU. `--free-nu` moves $\nu$ to
0.9989 and changes each RMSE by less than 0.02 %.

`--test PATH` (HDF5, groups `multisine` and/or `sinesweep`, each with `u`, `y` and optionally `fs`):
`multisine` is one steady-state period, simulated from rest for `--ms-periods` periods (default 3) and scored on the
last; `sinesweep` is simulated from rest (band-limited interpolant of the record followed by `max(1024, n // 8)`
zeros). RMSE = $\sqrt{\mathrm{mean}((\hat y - y)^2)}$ in m, printed and saved as `{"multisine_rmse": ..,
"sinesweep_rmse": ..}` in `test_rmse.json` (null for a missing group). `--make-test PATH` writes a synthetic test
file in that layout: a new random-phase multisine period (5–150 Hz, 50 N RMS) and a tapered 40 N linear sine sweep
(5–150 Hz), simulated with the nominal benchmark parameters by diffrax (adaptive Tsit5, `rtol=1e-8`, a different
integrator from the fit's), plus Gaussian noise; the noise-free outputs are stored as `y_clean`. The official files
were made differently (the benchmark's MATLAB example: Newmark integration at 20 × 750 Hz, then FIR decimation of
y), so scores on them also contain that difference; on `train.h5` it is below the noise (the nominal model leaves
7.36e-6 m against 7.46e-6 m noise).

Run: `python -m experiments.boucwen_benchmark [--test PATH] [--out results/boucwen_benchmark] [--quick]`.
"""

import argparse
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import fitting
import piezojax as pj
from experiments._command import output_folder, positive_int, run, stop_if_interrupted, writing

KIND = "experiments.boucwen_benchmark"  # what the output folder's marker records
OUT = "results/boucwen_benchmark"

DATA = Path(__file__).resolve().parent / "data" / "boucwen_benchmark" / "train.h5"
PERIOD = 8192
FIT_PERIODS = (1, 2, 3)  # 0-based; samples 8192..32767
VAL_PERIOD = 4  # samples 32768..40959
NOMINAL = {"m": 2.0, "c": 10.0, "k": 5e4, "alpha": 5e4, "beta": 1e3, "gamma": 0.8, "delta": -1.1, "nu": 1.0}
NOISE_DEFAULT = 7.3e-6  # m, the train data's noise level (RMS of half the period-to-period difference)
FREE = ("m", "c", "k", "alpha", "gamma", "delta")  # beta fixed (identifiability), nu fixed unless --free-nu


class BenchmarkFileError(pj.PiezojaxValueError):
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
# Model, predictor and fit (library blocks and `fitting` calls).


def oscillator(m, c, k, alpha, beta, gamma, delta, nu=1.0):
    """`pj.BoucWenOscillator` with $m, c, k, \\alpha$ constrained positive (`pj.Positive`), ready for `fitting`."""
    bw = pj.BoucWenOscillator(m=m, c=c, k=k, alpha=alpha, beta=beta, gamma=gamma, delta=delta, nu=nu)
    return pj.constrain(bw, lambda s: (s.m, s.c, s.k, s.alpha), pj.Positive)


def periodic_response(substeps: int, warmup: int) -> fitting.Predictor:
    """`displacement`: the model driven from rest by the record's input repeated periodically (the record is one
    period), starting `warmup` samples before the record's first sample (`warmup` = the record's length: its
    periodic steady state after one period from rest, as the benchmark data). RK4 with `substeps` steps per sample."""

    def fn(model, data):
        n = data.v_in.shape[0]
        u = jnp.tile(jnp.roll(data.v_in, warmup % n), -(-(warmup + n) // n))
        y = model.simulate(u, data.dt, hold="periodic", method="rk4", substeps=substeps, num_samples=warmup + n)
        return {"displacement": y[warmup:]}

    return fitting.Predictor(fn, ("displacement",))


def values(model) -> dict:
    """Physical values as floats, with the identifiable products beta*gamma and beta*delta."""
    model = pj.unwrap(model)
    d = {name: float(getattr(model, name)) for name in NOMINAL}
    d["beta*gamma"] = d["beta"] * d["gamma"]
    d["beta*delta"] = d["beta"] * d["delta"]
    return d


def _rms(problem, u) -> float:
    """RMS prediction error (m) of a problem's model at scaled parameters `u`."""
    errors = problem.experiment_errors(problem.residuals(u))
    return float(np.sqrt(np.mean(np.concatenate([e["displacement"] for e in errors]) ** 2)))


def fit_stage(params, dataset, predictor, free, max_steps, label) -> tuple:
    """One `fitting.fit`; prints and returns the RMS error before and after, steps and verdict."""
    result = fitting.fit(params, dataset, predictor=predictor, free=list(free), max_steps=max_steps, progress=False)
    stop_if_interrupted(result)
    w = result.weights["displacement"]
    before = float(np.sqrt(2 * result.initial_cost / result.num_residuals)) / w
    after = float(np.sqrt(2 * result.cost / result.num_residuals)) / w
    print(f"  [{label}] fitting.fit: RMS error {before:.3e} -> {after:.3e} m in {result.steps} steps "
          f"({result.accepted_steps} accepted), {result.seconds:.1f} s ({result.reason})", flush=True)
    summary = result.summary()
    info = {"steps": result.steps, "accepted_steps": result.accepted_steps, "success": result.success,
            "reason": result.reason, "seconds": result.seconds, "rms_before": before, "rms_after": after,
            "parameters": summary["parameters"], "condition": summary["condition"]}
    return result, info


def fit(data: dict, settings: dict) -> tuple:
    """Linear start, grid of hysteresis guesses, then `fitting.fit` stage 1 (short warm-up, 4 sub-steps) and stage 2
    (one period of warm-up, the evaluation's sub-steps); stage 3 frees nu with `settings["free_nu"]`.

    **Returns:** `(result, info)`: the last stage's `fitting.FitResult` and a JSON-ready dict of what each step did.
    """
    u, y, fs = data["u"], data["y"], data["fs"]
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
    beta0 = 1.0 / float(np.sqrt(np.mean(y_avg**2)))
    dataset = fitting.Dataset([fitting.Experiment.from_arrays(
        v_in=u_period, dt=1.0 / fs, displacement=y_avg, name="multisine (periods 1-3 averaged)")])

    # Grid of physics-free guesses (split of the linear stiffness, hysteresis scale, viscous fraction), scored by the
    # stage-1 problem's residuals.
    stage1 = periodic_response(settings["substeps1"], settings["warm1"])
    grid = {
        (split, scale, cfrac): oscillator(m_l, cfrac * c_l, (1 - split) * k_l, split * k_l, beta0, scale, 0.0)
        for split in (0.25, 0.5, 0.75) for scale in (0.3, 1.0, 3.0) for cfrac in (0.1, 0.5)
    }
    problem = fitting.Problem(next(iter(grid.values())), dataset, predictor=stage1, free=list(FREE), scales="value")
    costs = {key: _rms(problem, problem.u_of(model)) for key, model in grid.items()}
    finite = {key: c for key, c in costs.items() if np.isfinite(c)}
    if not finite:
        raise RuntimeError("every start of the grid gives non-finite predictions")
    best = min(finite, key=finite.get)
    start = grid[best]
    info["grid_best"] = {"alpha_fraction_of_k_lin": best[0], "beta_gamma_times_rms_y": best[1],
                         "c_fraction_of_c_lin": best[2], "rms": costs[best]}
    print(
        f"  start: alpha = {best[0]:.2f} k_lin, beta*gamma = {best[1]:.1f}/rms(y), c = {best[2]:.1f} c_lin, "
        f"delta = 0; stage-1 RMS {costs[best]:.3e} m ({time.perf_counter() - t0:.1f} s)",
        flush=True,
    )
    info["start"] = values(start)
    s1, s2 = settings["substeps1"], settings["substeps2"]
    result, info["stage1"] = fit_stage(start, dataset, stage1, FREE, settings["steps1"],
                                       f"stage 1: RK4 x{s1}, warm-up {settings['warm1']}")
    stage2 = periodic_response(s2, PERIOD)
    result, info["stage2"] = fit_stage(result.params, dataset, stage2, FREE, settings["steps2"],
                                       f"stage 2: RK4 x{s2}, from rest one period before, period 1-3 average")
    if settings["free_nu"]:
        params = pj.constrain(result.params, lambda s: s.nu, pj.Positive)
        result, info["stage3_free_nu"] = fit_stage(params, dataset, stage2, FREE + ("nu",), settings["steps2"],
                                                   "stage 3: nu free")
    info["fit_seconds"] = time.perf_counter() - t0
    return result, info


# ----------------------------------------------------------------------------------------------------------------
# Evaluation.


def rmse(a, b) -> float:
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


@eqx.filter_jit
def _simulate(model, u, dt, substeps, num_samples):
    return model.simulate(u, dt, hold="periodic", method="rk4", substeps=substeps, num_samples=num_samples)


def simulate(model, u, fs, substeps, num_samples=None) -> np.ndarray:
    """Displacement from rest under the band-limited periodic interpolant of `u` (RK4, `substeps` per sample)."""
    u = np.asarray(u, dtype=np.float64)
    return np.asarray(_simulate(pj.unwrap(model), jnp.asarray(u), 1.0 / fs, substeps, num_samples))


def evaluate_train(model, data, substeps):
    """One simulation from rest through the 5 periods; RMSE on period 0, the fit periods and the validation period."""
    pred = simulate(model, np.tile(data["u"][:PERIOD], 5), data["fs"], substeps)
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
    n = u.shape[0]
    y = simulate(model, np.tile(u, periods), fs, substeps)
    return y[-n:], rmse(y[-n:], y[-2 * n : -n]) if periods > 1 else float("nan")


def simulate_transient(model, u, fs, substeps):
    """Response from rest to a non-periodic record (band-limited interpolant of the record followed by
    `max(1024, n // 8)` zeros, so that its end does not wrap onto its start)."""
    n = u.shape[0]
    padded = np.concatenate([u, np.zeros(max(1024, n // 8))])
    return simulate(model, padded, fs, substeps, num_samples=n)


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
    with fitting.files.atomic_file(path) as tmp, h5py.File(tmp, "w") as f:
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
    with fitting.files.atomic_file(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def write_json(path, obj):
    fitting.files.save_json(path, obj)  # strict JSON (NaN and inf as null), atomic


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
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default=str(DATA), help="train.h5 of the benchmark")
    parser.add_argument("--test", default=None, help="test file (HDF5 groups multisine and/or sinesweep)")
    parser.add_argument("--out", default=OUT, help=f"output folder (default {OUT}); an earlier output of this "
                        "experiment is replaced whole, any other folder is refused")
    parser.add_argument("--quick", action="store_true", help="fewer LM steps and 4 RK4 sub-steps (tests)")
    parser.add_argument("--free-nu", action="store_true", help="also fit nu (stage 3)")
    parser.add_argument("--ms-periods", type=int, default=3, help="periods simulated for the multisine test")
    parser.add_argument("--make-test", default=None, metavar="PATH",
                        help="write a synthetic test file (nominal parameters + noise) to PATH and exit")
    parser.add_argument("--sweep-samples", type=positive_int, default=20000, help="sine sweep length for --make-test")
    parser.add_argument("--noise", type=float, default=NOISE_DEFAULT, help="noise RMS (m) for --make-test")
    args = parser.parse_args(argv)
    if args.ms_periods < 2:
        parser.error(f"--ms-periods must be at least 2, got {args.ms_periods}")

    pj.enable_fast_cpu_scans()
    jax.config.update("jax_enable_x64", True)
    pj.enable_compilation_cache()  # compiled programs kept for the next run ($PIEZOJAX_CACHE_DIR)
    start = time.perf_counter()

    if args.make_test is not None:
        out = make_synthetic_test(args.make_test, sweep_samples=args.sweep_samples, noise=args.noise)
        print(f"wrote {args.make_test}: multisine period {PERIOD} samples, sine sweep {args.sweep_samples} samples, "
              f"noise {args.noise:.2e} m ({out['seconds']:.1f} s)")
        return out

    out = output_folder(args.out, KIND, default=OUT)  # before any long work (--make-test writes only its file)
    test = load_test(args.test) if args.test is not None else None  # a bad file: one line, exit status 2
    data = load_train(args.data)

    if args.quick:
        settings = {"substeps1": 4, "warm1": 1024, "steps1": 60, "substeps2": 4, "steps2": 8}
    else:
        settings = {"substeps1": 4, "warm1": 2048, "steps1": 60, "substeps2": 8, "steps2": 40}
    settings["free_nu"] = bool(args.free_nu)
    noise = noise_level(data["y"])
    print(f"train.h5: {data['u'].shape[0]} samples at {data['fs']:.0f} Hz; noise level {noise:.3e} m "
          f"(periods 2 vs 3); settings {settings}", flush=True)

    result, info = fit(data, settings)
    model = result.model
    fitted = values(model)
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
    with writing(out, KIND) as tmp:
        write_json(tmp / "metrics.json", report)
        if scores is not None:
            write_json(tmp / "test_rmse.json", scores)
        save_figure(tmp / "validation.png", data, pred, test, test_preds)
    print(f"\nrun time {elapsed:.1f} s; results in {out}")
    return report


if __name__ == "__main__":
    sys.exit(run(main, "python -m experiments.boucwen_benchmark"))
