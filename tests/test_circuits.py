"""Self-sensing circuit forward models (papers 000, 001, 002): conservation laws, analytic responses, gradients."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.signal
from _selfsensing_helpers import jacfwd_vs_central_fd

import piezojax as pj
from piezojax._hysteresis.prandtl_ishlinskii import PrandtlIshlinskii


@eqx.filter_jit
def _apply(fn, *args, **kwargs):
    return fn(*args, **kwargs)


def jit(fn):
    """One compiled entry point for all calls (modules and bound methods are traced arguments)."""
    return lambda *args, **kwargs: _apply(fn, *args, **kwargs)


def zoh_lsim(num, den, dt, u):
    # Through state space: scipy's polynomial ZOH round trip loses ~1e-7 relative accuracy.
    sysd = scipy.signal.cont2discrete(scipy.signal.tf2ss(num, den), dt, "zoh")
    return scipy.signal.dlsim(sysd, u)[1][:, 0]

DT = 1e-3
N = 400
T = np.arange(N) * DT


def ramp_step(v0, tau=0.02):
    return v0 * (1 - np.exp(-T / tau))


@pytest.fixture(scope="module")
def tia():
    creep = pj.KelvinVoigtCreep([1 / 2e-10, 1 / 5e-10], [0.05, 0.3], k0=None)
    return pj.TransimpedanceCircuit(1e6, 4.2e-9, 0.66e-9, 2e-12, creep)


@pytest.fixture(scope="module")
def integrator():
    pi = PrandtlIshlinskii(jnp.array([0.08e-9, 0.05e-9, 0.03e-9]), jnp.array([0.5, 2.0, 5.0]), w0=1.6e-9)
    creep = pj.KelvinVoigtCreep([1 / 0.05e-9], [0.2], k0=None)  # creep charge 0.05 nC/V, tau = 0.2 s
    return pj.ChargeIntegratorCircuit(100e-9, 1.74e-9, 5e10, 3e-13, 1.03e-6, hysteresis=pi, creep=creep)


@pytest.fixture(scope="module")
def stack():
    return pj.SmartStackCircuit(1.6e-12, 104e-12, 6.3e6, 5e7, 0.05, 20.0, 2e7, crosstalk=-3e-4)


# ---------------------------------------------------------------- paper 000: transimpedance amplifier


def test_transimpedance_integral_recovers_charge_analytic(tia):
    # A held step V0 from t = 0: Q_k = (C_r - gamma) V0 + V0 sum_i q_i (1 - exp(-k dt / tau_i)) (ZOH creep).
    v0 = 80.0
    v = np.full(N, v0)
    v_out = np.asarray(jit(tia)(v, DT))
    q_recovered = -DT * np.cumsum(v_out / 1e6 + 2e-12)
    k = np.arange(N)
    q_expected = (4.2e-9 - 0.66e-9) * v0 + v0 * (
        2e-10 * (1 - np.exp(-k * DT / 0.05)) + 5e-10 * (1 - np.exp(-k * DT / 0.3))
    )
    np.testing.assert_allclose(q_recovered, q_expected, rtol=1e-10, atol=1e-22)
    np.testing.assert_allclose(np.asarray(jit(tia.charge)(v, DT)), q_expected, rtol=1e-12)
    # The first sample carries the whole step charge (the record starts from rest at 0 V).
    np.testing.assert_allclose(v_out[0], -1e6 * ((4.2e-9 - 0.66e-9) * v0 / DT + 2e-12), rtol=1e-12)


def test_transimpedance_ramp_current():
    # V = a t without creep: I = (C_r - gamma) a on every interval, V_out = -R_f (I + I_bias).
    a = 500.0
    c = pj.TransimpedanceCircuit(2e5, 4.2e-9, 0.66e-9, -1e-12)
    v_out = np.asarray(jit(c)(a * T, DT))
    np.testing.assert_allclose(v_out[1:], -2e5 * ((4.2e-9 - 0.66e-9) * a - 1e-12), rtol=1e-10)
    np.testing.assert_allclose(np.asarray(jit(c.current)(a * T, DT))[1:], (4.2e-9 - 0.66e-9) * a, rtol=1e-10)
    dq = np.asarray(jit(c.deformation_charge)(a * T, DT))
    np.testing.assert_allclose(dq, -0.66e-9 * a * T, rtol=1e-10, atol=1e-24)


def test_transimpedance_jacfwd_all_parameters(tia):
    v = ramp_step(60.0)
    n = jacfwd_vs_central_fd(lambda m: m(v, DT), tia)
    assert n == 8  # R_f, C_r, gamma, I_bias, 2 creep stiffnesses, 2 time constants


# ---------------------------------------------------------------- paper 001: charge integrator


def test_integrator_linear_analytic_drift():
    # Linear piezo, constant V: V_out_k = -((C_P - C_R) V + beta F + (V/R_FP + i_b) dt (k+1)) / C.
    c = pj.ChargeIntegratorCircuit(100e-9, 1.5e-9, 5e10, 3e-13, 1.03e-6, capacitance_p=1.74e-9)
    v = np.full(N, -10.0)
    f = np.linspace(0, 1e-3, N)
    v_out = np.asarray(jit(c)(v, DT, f))
    k = np.arange(N)
    expected = -((1.74e-9 - 1.5e-9) * -10.0 + 1.03e-6 * f + (-10.0 / 5e10 + 3e-13) * DT * (k + 1)) / 100e-9
    np.testing.assert_allclose(v_out, expected, rtol=1e-10, atol=1e-16)


def test_integrator_charge_conservation(integrator):
    v = -20 * np.abs(np.sin(2 * np.pi * 2 * T))
    f = 1e-3 * np.maximum(0, np.sin(2 * np.pi * 3 * T))
    v_out = np.asarray(jit(integrator)(v, DT, f))
    # Everything the integrator capacitor collects is accounted for: piezo charge, reference, leakage, bias.
    collected = -100e-9 * v_out
    expected = (np.asarray(jit(integrator.charge)(v, DT, f)) - 1.74e-9 * v
                + DT * np.cumsum(v / 5e10 + 3e-13))
    np.testing.assert_allclose(collected, expected, rtol=1e-10, atol=1e-21)
    # The charge is beta F + PI[V] + creep[V], each checked against its own block.
    pi = integrator.hysteresis
    creep_q = zoh_lsim([0.05e-9], [0.2, 1.0], DT, v)
    np.testing.assert_allclose(np.asarray(jit(integrator.charge)(v, DT, f)),
                               1.03e-6 * f + np.asarray(pi(jnp.asarray(v))) + creep_q, rtol=1e-9, atol=1e-20)


def test_integrator_jacfwd_all_parameters(integrator):
    v = -15 * np.abs(np.sin(2 * np.pi * 2 * T[:150]))
    f = 1e-3 * np.maximum(0, np.sin(2 * np.pi * 3 * T[:150]))
    n = jacfwd_vs_central_fd(lambda m: m(v, DT, f), integrator)
    assert n == 14  # C, C_R, R_FP, i_bias, beta, 3 PI weights, 3 thresholds, w0, creep stiffness and time


# ---------------------------------------------------------------- paper 002: smart stack


def test_stack_eq3_matches_printed_transfer_function(stack):
    x = 1e-6 * np.sin(2 * np.pi * 800 * T[:200] / 4) * np.linspace(0, 1, 200)
    dt = DT / 40
    f = np.asarray(jit(stack.sensor_force)(x, dt))
    kp, ks, ke, me, ce = 6.3e6, 5e7, 2e7, 0.05, 20.0
    num = [(ks * ke + ke * kp + kp * ks) * me, kp * ks * ce, ks * ke * kp]
    den = [(kp + ks) * me, (kp + ks) * ce, ks * ke + ke * kp]
    expected = scipy.signal.lsim((num, den), x, np.arange(x.shape[0]) * dt)[1]  # FOH, as the circuit
    np.testing.assert_allclose(f, expected, rtol=1e-8, atol=1e-10 * np.max(np.abs(expected)))
    # The object returned for eq. (3) is the same rational function, with static gain kp ks / (kp + ks).
    np.testing.assert_allclose(float(stack.stage_transfer_function().dc_gain()), kp * ks / (kp + ks), rtol=1e-12)


def test_stack_sensor_voltage(stack):
    v_a = 10 * np.sin(2 * np.pi * 5 * T)
    x = 1e-7 * v_a
    v_s = np.asarray(jit(stack)(v_a, DT, x_a=x))
    expected = 1.6e-12 / 104e-12 * np.asarray(jit(stack.sensor_force)(x, DT)) - 3e-4 * v_a
    np.testing.assert_allclose(v_s, expected, rtol=1e-12, atol=1e-18)
    # With an actuator block the same output comes from V_a alone.
    with_act = eqx.tree_at(lambda s: s.actuator, stack, PrandtlIshlinskii(jnp.array([1e-8]), jnp.array([1.0]),
                                                                         w0=1e-7), is_leaf=lambda x: x is None)
    x_pi = np.asarray(with_act.actuator(jnp.asarray(v_a)))
    np.testing.assert_allclose(np.asarray(jit(with_act)(v_a, DT)), np.asarray(jit(stack)(v_a, DT, x_a=x_pi)), rtol=1e-12)


def test_stack_jacfwd_all_parameters(stack):
    v_a = 10 * np.sin(2 * np.pi * 50 * T)
    x = 1e-7 * v_a
    dt = DT / 10
    n = jacfwd_vs_central_fd(lambda m: m(v_a, dt, x_a=x), stack)
    assert n == 8


# ---------------------------------------------------------------- jit / vmap


def test_jit_and_vmap(tia):
    v = np.stack([ramp_step(25.0), ramp_step(150.0)])
    out = jax.jit(jax.vmap(lambda x: tia(x, DT)))(v)
    np.testing.assert_allclose(np.asarray(out[1]), np.asarray(jit(tia)(v[1], DT)), rtol=1e-10)
    np.testing.assert_allclose(np.asarray(out[1]), 6 * np.asarray(out[0]) - 5 * (-1e6 * 2e-12), rtol=1e-9)


# ---------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "make, name",
    [
        (lambda: pj.TransimpedanceCircuit(0.0, 4e-9), "feedback_resistance"),
        (lambda: pj.TransimpedanceCircuit(-1e6, 4e-9), "feedback_resistance"),
        (lambda: pj.TransimpedanceCircuit(1e6, 0.0), "capacitance"),
        (lambda: pj.TransimpedanceCircuit(1e6, 4e-9, -1e-9), "gamma"),
        (lambda: pj.ChargeIntegratorCircuit(0.0, 1e-9, 1e10, 0.0, 1e-6), "integrator_capacitance"),
        (lambda: pj.ChargeIntegratorCircuit(1e-7, -1e-9, 1e10, 0.0, 1e-6), "reference_capacitance"),
        (lambda: pj.ChargeIntegratorCircuit(1e-7, 1e-9, 0.0, 0.0, 1e-6), "leakage_resistance"),
        (lambda: pj.ChargeIntegratorCircuit(1e-7, 1e-9, 1e10, np.nan, 1e-6), "bias_current"),
        (lambda: pj.SmartStackCircuit(1e-12, 0.0, 1, 1, 1, 1, 1), "amplifier_capacitance"),
        (lambda: pj.SmartStackCircuit(1e-12, 1e-10, 1, 1, 1, -1, 1), "c_e"),
        # a component of the wrong kind is refused where the circuit is built (a function is not a pj.AbstractCreep,
        # a creep law is not a hysteresis operator), naming the argument and the types it may have
        (lambda: pj.TransimpedanceCircuit(1e6, 4e-9, creep=lambda v, dt: v),
         r"`creep` must be a pj.AbstractCreep or pj.AbstractLinearSystem .*got function"),
        (lambda: pj.ChargeIntegratorCircuit(1e-7, 1e-9, 1e10, 0.0, 1e-6, hysteresis=pj.KelvinVoigtCreep([1e9], [1.0])),
         r"`hysteresis` must be a pj.AbstractHysteresis .*got KelvinVoigtCreep"),
        (lambda: pj.ForceDisplacementObserver(1e-7, 1e-9, 1e10, 0.0, 1e-6, -4e-3, 150.0, creep=np.ones(3)),
         r"`creep` must be .*got ndarray"),
        (lambda: pj.SmartStackCircuit(1e-12, 1e-10, 1, 1, 1, 1, 1, actuator=pj.TransferFunction([1.0], [1.0, 1.0])),
         r"`actuator` must be a pj.AbstractHysteresis .*got TransferFunction"),
    ],
)
def test_bad_parameters(make, name):
    with pytest.raises(pj.PiezojaxValueError, match=name):
        make()


def test_traced_nonpositive_parameter_errors(tia):
    bad = eqx.tree_at(lambda m: m.feedback_resistance, tia, jnp.asarray(-1.0))
    with pytest.raises(Exception, match="feedback_resistance"):
        jax.block_until_ready(jax.jit(lambda m: m(np.ones(10), DT))(bad))


def test_mismatched_lengths_and_nan(integrator, stack, tia):
    with pytest.raises(pj.PiezojaxValueError, match="`v_in` has 10.*`f_ext` has 9"):
        integrator(np.ones(10), DT, np.ones(9))
    with pytest.raises(pj.PiezojaxValueError, match="x_a"):
        stack(np.ones(10), DT, x_a=np.ones(11))
    with pytest.raises(Exception, match="`v_in` contains NaN"):
        v = np.ones(10)
        v[3] = np.nan
        jax.block_until_ready(tia(v, DT))
    with pytest.raises(pj.PiezojaxValueError, match="dt"):
        tia(np.ones(10), -1.0)
    with pytest.raises(pj.PiezojaxValueError, match="v_in"):
        tia(np.ones((2, 10)), DT)


def test_running_integral_keeps_its_parameters_outside_the_sum():
    from piezojax._circuits.base import running_integral

    x = np.sin(np.linspace(0, 7, 400)) + 0.3
    gain, bias, dt = -1 / 3e9, 2e-13, 1e-3
    expected = dt * np.cumsum(gain * x + bias)
    got = np.asarray(running_integral(jnp.asarray(x), dt, gain, bias))
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12 * np.max(np.abs(expected)))
    np.testing.assert_allclose(np.asarray(running_integral(jnp.asarray(x), dt)), dt * np.cumsum(x), rtol=1e-13)
    # the Jacobian with respect to (gain, bias) is [dt sum x, dt (k + 1)] ...
    jac = jax.jacfwd(lambda p: running_integral(jnp.asarray(x), dt, p[0], p[1]))(jnp.array([gain, bias]))
    np.testing.assert_allclose(np.asarray(jac[:, 0]), dt * np.cumsum(x), rtol=1e-13)
    np.testing.assert_allclose(np.asarray(jac[:, 1]), dt * np.arange(1, x.size + 1), rtol=1e-13)
    # ... formed with the data's running sum only: no running sum of the tangents (one per direction under jacfwd)
    jaxpr = jax.make_jaxpr(jax.jacfwd(lambda p: running_integral(jnp.asarray(x), dt, p[0], p[1])))(
        jnp.array([gain, bias]))
    assert str(jaxpr).count("cumsum[") == 1
    with pytest.raises(pj.PiezojaxValueError, match="`gain` and `bias` must be scalars"):
        running_integral(jnp.asarray(x), dt, gain, jnp.ones(x.size))


def test_float32_circuits_and_observers_stay_float32():
    """Under x64, Python-number defaults (`bias_current`, `gamma`, `crosstalk`, `offset`) follow the float32
    arguments: a float32 circuit or observer computes in float32 (they had turned it to float64)."""
    f32 = np.float32
    v = jnp.linspace(0.0, 1.0, 8, dtype=jnp.float32)
    tia = pj.TransimpedanceCircuit(f32(1e6), f32(4.2e-9))
    assert tia(v, f32(1e-3)).dtype == jnp.float32
    layer = pj.SensorLayerObserver(f32(1.6e-12), f32(104e-12), f32(6.3e6), f32(5e7))
    assert {leaf.dtype for leaf in jax.tree.leaves(layer)} == {jnp.dtype("float32")}
