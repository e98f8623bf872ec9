"""Creep blocks: logarithmic (FFT superposition), Kelvin–Voigt chain, LTI creep transfer function."""

import contextlib
import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.signal
from hypothesis import given, strategies as st
from jax.flatten_util import ravel_pytree

import piezojax as pj

LN10 = np.log(10.0)


@eqx.filter_jit
def _sim(block, u, dt, hold):
    return block.simulate(u, dt, hold=hold)


def sim(block, u, dt, hold="zoh"):
    """Compiled simulate (eager dispatch costs seconds of compilation per call); `dt` traced, so one compile serves
    every step size (the linear blocks' matrix exponential alone takes seconds to compile)."""
    return _sim(block, jnp.asarray(u), jnp.asarray(dt), hold)


@eqx.filter_jit
def step_response(block, t):
    return block.step_response(t)


def log_kernel(tau, gamma, t0, gain=1.0, offset=1.0):
    return gain * (offset + gamma * np.log10(np.maximum(tau, t0) / t0))


def jac_vs_fd(fn, model, rel=1e-4):
    """jacfwd of fn(model) wrt every inexact array leaf, and a 4-point central finite-difference Jacobian.

    The step is relative to each parameter (the kernels have large high derivatives in e.g. t0 near a sample).
    """
    params, static = eqx.partition(model, eqx.is_inexact_array)
    flat, unravel = ravel_pytree(params)
    f = jax.jit(lambda p: fn(eqx.combine(unravel(p), static)))
    jac = np.asarray(jax.jit(jax.jacfwd(f))(flat))
    fd = np.zeros_like(jac)
    for i in range(flat.shape[0]):
        h = rel * max(abs(float(flat[i])), 1e-2)
        e = jnp.zeros_like(flat).at[i].set(h)
        d1 = np.asarray(f(flat + e)) - np.asarray(f(flat - e))
        d2 = np.asarray(f(flat + 2 * e)) - np.asarray(f(flat - 2 * e))
        fd[:, i] = (8 * d1 - d2) / (12 * h)
    return jac, fd


@contextlib.contextmanager
def raises_runtime(match):
    """An error raised while running compiled code (eqx.error_if), whose message (anywhere in the chain) matches."""
    with pytest.raises(Exception) as info:
        yield
    texts, e = [], info.value
    while e is not None:
        texts.append(str(e))
        e = e.__cause__ or e.__context__
    assert re.search(match, "\n".join(texts)), texts


# ---------------------------------------------------------------------------------------------------------------------
# Logarithmic creep


def test_log_step_response_defines_the_block():
    creep = pj.LogarithmicCreep(gamma=0.03, t0=0.05, gain=2.0)
    dt, n, j0 = 1e-2, 400, 37
    u = np.zeros(n)
    u[j0:] = 1.0
    y = np.asarray(sim(creep, u, dt))
    k = np.arange(n)
    expected = np.where(k >= j0, log_kernel((k - j0) * dt, 0.03, 0.05, 2.0), 0.0)
    np.testing.assert_allclose(y, expected, rtol=0, atol=1e-13)
    # the analytic step response method agrees with the law δ0 (1 + γ log10(t/t0)) for t ≥ t0
    t = np.array([0.0, 0.01, 0.05, 0.5, 5.0, 500.0])
    np.testing.assert_allclose(step_response(creep, t), log_kernel(t, 0.03, 0.05, 2.0), rtol=1e-14)
    assert float(creep.step_response(500.0)) == pytest.approx(2.0 * (1 + 0.03 * 4), rel=1e-14)
    assert float(creep.instantaneous_gain()) == 2.0


def direct_zoh(u, dt, gamma, t0, gain, offset=1.0):
    du = np.diff(u, prepend=0.0)
    n = len(u)
    y = np.zeros(n)
    for k in range(n):
        for j in range(k + 1):
            y[k] += du[j] * log_kernel((k - j) * dt, gamma, t0, gain, offset)
    return y


def direct_foh(u, dt, gamma, t0, gain):
    """Piecewise-linear input from rest: step u0 at t=0, then ramps; each ramp's response by numerical quadrature."""
    n = len(u)
    y = np.zeros(n)

    def mean_h(a):
        val, _ = scipy.integrate.quad(
            lambda s: log_kernel(s, gamma, t0, gain), a, a + dt, points=[t0] if a < t0 < a + dt else None,
            epsabs=1e-14, epsrel=1e-13,
        )
        return val / dt

    means = [mean_h(m * dt) for m in range(n)]
    for k in range(n):
        y[k] = u[0] * log_kernel(k * dt, gamma, t0, gain)
        for j in range(1, k + 1):
            y[k] += (u[j] - u[j - 1]) * means[k - j]
    return y


def test_log_matches_direct_sum(rng):
    u = rng.standard_normal(150)
    dt, gamma, t0, gain = 3e-3, 0.04, 0.02, 1.5
    creep = pj.LogarithmicCreep(gamma, t0, gain)
    np.testing.assert_allclose(sim(creep, u, dt), direct_zoh(u, dt, gamma, t0, gain), rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        sim(creep, u, dt, hold="foh"), direct_foh(u, dt, gamma, t0, gain), rtol=0, atol=1e-11
    )
    # creep part alone (parallel use): same sum with the instantaneous 1 removed
    part = pj.LogarithmicCreep(gamma, t0, gain, instantaneous=False)
    np.testing.assert_allclose(sim(part, u, dt), direct_zoh(u, dt, gamma, t0, gain, 0.0), atol=1e-12)
    assert float(part.instantaneous_gain()) == 0.0


def test_log_foh_ramp_is_exact():
    # the ramp response R(t) = ∫_0^t h: t + γ (t log10(t/t0) - (t - t0)/ln10) for t ≥ t0
    dt, n, gamma, t0 = 1e-3, 3000, 0.02, 0.1
    t = np.arange(n) * dt
    y = sim(pj.LogarithmicCreep(gamma, t0), t, dt, hold="foh")
    safe = np.maximum(t, t0)
    ramp = t + gamma * np.where(t >= t0, t * np.log10(safe / t0) - (t - t0) / LN10, 0.0)
    np.testing.assert_allclose(y, ramp, rtol=0, atol=1e-12)


@given(
    a=st.floats(-3, 3),
    b=st.floats(-3, 3),
    shift=st.integers(0, 40),
    seed=st.integers(0, 2**31),
)
def test_log_superposition_and_time_invariance(a, b, shift, seed):
    r = np.random.default_rng(seed)
    n = 128
    u1, u2 = r.standard_normal(n), r.standard_normal(n)
    creep = pj.LogarithmicCreep(0.05, 0.01)
    y1, y2 = np.asarray(sim(creep, u1, 1e-3)), np.asarray(sim(creep, u2, 1e-3))
    np.testing.assert_allclose(sim(creep, a * u1 + b * u2, 1e-3), a * y1 + b * y2, rtol=0, atol=1e-11)
    delayed = np.concatenate([np.zeros(shift), u1])[:n]
    yd = np.asarray(sim(creep, delayed, 1e-3))
    np.testing.assert_allclose(yd[shift:], y1[: n - shift], rtol=0, atol=1e-11)
    np.testing.assert_allclose(yd[:shift], 0.0, atol=1e-12)


def test_log_jacfwd_matches_fd(rng):
    u = jnp.asarray(rng.standard_normal(200))
    for hold in ("zoh", "foh"):
        creep = pj.LogarithmicCreep(0.04, 0.0123, 1.3)
        jac, fd = jac_vs_fd(lambda c: c.simulate(u, 1e-3, hold=hold), creep)
        assert jac.shape == (200, 3)
        np.testing.assert_allclose(jac, fd, rtol=1e-6, atol=1e-8)
        assert np.abs(jac[:, 1]).max() > 1e-3  # t0 really enters


def test_log_vmap_and_float32(rng):
    creep = pj.LogarithmicCreep(0.02, 0.1)
    u = rng.standard_normal((4, 300))
    batched = jax.vmap(lambda x: sim(creep, x, 1e-3, hold="foh"))(u)
    for i in range(4):
        np.testing.assert_allclose(batched[i], sim(creep, u[i], 1e-3, hold="foh"), atol=1e-14)
    # float32 signal + float32 parameters run in float32 and stay accurate on a long record
    t = np.arange(100_000) * 1e-3
    c32 = pj.LogarithmicCreep(np.float32(0.02), np.float32(0.1))
    y32 = sim(c32, jnp.asarray(np.ones_like(t), jnp.float32), np.float32(1e-3))
    assert y32.dtype == jnp.float32
    np.testing.assert_allclose(y32, log_kernel(t, 0.02, 0.1), rtol=2e-5)


def test_log_bad_input():
    with pytest.raises(ValueError, match="t0"):
        pj.LogarithmicCreep(0.02, 0.0)
    with pytest.raises(ValueError, match="t0"):
        pj.LogarithmicCreep(0.02, -1.0)
    with pytest.raises(ValueError, match="gamma"):
        pj.LogarithmicCreep(np.ones(2), 0.1)
    creep = pj.LogarithmicCreep(0.02, 0.1)
    with pytest.raises(ValueError, match="`u`"):
        creep.simulate(jnp.zeros(0), 1e-3)
    with pytest.raises(ValueError, match="`u`"):
        creep.simulate(jnp.zeros((2, 5)), 1e-3)
    with raises_runtime("`u` contains NaN"):
        sim(creep, jnp.array([0.0, jnp.nan, 1.0]), 1e-3)
    with pytest.raises(ValueError, match="`dt`"):
        creep.simulate(jnp.ones(5), 0.0)
    with pytest.raises(ValueError, match="hold"):
        creep.simulate(jnp.ones(5), 1e-3, hold="cubic")
    # a bad value that bypasses __init__ (as fitting does with tree_at) is caught under jit
    bad = eqx.tree_at(lambda c: c.t0, creep, jnp.asarray(-0.1))
    with raises_runtime("t0"):
        jax.jit(lambda c: c.simulate(jnp.ones(5), 1e-3))(bad)
    with raises_runtime("dt"):
        sim(creep, jnp.ones(5), -1e-3)  # traced dt: checked at run time


# ---------------------------------------------------------------------------------------------------------------------
# Kelvin–Voigt chain


def kv_step(t, k, tau, k0):
    t = np.asarray(t)[..., None]
    return (0.0 if k0 is None else 1 / k0) + np.sum(-np.expm1(-t / tau) / k, axis=-1)


def kv_scipy(u, dt, k, tau, k0, interp):
    """Reference: scipy.signal.lsim, one first-order lag per element, summed."""
    t = np.arange(len(u)) * dt
    y = (0.0 if k0 is None else 1 / k0) * u
    for ki, ti in zip(k, tau):
        _, yi, _ = scipy.signal.lsim(([1 / ki], [ti, 1.0]), u, t, interp=interp)
        y = y + yi
    return y


K, TAU = np.array([20.0, 50.0, 8.0]), np.array([0.05, 2.0, 40.0])


def test_kv_step_response_analytic():
    creep = pj.KelvinVoigtCreep(K, TAU, k0=2.0)
    dt, n = 1e-2, 3000
    t = np.arange(n) * dt
    np.testing.assert_allclose(sim(creep, np.ones(n), dt), kv_step(t, K, TAU, 2.0), rtol=1e-13)
    np.testing.assert_allclose(step_response(creep, t), kv_step(t, K, TAU, 2.0), rtol=1e-14)
    assert float(creep.instantaneous_gain()) == 0.5
    # exact ramp response t/k0 + Σ (t - τ(1 - e^{-t/τ}))/k_i with the FOH hold
    ramp = t / 2.0 + np.sum((t[:, None] - TAU * (1 - np.exp(-t[:, None] / TAU))) / K, axis=1)
    np.testing.assert_allclose(sim(creep, t, dt, hold="foh"), ramp, rtol=1e-12, atol=1e-14)


def test_kv_matches_scipy_lsim(rng):
    u = rng.standard_normal(500)
    dt = 7e-3
    for k0 in (1.5, None):
        creep = pj.KelvinVoigtCreep(K, TAU, k0=k0)
        for hold, interp in (("zoh", False), ("foh", True)):
            ref = kv_scipy(u, dt, K, TAU, k0, interp)
            np.testing.assert_allclose(sim(creep, u, dt, hold=hold), ref, rtol=0, atol=1e-11)


def test_kv_slow_creep_with_fast_sampling_stays_exact():
    # dt/τ = 1e-8: the FOH coefficients would cancel catastrophically if computed naively
    k, tau, dt, n = np.array([4.0]), np.array([1e5]), 1e-3, 20_000
    t = np.arange(n) * dt
    creep = pj.KelvinVoigtCreep(k, tau, k0=None)
    x = t / tau[0]  # ≤ 2e-4: the series of (x - 1 + e^{-x}) is exact to 1e-14 here (the closed form is not)
    ramp = tau[0] * x**2 * (1 / 2 - x / 6 + x**2 / 24) / k[0]
    y = np.asarray(sim(creep, t, dt, hold="foh"))
    np.testing.assert_allclose(y[1:], ramp[1:], rtol=1e-8)
    y0 = np.asarray(sim(creep, np.ones(n), dt))
    np.testing.assert_allclose(y0[1:], kv_step(t, k, tau, None)[1:], rtol=1e-9)


def test_kv_jacfwd_matches_fd(rng):
    u = jnp.asarray(rng.standard_normal(300))
    for k0, hold in ((2.0, "zoh"), (None, "foh")):
        creep = pj.KelvinVoigtCreep(K, TAU * 0.01, k0=k0)
        jac, fd = jac_vs_fd(lambda c: c.simulate(u, 1e-3, hold=hold), creep)
        assert jac.shape == (300, 6 + (k0 is not None))
        np.testing.assert_allclose(jac, fd, rtol=1e-5, atol=1e-9)


def test_settled_start_derivatives_match_fd(rng):
    # `simulate(u, dt, u0=c)` = settled_gain() * c + C[u - c]: the settled gain's derivatives enter every sample (a
    # fitted remanent state before a series creep); the Kelvin–Voigt gain once came out as step_response(inf), whose
    # derivative in tau is inf * exp(-inf) = NaN
    u = jnp.asarray(3.0 + rng.standard_normal(300))
    blocks = [pj.KelvinVoigtCreep(K, TAU * 0.01, k0=2.0), pj.KelvinVoigtCreep(K, TAU * 0.01, k0=None),
              pj.LagCreep(fractions=[0.2, 0.1], time_constants=[0.02, 0.3]),
              pj.LinearCreep(pj.StableTransferFunction(gain=0.7, poles=[-5.0, -40.0], zeros=[-20.0]))]
    for creep in blocks:
        jac, fd = jac_vs_fd(lambda c: c.simulate(u, 1e-3, u0=3.0), creep)
        assert np.all(np.isfinite(jac)), type(creep).__name__
        np.testing.assert_allclose(jac, fd, rtol=1e-5, atol=1e-9 * np.abs(fd).max(), err_msg=type(creep).__name__)


def test_lag_scan_hand_derivatives_equal_autodiff(rng):
    # the hand-derived JVP (sensitivities in one scan) against autodiff through the plain recurrence: parameter and
    # input directions, forward (jacfwd) and reverse (grad) mode, and second order
    from piezojax._creep.lags import lag_scan

    def plain(a, b0, b1, c, u, u_next):
        def step(x, uu):
            return a * x + b0 * uu[0] + b1 * uu[1], jnp.sum(c * x)

        return jax.lax.scan(step, jnp.zeros_like(c), jnp.stack([u, u_next], axis=1))[1]

    n = 200
    args = (jnp.array([0.9, 0.99, 0.5]), jnp.array([0.1, 0.01, 0.3]), jnp.array([0.02, 0.0, 0.2]),
            jnp.array([1.5, -0.7, 2.0]), jnp.asarray(rng.standard_normal(n)), jnp.asarray(rng.standard_normal(n)))
    np.testing.assert_allclose(lag_scan(*args), plain(*args), rtol=1e-13, atol=1e-13)
    every = tuple(range(6))
    for got, want in zip(jax.jit(jax.jacfwd(lag_scan, argnums=every))(*args),
                         jax.jit(jax.jacfwd(plain, argnums=every))(*args)):
        np.testing.assert_allclose(got, want, rtol=1e-11, atol=1e-12)
    loss = lambda f: lambda *a: jnp.sum(jnp.sin(f(*a)))  # noqa: E731
    for got, want in zip(jax.grad(loss(lag_scan), argnums=every)(*args), jax.grad(loss(plain), argnums=every)(*args)):
        np.testing.assert_allclose(got, want, rtol=1e-11, atol=1e-12)
    hess = jax.hessian(loss(lag_scan), argnums=0)(*args)
    np.testing.assert_allclose(hess, jax.hessian(loss(plain), argnums=0)(*args), rtol=1e-9, atol=1e-10)
    # parameters only (measured input: symbolic-zero input tangents) — the path a fit takes
    jp = jax.jacfwd(lambda p: lag_scan(p[0], p[1], p[2], p[3], args[4], args[5]))(jnp.stack(args[:4]))
    np.testing.assert_allclose(jp, jax.jacfwd(lambda p: plain(p[0], p[1], p[2], p[3], args[4], args[5]))(
        jnp.stack(args[:4])), rtol=1e-11, atol=1e-12)


def test_kv_vmap(rng):
    creep = pj.KelvinVoigtCreep(K, TAU)
    u = rng.standard_normal((3, 200))
    batched = jax.vmap(lambda x: sim(creep, x, 1e-2, hold="foh"))(u)
    for i in range(3):
        np.testing.assert_allclose(batched[i], sim(creep, u[i], 1e-2, hold="foh"), atol=1e-14)
    # vmap over parameter sets as well (e.g. a population of actuators)
    creeps = jax.vmap(lambda k: pj.KelvinVoigtCreep(k, TAU))(jnp.stack([K, 2 * K]))
    ys = jax.jit(jax.vmap(lambda c: c.simulate(u[0], 1e-2)))(creeps)
    np.testing.assert_allclose(ys[1] - u[0], (ys[0] - u[0]) / 2, atol=1e-14)


def test_kv_bad_input():
    with pytest.raises(ValueError, match="time_constants"):
        pj.KelvinVoigtCreep([1.0, 2.0], [0.1, -0.2])
    with pytest.raises(ValueError, match="stiffnesses"):
        pj.KelvinVoigtCreep([0.0, 2.0], [0.1, 0.2])
    with pytest.raises(ValueError, match="same shape"):
        pj.KelvinVoigtCreep([1.0, 2.0], [0.1])
    with pytest.raises(ValueError, match="k0"):
        pj.KelvinVoigtCreep([1.0], [0.1], k0=-1.0)
    with pytest.raises(ValueError, match="time_constants"):
        pj.KelvinVoigtCreep([1.0], [np.nan])
    creep = pj.KelvinVoigtCreep([1.0], [0.1])
    with raises_runtime("`u` contains NaN"):
        sim(creep, jnp.array([0.0, jnp.inf]), 1e-3)
    bad = eqx.tree_at(lambda c: c.time_constants, creep, jnp.asarray([-0.1]))
    with raises_runtime("time_constants"):
        jax.jit(lambda c: c.simulate(jnp.ones(5), 1e-3))(bad)


# ---------------------------------------------------------------------------------------------------------------------
# LTI creep transfer function F_C(s) (paper 001 eq. 9)


def test_first_order_linear_creep_step_response_analytic():
    # F_C(s) = (a0 s + a1)/(s + b1): h(t) = a1/b1 + (a0 - a1/b1) e^{-b1 t}
    a0, a1, b1 = 1.0, 0.3, 0.2
    t = np.arange(2000) * 1e-2
    h = a1 / b1 + (a0 - a1 / b1) * np.exp(-b1 * t)
    creep = pj.LinearCreep.from_tf([a0, a1], [1.0, b1])  # stable parametrisation: pole -b1
    np.testing.assert_allclose(sim(creep, np.ones_like(t), 1e-2), h, rtol=1e-12)
    np.testing.assert_allclose(step_response(creep, t[::100]), h[::100], rtol=1e-12)
    assert float(creep.instantaneous_gain()) == pytest.approx(a0, rel=1e-14)


NUM4 = np.array([0.0, 0.0, 0.0, 0.02, 0.002])
DEN4 = np.array([1.0, 1.2, 0.4, 0.04, 0.001])


def test_fourth_order_linear_creep_matches_scipy(rng):
    creep = pj.LinearCreep.from_tf(NUM4, DEN4)
    assert creep.system.order == 4
    dt, n = 0.05, 1500
    u = np.cumsum(rng.standard_normal(n)) * 0.1
    t = np.arange(n) * dt
    for hold, interp in (("zoh", False), ("foh", True)):
        _, ref, _ = scipy.signal.lsim((NUM4, DEN4), u, t, interp=interp)
        np.testing.assert_allclose(sim(creep, u, dt, hold=hold), ref, rtol=0, atol=1e-10 * np.abs(ref).max())
    _, step = scipy.signal.step((NUM4, DEN4), T=t)
    np.testing.assert_allclose(sim(creep, np.ones(n), dt), step, rtol=1e-9, atol=1e-12)


def test_linear_creep_jacfwd_and_bad_input(rng):
    system = pj.StableTransferFunction(gain=0.2, omega=[0.3], zeta=[0.7], poles=[-0.05, -1.0], zeros=[-0.5])
    creep = pj.LinearCreep(system)
    u = jnp.asarray(rng.standard_normal(300))
    jac, fd = jac_vs_fd(lambda c: c.simulate(u, 0.05), creep)
    assert jac.shape == (300, 6)  # gain, omega, zeta, two poles, one zero
    np.testing.assert_allclose(jac, fd, rtol=1e-5, atol=1e-9 * np.abs(fd).max())
    with pytest.raises(ValueError, match="den"):
        pj.LinearCreep.from_tf([1.0], [1.0, -0.1])  # unstable: a creep must settle
    with pytest.raises(ValueError, match="system"):
        pj.LinearCreep([1.0, 2.0])
    with pytest.raises(ValueError, match="poles"):
        pj.LinearCreep(pj.StableTransferFunction(poles=[0.1]))


def _lag_reference(u, dt, tau, hold):
    # continuous-time lag integrated by scipy (not piezojax): the input between samples as each hold defines it
    n = len(u)
    t = np.arange(n) * dt

    def u_of(s):
        if hold == "zoh":  # u[k] on [t_k, t_k+1)
            return u[min(int(np.floor(s / dt + 1e-12)), n - 1)]
        if hold == "interval":  # u[k] on (t_k-1, t_k]
            return u[min(int(np.ceil(s / dt - 1e-12)), n - 1)]
        k = min(int(np.floor(s / dt)), n - 2)  # foh: linear between samples
        return u[k] + (u[k + 1] - u[k]) * (s / dt - k)

    y, x = np.zeros(n), 0.0
    if hold == "interval":  # the first sample is the mean over (t_-1, t_0]: from rest at t_-1
        x = -np.expm1(-dt / tau) * u[0]
    y[0] = x
    for k in range(1, n):
        sol = scipy.integrate.solve_ivp(lambda s, z: [(u_of(s) - z[0]) / tau], (t[k - 1], t[k]), [x],
                                        rtol=1e-11, atol=1e-14, max_step=dt / 8)
        x = sol.y[0, -1]
        y[k] = x
    return y


@pytest.mark.parametrize("hold", ["zoh", "foh", "interval"])
def test_lag_conventions_match_ode_and_numpy_columns(rng, hold):
    # the one first-order lag: JAX (`lag_sum`) and NumPy (`lag_columns`) forms agree, and each hold is the exact
    # solution of tau y' = u - y for its input between samples (integrated by scipy)
    from piezojax._creep.lags import lag_columns, lag_sum

    dt, taus, c = 1e-3, np.array([2e-3, 0.05]), np.array([0.7, -1.3])
    u = rng.standard_normal(40)
    got = np.asarray(lag_sum(jnp.asarray(c), jnp.asarray(taus), jnp.asarray(u), jnp.asarray(dt), hold))
    cols = lag_columns(u, dt, taus, hold)
    np.testing.assert_allclose(cols @ c, got, rtol=1e-12, atol=1e-13)
    for j, tau in enumerate(taus):
        np.testing.assert_allclose(cols[:, j], _lag_reference(u, dt, tau, hold), rtol=1e-7, atol=1e-9)
    if hold != "interval":  # the creep blocks read their input with the same lags
        np.testing.assert_allclose(pj.KelvinVoigtCreep(1 / c[:1], taus[:1], k0=None).simulate(u, dt, hold=hold),
                                   cols[:, :1] @ c[:1], rtol=1e-12, atol=1e-13)
    # "interval" is "zoh" one sample earlier
    if hold == "interval":
        np.testing.assert_allclose(cols[:-1], lag_columns(u, dt, taus, "zoh")[1:], rtol=1e-12, atol=1e-13)
    with pytest.raises(pj.PiezojaxValueError, match="`hold` must be one of"):
        lag_columns(u, dt, taus, "linear")
