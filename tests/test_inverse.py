"""Inverse compensation: the root-finding hysteresis inverse, Maxwell slip's PI form, the linear dynamics' stable
inverse and the whole-actuator inverse — round trips on random models and inputs, saturation, derivatives, errors."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from hypothesis.extra.numpy import arrays

import piezojax as pj

N = 120
LO, HI = -60.0, 160.0


def _signal(seed: int, n: int = N) -> jnp.ndarray:
    """A random input in [-40, 140] with reversals of every size: a decaying sine plus a random walk, ramped up
    from 0 over 10 samples (RK4's steps stay stable)."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 3.0, n)
    v = 50 + 70 * np.sin(2 * np.pi * t + rng.uniform(0, 2 * np.pi)) * np.exp(-0.4 * t)
    v = v + np.cumsum(rng.normal(0, 3.0, n))
    return jnp.asarray(np.clip(v, -40.0, 140.0) * np.minimum(1.0, np.arange(n) / 10))


# one compilation per operator structure: parameters and signals are arguments
@jax.jit
def _pi_round_trip(w, r, w0, v):
    op = pj.PrandtlIshlinskii(w, r, w0=w0)
    y = op(v)
    v_root = op.inverse(LO, HI)(y)
    return y, v_root, op.inverse()(y), op(v_root)


@jax.jit
def _bouc_wen_round_trip(a, beta, gamma, d, v):
    op = pj.BoucWen(a, beta, gamma, d=d, method="closed_form")
    y = op(v)
    v_inv = op.inverse(LO, HI)(y)
    return y, v_inv, op(v_inv)


@jax.jit
def _bouc_wen_rk4_round_trip(a, beta, gamma, n, d, v):
    op = pj.BoucWen(a, beta, gamma, n=n, d=d, method="rk4")
    y = op(v)
    v_inv = op.inverse(LO, HI)(y)
    return y, v_inv, op(v_inv)


@settings(max_examples=15)
@given(
    w=arrays(np.float64, 6, elements=st.floats(-0.05, 0.4)),
    gaps=arrays(np.float64, 6, elements=st.floats(0.5, 10.0)),
    w0=st.floats(0.35, 2.0),
    seed=st.integers(0, 10_000),
)
def test_pi_root_finding_inverse_matches_the_analytic_inverse(w, gaps, w0, seed):
    """On random PI operators with a strictly increasing loading curve (some negative weights), the root-finding
    inverse returns the input to rounding, as the analytic inverse does."""
    assert np.all(w0 + np.cumsum(w) > 0)  # six weights >= -0.05 after w0 >= 0.35: strictly increasing loading
    v = _signal(seed)
    r = np.cumsum(gaps) - gaps[0]  # 0 = r_1 < r_2 < ... (distinct: the inverse's thresholds stay ascending)
    y, v_root, v_analytic, y_back = _pi_round_trip(jnp.asarray(w), jnp.asarray(r), jnp.asarray(w0), v)
    scale = float(jnp.max(jnp.abs(y))) + 1.0
    np.testing.assert_allclose(v_root, v, atol=1e-9 * 200)
    np.testing.assert_allclose(v_analytic, v, atol=1e-9 * 200)
    np.testing.assert_allclose(y_back, y, atol=1e-11 * scale)


@settings(max_examples=15)
@given(
    a=st.floats(0.2, 2.0),
    beta=st.floats(0.005, 0.1),
    ratio=st.floats(-0.9, 0.9),
    margin=st.floats(1.05, 3.0),
    seed=st.integers(0, 10_000),
)
def test_bouc_wen_inverse_round_trip(a, beta, ratio, margin, seed):
    """y = d v - z is increasing when d exceeds the largest slope of z, max(A, 2 beta A / (beta + gamma)): the
    inverse recovers the input (closed form, n = 1, and RK4 with n = 1.5) to 1e-9 of the range."""
    gamma = ratio * beta
    d = margin * max(a, 2 * beta * a / (beta + gamma))
    v = _signal(seed)
    y, v_inv, y_back = _bouc_wen_round_trip(a, beta, gamma, d, v)
    np.testing.assert_allclose(v_inv, v, atol=2e-7)
    np.testing.assert_allclose(y_back, y, atol=1e-9 * float(jnp.max(jnp.abs(y))))
    y, v_inv, y_back = _bouc_wen_rk4_round_trip(a, beta, gamma, 1.5, d, v)
    np.testing.assert_allclose(v_inv, v, atol=2e-7)
    np.testing.assert_allclose(y_back, y, atol=1e-9 * float(jnp.max(jnp.abs(y))))


@pytest.mark.parametrize("smoothing", [0.0, 6.0])
def test_preisach_inverse_reproduces_the_output(smoothing):
    """The Preisach output reached by an input is reached again by the inverse (exact: the switching input;
    smooth: a continuous root); with random positive weights and an offset."""
    rng = np.random.default_rng(3)
    op = pj.Preisach.uniform(-40.0, 140.0, 12, smoothing=smoothing)
    op = pj.Preisach(op.alpha, op.beta, jnp.asarray(rng.uniform(0.1, 1.0, op.num_relays)), offset=0.3,
                     smoothing=smoothing)
    for seed in (0, 1, 2):
        v = _signal(seed)
        y = op(v)
        v_inv = op.inverse(LO, HI)(y)
        np.testing.assert_allclose(op(v_inv), y, atol=1e-10 * float(jnp.max(jnp.abs(y))))
        if smoothing:
            # strictly increasing where the input moves: the input itself comes back
            moved = np.abs(np.diff(np.asarray(v), prepend=0.0)) > 0.5
            assert float(jnp.median(jnp.abs(v_inv - v)[moved])) < 1e-6


@settings(max_examples=15)
@given(
    k=arrays(np.float64, 4, elements=st.floats(0.1, 5.0)),
    r=arrays(np.float64, 4, elements=st.floats(0.5, 40.0), unique=True),
    linear=st.floats(0.05, 2.0),
    seed=st.integers(0, 10_000),
)
def test_maxwell_slip_analytic_inverse_through_its_pi_form(k, r, linear, seed):
    """`as_prandtl_ishlinskii(l)` is l x + MS[x] for every input (elements in any order), and its analytic
    inverse (paper 003: V = q/C + V_H(q) inverted) returns the input."""
    order = np.random.default_rng(seed).permutation(4)
    v = _signal(seed)
    y_pi, y_ms, v_back = _maxwell_pi(jnp.asarray(k[order]), jnp.asarray(k[order] * r[order]), jnp.asarray(linear), v)
    np.testing.assert_allclose(y_pi, linear * v + y_ms, atol=1e-11 * float(jnp.max(jnp.abs(y_pi))))
    np.testing.assert_allclose(v_back, v, atol=1e-9)


@jax.jit
def _maxwell_pi(k, f, linear, v):
    ms = pj.MaxwellSlip(k, f)
    pi = ms.as_prandtl_ishlinskii(linear)
    return pi(v), ms(v), pi.inverse()(pi(v))


def test_saturation_at_the_bounds_and_a_saturating_operator():
    """Alone, the Maxwell slip saturates at sum f_i: targets beyond return the bound; inside they come back."""
    ms = pj.MaxwellSlip(jnp.array([2.0, 1.0]), jnp.array([1.0, 2.0]))  # saturates at +-3 beyond |x| = 2
    inv = ms.inverse(-5.0, 5.0)
    got = inv(jnp.array([1.0, 2.5, 4.0, -4.0, 0.0]))
    np.testing.assert_allclose(ms(got), [1.0, 2.5, 3.0, -3.0, 0.0], atol=1e-12)
    assert float(got[2]) == 5.0 and float(got[3]) == -5.0
    # a target below what the lower bound reaches returns the bound
    pi = pj.PrandtlIshlinskii(jnp.array([0.2]), jnp.array([5.0]), w0=1.0)
    np.testing.assert_array_equal(pi.inverse(0.0, 10.0)(jnp.array([-3.0, 50.0])), [0.0, 10.0])


def test_decreasing_operator_is_inverted():
    op = pj.ScaledHysteresis(pj.PrandtlIshlinskii(jnp.array([0.3, 0.1]), jnp.array([5.0, 20.0]), w0=0.5), -2.0)
    v = _signal(7)
    np.testing.assert_allclose(op.inverse(LO, HI)(op(v)), v, atol=1e-9)


def test_inverse_derivatives_match_finite_differences_and_work_under_vmap():
    v = _signal(11, 80)
    y = pj.BoucWen(0.8, 0.03, 0.01, d=2.0)(v)

    @jax.jit
    def loss(params, target):
        a, beta, d = params
        return jnp.sum(pj.BoucWen(a, beta, 0.01, d=d).inverse(LO, HI)(target) ** 2)

    p = jnp.array([0.8, 0.03, 2.0])
    g_p, g_y = jax.jit(jax.grad(loss, argnums=(0, 1)))(p, y)
    for i, h in enumerate((1e-6, 1e-8, 1e-6)):
        e = jnp.zeros(3).at[i].set(h)
        fd = (loss(p + e, y) - loss(p - e, y)) / (2 * h)
        assert float(g_p[i]) == pytest.approx(float(fd), rel=1e-5)
    for k in (5, 40, 79):
        e = jnp.zeros_like(y).at[k].set(1e-6)
        fd = (loss(p, y + e) - loss(p, y - e)) / 2e-6
        assert float(g_y[k]) == pytest.approx(float(fd), rel=1e-5, abs=1e-6)
    # forward mode agrees with reverse mode
    j_fwd = jax.jacfwd(lambda q: loss(q, y))(p)
    np.testing.assert_allclose(j_fwd, g_p, rtol=1e-9)
    batch = jax.vmap(lambda t: pj.BoucWen(0.8, 0.03, 0.01, d=2.0).inverse(LO, HI)(t))(jnp.stack([y, 0.5 * y]))
    np.testing.assert_allclose(batch[0], v, atol=1e-9)


def test_inverse_bad_arguments_are_named():
    op = pj.BoucWen(0.8, 0.03, 0.01, d=2.0)
    with pytest.raises(pj.PiezojaxValueError, match="`lower` and `upper`"):
        op.inverse()
    with pytest.raises(pj.PiezojaxValueError, match="`lower` must be < `upper`"):
        op.inverse(5.0, 1.0)
    with pytest.raises(pj.PiezojaxValueError, match="`upper`"):
        op.inverse(0.0, float("inf"))
    with pytest.raises(pj.PiezojaxValueError, match="`max_iterations`"):
        op.inverse(0.0, 1.0, max_iterations=0)
    with pytest.raises(pj.PiezojaxValueError, match="`signal`"):
        op.inverse(0.0, 1.0)(jnp.array([0.0, jnp.nan]))


# --- linear dynamics ---------------------------------------------------------------------------------------------


def test_relative_degree():
    assert pj.StableTransferFunction(2.0, omega=[30.0], zeta=[0.3], poles=[-5.0]).relative_degree() == 3
    assert pj.StableTransferFunction(2.0, omega=[30.0], zeta=[0.3], poles=[-5.0], zeros=[-2.0]).relative_degree() == 2
    assert pj.TransferFunction([1.0, 3.0], [1.0, 2.0]).relative_degree() == 0
    assert pj.StateSpace([[-1.0]], [1.0], [2.0]).relative_degree() == 1


@pytest.mark.parametrize(
    "system, bandwidth",
    [
        (pj.StableTransferFunction(1e-7, omega=[2 * np.pi * 950], zeta=[0.05]), None),
        (pj.StableTransferFunction(2.0, omega=[30.0], zeta=[0.3], poles=[-5.0], zeros=[-2.0]), 100.0),
        (pj.StableTransferFunction(0.5, omega=[30.0, 80.0], zeta=[0.3, 0.02], zero_omega=[50.0], zero_zeta=[0.1]),
         400.0),
        (pj.TransferFunction([1.0, 3.0], [1.0, 2.0]), None),
    ],
)
def test_linear_inverse_is_the_low_pass_over_g(system, bandwidth):
    """(F/G) G = F = (wf / (s + wf))^r at every frequency (an analytic reference), and the inverse is stable."""
    inv = system.inverse(bandwidth)
    r = system.relative_degree()
    A = np.asarray(system.state_space()[0])
    wf = bandwidth if bandwidth is not None else np.max(np.abs(np.linalg.eigvals(A)))
    w = jnp.logspace(-1, 4, 60)
    product = inv.frequency_response(w) * system.frequency_response(w)
    np.testing.assert_allclose(product, (wf / (1j * np.asarray(w) + wf)) ** r, rtol=1e-8)
    assert np.max(np.linalg.eigvals(np.asarray(inv.state_space()[0])).real) < 0


def test_linear_inverse_refuses_non_minimum_phase_and_bad_degree():
    with pytest.raises(pj.PiezojaxValueError, match="non-minimum phase"):
        pj.StableTransferFunction(1.0, omega=[3.0], zeta=[0.3], zeros=[2.0]).inverse()
    g = pj.StableTransferFunction(1.0, omega=[3.0], zeta=[0.3])
    with pytest.raises(pj.PiezojaxValueError, match="relative_degree"):
        g.inverse(relative_degree=1)
    with pytest.raises(pj.PiezojaxValueError, match="`bandwidth`"):
        g.inverse(bandwidth=-1.0)


def test_a_traced_system_asks_for_its_degree_and_bandwidth_naming_grad():
    """Under differentiation the defaults, which need concrete values, name what to pass and why; with both given
    the inverse is differentiable."""

    def drive(omega, **kw):
        g = pj.StableTransferFunction(1.0, omega=[omega], zeta=[0.3])
        return jnp.sum(g.inverse(**kw).simulate(jnp.linspace(0.0, 1.0, 50), 1e-2))

    with pytest.raises(pj.PiezojaxValueError, match=r"traced \(under jit, vmap or grad\).*`relative_degree`"):
        jax.grad(drive)(3.0)
    with pytest.raises(pj.PiezojaxValueError, match=r"pass `bandwidth` when the system's values are traced"):
        jax.grad(lambda w: drive(w, relative_degree=2))(3.0)
    assert np.isfinite(jax.grad(lambda w: drive(w, relative_degree=2, bandwidth=10.0))(3.0))


# --- whole actuator ----------------------------------------------------------------------------------------------

DT = 2e-4
T = jnp.arange(0.0, 0.6, DT)
V = 60.0 + 50.0 * jnp.sin(2 * jnp.pi * 3 * T - np.pi / 2) + 10.0 * jnp.sin(2 * jnp.pi * 7 * T)
PI = pj.PrandtlIshlinskii(jnp.full(8, 0.02), jnp.linspace(3.0, 45.0, 8), w0=0.1)
BW = pj.BoucWen(0.05, 0.004, 0.001, d=0.2)
DYN = pj.StableTransferFunction(1e-6, omega=[2 * jnp.pi * 400.0], zeta=[0.05])


def _actuators():
    kv_parallel = pj.KelvinVoigtCreep(jnp.array([50.0, 20.0]), jnp.array([0.05, 0.5]), k0=None)
    kv_series = pj.KelvinVoigtCreep(jnp.array([20.0, 10.0]), jnp.array([0.05, 0.5]))
    return {
        "pi parallel": pj.Actuator(PI, kv_parallel, capacitance=1e-9),
        "pi series, prehistory, offset": pj.Actuator(PI, kv_series, structure="series", prehistory=80.0, offset=1e-6),
        "bouc-wen parallel, log creep": pj.Actuator(BW, pj.LogarithmicCreep(0.02, 0.05, instantaneous=False)),
        "no hysteresis, lag creep series": pj.Actuator(None, pj.LagCreep([0.1], [0.2]), structure="series"),
    }


@pytest.mark.parametrize("name", list(_actuators()))
def test_actuator_inverse_without_dynamics_is_exact(name):
    """Without dynamics the chain is inverted exactly: hysteresis (analytic or root finding) and the creep's
    fixed point, in both structures, from a prehistory state too."""
    act = _actuators()[name]
    d = act.simulate(V, DT).displacement
    bounds = [{"lower": -100.0, "upper": 300.0}] if isinstance(act.hysteresis, pj.BoucWen) else [{}, {
        "lower": -100.0, "upper": 300.0}]
    for kw in bounds:
        v_inv = act.inverse(**kw)(d, DT)
        np.testing.assert_allclose(v_inv, V, atol=1e-7)


@pytest.mark.parametrize("name", list(_actuators()))
def test_actuator_inverse_of_a_constant_reference(name):
    """A constant reference has no range for the parallel iteration's chord slope: the chord from the rest point is
    used instead (it had divided by a zero range: NaN). Held at a level, the drive creeps back as the creep builds up;
    held at the rest output, it stays at 0 V."""
    act = _actuators()[name]
    level = act.simulate(jnp.full(400, 40.0), DT).displacement[0]
    rest = act.simulate(jnp.zeros(2), DT).displacement[0]
    for d in (jnp.full(400, level), jnp.full(1, level), jnp.full(400, rest)):
        v = act.inverse(lower=-100.0, upper=300.0)(d, DT)
        np.testing.assert_allclose(act.simulate(v, DT).displacement, d, rtol=1e-9, atol=1e-15 * float(abs(level)))
    np.testing.assert_allclose(v, 0.0, atol=1e-9)


@pytest.mark.parametrize("structure", ["parallel", "series"])
def test_actuator_inverse_with_dynamics_tracks_the_reference(structure):
    """With a 400 Hz resonance, the simulated displacement follows the reference to < 1e-4 of its range after the
    start-up transient (the record starts away from rest); without preview the low-pass's delay costs 10x more."""
    creep = (pj.KelvinVoigtCreep(jnp.array([50.0, 20.0]), jnp.array([0.05, 0.5]), k0=None) if structure == "parallel"
             else pj.KelvinVoigtCreep(jnp.array([20.0, 10.0]), jnp.array([0.05, 0.5])))
    act = pj.Actuator(PI, creep, DYN, structure=structure)
    d = act.simulate(V, DT).displacement
    settled = slice(int(0.05 / DT), None)

    def error(inv):
        e = act.simulate(eqx.filter_jit(inv)(d, DT), DT).displacement - d
        return float(jnp.sqrt(jnp.mean(e[settled] ** 2)) / jnp.ptp(d))

    with_preview = error(act.inverse())
    assert with_preview < 1e-4
    assert error(act.inverse(preview=False)) > 10 * with_preview


def test_actuator_inverse_derivatives_and_vmap():
    act = pj.Actuator(PI, pj.KelvinVoigtCreep(jnp.array([50.0]), jnp.array([0.05]), k0=None), DYN)
    inv = act.inverse(iterations=8)
    d = act.simulate(V[:400], DT).displacement

    @jax.jit
    def loss(target):
        return jnp.sum(inv(target, DT) ** 2)

    g = jax.jit(jax.grad(loss))(d)
    for k in (100, 250):
        e = jnp.zeros_like(d).at[k].set(1e-10)
        assert float(g[k]) == pytest.approx(float((loss(d + e) - loss(d - e)) / 2e-10), rel=1e-5)
    batch = eqx.filter_jit(jax.vmap(lambda t: inv(t, DT)))(jnp.stack([d, 0.5 * d]))
    np.testing.assert_allclose(batch[0], inv(d, DT), rtol=1e-12)
    # with respect to an actuator parameter, through a rebuilt inverse (degree and bandwidth given under jit)
    @jax.jit
    def by_gain(gain):
        a = eqx.tree_at(lambda m: m.dynamics.gain, act, jnp.asarray(gain))
        return jnp.sum(a.inverse(bandwidth=2 * jnp.pi * 400.0, relative_degree=2, iterations=8)(d, DT))

    g_gain = jax.jit(jax.grad(by_gain))(jnp.asarray(1e-6))
    assert float(g_gain) == pytest.approx(float((by_gain(1e-6 + 1e-12) - by_gain(1e-6 - 1e-12)) / 2e-12), rel=1e-5)


def test_actuator_inverse_errors():
    act = pj.Actuator(PI, None, DYN)
    with pytest.raises(pj.PiezojaxValueError, match="both `lower` and `upper`"):
        act.inverse(lower=0.0)
    with pytest.raises(pj.PiezojaxValueError, match="`iterations`"):
        act.inverse(iterations=-1)
    with pytest.raises(pj.PiezojaxValueError, match="`lower` and `upper`"):
        pj.Actuator(BW).inverse()
    with pytest.raises(pj.PiezojaxValueError, match="hysteresis_state"):
        pj.Actuator(PI, hysteresis_state=PI.init()).inverse()
    with pytest.raises(pj.PiezojaxValueError, match="instantaneous gain"):
        pj.Actuator(PI, pj.KelvinVoigtCreep(jnp.array([50.0]), jnp.array([0.05]), k0=None), structure="series").inverse()
    with pytest.raises(pj.PiezojaxValueError, match="`displacement`"):
        act.inverse()(jnp.array([0.0, jnp.inf]), DT)
    with pytest.raises(pj.PiezojaxValueError, match="`hold`"):
        act.inverse()(jnp.zeros(3), DT, hold="linear")
    # a parallel creep far stronger than the hysteresis: the iteration diverges, and the error says so (its iterate
    # had turned NaN first, and the hysteresis inverse's input check reported a NaN `signal` instead)
    t = jnp.arange(0.0, 0.3, 1e-3)
    strong = pj.Actuator(pj.PrandtlIshlinskii(jnp.full(4, 5e-9), jnp.linspace(0.0, 50.0, 4), w0=2e-8),
                         pj.KelvinVoigtCreep(jnp.array([5e5]), jnp.array([0.005]), k0=None))
    with pytest.raises(eqx.EquinoxRuntimeError, match="parallel creep's fixed-point iteration did not converge"):
        eqx.filter_jit(lambda a: a.inverse(iterations=20)(1e-6 * (1 - jnp.cos(2 * jnp.pi * 5 * t)), 1e-3))(strong)
