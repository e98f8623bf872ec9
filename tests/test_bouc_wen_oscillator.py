"""BoucWenOscillator: the hysteretic benchmark system, integrated with diffrax."""

import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate

import piezojax as pj
from piezojax._nonlinear.bouc_wen_oscillator import BoucWenOscillator, safe_abs_pow

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
