"""BoucWenOscillator: the hysteretic benchmark system, integrated with diffrax or by fixed-step RK4 (and the RK4
scan and stage inputs it is built from)."""

import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate

import piezojax as pj
from piezojax._nonlinear.bouc_wen_oscillator import BoucWenOscillator, safe_abs_pow
from piezojax._nonlinear.fixed_step import rk4_scan, stage_inputs

DATA = pathlib.Path(__file__).resolve().parents[1] / "experiments" / "data" / "boucwen_benchmark" / "train.h5"
FS = 750.0
# Compiled once, shared by the tests below (compilation dominates their run time).
SIM = jax.jit(lambda u_: BoucWenOscillator().simulate(u_, 1 / FS))


def test_exported():
    assert pj.BoucWenOscillator is BoucWenOscillator


@pytest.fixture(scope="module")
def benchmark_record():
    h5py = pytest.importorskip("h5py")
    if not DATA.exists():
        pytest.skip(f"benchmark data not found at {DATA}")
    with h5py.File(DATA, "r") as f:
        g = f["multisine"]
        u = np.asarray(g["u"]).ravel()
        y = np.asarray(g["y"]).ravel()
        fs = float(np.asarray(g["fs"]).ravel()[0])
    assert fs == FS
    return u, y


def test_reproduces_benchmark_from_rest(benchmark_record):
    """First 1000 samples of train.h5 from its input, nominal parameters, starting from rest at sample 0, with the
    band-limited periodic hold of the 8192-sample multisine period: residual at the noise level (~7.4e-6 m, the
    RMS of half the period-to-period difference of the data), zero-mean and white. Linear interpolation of the
    input is measurably worse (the data were made from the continuous-time multisine)."""
    u, y = benchmark_record
    period = 8192
    # The data's periods differ only by noise: period-to-period RMS difference / sqrt(2) is the noise level
    # (periods 2 and 3: the first holds the start-up transient).
    noise = np.sqrt(np.mean((y[period:2 * period] - y[2 * period:3 * period]) ** 2) / 2)
    assert 6e-6 < noise < 9e-6
    bw = BoucWenOscillator()
    sim = jax.jit(lambda u_, hold: bw.simulate(u_, 1 / FS, hold=hold, num_samples=1000), static_argnums=1)
    res = y[:1000] - np.asarray(sim(u[:period], "periodic"))
    rms = np.sqrt(np.mean(res**2))
    print(f"benchmark: RMS residual {rms:.3e} m, noise level {noise:.3e} m")
    assert rms < 1.05 * noise, (rms, noise)
    assert abs(res.mean()) < 3 * noise / np.sqrt(1000)
    # The residual is noise: its lag-1 autocorrelation equals the noise's own (0.15, from the difference of two
    # periods of the data); a model error would be smooth, i.e. correlated close to 1.
    d = y[period:2 * period] - y[2 * period:3 * period]
    r_noise = np.corrcoef(d[:-1], d[1:])[0, 1]
    r_res = np.corrcoef(res[:-1], res[1:])[0, 1]
    assert abs(r_res - r_noise) < 0.1, (r_res, r_noise)
    # Starting from rest matters: the data's first samples are near 0 and match the start-up transient.
    assert np.sqrt(np.mean(res[:100] ** 2)) < 1.2 * noise
    rms_linear = np.sqrt(np.mean((y[:1000] - np.asarray(sim(u[:period], "linear"))) ** 2))
    assert rms_linear > 1.3 * rms


def _reference(bw, u, dt):
    """High-accuracy scipy DOP853 solution with the linearly interpolated input, one sample interval at a time."""
    p = {n: float(getattr(bw, n)) for n in ("m", "c", "k", "alpha", "beta", "gamma", "delta", "nu")}

    def f(t, s, k):
        y, v, z = s
        uu = u[k] + (u[k + 1] - u[k]) * (t - k * dt) / dt
        az = abs(z) ** p["nu"]
        dz = p["alpha"] * v - p["beta"] * (p["gamma"] * abs(v) * np.sign(z) * az + p["delta"] * v * az)
        return [v, (uu - p["c"] * v - p["k"] * y - z) / p["m"], dz]

    s = np.zeros(3)
    out = [0.0]
    for k in range(len(u) - 1):
        sol = scipy.integrate.solve_ivp(f, (k * dt, (k + 1) * dt), s, args=(k,), method="DOP853", rtol=1e-12,
                                        atol=[1e-16, 1e-13, 1e-10])
        s = sol.y[:, -1]
        out.append(s[0])
    return np.array(out)


@pytest.fixture(scope="module")
def short_input():
    rng = np.random.default_rng(7)
    n = 150
    t = np.arange(n) / FS
    u = sum(30 * np.sin(2 * np.pi * f * t + ph) for f, ph in zip((7.0, 23.0, 61.0), rng.uniform(0, 6, 3)))
    return u


def test_matches_scipy_reference(short_input):
    """Default adaptive Tsit5 (rtol 1e-8) and fixed steps (4 per sample) against DOP853 at rtol 1e-12. Measured:
    2.5e-9 m and 8.7e-8 m of 5.3e-4 m (the fixed-step error is second order: kinks of the vector field)."""
    u = short_input
    bw = BoucWenOscillator()
    ref = _reference(bw, u, 1 / FS)
    scale = np.abs(ref).max()
    adaptive = SIM(u)
    np.testing.assert_allclose(adaptive, ref, rtol=0, atol=2e-5 * scale)
    fixed = jax.jit(lambda u_: bw.simulate(u_, 1 / FS, rtol=None, substeps=4))(u)
    np.testing.assert_allclose(fixed, ref, rtol=0, atol=5e-4 * scale)


def test_jacfwd_matches_central_differences(short_input):
    u = short_input[:60]
    static = eqx.partition(BoucWenOscillator(), eqx.is_array)[1]

    def fn(logp, base):
        # Log-multipliers of the parameters (the well-scaled fitting coordinates; delta < 0 keeps its sign).
        model = eqx.combine(base, static)
        model = jax.tree_util.tree_map(lambda p, lp: p * jnp.exp(lp), model, logp)
        return model.simulate(u, 1 / FS, rtol=None) * 1e3  # fixed steps: FD sees no step-size changes

    # One compilation gives the Jacobian and (as aux) the values used for the finite differences.
    jac_fn = jax.jit(jax.jacfwd(lambda lp, b: (fn(lp, b), fn(lp, b)), has_aux=True))

    def fn_jit(lp, b):
        return jac_fn(lp, b)[1]

    for nu in (1.0, 1.5):
        base = eqx.partition(BoucWenOscillator(nu=nu), eqx.is_array)[0]
        p0 = jax.tree_util.tree_map(jnp.zeros_like, base)
        jac = jac_fn(p0, base)[0]
        h = 1e-6
        for name in ("m", "c", "k", "alpha", "beta", "gamma", "delta", "nu"):
            col = getattr(jac, name)
            # Finite everywhere, including z = 0 at the start: the safe power has no NaN derivative.
            assert np.all(np.isfinite(col)), name
            plus = eqx.tree_at(lambda t: getattr(t, name), p0, jnp.asarray(h))
            minus = eqx.tree_at(lambda t: getattr(t, name), p0, jnp.asarray(-h))
            fd = (fn_jit(plus, base) - fn_jit(minus, base)) / (2 * h)
            scale = np.abs(fd).max()
            assert scale > 1e-8, name
            np.testing.assert_allclose(col, fd, rtol=0, atol=2e-5 * scale, err_msg=f"nu={nu}, parameter {name}")


def test_vmap_over_inputs(short_input):
    us = np.stack([short_input, 0.5 * short_input, -short_input])
    batched = jax.jit(jax.vmap(SIM))(us)
    scale = np.abs(batched).max()
    # Adaptive steps: under vmap each member keeps its own step size but the batch shares the loop, so members
    # agree with the unbatched runs to the solver tolerance (measured 3e-12 m of 5e-4 m), not bit for bit.
    for i in range(3):
        np.testing.assert_allclose(batched[i], SIM(us[i]), rtol=0, atol=1e-6 * scale)
    # Odd symmetry of the model: -u gives -y.
    np.testing.assert_allclose(batched[2], -batched[0], rtol=0, atol=1e-6 * scale)


def test_safe_abs_pow():
    x = jnp.array([0.0, 0.5, -2.0])
    np.testing.assert_allclose(safe_abs_pow(x, 1.5), np.abs(np.asarray(x)) ** 1.5)
    dx, dp = jax.jacfwd(lambda x_, p_: safe_abs_pow(x_, p_), argnums=(0, 1))(x, jnp.asarray(1.5))
    assert np.all(np.isfinite(dx)) and np.all(np.isfinite(dp))
    assert dp[0] == 0.0
    np.testing.assert_allclose(dp[1], 0.5**1.5 * np.log(0.5))


def test_bad_input(short_input):
    bw = BoucWenOscillator()
    with pytest.raises(ValueError, match="`m`"):
        BoucWenOscillator(m=0.0)
    with pytest.raises(ValueError, match="`nu`"):
        BoucWenOscillator(nu=-1.0)
    with pytest.raises(ValueError, match="`k`"):
        BoucWenOscillator(k=np.nan)
    with pytest.raises(ValueError, match="`dt`"):
        bw.simulate(short_input, -1.0)
    with pytest.raises(ValueError, match="`u`"):
        bw.simulate(np.zeros(0), 1 / FS)
    with pytest.raises(ValueError, match="`u`"):
        bw.simulate(np.zeros((10, 2)), 1 / FS)
    with pytest.raises(ValueError, match="`hold`"):
        bw.simulate(short_input, 1 / FS, hold="spline")
    with pytest.raises(ValueError, match="`num_samples`"):
        bw.simulate(short_input, 1 / FS, num_samples=10_000)
    with pytest.raises(ValueError, match="`method`"):
        bw.simulate(short_input, 1 / FS, method="euler")
    with pytest.raises(ValueError, match='needs `hold="periodic"`'):
        bw.simulate(short_input, 1 / FS, method="rk4")
    with pytest.raises(ValueError, match="`num_samples`"):
        bw.simulate(short_input, 1 / FS, hold="periodic", method="rk4", num_samples=10_000)
    with pytest.raises(ValueError, match="`substeps`"):
        bw.simulate(short_input, 1 / FS, hold="periodic", method="rk4", substeps=0)
    # Data-dependent checks under jit (one compilation): NaN input, traced bad parameter, traced bad step.
    u = short_input[:20]
    run = jax.jit(lambda u_, m_, dt_: eqx.tree_at(lambda s: s.m, bw, m_).simulate(u_, dt_))
    assert np.all(np.isfinite(run(u, 2.0, 1 / FS)))
    with pytest.raises(Exception, match="`u` contains NaN"):
        run(np.where(np.arange(20) == 5, np.nan, u), 2.0, 1 / FS)
    with pytest.raises(Exception, match="BoucWenOscillator"):
        run(u, -2.0, 1 / FS)
    with pytest.raises(Exception, match="`dt`"):
        run(u, 2.0, -1 / FS)


# ---------------------------------------------------------------------------------------------------------------
# method="rk4": fixed-step RK4 under the band-limited input, and the parts it is built from.

DT = 1 / FS


def test_stage_inputs_band_limited():
    """Column 0 holds the samples, the last column the next sample (wrapping), and a sine with a whole number of
    periods in the record is interpolated exactly at the half-step times."""
    n, s = 64, 3
    t = np.arange(n) * DT
    f = 5 * FS / n
    u = np.sin(2 * np.pi * f * t + 0.3)
    tab = np.asarray(stage_inputs(jnp.asarray(u), DT, s))
    assert tab.shape == (n, 2 * s + 1)
    np.testing.assert_allclose(tab[:, 0], u, atol=1e-12)
    np.testing.assert_allclose(tab[:, -1], np.roll(u, -1), atol=1e-12)
    tt = t[:, None] + np.arange(2 * s + 1)[None, :] * DT / (2 * s)
    np.testing.assert_allclose(tab, np.sin(2 * np.pi * f * tt + 0.3), atol=1e-12)
    # transient record: zero padding, so the last sample's end point is u = 0 (the first pad sample)
    tab2 = np.asarray(stage_inputs(jnp.asarray(u), DT, s, periodic=False, pad=8))
    assert tab2.shape == (n, 2 * s + 1)
    assert tab2[-1, -1] == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(ValueError, match="substeps"):
        stage_inputs(jnp.asarray(u), DT, 0)
    with pytest.raises(ValueError, match="`u`"):
        stage_inputs(jnp.zeros((4, 2)), DT, 2)


def test_rk4_fourth_order_on_linear_ode():
    r"""$\dot x = -a x + u$, $u = \sin\omega t$ from rest: exact solution known; RK4 error falls 16x per halving."""
    n, a = 200, 30.0
    w = 2 * np.pi * 10 * FS / n  # 10 periods in the record: the band-limited input is exact
    t = np.arange(n) * DT
    u = np.sin(w * t)
    exact = (a * np.sin(w * t) - w * np.cos(w * t) + w * np.exp(-a * t)) / (a * a + w * w)
    errs = []
    for s in (1, 2, 4):
        _, xs = rk4_scan(lambda x, u_t, _: -a * x + u_t, jnp.zeros(1), stage_inputs(jnp.asarray(u), DT, s), DT)
        errs.append(np.max(np.abs(np.asarray(xs[:, 0]) - exact)))
    assert errs[2] < 1e-7 * np.max(np.abs(exact))
    assert 12 < errs[0] / errs[1] < 20 and 12 < errs[1] / errs[2] < 20, errs
    # jit / grad / jacfwd / vmap: d/da of the final state, three ways, and a batch of two inputs
    table = stage_inputs(jnp.asarray(u), DT, 2)

    def final(a_):
        return rk4_scan(lambda x, u_t, aa: -aa * x + u_t, jnp.zeros(1), table, DT, a_)[0][0]

    g = jax.grad(final)(a)
    assert float(jax.jit(jax.jacfwd(final))(a)) == pytest.approx(float(g), rel=1e-10)
    fd = (float(final(a + 1e-4)) - float(final(a - 1e-4))) / 2e-4
    assert float(g) == pytest.approx(fd, rel=1e-6)
    tables = jnp.stack([table, 2 * table])
    batch = jax.vmap(lambda tb: rk4_scan(lambda x, u_t, _: -a * x + u_t, jnp.zeros(1), tb, DT)[1])(tables)
    np.testing.assert_allclose(np.asarray(batch[1]), 2 * np.asarray(batch[0]), rtol=1e-12, atol=1e-18)


@pytest.fixture(scope="module")
def periodic_input():
    """Two periods of a 256-sample multisine (4 lines, 40 N each) and the adaptive Tsit5 response (rtol 1e-10)."""
    n = 256
    rng = np.random.default_rng(3)
    t = np.arange(n) / FS
    u = sum(40 * np.sin(2 * np.pi * k * FS / n * t + ph) for k, ph in zip((3, 8, 21, 40), rng.uniform(0, 6, 4)))
    u2 = np.tile(u, 2)
    return u2, np.asarray(BoucWenOscillator().simulate(u2, DT, hold="periodic", rtol=1e-10))


RK4 = jax.jit(lambda m, u_, s: m.simulate(u_, DT, hold="periodic", method="rk4", substeps=s), static_argnums=2)


def test_rk4_method_converges_to_adaptive(periodic_input):
    """`method="rk4"` against adaptive Tsit5 with the same periodic hold: the error falls with the sub-steps (about
    second order, the kinks of the vector field; measured RMS 1.5e-7, 2.6e-8, 9.9e-9 m with 4, 8, 16 sub-steps of a
    1.3e-3 m response)."""
    u2, ref = periodic_input
    bw = BoucWenOscillator()
    errs = {s: np.sqrt(np.mean((np.asarray(RK4(bw, u2, s)) - ref) ** 2)) for s in (4, 8, 16)}
    assert errs[4] < 3e-7 and errs[8] < errs[4] / 2.5 and errs[16] < errs[8] / 2, errs
    assert errs[16] < 1e-5 * np.abs(ref).max(), errs
    # state0 / return_state / num_samples: the second period from the state at its start is the same trajectory
    n = u2.shape[0] // 2
    y, states = bw.simulate(u2, DT, hold="periodic", method="rk4", substeps=4, return_state=True)
    assert states.shape == (2 * n, 3)
    np.testing.assert_allclose(np.asarray(states[:, 0]), np.asarray(y), rtol=0, atol=0)
    second = bw.simulate(u2[:n], DT, hold="periodic", method="rk4", substeps=4, state0=states[n])
    np.testing.assert_allclose(np.asarray(second), np.asarray(y[n:]), rtol=0, atol=1e-12 * np.abs(ref).max())
    head = bw.simulate(u2, DT, hold="periodic", method="rk4", substeps=4, num_samples=10)
    np.testing.assert_allclose(np.asarray(head), np.asarray(y[:10]), rtol=0, atol=1e-18)


def test_rk4_method_derivatives(periodic_input):
    """jacfwd (what the fit uses) against central differences and against reverse mode, in log-multipliers of the
    parameters (nu = 1.5, so that every parameter has an effect), over 100 samples with 2 sub-steps."""
    u = periodic_input[0][:100]
    base = BoucWenOscillator(nu=1.5)
    names = ("m", "c", "k", "alpha", "beta", "gamma", "delta", "nu")

    def f(lp):
        model = eqx.tree_at(lambda s: [getattr(s, n) for n in names], base,
                            [getattr(base, n) * jnp.exp(lp[i]) for i, n in enumerate(names)])
        return model.simulate(u, DT, hold="periodic", method="rk4", substeps=2) * 1e3

    lp = jnp.zeros(len(names))
    jac = np.asarray(jax.jit(jax.jacfwd(f))(lp))
    assert np.all(np.isfinite(jac))
    rev = np.asarray(jax.jit(jax.grad(lambda v: jnp.sum(f(v) ** 2)))(lp))
    y = np.asarray(f(lp))
    np.testing.assert_allclose(rev, 2 * jac.T @ y, rtol=1e-9, atol=1e-12 * np.abs(rev).max())
    fj, h = jax.jit(f), 1e-6
    for i, name in enumerate(names):
        e = jnp.zeros(len(names)).at[i].set(h)
        fd = (np.asarray(fj(lp + e)) - np.asarray(fj(lp - e))) / (2 * h)
        assert np.abs(fd).max() > 1e-8, name
        np.testing.assert_allclose(jac[:, i], fd, rtol=0, atol=2e-5 * np.abs(fd).max(), err_msg=name)
