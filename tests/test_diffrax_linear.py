"""The shared diffrax path (`simulate_ode`) on a linear system against the exact matrix-exponential solution."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
import scipy.signal

import piezojax as pj
from piezojax._nonlinear._input import SampledInput


def _random_stable_third_order(rng):
    """A random stable 3rd-order SISO system (a real pole and a complex pair), as (A, B, C, D)."""
    p_real = -rng.uniform(50.0, 300.0)
    wn, zeta = rng.uniform(100.0, 400.0), rng.uniform(0.05, 0.5)
    den = np.polymul([1.0, -p_real], [1.0, 2 * zeta * wn, wn**2])
    num = rng.normal(size=3) * np.array([1.0, 1e2, 1e4])
    a, b, c, d = scipy.signal.tf2ss(num, den)
    return a, b[:, 0], c[0], float(d[0, 0]), num, den


def _expm_simulation(a, b, c, d, u, dt, hold):
    """Exact solution at the samples for the held input (Van Loan block matrix exponential, written here)."""
    n = a.shape[0]
    big = np.zeros((n + 2, n + 2))
    big[:n, :n] = a * dt
    big[:n, n] = b * dt
    big[n, n + 1] = 1.0
    e = scipy.linalg.expm(big)
    phi, g0, g1 = e[:n, :n], e[:n, n], e[:n, n + 1]  # g1 = int_0^dt e^{A(dt-s)} B s/dt ds
    x = np.zeros(n)
    ys = []
    for k in range(len(u)):
        ys.append(c @ x + d * u[k])
        if k + 1 == len(u):
            break
        if hold == "zoh":
            x = phi @ x + g0 * u[k]
        else:
            x = phi @ x + g0 * u[k] + g1 * (u[k + 1] - u[k])
    return np.array(ys)


@pytest.fixture(scope="module")
def system():
    rng = np.random.default_rng(3)
    a, b, c, d, num, den = _random_stable_third_order(rng)
    dt = 1e-3
    u = np.cumsum(rng.normal(size=200))
    return a, b, c, d, num, den, dt, u


@pytest.mark.parametrize("hold", ["zoh", "linear"])
def test_linear_system_matches_matrix_exponential(system, hold):
    a, b, c, d, num, den, dt, u = system
    A, Bv = jnp.asarray(a), jnp.asarray(b)

    def vf(t, x, u_t, args):
        return A @ x + Bv * u_t

    xs = jax.jit(lambda u_: pj.simulate_ode(vf, jnp.zeros(3), u_, dt, hold=hold))(u)
    y = xs @ c + d * u
    ref = _expm_simulation(a, b, c, d, u, dt, "zoh" if hold == "zoh" else "foh")
    scale = np.abs(ref).max()
    np.testing.assert_allclose(y, ref, rtol=0, atol=1e-6 * scale)
    # scipy agrees with the reference we wrote (lsim is the linear hold).
    if hold == "linear":
        _, y_lsim, _ = scipy.signal.lsim((num, den), u, np.arange(len(u)) * dt)
        np.testing.assert_allclose(y_lsim, ref, rtol=0, atol=1e-9 * scale)
    # And piezojax's linear block (exact discretisation) agrees too.
    tf = pj.TransferFunction(num, den)
    y_tf = tf.simulate(u, dt, hold="zoh" if hold == "zoh" else "foh")
    np.testing.assert_allclose(y_tf, ref, rtol=0, atol=1e-6 * scale)


def test_adaptive_mode_and_jacfwd(system):
    """Adaptive (PID) mode hits the same solution; jacfwd through the diffrax path equals the exact sensitivity
    (the output is linear in B, so d y / d B_i is the response of the system with input matrix e_i)."""
    a, b, c, d, num, den, dt, u = system
    A = jnp.asarray(a)

    def run(bvec):
        return pj.simulate_ode(lambda t, x, u_t, bb: A @ x + bb * u_t, jnp.zeros(3), u, dt, bvec, hold="zoh",
                               rtol=1e-10, atol=1e-10)

    def out(bb):
        y = run(bb) @ c
        return y, y

    jac, y = jax.jit(jax.jacfwd(out, has_aux=True))(jnp.asarray(b))  # one compilation for both
    ref = _expm_simulation(a, b, c, d, u, dt, "zoh")
    np.testing.assert_allclose(y + d * u, ref, rtol=0, atol=1e-6 * np.abs(ref).max())
    for i in range(3):
        e = np.zeros(3)
        e[i] = 1.0
        col = _expm_simulation(a, e, c, 0.0, u, dt, "zoh")
        np.testing.assert_allclose(jac[:, i], col, rtol=0, atol=1e-6 * np.abs(col).max())


def test_periodic_hold_is_band_limited_interpolation():
    """The periodic hold reproduces a band-limited periodic signal between its samples (including the Nyquist
    cosine), with the Hermite error bound (omega h)^4 / 384 at the knots' spacing."""
    n, dt = 64, 0.01
    t = np.arange(n) * dt

    def sig(tt):
        return np.sin(2 * np.pi * 3.125 * tt) + 0.3 * np.cos(2 * np.pi * 50 * tt) + 0.2 * np.sin(2 * np.pi * 20.3125 * tt)

    tt = np.linspace(0.0, 2 * n * dt, 2001)  # two periods: the held signal repeats

    @jax.jit
    def held(samples, times):
        inp = SampledInput.from_samples(samples, dt, hold="periodic", upsample=16)
        return jax.vmap(inp.evaluate)(times)

    err = np.abs(np.asarray(held(sig(t), jnp.asarray(tt))) - sig(tt)).max()
    # Cubic Hermite bound h^4 max|fourth derivative| / 384 with exact knot values and slopes (measured 1.17e-6).
    h = dt / 16
    bound = h**4 / 384 * sum(a * (2 * np.pi * f) ** 4 for a, f in ((1.0, 3.125), (0.3, 50.0), (0.2, 20.3125)))
    assert err < bound
    np.testing.assert_allclose(held(sig(t), jnp.asarray(t)), sig(t), atol=1e-12)


def test_bad_input():
    f = lambda t, x, u, a: -x + u  # noqa: E731
    with pytest.raises(ValueError, match="`dt`"):
        pj.simulate_ode(f, jnp.zeros(()), jnp.ones(10), 0.0)
    with pytest.raises(ValueError, match="`u`"):
        pj.simulate_ode(f, jnp.zeros(()), jnp.ones(0), 0.1)
    with pytest.raises(ValueError, match="`hold`"):
        pj.simulate_ode(f, jnp.zeros(()), jnp.ones(10), 0.1, hold="sinc")
    with pytest.raises(ValueError, match="`substeps`"):
        pj.simulate_ode(f, jnp.zeros(()), jnp.ones(10), 0.1, substeps=0)
    with pytest.raises(Exception, match="`u` contains NaN"):
        pj.simulate_ode(f, jnp.zeros(()), jnp.array([1.0, jnp.nan]), 0.1)


def test_a_failed_integration_raises_or_refuses_as_nan_per_member():
    # y' = a y^2 from y(0) = 1 blows up at t = 1/a: with a = 2 inside the record of 1 s the adaptive steps shrink
    # until the step budget is spent (diffrax fails); with a = 0.5 the solution is 1 / (1 - a t)
    from piezojax._checks import refusals_as_nan

    f = lambda t, y, u, a: a * y**2  # noqa: E731
    dt, n = 0.1, 11

    def run(a):
        return pj.simulate_ode(f, jnp.ones(()), jnp.zeros(n), dt, a, hold="zoh", rtol=1e-8)

    with pytest.raises(eqx.EquinoxRuntimeError):
        jax.block_until_ready(eqx.filter_jit(run)(jnp.asarray(2.0)))
    with refusals_as_nan():
        ys = jax.jit(jax.vmap(run))(jnp.array([0.5, 2.0]))  # traced in the refusal mode: each member alone
    t = np.arange(n) * dt
    np.testing.assert_allclose(np.asarray(ys[0]), 1 / (1 - 0.5 * t), rtol=1e-6)
    assert np.all(np.isnan(np.asarray(ys[1])))
    # fixed steps have no step budget: the states that blow up come back as they are (a start's candidate scan and
    # the plot of a failed fit rely on it), documented
    ys = pj.simulate_ode(f, jnp.ones(()), jnp.zeros(n), dt, 5.0, hold="zoh")
    assert np.isfinite(float(ys[1])) and not np.all(np.isfinite(np.asarray(ys)))
