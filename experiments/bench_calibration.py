r"""Benchmark: the joint calibration of an actuator model with `fitting.fit` against scipy + numba.

Run: `python -m experiments.bench_calibration [--quick | --large] [--method M] [--bounds-variant] [--max-steps N]
[--progress] [--warm-cache]`

The model is `pj.Actuator(PrandtlIshlinskii(15 plays), KelvinVoigtCreep(2 lags, k0=None),
StableTransferFunction(1, omega, zeta))` (parallel structure): the displacement is
$\delta = G(s)\,[H[V] + C[V]]$ with $H[V] = w_0 V + \sum_i w_i P_{r_i}[V]$ (exact plays), the creep
$C[V] = \sum_j x_j/k_j$ with $x_{j,k+1} = a_j x_{j,k} + (1 - a_j) V_k$, $a_j = e^{-dt/\tau_j}$ (exact ZOH), and a
second-order $G(s) = \omega^2/(s^2 + 2\zeta\omega s + \omega^2)$ discretised exactly (ZOH). The static gain of $G$
is fixed at 1 (it is redundant with the weights and the creep compliances), leaving 37 free parameters:
$w_0$, 15 weights, 15 thresholds, 2 stiffnesses, 2 time constants, $\omega$, $\zeta$.

`--large` is the compass-scale problem: 22 plays (the same total weight and decay spread over them; 51 free
parameters) and 8 experiments of 1e5 samples.

Data: 8 synthetic experiments of 2e4 samples at 10 kHz (decaying sines of different frequencies and offsets,
staircases, a random multi-level signal; 0..100 V) simulated by the true model with white noise of 0.1 % of the
displacement range. The truth is exactly the fitted family: this measures solver speed, not model adequacy.

Start (the same for every fit): the truth perturbed by a fixed random draw: weights, threshold gaps, creep
stiffnesses and time constants multiplied by $e^{0.3\,\xi}$, $w_0$ by 0.8, $\omega$ by 1.1, $\zeta$ by 1.5.

Fits, all on the same data, the same residuals $r = w_c(\hat\delta - \delta)$ with $w_c = 1/\mathrm{range}$
(`weights="range"`) and the same cost $\tfrac12\|r\|^2$:

1. `fitting.fit` (forward-mode Jacobian, `max_steps` 100; quick: 60) with `method="trust_region"` (default here):
   scipy's TRF algorithm for unbounded problems (the same trust region, `x_scale="jac"` scaling, radius updates and
   `ftol`/`xtol` tests as the baseline (2)), so that the two differ in how the model and its Jacobian are computed,
   not in the algorithm; or `--method levenberg_marquardt` (the engine's default, optimistix's algorithm, which needs
   about twice the Jacobians here). Constraints by reparametrisation: weights, $w_0$, stiffnesses, time constants,
   $\omega$, $\zeta$ `Positive` (softplus), thresholds `OrderedPositive`. The solver works in
   $u = \theta_{raw}/s$ with $s_j = |\theta_{raw,0,j}|/\|J_j\|$ (unit Jacobian columns at the start, i.e. scipy's
   `x_scale="jac"` at the start; passed as `scales=`; the trust region rescales further as scipy does).
   The engine linearises only at accepted points, into $J^\top J$ and $J^\top r$, and solves the damped
   $p \times p$ system (Levenberg–Marquardt: by `lx.Cholesky()`, its default, or `--linear-solver qr` for `lx.QR()`;
   trust region: from the eigen-decomposition of the scaled $J^\top J$).
   Compilation is measured by a first fit with `max_steps=1` (compile + one step); the timed fit then reuses the
   cached compiled steps.
2. scipy "same u": `scipy.optimize.least_squares(method="trf", jac="2-point", x_scale="jac")` over exactly the same
   vector $u$, start and reparametrisation (written in numpy), the simulation a numba loop of the same discrete model:
   the cost function is identical to (1). numba compile time is reported separately (a warm-up call compiles first).
3. optional (`--bounds-variant`), scipy "bounds", what a user writes without reparametrisation: physical parameters
   divided by their start values ($x_0 = 1$, so the default finite-difference step suits every parameter), bounds
   $x \ge 0$ (1e-6 for the creep, $\omega$, $\zeta$ and $w_0$), thresholds unordered, `x_scale="jac"`.

`--warm-cache` also times the whole engine fit, compilation included, in two fresh processes that share a new
persistent compilation cache (`pj.enable_compilation_cache`): the first fills it, the second loads the compiled
programs from it, as a second `piezojax fit` of records of the same layout does.

Before fitting, the numba simulation is checked against `pj.Actuator.simulate` (max |difference| / range) and the
engine's Jacobian against central finite differences of its residuals. Printed: wall and CPU (process) time,
final cost, Jacobians (engine: linearisations, one per accepted step plus the start; scipy `njev`), residual
evaluations (engine: trial steps plus the start; scipy `nfev`) and numba simulation calls (including finite
differences), the speed ratios, the engine re-run (compiled, same iterates) with `max_steps` set to the first step
whose cost is at or below scipy's final cost ("stopped at scipy's cost": the time to equal cost), and a profile
(one Jacobian, one residual, one linearisation $J^\top J, J^\top r$, the LM time per step). On a shared machine,
CPU time is the steadier measure.
"""

import argparse
import math
import sys
import time

import numpy as np

try:
    import numba
except ImportError:  # pragma: no cover - numba is a benchmark dependency
    numba = None

N_PLAYS = 15
DT = 1e-4
NOISE_FRACTION = 1e-3


# ---------------------------------------------------------------------------------------------------------------------
# The baseline simulator: numba loop of exactly the discrete model piezojax simulates.
# ---------------------------------------------------------------------------------------------------------------------


def _simulate_loop(v, w0, w, r, a, one_minus_a, c, Ad, Bd, Cd, Dd, out):
    """Fused PI + Kelvin–Voigt creep + linear dynamics over a batch `v` (E, N) from rest; writes `out` (E, N)."""
    n = r.shape[0]
    nc = a.shape[0]
    nd = Bd.shape[0]
    z = np.zeros(n)
    xc = np.zeros(nc)
    xd = np.zeros(nd)
    xn = np.zeros(nd)
    for e in range(v.shape[0]):
        for i in range(n):
            z[i] = 0.0
        for j in range(nc):
            xc[j] = 0.0
        for j in range(nd):
            xd[j] = 0.0
        v_prev = 0.0
        for k in range(v.shape[1]):
            vk = v[e, k]
            d = vk - v_prev
            h = w0 * vk
            for i in range(n):
                zi = z[i] + d
                if zi < -r[i]:
                    zi = -r[i]
                if zi > r[i]:
                    zi = r[i]
                z[i] = zi
                h += w[i] * (vk - zi)
            creep = 0.0
            for j in range(nc):
                creep += c[j] * xc[j]
                xc[j] = a[j] * xc[j] + one_minus_a[j] * vk
            u = h + creep
            y = Dd * u
            for p in range(nd):
                y += Cd[p] * xd[p]
                s = Bd[p] * u
                for q in range(nd):
                    s += Ad[p, q] * xd[q]
                xn[p] = s
            for p in range(nd):
                xd[p] = xn[p]
            out[e, k] = y
            v_prev = vk
    return out


if numba is not None:
    _simulate_loop_jit = numba.njit(cache=False, fastmath=False)(_simulate_loop)
else:  # pragma: no cover
    _simulate_loop_jit = _simulate_loop


def zoh_second_order(omega: float, zeta: float, gain: float, dt: float):
    """Exact ZOH discretisation of piezojax's realisation of $g\\,\\omega^2/(s^2 + 2\\zeta\\omega s + \\omega^2)$:
    $\\dot x_1 = \\omega x_2$, $\\dot x_2 = \\omega(u - x_1) - 2\\zeta\\omega x_2$, $y = g x_1$; one matrix
    exponential of the augmented matrix $[[A dt, B dt], [0, 0]]$."""
    import scipy.linalg

    A = np.array([[0.0, omega], [-omega, -2.0 * zeta * omega]])
    B = np.array([0.0, omega])
    M = np.zeros((3, 3))
    M[:2, :2] = A * dt
    M[:2, 2] = B * dt
    F = scipy.linalg.expm(M)
    return F[:2, :2].copy(), F[:2, 2].copy(), np.array([gain, 0.0]), 0.0


class NumbaActuator:
    """Physical parameters → displacement of the same discrete model, by the numba loop (numpy set-up per call)."""

    def __init__(self, v: np.ndarray, dt: float, gain: float = 1.0):
        self.v = np.ascontiguousarray(v, dtype=float)
        self.dt = float(dt)
        self.gain = float(gain)
        self.out = np.empty_like(self.v)
        self.calls = 0

    def __call__(self, w0, w, r, k, tau, omega, zeta) -> np.ndarray:
        self.calls += 1
        x = self.dt / np.asarray(tau, float)
        Ad, Bd, Cd, Dd = zoh_second_order(float(omega), float(zeta), self.gain, self.dt)
        return _simulate_loop_jit(
            self.v, float(w0), np.asarray(w, float), np.asarray(r, float), np.exp(-x), -np.expm1(-x),
            1.0 / np.asarray(k, float), Ad, Bd, Cd, Dd, self.out,
        ).copy()


def _softplus(x):
    return np.logaddexp(0.0, x)


# ---------------------------------------------------------------------------------------------------------------------
# Data and models
# ---------------------------------------------------------------------------------------------------------------------


def truth_parameters(n_plays: int = N_PLAYS) -> dict:
    """The true parameters; `n_plays` other than 15 spreads the same total play weight and decay over that many
    plays (thresholds 3..60 V)."""
    i = np.arange(n_plays)
    scale = N_PLAYS / n_plays
    return dict(
        w0=0.05e-6,  # m/V
        w=0.025e-6 * scale * np.exp(-i * scale / 6.0),
        r=np.linspace(3.0, 60.0, n_plays),  # V
        k=np.array([2.5e8, 1.5e8]),  # V/m: creep compliances 4e-9 and 6.7e-9 m/V
        tau=np.array([0.05, 0.6]),  # s
        omega=2 * np.pi * 400.0,  # rad/s
        zeta=0.08,
    )


def start_parameters(truth: dict, seed: int = 7) -> dict:
    rng = np.random.default_rng(seed)
    gaps = np.diff(truth["r"], prepend=0.0)
    n_plays = gaps.size
    return dict(
        w0=truth["w0"] * 0.8,
        w=truth["w"] * np.exp(0.3 * rng.standard_normal(n_plays)),
        r=np.cumsum(gaps * np.exp(0.3 * rng.standard_normal(n_plays))),
        k=truth["k"] * np.exp(0.3 * rng.standard_normal(2)),
        tau=truth["tau"] * np.exp(0.3 * rng.standard_normal(2)),
        omega=truth["omega"] * 1.1,
        zeta=truth["zeta"] * 1.5,
    )


def input_signals(n_exp: int, n: int, dt: float, seed: int = 3) -> np.ndarray:
    """`n_exp` voltage records (0..100 V) of `n` samples: decaying sines, staircases, random levels (smoothed)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    T = n * dt
    out = []
    freqs = [1.0, 2.5, 5.0, 10.0, 20.0, 40.0]
    for e in range(n_exp):
        kind = e % 4
        if kind in (0, 1):
            f = freqs[e % len(freqs)] * max(1.0, 2.0 / T)
            env = np.exp(-2.5 * t / T)
            off = 50.0 + 10.0 * rng.standard_normal()
            amp = min(off, 100.0 - off)
            v = off + amp * env * np.sin(2 * np.pi * f * t - np.pi / 2)
            v = np.concatenate([np.linspace(0.0, v[0], max(n // 20, 2)), v])[:n]
        elif kind == 2:
            levels = np.concatenate([[0.0], rng.uniform(0, 100, 7)])
            v = np.repeat(levels, int(math.ceil(n / levels.size)))[:n]
        else:
            m = max(n // 400, 4)
            levels = rng.uniform(0, 100, m)
            v = np.interp(t, np.linspace(0, T, m), levels)
            v[: n // 20] = np.linspace(0.0, v[n // 20], n // 20)
        # one-pole smoothing (tau = 2 ms) so steps are not instantaneous
        a = np.exp(-dt / 2e-3)
        y = np.empty_like(v)
        acc = 0.0
        for k in range(n):
            acc = a * acc + (1 - a) * v[k]
            y[k] = acc
        out.append(np.clip(y, 0.0, 100.0))
    return np.stack(out)


def jax_model(p: dict):
    import piezojax as pj

    return pj.Actuator(
        pj.PrandtlIshlinskii(p["w"], p["r"], w0=p["w0"]),
        pj.KelvinVoigtCreep(p["k"], p["tau"], k0=None),
        pj.StableTransferFunction(1.0, omega=[p["omega"]], zeta=[p["zeta"]]),
    )


def constrained(model):
    import piezojax as pj

    m = pj.constrain(model, lambda m: m.hysteresis.w0, pj.Positive)
    m = pj.constrain(m, lambda m: m.hysteresis.weights, pj.Positive)
    m = pj.constrain(m, lambda m: m.hysteresis.thresholds, pj.OrderedPositive)
    m = pj.constrain(m, lambda m: m.creep.stiffnesses, pj.Positive)
    m = pj.constrain(m, lambda m: m.creep.time_constants, pj.Positive)
    m = pj.constrain(m, lambda m: m.dynamics.omega, pj.Positive)
    return pj.constrain(m, lambda m: m.dynamics.zeta, pj.Positive)


FREE = ["hysteresis.w0", "hysteresis.weights", "hysteresis.thresholds", "creep", "dynamics.omega", "dynamics.zeta"]


def u_to_physical(u: np.ndarray, scales: np.ndarray, names: list[str]) -> dict:
    """The numpy version of the reparametrisation: scaled raw vector `u` → physical parameters (same order as
    `problem.parameter_names()`; the raw and physical vectors have the same layout)."""
    raw = np.asarray(u, float) * scales
    out: dict[str, list] = {}
    for name, x in zip(names, raw):
        out.setdefault(name.split("[")[0], []).append(x)
    g = {k: np.asarray(v) for k, v in out.items()}
    return dict(
        w0=float(_softplus(g["hysteresis.w0"])[0]),
        w=_softplus(g["hysteresis.weights"]),
        r=np.cumsum(_softplus(g["hysteresis.thresholds"])),
        k=_softplus(g["creep.stiffnesses"]),
        tau=_softplus(g["creep.time_constants"]),
        omega=float(_softplus(g["dynamics.omega"])[0]),
        zeta=float(_softplus(g["dynamics.zeta"])[0]),
    )


_KEYS = ("w0", "w", "r", "k", "tau", "omega", "zeta")


def pack(p: dict) -> np.ndarray:
    return np.concatenate([np.atleast_1d(np.asarray(p[k], float)) for k in _KEYS])


def unpack(x: np.ndarray) -> dict:
    n = (x.size - 7) // 2  # the plays: 2n + 7 parameters
    return dict(w0=x[0], w=x[1 : 1 + n], r=x[1 + n : 1 + 2 * n], k=x[1 + 2 * n : 3 + 2 * n],
                tau=x[3 + 2 * n : 5 + 2 * n], omega=x[5 + 2 * n], zeta=x[6 + 2 * n])


# ---------------------------------------------------------------------------------------------------------------------


def _line(label, value):
    print(f"  {label:<58s} {value}")


def run(
    quick: bool = False,
    bounds_variant: bool = False,
    max_steps: int | None = None,
    warm_run: bool = True,
    progress: bool = False,
    scipy_max_nfev: int | None = None,
    linear_solver: str = "cholesky",
    run_scipy: bool = True,
    method: str = "trust_region",
    large: bool = False,
) -> dict:
    """Run the benchmark; print the table and return the measured numbers as a dict. `quick`: 4 experiments x 2500
    samples; `large`: 8 x 1e5 samples and 22 plays (51 parameters); else 8 x 2e4 and 15 plays (37 parameters)."""
    if quick and large:
        raise ValueError("run: quick and large exclude each other")
    import jax
    import jax.numpy as jnp
    import scipy.optimize

    import fitting

    n_exp, n = (4, 2500) if quick else (8, 100_000) if large else (8, 20_000)
    n_plays = 22 if large else N_PLAYS
    results: dict = {"n_exp": n_exp, "n": n, "n_plays": n_plays}
    truth = truth_parameters(n_plays)
    start = start_parameters(truth)
    v = input_signals(n_exp, n, DT)

    # --- data from the true model (piezojax), noise ---------------------------------------------------------------
    true_model = jax_model(truth)
    sim = jax.jit(jax.vmap(lambda m, x: m.simulate(x, DT).displacement, in_axes=(None, 0)))
    clean = np.asarray(sim(true_model, jnp.asarray(v)))
    rng = np.random.default_rng(11)
    noise_std = NOISE_FRACTION * float(np.ptp(clean))
    y = clean + noise_std * rng.standard_normal(clean.shape)
    t = np.arange(n) * DT
    ds = fitting.Dataset(
        [fitting.Experiment.from_arrays(t=t, v_in=v[e], name=f"e{e}", displacement=y[e]) for e in range(n_exp)]
    )
    print(f"calibration benchmark: {n_exp} experiments x {n} samples, PI({n_plays}) + 2-lag creep + 2nd order, "
          f"noise {NOISE_FRACTION:.1%} of range")

    # --- numba model vs piezojax ----------------------------------------------------------------------------------
    t0 = time.perf_counter()
    nb_small = NumbaActuator(v[:1, :10], DT)
    nb_small(**start)
    numba_compile = time.perf_counter() - t0
    nb = NumbaActuator(v, DT)
    start_model = jax_model(start)
    diffs = []
    for p, m in ((truth, true_model), (start, start_model)):
        ref = np.asarray(sim(m, jnp.asarray(v)))
        diffs.append(float(np.max(np.abs(nb(**p) - ref)) / np.ptp(ref)))
    t0 = time.perf_counter()
    for _ in range(3):
        nb(**start)
    numba_eval = (time.perf_counter() - t0) / 3
    nb.calls = 0
    results["numba_vs_piezojax_max_rel"] = max(diffs)
    results["numba_compile_s"] = numba_compile
    results["numba_eval_s"] = numba_eval

    # --- the engine's problem, its Jacobian vs finite differences ---------------------------------------------------
    params0 = constrained(start_model)
    # Parameter scaling (both solvers): theta_raw = s u with s_j = |theta_raw,0| / ||J_j||, i.e. unit Jacobian
    # columns at the start (what scipy's x_scale="jac" does at its first iteration). optimistix's damping is isotropic
    # in u, so this matters: with s = |theta_raw,0| alone the engine needed about 3x more steps (measured, quick data).
    problem = fitting.Problem(params0, ds, free=FREE, weights="range", scales="value")
    _, jt0 = problem.residuals_and_jacobian(problem.u0)
    col = np.linalg.norm(np.asarray(jt0), axis=1)
    fit_scales = np.asarray(problem.scales) / np.where(col > 0, col, 1.0)
    problem = fitting.Problem(params0, ds, free=FREE, weights="range", scales=jnp.asarray(fit_scales))
    names = problem.parameter_names()
    scales = np.asarray(problem.scales)
    u0 = np.asarray(problem.u0)
    weight = float(problem.weights["displacement"])
    p_count = u0.size
    # the numpy reparametrisation must reproduce the engine's
    phys_np = pack(u_to_physical(u0, scales, names))
    phys_jax = pack(dict(zip(_KEYS, _physical_by_key(problem, u0))))
    results["reparam_max_rel"] = float(np.max(np.abs(phys_np - phys_jax) / np.abs(phys_jax)))

    # the data enter as arguments, not as constants folded into the compiled function
    core_residuals = jax.jit(lambda core, u: core.residuals(u))

    def res_fn(u):
        return core_residuals(problem.core, u)

    r0, jt = problem.residuals_and_jacobian(jnp.asarray(u0))
    J = np.asarray(jt).T
    h = 1e-6
    fd = np.empty_like(J)
    for j in range(p_count):
        e = np.zeros(p_count)
        e[j] = h
        fd[:, j] = (np.asarray(res_fn(jnp.asarray(u0 + e))) - np.asarray(res_fn(jnp.asarray(u0 - e)))) / (2 * h)
    col_err = np.linalg.norm(J - fd, axis=0) / np.maximum(np.linalg.norm(fd, axis=0), 1e-300)
    results["jacobian_fd_max_col_rel"] = float(np.max(col_err))
    results["jacobian_fd_median_col_rel"] = float(np.median(col_err))

    # the same residuals in numpy/numba (identical cost function)
    target = np.asarray(y)

    def residuals_u(u):
        return ((nb(**u_to_physical(u, scales, names)) - target) * weight).ravel()

    r0_nb = residuals_u(u0)
    results["residual_numba_vs_engine_max"] = float(np.max(np.abs(r0_nb - np.asarray(r0))))
    noise_floor = 0.5 * (n_exp * n - p_count) * (weight * noise_std) ** 2
    results["noise_floor_cost"] = noise_floor
    results["initial_cost"] = 0.5 * float(np.sum(r0_nb**2))
    results["p"] = p_count

    print(f"  free parameters: {p_count}; residuals: {n_exp * n}; start: perturbed truth (seeded)")
    _line("numba vs piezojax forward, max |diff| / range (truth, start)", f"{diffs[0]:.2e}, {diffs[1]:.2e}")
    _line("numpy vs engine reparametrisation, max rel. diff", f"{results['reparam_max_rel']:.2e}")
    _line("numba vs engine residuals at the start, max |diff|", f"{results['residual_numba_vs_engine_max']:.2e}")
    _line("engine Jacobian vs central FD (h=1e-6 in u): max / median col. rel. err",
          f"{results['jacobian_fd_max_col_rel']:.2e} / {results['jacobian_fd_median_col_rel']:.2e}")
    _line("numba compile (excluded from scipy timings)", f"{numba_compile:.2f} s")
    _line("numba one simulation of all experiments", f"{numba_eval * 1e3:.2f} ms")
    _line("initial cost; noise-floor cost 0.5*(m-p)*(w*sigma)^2", f"{results['initial_cost']:.6e}; {noise_floor:.6e}")

    # --- (1) the engine, cold (with compile) and warm --------------------------------------------------------------
    jax_runs = []
    if max_steps is None:
        max_steps = 60 if quick else 100

    def engine_fit(steps):
        t0, c0 = time.perf_counter(), time.process_time()
        import lineax as lx

        solver = lx.QR() if linear_solver == "qr" else lx.Cholesky()
        r = fitting.fit(params0, ds, free=FREE, weights="range", scales=jnp.asarray(fit_scales), max_steps=steps,
                        progress=progress, linear_solver=solver, method=method)
        return r, time.perf_counter() - t0, time.process_time() - c0

    # Compilation: a first fit with max_steps=1 compiles the initialisation and the step (cached by structure and
    # shapes) and makes one step; the timed fit then runs compiled code only. "incl. compile" adds the two.
    if warm_run:
        _, wall_c, cpu_c = engine_fit(1)
        results.update(jax_compile_wall_s=wall_c, jax_compile_cpu_s=cpu_c)
    fr, wall, cpu = engine_fit(max_steps)
    jax_runs = [("warm" if warm_run else "cold", wall, fr)]
    results.update(jax_warm_wall_s=wall, jax_warm_cpu_s=cpu) if warm_run else results.update(
        jax_cold_wall_s=wall, jax_cold_cpu_s=cpu)
    if warm_run:
        results.update(jax_cold_wall_s=wall + results["jax_compile_wall_s"],
                       jax_cold_cpu_s=cpu + results["jax_compile_cpu_s"])
    fr = jax_runs[-1][2]
    results.update(method=method, jax_cost=fr.cost, jax_steps=fr.steps, jax_accepted=fr.accepted_steps,
                   jax_success=fr.success, jax_reason=fr.reason)
    # per-operation timings (warm) for the profile
    u_fit = jnp.asarray(fr.u)
    results["jax_jacobian_s"] = _best(lambda: jax.block_until_ready(problem.residuals_and_jacobian(u_fit)), 3)
    results["jax_residuals_s"] = _best(lambda: jax.block_until_ready(res_fn(u_fit)), 3)
    results["normal_equations_s"] = _best(lambda: jax.block_until_ready(problem.normal_equations(u_fit)), 3)

    # --- (2) scipy, same parametrisation ---------------------------------------------------------------------------
    if not run_scipy:
        compiled = (f"compiled {results['jax_warm_wall_s']:.2f} s wall, {results['jax_warm_cpu_s']:.2f} s CPU, "
                    if warm_run else "")
        print(f"  engine ({method}, {linear_solver}): {compiled}cost {fr.cost:.6e}, {fr.steps} steps, {fr.code}; "
              f"incl. compile {results['jax_cold_wall_s']:.2f} s wall, {results['jax_cold_cpu_s']:.2f} s CPU")
        return results
    nb.calls = 0
    t0, c0 = time.perf_counter(), time.process_time()
    sp = scipy.optimize.least_squares(residuals_u, u0, method="trf", jac="2-point", x_scale="jac",
                                      max_nfev=scipy_max_nfev)
    wall = time.perf_counter() - t0
    results.update(scipy_u_wall_s=wall, scipy_u_cpu_s=time.process_time() - c0, scipy_u_cost=float(sp.cost),
                   scipy_u_nfev=int(sp.nfev),
                   scipy_u_njev=int(sp.njev), scipy_u_calls=nb.calls, scipy_u_status=int(sp.status))

    # --- (1b) the engine stopped at scipy's final cost: the first accepted step whose cost is <= scipy's (the same
    # deterministic iterates, re-run with max_steps = that step and timed; compiled)
    hist, hsteps = np.asarray(fr.history), np.asarray(fr.history_steps)
    reached = np.flatnonzero(hist <= sp.cost)
    if reached.size:
        k_eq = int(hsteps[reached[0]])
        fr_eq, wall_eq, cpu_eq = engine_fit(k_eq)
        results.update(jax_eq_steps=k_eq, jax_eq_wall_s=wall_eq, jax_eq_cpu_s=cpu_eq, jax_eq_cost=fr_eq.cost,
                       jax_eq_jacobians=fr_eq.accepted_steps + 1)

    # --- (3) scipy, physical parameters with bounds ----------------------------------------------------------------
    if bounds_variant:
        x_start = pack(start)

        def residuals_x(x):
            return ((nb(**unpack(x * x_start)) - target) * weight).ravel()

        lower = np.zeros(p_count)
        positive = np.ones(p_count, bool)
        positive[1 + n_plays : 1 + 2 * n_plays] = False  # thresholds may reach 0
        positive[1 : 1 + n_plays] = False  # weights may reach 0
        lower[positive] = 1e-6
        nb.calls = 0
        t0, c0 = time.perf_counter(), time.process_time()
        sb = scipy.optimize.least_squares(residuals_x, np.ones(p_count), method="trf", jac="2-point",
                                          x_scale="jac", bounds=(lower, np.inf))
        wall = time.perf_counter() - t0
        results.update(scipy_b_wall_s=wall, scipy_b_cpu_s=time.process_time() - c0, scipy_b_cost=float(sb.cost),
                       scipy_b_nfev=int(sb.nfev),
                       scipy_b_njev=int(sb.njev), scipy_b_calls=nb.calls, scipy_b_status=int(sb.status))

    # --- table -------------------------------------------------------------------------------------------------------
    print("\n  fit                                  wall [s]  CPU [s]  final cost    Jacobians f-evals sim-calls  note")
    r = fr
    rows = [("warm", "compiled"), ("cold", "incl. compile")] if warm_run else [("cold", "incl. compile")]
    for label, note in rows:
        print(f"  piezojax fitting.fit ({note})".ljust(39) + f"{results[f'jax_{label}_wall_s']:8.2f} "
              f"{results[f'jax_{label}_cpu_s']:8.2f}  {r.cost:.6e} {r.accepted_steps + 1:7d} "
              f"{r.steps + 1:7d} {'-':>9s}  "
              f"{method} {r.seconds:.2f} s, {r.accepted_steps} accepted, {r.code}")
    if "jax_eq_wall_s" in results:
        print("  piezojax, stopped at scipy's cost".ljust(39) + f"{results['jax_eq_wall_s']:8.2f} "
              f"{results['jax_eq_cpu_s']:8.2f}  {results['jax_eq_cost']:.6e} {results['jax_eq_jacobians']:7d} "
              f"{results['jax_eq_steps'] + 1:7d} {'-':>9s}  compiled; max_steps = first step at <= scipy's cost")
    for key, label in (("scipy_u", "same u"), ("scipy_b", "bounds")):
        if f"{key}_wall_s" in results:
            print(f"  scipy TRF 2-point + numba ({label})".ljust(39) + f"{results[key + '_wall_s']:8.2f} "
                  f"{results[key + '_cpu_s']:8.2f}  {results[key + '_cost']:.6e} {results[key + '_njev']:7d} "
                  f"{results[key + '_nfev']:7d} {results[key + '_calls']:9d}  status {results[key + '_status']}")
    print()
    for key, label in (("scipy_u", "same u"), ("scipy_b", "bounds")):
        if f"{key}_wall_s" not in results:
            continue
        for jl in ("cold", "warm") if warm_run else ("cold",):
            ratio = results[f"{key}_wall_s"] / results[f"jax_{jl}_wall_s"]
            cpu_ratio = results[f"{key}_cpu_s"] / results[f"jax_{jl}_cpu_s"]
            results[f"speedup_{key}_{jl}"] = ratio
            results[f"cpu_speedup_{key}_{jl}"] = cpu_ratio
            _line(f"speed-up vs scipy ({label}), piezojax {jl}: wall / CPU time", f"{ratio:.2f}x / {cpu_ratio:.2f}x")
        _line(f"final cost piezojax / scipy ({label})", f"{fr.cost / results[f'{key}_cost']:.6f}")
        if key == "scipy_u" and "jax_eq_wall_s" in results:
            for jl, extra in (("warm", 0.0), ("cold", results.get("jax_compile_wall_s", 0.0))):
                ratio = results["scipy_u_wall_s"] / (results["jax_eq_wall_s"] + extra)
                results[f"speedup_equal_cost_{jl}"] = ratio
                _line(f"speed-up to scipy's final cost, piezojax {jl}: wall", f"{ratio:.2f}x")
    print("\n  profile (warm, at the optimum):")
    _line("one residual evaluation (jit)", f"{results['jax_residuals_s'] * 1e3:.1f} ms")
    _line("one residuals + Jacobian (engine, jit)", f"{results['jax_jacobian_s'] * 1e3:.1f} ms")
    _line("one linearisation J^T J, J^T r (engine, jit)", f"{results['normal_equations_s'] * 1e3:.1f} ms")
    results["linearisation_over_residuals"] = results["normal_equations_s"] / results["jax_residuals_s"]
    _line("linearisation / residual evaluation", f"{results['linearisation_over_residuals']:.1f}x")
    _line("engine wall per step (warm solve / steps)", f"{fr.seconds / max(fr.steps, 1) * 1e3:.1f} ms")
    if warm_run:
        _line("compile: warm-up fit with max_steps=1 (compile + 1 step), wall",
              f"{results['jax_compile_wall_s']:.1f} s")
    _line("scipy wall per Jacobian (same u)",
          f"{results['scipy_u_wall_s'] / max(results['scipy_u_njev'], 1) * 1e3:.1f} ms")
    sys.stdout.flush()
    return results


def _physical_by_key(problem, u0):
    """The engine's physical parameters at `u0`, grouped in `_KEYS` order."""
    import jax.numpy as jnp

    m = problem.model_at(jnp.asarray(u0))
    return [m.hysteresis.w0, m.hysteresis.weights, m.hysteresis.thresholds, m.creep.stiffnesses,
            m.creep.time_constants, m.dynamics.omega, m.dynamics.zeta]


def _best(fn, repeats):
    fn()
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="4 experiments x 2500 samples (for tests)")
    parser.add_argument("--large", action="store_true", help="8 experiments x 1e5 samples, 22 plays (51 parameters)")
    parser.add_argument("--bounds-variant", action="store_true", help="also fit scipy on bounded physical parameters")
    parser.add_argument("--max-steps", type=int, default=None, help="engine steps (default 100, quick 60)")
    parser.add_argument("--progress", action="store_true", help="print the engine's progress on stderr")
    parser.add_argument("--linear-solver", choices=("qr", "cholesky"), default="cholesky",
                        help="the engine's LM linear solve: lx.Normal(lx.Cholesky()) (default) or lx.QR()")
    parser.add_argument("--no-scipy", action="store_true", help="run only the engine")
    parser.add_argument("--method", choices=("trust_region", "levenberg_marquardt"), default="trust_region",
                        help="the engine's `fitting.solve(method=...)` (default trust_region: scipy's algorithm)")
    parser.add_argument("--warm-cache", action="store_true",
                        help="also time the whole engine fit (compilation included) in two fresh processes sharing a "
                             "new persistent compilation cache: the first fills it, the second loads from it")
    parser.add_argument("--cache-dir", default=None, help=argparse.SUPPRESS)  # the child processes of --warm-cache
    args = parser.parse_args(argv)
    import piezojax as pj

    pj.enable_fast_cpu_scans()
    if args.cache_dir is not None:
        pj.enable_compilation_cache(args.cache_dir)
    import jax

    jax.config.update("jax_enable_x64", True)
    if args.cache_dir is not None:  # a child: one cold engine fit, its numbers as JSON on the last line
        import json

        out = run(quick=args.quick, large=args.large, max_steps=args.max_steps, warm_run=False, run_scipy=False,
                  method=args.method,
                  linear_solver=args.linear_solver)
        print(json.dumps({k: out[k] for k in ("jax_cold_wall_s", "jax_cost")}))
        return out
    results = run(quick=args.quick, large=args.large, bounds_variant=args.bounds_variant, max_steps=args.max_steps,
                  progress=args.progress, linear_solver=args.linear_solver, run_scipy=not args.no_scipy,
                  method=args.method)
    if args.warm_cache:
        results.update(_warm_cache_runs(args, results.get("scipy_u_wall_s")))
    return results


def _warm_cache_runs(args, scipy_wall: float | None) -> dict:
    """The engine fit, compilation included, in two fresh processes with a new shared compilation cache."""
    import json
    import subprocess
    import tempfile

    walls = []
    with tempfile.TemporaryDirectory() as cache:
        cmd = [sys.executable, "-m", "experiments.bench_calibration", "--cache-dir", cache, "--method", args.method,
               "--linear-solver", args.linear_solver]
        cmd += ["--quick"] if args.quick else ["--large"] if args.large else []
        cmd += ["--max-steps", str(args.max_steps)] if args.max_steps is not None else []
        for _ in range(2):
            done = subprocess.run(cmd, capture_output=True, text=True, check=True)
            walls.append(json.loads(done.stdout.strip().splitlines()[-1])["jax_cold_wall_s"])
    print(f"\n  fresh process, whole engine fit incl. compile: empty cache {walls[0]:.2f} s, "
          f"warm cache {walls[1]:.2f} s")
    if scipy_wall is not None:
        print(f"  speed-up vs scipy (same u), fresh process: empty cache {scipy_wall / walls[0]:.2f}x, "
              f"warm cache {scipy_wall / walls[1]:.2f}x")
    return {"jax_fresh_empty_cache_wall_s": walls[0], "jax_fresh_warm_cache_wall_s": walls[1]}


if __name__ == "__main__":
    main()
