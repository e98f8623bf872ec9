"""ElectromechanicalActuator (Goldfarb & Celanovic model with Maxwell-slip hysteresis, paper 003 §3.3)."""

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize
import scipy.signal

import piezojax as pj
from piezojax._nonlinear.electromechanical import ElectromechanicalActuator, maxwell_voltages, solve_charge

M, K, C, T = 0.01, 1e5, 1e-6, 0.5
B = 2 * 0.1 * np.sqrt(K * M)  # damping ratio 0.1, resonance sqrt(k/m) = 3162 rad/s
CAPS = np.array([0.5e-6, 0.5e-6, 0.5e-6, 0.5e-6, 0.5e-6, 0.5e-6])
LIMS = np.array([2.0, 4.0, 6.0, 8.0, 10.0, 12.0])


def test_exported():
    assert pj.ElectromechanicalActuator is ElectromechanicalActuator


def _linear_reference(v, f, dt, hold, t_em=T):
    """x and q of the linear model m x'' + b x' + k x = T v - f, q = C v + T x (exact discretisation)."""
    a = np.array([[0.0, 1.0], [-K / M, -B / M]])
    bmat = np.array([[0.0, 0.0], [t_em / M, -1.0 / M]])
    sys = (a, bmat, np.array([[1.0, 0.0]]), np.zeros((1, 2)))
    u = np.stack([v, f], axis=1)
    t = np.arange(len(v)) * dt
    if hold == "linear":
        _, x, _ = scipy.signal.lsim(sys, u, t)
    else:
        ad, bd, cd, dd, _ = scipy.signal.cont2discrete(sys, dt, method="zoh")
        s = np.zeros(2)
        x = []
        for uk in u:
            x.append(s[0])
            s = ad @ s + bd @ uk
        x = np.array(x)
    return x, C * v + t_em * x


@pytest.mark.parametrize("hold, elements", [("linear", "none"), ("zoh", "zero_breakaway")])
def test_no_hysteresis_reduces_to_linear_model(hold, elements):
    """V_H = 0 (no elements, or elements with zero breakaway voltage): exact linear solution (lsim / ZOH expm)."""
    rng = np.random.default_rng(0)
    dt, n = 1e-4, 300
    t = np.arange(n) * dt
    v = 20 * np.cumsum(rng.normal(size=n)) / np.sqrt(n)
    f = 0.5 * np.sin(2 * np.pi * 150 * t)
    if elements == "none":
        act = ElectromechanicalActuator(M, B, K, C, [T])
    else:
        act = ElectromechanicalActuator(M, B, K, C, [T], CAPS, np.zeros(6))
    out = act.simulate(v, dt, f, hold=hold, substeps=8)
    x_ref, q_ref = _linear_reference(v, f, dt, hold)
    assert np.abs(out["v_h"]).max() == 0.0
    np.testing.assert_allclose(out["x"], x_ref, rtol=0, atol=1e-7 * np.abs(x_ref).max())
    np.testing.assert_allclose(out["q"], q_ref, rtol=0, atol=1e-7 * np.abs(q_ref).max())
    np.testing.assert_allclose(out["v_p"], v, rtol=0, atol=1e-12)


def test_zero_order_hold_with_elements_converges_at_the_integrator_order():
    """With a zero-order hold the input, and so the charge, jumps at every sample; the elements must start the
    substeps from the state after that jump. They had moved on a straight path from before it, which made the
    hysteresis voltage first order in the substep (3.9e-3 at 8 substeps, 1.8e-4 at 128, against 512)."""
    act = ElectromechanicalActuator(m=0.01, b=5.0, k=1e5, capacitance=1e-6, t_em=[0.5],
                                    element_capacitances=jnp.full(5, 2e-6), breakaway_voltages=jnp.arange(1.0, 6.0))
    t = np.arange(400) * 1e-4
    v = 60 * np.sin(2 * np.pi * 50 * t) * np.minimum(1, t / 0.002) + 20 * np.sin(2 * np.pi * 130 * t)
    fine = act.simulate(v, 1e-4, hold="zoh", substeps=256)
    for substeps, tol in ((8, 2e-5), (32, 2e-6)):  # measured 3.0e-6 and 4.2e-7 against 512 substeps
        out = act.simulate(v, 1e-4, hold="zoh", substeps=substeps)
        for key in ("v_h", "x", "q"):
            err = float(jnp.max(jnp.abs(out[key] - fine[key])) / jnp.max(jnp.abs(fine[key])))
            assert err < tol, (substeps, key, err)


def test_solve_charge_is_exact():
    """The piecewise-linear implicit solve equals a bracketing root find of q + C V_H(q) = rhs."""
    rng = np.random.default_rng(1)
    caps = rng.uniform(0.2e-6, 2e-6, 7)
    lims = rng.uniform(0.0, 10.0, 7)
    solve = jax.jit(solve_charge)
    for _ in range(20):
        s0 = rng.uniform(-1, 1, 7) * lims
        q0 = rng.normal() * 1e-5
        rhs = rng.normal() * 1e-4

        def g(q):
            return q + C * np.sum(np.clip(s0 + (q - q0) / caps, -lims, lims)) - rhs

        q_ref = scipy.optimize.brentq(g, -1.0, 1.0, xtol=1e-300, rtol=1e-15)
        q, v_h, volts = solve(jnp.asarray(s0), jnp.asarray(q0), jnp.asarray(rhs), jnp.asarray(C),
                                     jnp.asarray(caps), jnp.asarray(lims))
        assert abs(float(q) - q_ref) <= 1e-14 * max(abs(q_ref), 1e-6)
        np.testing.assert_allclose(volts, np.clip(s0 + (q_ref - q0) / caps, -lims, lims), atol=1e-9)
        assert abs(float(q) + C * float(v_h) - rhs) <= 1e-18


@pytest.fixture(scope="module")
def loops():
    """q-V loops under a 100 V sine at 0.1 Hz (3 cycles) and 0.2 Hz (6 cycles): same dt and record length (one
    compilation), so 0.2 Hz has half the samples per cycle."""
    act = ElectromechanicalActuator(M, B, K, C, [T, 1e-3], CAPS, LIMS)
    dt = 2e-3
    sim = jax.jit(lambda a, v: a.simulate(v, dt, substeps=8))
    res = {}
    n = int(round(30.0 / dt))
    t = np.arange(n + 1) * dt
    for freq in (0.1, 0.2):
        v = 100 * np.sin(2 * np.pi * freq * t)
        res[freq] = (v, jax.tree_util.tree_map(np.asarray, sim(act, v)), int(round(1 / freq / dt)))
    return act, res


def test_loop_closed_and_consistent(loops):
    act, res = loops
    for freq, (v, out, per) in res.items():
        q = out["q"]
        # Second cycle equals the third (the first starts from the relaxed state, the loop is then closed).
        np.testing.assert_allclose(q[per:2 * per], q[2 * per:3 * per], rtol=0, atol=1e-9 * np.abs(q).max())
        # The loop is a real hysteresis loop: its area is large against a purely linear (zero-area) relation.
        area = abs(np.trapezoid(q[2 * per:3 * per + 1], v[2 * per:3 * per + 1]))
        assert area > 0.01 * np.ptp(q) * np.ptp(v)
        # Every output satisfies the implicit relation q = C V_p + T_em(V_in) x, V_in = V_H + V_p, exactly ...
        t_em = T + 1e-3 * v
        np.testing.assert_allclose(q, C * out["v_p"] + t_em * out["x"], rtol=0, atol=1e-12 * np.abs(q).max())
        np.testing.assert_allclose(out["v_h"] + out["v_p"], v, rtol=0, atol=1e-9)
        # ... and V_H is the Maxwell-slip operator (independent numpy implementation) of the simulated charge path.
        s = np.zeros(6)
        qp = 0.0
        v_h = np.empty_like(q)
        for i, qq in enumerate(q):
            s = np.clip(s + (qq - qp) / CAPS, -LIMS, LIMS)
            qp = qq
            v_h[i] = s.sum()
        # (Up to the part of a charge reversal that falls between two samples, which the model follows through its
        # sub-steps and the sampled reference cannot see: measured 7e-5 V of 42 V.)
        np.testing.assert_allclose(out["v_h"], v_h, rtol=0, atol=1e-5 * LIMS.sum())
        # Saturation: at the peaks every element slips, V_H = sum of breakaway voltages.
        assert abs(out["v_h"].max() - LIMS.sum()) < 1e-9


def test_loop_rate_independent(loops):
    """The q-V loop at 0.1 Hz and 0.2 Hz agrees at equal phase. The tolerance 2e-4 (relative to max |q|) is set by
    the physics, not the numerics: T_em x is 70 % of q here and the mechanics are not quasi-static to better than
    about (dV_p/dt) / (omega_n V) = 2e-4 (lag 2 zeta omega / omega_n = 8e-5 rad at 0.2 Hz; the kinks of V_p where
    elements start slipping ring the resonance)."""
    act, res = loops
    v1, out1, per1 = res[0.1]
    v2, out2, per2 = res[0.2]
    phase1 = 2 * per1 + np.arange(0, per1, 50)  # 100 phases of the third cycle
    phase2 = 2 * per2 + np.arange(0, per2, 25)
    np.testing.assert_allclose(v1[phase1], v2[phase2], atol=1e-9)
    q1, q2 = out1["q"][phase1], out2["q"][phase2]
    err = np.abs(q1 - q2).max() / np.abs(q1).max()
    print("rate independence, max |q(0.1 Hz) - q(0.2 Hz)| / max |q| =", err)
    assert err < 2e-4
    # Quasi-static check: x = T_em V_p / k, so q = (C + T_em^2 / k) V_p up to the same dynamic effects.
    t_em = T + 1e-3 * v1
    q_static = (C + t_em**2 / K) * out1["v_p"]
    late = slice(per1, None)  # after the start-up ringing of the first cycle
    assert np.abs(out1["q"][late] - q_static[late]).max() / np.abs(q1).max() < 5e-4


def _small_problem():
    act = ElectromechanicalActuator(M, B, K, C, [T, 1e-3], [0.5e-6, 0.7e-6, 0.4e-6], [2.0, 5.0, 9.0])
    dt, n = 2e-4, 40
    t = np.arange(n) * dt
    v = 60 * np.sin(2 * np.pi * 100 * t) + 20 * np.sin(2 * np.pi * 310 * t)
    f = 0.3 * np.cos(2 * np.pi * 200 * t)
    return act, dt, v, f


def test_jacfwd_matches_central_differences():
    act, dt, v, f = _small_problem()
    params, static = eqx.partition(act, eqx.is_array)
    flat, unravel = jax.flatten_util.ravel_pytree(params)

    def fn(p):
        out = eqx.combine(unravel(p), static).simulate(v, dt, f, substeps=4)
        return jnp.concatenate([out["x"] * 1e6, out["q"] * 1e6])

    # One compilation gives the Jacobian and (as aux) the value used for the finite differences.
    jac_and_value = jax.jit(jax.jacfwd(lambda p: (fn(p), fn(p)), has_aux=True))
    jac, value = jac_and_value(flat)
    assert jac.shape == (80, flat.shape[0]) and np.all(np.isfinite(jac))
    for i in range(flat.shape[0]):
        h = 1e-6 * abs(float(flat[i]))
        e = jnp.zeros_like(flat).at[i].set(h)
        fd = (jac_and_value(flat + e)[1] - jac_and_value(flat - e)[1]) / (2 * h)
        scale = np.abs(fd).max()
        assert scale > 0, i  # every parameter matters in this test
        np.testing.assert_allclose(jac[:, i], fd, rtol=0, atol=1e-5 * scale, err_msg=f"parameter {i}")
    # Reverse mode agrees with forward mode.
    g = jax.grad(lambda p: jnp.sum(fn(p) ** 2))(flat)
    np.testing.assert_allclose(g, 2 * jac.T @ value, rtol=1e-9)


def test_vmap_over_inputs():
    act, dt, v, f = _small_problem()
    vs = np.stack([v, 0.5 * v, -v])
    one = jax.jit(lambda vi: act.simulate(vi, dt, f, substeps=4)["x"])
    batched = jax.jit(jax.vmap(one))(vs)
    for i in range(3):
        np.testing.assert_allclose(batched[i], one(vs[i]), rtol=1e-12, atol=1e-20)


def test_maxwell_voltages_tie_gradient():
    """A saturated element with no charge change keeps derivative 1 with respect to its breakaway voltage
    (`jnp.clip` would give 0.5 at the tie)."""
    d = jax.grad(lambda lim: maxwell_voltages(lim, 0.0, 0.0, 1.0, lim))(2.0)
    assert d == 1.0


def test_bad_input():
    act, dt, v, f = _small_problem()
    with pytest.raises(ValueError, match="`m`"):
        ElectromechanicalActuator(0.0, B, K, C, [T])
    with pytest.raises(ValueError, match="`capacitance`"):
        ElectromechanicalActuator(M, B, K, -1e-6, [T])
    with pytest.raises(ValueError, match="`breakaway_voltages`"):
        ElectromechanicalActuator(M, B, K, C, [T], [1e-6], [-1.0])
    with pytest.raises(ValueError, match="same shape"):
        ElectromechanicalActuator(M, B, K, C, [T], [1e-6, 1e-6], [1.0])
    with pytest.raises(ValueError, match="`dt`"):
        act.simulate(v, 0.0)
    with pytest.raises(ValueError, match="`v_in`"):
        act.simulate(np.zeros(0), dt)
    with pytest.raises(ValueError, match="`f_ext`"):
        act.simulate(v, dt, f[:-1])
    with pytest.raises(ValueError, match="`hold`"):
        act.simulate(v, dt, hold="cubic")
    # Data-dependent checks under jit (one compilation): NaN input, traced bad parameter, too coarse steps.
    run = jax.jit(lambda v_, m_, dt_: eqx.tree_at(lambda a: a.m, act, m_).simulate(v_, dt_, substeps=1)["x"])
    assert np.all(np.isfinite(run(v, M, dt)))
    with pytest.raises(Exception, match="`v_in` contains NaN"):
        run(np.where(np.arange(v.shape[0]) == 3, np.nan, v), M, dt)
    with pytest.raises(Exception, match="ElectromechanicalActuator"):
        run(v, -1.0, dt)
    with pytest.raises(Exception, match="substeps"):
        run(v, M, 1e-2)
    with pytest.raises(Exception, match="`dt`"):
        run(v, M, -1e-4)


# ------------------------------------------------------------------------------------------------------ inverse

from piezojax._nonlinear.electromechanical import electrical_inverse  # noqa: E402

T_POLY = [T, 1e-3, -2e-6]  # T_em(V) varies by a few % over +-60 V


@pytest.mark.parametrize("t_em", [[T], T_POLY], ids=["constant", "polynomial"])
def test_electrical_inverse_recovers_the_forward_voltage(t_em):
    """Given the forward model's force T(V) V_p and displacement, the per-sample inverse returns V: to round-off on a
    monotone rise (charge monotone within each sample), within the forward model's path error at reversals."""
    act = ElectromechanicalActuator(M, B, K, C, t_em, CAPS, LIMS)
    dt = 1e-4
    t = np.arange(3000) * dt
    rise = 60 * (1 - np.cos(np.pi * t / t[-1])) / 2
    wavy = 60 * np.sin(2 * np.pi * 3 * t) * np.exp(-t) + 20 * np.sin(2 * np.pi * 11 * t)
    for v, tol in ((rise, 1e-9), (wavy, 2e-5 * 60)):
        out = act.simulate(v, dt)
        force = act.coupling(jnp.asarray(v)) * out["v_p"]
        v_inv, q, res = electrical_inverse(act, force, out["x"], 8)
        assert float(res.max()) < 1e-9
        np.testing.assert_allclose(v_inv, v, rtol=0, atol=tol)
        np.testing.assert_allclose(q, out["q"], rtol=0, atol=1e-6 * np.abs(out["q"]).max())


@pytest.mark.parametrize("dynamics, tol", [(True, 1e-3), (False, 5e-3)])
def test_inverse_tracks_a_smooth_reference(dynamics, tol):
    """simulate(inverse(x_d)) follows x_d: the whole inverse within 0.1 % of the range for a 10 Hz reference on a
    500 Hz resonance; the quasi-static one within 0.5 % (it ignores the (f/f_n)^2 dynamic gain)."""
    act = ElectromechanicalActuator(M, B, K, C, T_POLY, CAPS, LIMS)
    dt = 1e-4
    t = np.arange(4000) * dt
    ref = 5e-5 * np.sin(2 * np.pi * 5 * t) ** 2
    inv = act.inverse(dynamics=dynamics)
    v = eqx.filter_jit(lambda i, r: i(r, dt))(inv, ref)
    x = act.simulate(v, dt)["x"]
    err = float(np.max(np.abs(x - ref)) / np.ptp(ref))
    assert err < tol
    # without the inverse (a plain gain through the static chord) the error is far larger
    gain = float(np.polyfit(act.simulate(v, dt)["x"], v, 1)[0])
    plain = act.simulate(gain * ref, dt)["x"]
    assert float(np.max(np.abs(plain - ref)) / np.ptp(ref)) > 10 * err


def test_inverse_differentiable_and_vmappable():
    act = ElectromechanicalActuator(M, B, K, C, T_POLY, CAPS, LIMS)
    dt = 1e-4
    t = np.arange(600) * dt
    refs = jnp.stack([3e-5 * np.sin(2 * np.pi * f * t) ** 2 for f in (5.0, 8.0)])

    def loss(a, r):
        return jnp.sum(a.inverse()(r, dt) ** 2)

    v = jax.vmap(lambda r: act.inverse()(r, dt))(refs)
    np.testing.assert_allclose(v[1], act.inverse()(refs[1], dt), rtol=1e-12, atol=1e-12)
    g = jax.grad(loss)(act, refs[0])
    h = 1e-6 * float(act.k)
    fd = (loss(eqx.tree_at(lambda a: a.k, act, act.k + h), refs[0])
          - loss(eqx.tree_at(lambda a: a.k, act, act.k - h), refs[0])) / (2 * h)
    np.testing.assert_allclose(g.k, fd, rtol=1e-5)
    gr = jax.grad(lambda r: loss(act, r))(refs[0])
    assert np.all(np.isfinite(gr))


def test_inverse_bad_input():
    act = ElectromechanicalActuator(M, B, K, C, [T], CAPS, LIMS)
    with pytest.raises(pj.PiezojaxValueError, match="iterations"):
        act.inverse(iterations=0)
    with pytest.raises(pj.PiezojaxValueError, match="bandwidth"):
        act.inverse(bandwidth=-1.0)
    with pytest.raises(pj.PiezojaxValueError, match="hold"):
        act.inverse()(np.zeros(10), 1e-4, hold="foh")
    with pytest.raises(pj.PiezojaxValueError, match="displacement"):
        act.inverse()(np.zeros((2, 10)), 1e-4)


def test_inverse_with_a_near_jump_element():
    """Elements of tiny capacitance (a fit's dead elements, e.g. 3e-13 F and 0.1 mV) make r(V) a near-jump at the
    previous sample's charge, where plain Newton cycles near the reference's turning points (it failed here with 30
    iterations); the bracketed iteration converges, the forward model follows the inverse's voltage, and the
    gradient (implicit function) matches central differences."""
    caps = jnp.concatenate([jnp.asarray(CAPS), jnp.array([6e-9, 3e-13])])
    lims = jnp.concatenate([jnp.asarray(LIMS), jnp.array([3e-2, 1e-4])])
    act = ElectromechanicalActuator(M, B, K, C, T_POLY, caps, lims)
    dt = 1e-4
    t = np.arange(1500) * dt
    ref = 4e-5 * np.sin(2 * np.pi * 5 * t) ** 2
    inv = act.inverse(dynamics=False, iterations=30)
    v = inv(ref, dt)
    x = act.simulate(v, dt)["x"]
    assert float(np.max(np.abs(x - ref)) / np.ptp(ref)) < 5e-3

    def loss(a):
        return jnp.sum(a.inverse(dynamics=False, iterations=30)(ref, dt) ** 2)

    g = jax.grad(loss)(act)
    for where, h in ((lambda a: a.t_em, 1e-6 * T), (lambda a: a.capacitance, 1e-6 * C)):
        base = where(act)
        e = jnp.zeros_like(base).at[..., 0].set(h) if base.ndim else h
        fd = (loss(eqx.tree_at(where, act, base + e)) - loss(eqx.tree_at(where, act, base - e))) / (2 * h)
        got = where(g)[0] if base.ndim else where(g)
        np.testing.assert_allclose(got, fd, rtol=1e-4)
