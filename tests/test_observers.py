"""Observers of papers 000, 001, 002: exact inversion of their circuits, predicted errors, gradients, bad input."""

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
    return lambda *args, **kwargs: _apply(fn, *args, **kwargs)


def zoh_lsim(num, den, dt, u):
    sysd = scipy.signal.cont2discrete(scipy.signal.tf2ss(num, den), dt, "zoh")
    return scipy.signal.dlsim(sysd, u)[1][:, 0]


# ---------------------------------------------------------------- paper 000

DT0 = jnp.asarray(2e-4)
N0 = 600
T0 = np.arange(N0) * float(DT0)
V0 = 100 * (1 - np.exp(-T0 / 0.005))
# G(s): K w1 wn^2 / ((s + w1)(s^2 + 2 zeta wn s + wn^2)), a 3rd-order model as in the paper
K, W1, WN, ZETA = 1e-7, 2 * np.pi * 80, 2 * np.pi * 400, 0.1
G_NUM = [K * W1 * WN**2]
G_DEN = list(np.polymul([1, W1], [1, 2 * ZETA * WN, WN**2]))
RF, CR, GAMMA, IB, ALPHA, BETA = 1e5, 4.2e-9, 0.66e-9, 1e-12, 0.8971, 6.9067e7


@pytest.fixture(scope="module")
def setup000():
    creep = pj.KelvinVoigtCreep([1 / 3e-10, 1 / 4e-10], [0.01, 0.05], k0=None)
    circuit = pj.TransimpedanceCircuit(RF, CR, GAMMA, IB, creep)
    obs = pj.DynamicImpedanceObserver(RF, CR, GAMMA, IB, ALPHA, BETA, pj.TransferFunction(G_NUM, G_DEN))
    v_out = np.asarray(jit(circuit)(V0, DT0))
    q_creep = np.asarray(jit(circuit.charge)(V0, DT0)) - (CR - GAMMA) * V0
    return circuit, obs, v_out, q_creep


def test_000_recovers_creep_charge_and_displacement(setup000):
    circuit, obs, v_out, q_creep = setup000
    q_delta = np.asarray(jit(obs.deformation_charge)(V0, v_out, DT0))
    np.testing.assert_allclose(q_delta + GAMMA * V0, q_creep, rtol=0, atol=1e-9 * np.max(np.abs(q_creep)))
    est = jit(obs)(V0, v_out, DT0)
    assert est.force is None
    expected = zoh_lsim(G_NUM, G_DEN, float(DT0), ALPHA * V0 + BETA * q_creep)
    np.testing.assert_allclose(np.asarray(est.displacement), expected, rtol=0, atol=1e-9 * np.max(np.abs(expected)))


def test_000_static_impedance_error_is_predicted(setup000):
    # Dropping gamma removes beta*gamma*V_in from F_t: the error is exactly -beta*gamma*G[V_in], i.e. a relative
    # error of -beta*gamma/alpha = -5.1 % of the instantaneous part with the paper's alpha, beta, gamma.
    circuit, obs, v_out, q_creep = setup000
    d_dyn = np.asarray(jit(obs)(V0, v_out, DT0).displacement)
    d_static = np.asarray(jit(obs.static_impedance())(V0, v_out, DT0).displacement)
    predicted = -BETA * GAMMA * zoh_lsim(G_NUM, G_DEN, float(DT0), V0)
    np.testing.assert_allclose(d_static - d_dyn, predicted, rtol=0, atol=1e-9 * np.max(np.abs(predicted)))
    np.testing.assert_allclose(predicted[-1] / (K * V0[-1]), -BETA * GAMMA, rtol=1e-3)
    assert abs(BETA * GAMMA / ALPHA - 0.0508) < 1e-3


def test_000_jacfwd_all_parameters(setup000):
    circuit, obs, v_out, q_creep = setup000
    n = jacfwd_vs_central_fd(lambda o: o(V0[:300], v_out[:300], DT0).displacement, obs)
    assert n >= 6 + 5  # R_f, C_r, gamma, I_bias, alpha, beta and the nonzero coefficients of G


# ---------------------------------------------------------------- paper 001

DT1 = jnp.asarray(1e-3)
N1 = 500
T1 = np.arange(N1) * float(DT1)
V1 = -20 * np.clip(np.sin(2 * np.pi * 1.5 * T1), 0, None) - 5 * np.clip(np.sin(2 * np.pi * 4 * T1), 0, None)
F1 = 1e-3 * np.clip(np.sin(2 * np.pi * 1.5 * T1) - 0.3, 0, None)
C_INT, C_REF, R_FP, I_B, BETA1, ALPHA1, K_BEAM = 100e-9, 1.74e-9, 5e10, 3e-13, 1.03e-6, -4.0e-3, 163.0
K_Z = 1 / (1 / K_BEAM + BETA1 / ALPHA1)


@pytest.fixture(scope="module")
def setup001():
    pi = PrandtlIshlinskii(jnp.array([0.08e-9, 0.05e-9, 0.03e-9]), jnp.array([0.5, 2.0, 5.0]), w0=1.6e-9)
    creep = pj.KelvinVoigtCreep([1 / 0.05e-9], [0.2], k0=None)
    circuit = pj.ChargeIntegratorCircuit(C_INT, C_REF, R_FP, I_B, BETA1, hysteresis=pi, creep=creep)
    obs = pj.ForceDisplacementObserver(C_INT, C_REF, R_FP, I_B, BETA1, ALPHA1, K_Z, hysteresis=pi, creep=creep)
    v_out = np.asarray(jit(circuit)(V1, DT1, F1))
    q_v = np.asarray(jit(circuit.charge)(V1, DT1))  # charge of the free actuator (F = 0)
    return circuit, obs, v_out, q_v


def test_001_recovers_force_and_displacement_exactly(setup001):
    circuit, obs, v_out, q_v = setup001
    est = jit(obs)(V1, v_out, DT1)
    np.testing.assert_allclose(np.asarray(est.force), F1, rtol=0, atol=1e-9 * F1.max())
    # Truth of the kind a bench simulates: delta = Q_V/alpha - F/k_beam; with k_Z identified the paper's way
    # (1/k_Z = 1/k_beam + beta/alpha) eq. (6) reproduces it.
    delta_true = q_v / ALPHA1 - F1 / K_BEAM
    np.testing.assert_allclose(np.asarray(est.displacement), delta_true, rtol=0, atol=1e-9 * np.abs(delta_true).max())
    # Using the beam stiffness itself for k_Z leaves the predicted error beta F / alpha.
    naive = eqx.tree_at(lambda o: o.stiffness, obs, jnp.asarray(K_BEAM))
    err = np.asarray(jit(naive)(V1, v_out, DT1).displacement) - delta_true
    np.testing.assert_allclose(err, BETA1 * F1 / ALPHA1, rtol=0, atol=1e-9 * np.abs(delta_true).max())


def test_001_preisach_charge_read_from_its_value_at_rest():
    # a Preisach charge operator whose demagnetised output at 0 V is not 0: the integrator, reset at rest, reads the
    # change from it, in the circuit and the observer alike, so a constant in the operator changes nothing
    def parts(offset):
        pre = pj.Preisach.uniform(-25.0, 25.0, 3, mu=1e-9 * jnp.array([0.9, 0.1, 0.3, 0.2, 0.5, 0.05]), offset=offset)
        circuit = pj.ChargeIntegratorCircuit(C_INT, C_REF, R_FP, I_B, BETA1, hysteresis=pre)
        obs = pj.ForceDisplacementObserver(C_INT, C_REF, R_FP, I_B, BETA1, ALPHA1, K_Z, hysteresis=pre)
        return circuit, obs

    circuit, obs = parts(0.7e-9)
    assert not circuit.hysteresis.rests_at_zero
    v_out = np.asarray(jit(circuit)(V1, DT1, F1))
    est = jit(obs)(V1, v_out, DT1)
    np.testing.assert_allclose(np.asarray(est.force), F1, rtol=0, atol=1e-9 * F1.max())
    plain_circuit, plain_obs = parts(0.0)
    np.testing.assert_allclose(v_out, np.asarray(plain_circuit(V1, DT1, F1)), rtol=0, atol=1e-12 * np.ptp(v_out))
    np.testing.assert_allclose(np.asarray(est.force), np.asarray(plain_obs(V1, v_out, DT1).force), rtol=0,
                               atol=1e-9 * F1.max())
    # at V = 0 and no force the integrator reads only the bias current, as without any piezo charge
    bias_only = pj.ChargeIntegratorCircuit(C_INT, C_REF, R_FP, I_B, BETA1, capacitance_p=0.0)
    assert V1[0] == 0.0 and F1[0] == 0.0
    assert v_out[0] == pytest.approx(float(bias_only(V1, DT1, F1)[0]), rel=1e-9)


def test_001_butterworth_force_term(setup001):
    circuit, obs, v_out, q_v = setup001
    num, den = scipy.signal.butter(3, 2 * np.pi * 20.0, analog=True)
    filtered = eqx.tree_at(lambda o: o.filter_cutoff, obs, jnp.asarray(20.0), is_leaf=lambda x: x is None)
    est = jit(filtered)(V1, v_out, DT1)
    expected = q_v / ALPHA1 + BETA1 * F1 / ALPHA1 - zoh_lsim(num, den, float(DT1), F1) / K_Z
    np.testing.assert_allclose(np.asarray(est.displacement), expected, rtol=0, atol=1e-9 * np.abs(expected).max())
    np.testing.assert_allclose(np.asarray(est.force), F1, rtol=0, atol=1e-9 * F1.max())


def test_001_jacfwd_all_parameters(setup001):
    circuit, obs, v_out, q_v = setup001
    filtered = eqx.tree_at(lambda o: o.filter_cutoff, obs, jnp.asarray(20.0), is_leaf=lambda x: x is None)
    s = slice(0, 200)
    def both(o):
        est = o(V1[s], v_out[s], DT1)
        return jnp.concatenate([est.displacement * 1e3, est.force])

    n = jacfwd_vs_central_fd(both, filtered)
    assert n == 17  # C, C_R, R_FP, i_bias, beta, alpha, k_Z, 7 PI, 2 creep, cutoff


# ---------------------------------------------------------------- paper 002

D33_OVER_C = 0.015381  # V/N, paper 002
KS = 5e7
KP = 1 / (11.6126e-6 / (1 / D33_OVER_C) - 1 / KS)  # series stiffness from the displacement sensitivity
C_AMP = 104e-12
D33 = D33_OVER_C * C_AMP
ME, CE, KE, PC = 0.05, 20.0, 2e7, -0.006636 / 20 * 0.3


@pytest.fixture(scope="module")
def setup002():
    circuit = pj.SmartStackCircuit(D33, C_AMP, KP, KS, ME, CE, KE, crosstalk=PC)
    obs = pj.SensorLayerObserver(D33, C_AMP, KP, KS, crosstalk=PC)
    return circuit, obs


def test_002_paper_sensitivities(setup002):
    circuit, obs = setup002
    est = obs(np.zeros(3), np.ones(3))
    np.testing.assert_allclose(np.asarray(est.displacement), 11.6126e-6, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(est.force), 1 / 0.015381, rtol=1e-12)


def test_002_errors_are_the_predicted_ones(setup002):
    circuit, obs = setup002
    dt = jnp.asarray(1e-4)
    t = np.arange(800) * float(dt)
    v_a = 50 * np.sin(2 * np.pi * 20 * t) ** 2
    x_a = 1.1e-7 * v_a + 2e-8 * np.sin(2 * np.pi * 20 * t)  # any actuator law; the observer never sees it
    v_s = np.asarray(jit(circuit)(v_a, dt, x_a=x_a))
    est = jit(obs)(v_a, v_s, dt)
    k_ser = KP * KS / (KP + KS)
    high_pass = scipy.signal.lsim(([ME, 0, 0], [ME, CE, KE]), x_a, t)[1]  # linear interpolation (FOH)
    err = np.asarray(est.displacement) - x_a
    np.testing.assert_allclose(err, KE / k_ser * high_pass, rtol=0, atol=1e-9 * np.abs(x_a).max())
    # Below the stage zero (20 Hz << 3 kHz) that dynamic error is tiny: eq. (9) is accurate.
    assert np.max(np.abs(err)) < 1e-3 * np.max(np.abs(x_a))
    np.testing.assert_allclose(np.asarray(est.force), np.asarray(jit(circuit.sensor_force)(x_a, dt)), rtol=1e-12)
    # Omitting the crosstalk (eq. 9 as printed) adds C p_c V_a / (d33 k_ser) (p_c < 0): here up to 2.9 % of the range.
    err_nox = np.asarray(jit(obs.without_crosstalk())(v_a, v_s, dt).displacement) - x_a
    np.testing.assert_allclose(err_nox - err, C_AMP * PC * v_a / (D33 * k_ser), rtol=1e-9, atol=1e-20)
    assert 0.01 < np.max(np.abs(err_nox)) / np.ptp(x_a) < 0.05


def test_002_jacfwd_all_parameters(setup002):
    circuit, obs = setup002
    v_a = np.linspace(0, 100, 50)
    v_s = 0.5 * np.sqrt(v_a)
    n = jacfwd_vs_central_fd(lambda o: o(v_a, v_s).displacement, obs)
    assert n == 5


# ---------------------------------------------------------------- bad input


def test_bad_input(setup000, setup001, setup002):
    _, obs0, v_out, _ = setup000
    bad = v_out.copy()
    bad[10] = np.nan
    with pytest.raises(Exception, match="`v_out` contains NaN"):
        jax.block_until_ready(jit(obs0)(V0, bad, DT0).displacement)
    with pytest.raises(pj.PiezojaxValueError, match="`v_in` has 600.*`v_out` has 599"):
        obs0(V0, v_out[:-1], DT0)
    _, obs1, _, _ = setup001
    with pytest.raises(pj.PiezojaxValueError, match="v_out"):
        obs1(V1, V1[:10], DT1)
    with pytest.raises(pj.PiezojaxValueError, match="feedback_resistance"):
        pj.DynamicImpedanceObserver(0.0, CR, GAMMA, IB, ALPHA, BETA, pj.TransferFunction(G_NUM, G_DEN))
    with pytest.raises(pj.PiezojaxValueError, match="reference_capacitance"):
        pj.ForceDisplacementObserver(C_INT, 0.0, R_FP, I_B, BETA1, ALPHA1, K_Z)
    with pytest.raises(pj.PiezojaxValueError, match="stiffness"):
        pj.ForceDisplacementObserver(C_INT, C_REF, R_FP, I_B, BETA1, ALPHA1, -1.0)
    with pytest.raises(ValueError, match="dynamics"):
        pj.DynamicImpedanceObserver(RF, CR, GAMMA, IB, ALPHA, BETA, lambda u: u)
    zero_alpha = eqx.tree_at(lambda o: o.displacement_coefficient, obs1, jnp.asarray(0.0))
    with pytest.raises(Exception, match="displacement_coefficient"):
        jax.block_until_ready(jit(zero_alpha)(V1, V1, DT1).displacement)
    _, obs2 = setup002
    with pytest.raises(pj.PiezojaxValueError, match="d33"):
        pj.SensorLayerObserver(-1.0, C_AMP, KP, KS)


def test_reverse_mode_grad_matches_forward(setup000, setup002):
    # jax.grad of a least-squares cost through the whole observer (what a fitter differentiates) equals the
    # forward-mode Jacobian contracted with the residual.
    _, obs, v_out, q_creep = setup000
    s = slice(0, 150)
    target = zoh_lsim(G_NUM, G_DEN, float(DT0), ALPHA * V0 + BETA * q_creep)[s] * 1.01

    def residual(o):
        return (o(V0[s], v_out[s], DT0).displacement - target) * 1e6

    params, static = eqx.partition(obs, eqx.is_inexact_array)
    cost = lambda p: 0.5 * jnp.sum(residual(eqx.combine(p, static)) ** 2)  # noqa: E731
    g = jax.jit(jax.grad(cost))(params)
    r = residual(obs)
    jac = jax.jit(jax.jacfwd(lambda p: residual(eqx.combine(p, static))))(params)
    for gl, jl in zip(jax.tree_util.tree_leaves(g), jax.tree_util.tree_leaves(jac)):
        expected = np.tensordot(np.asarray(r), np.asarray(jl), axes=1)
        np.testing.assert_allclose(np.asarray(gl), expected, rtol=1e-8, atol=1e-12 * np.max(np.abs(expected)))


def test_observers_declare_what_they_estimate():
    # the declaration (a class variable) matches what the call returns; a calibration reads the declaration
    import fitting

    v = jnp.linspace(0.0, 1.0, 16)
    for bench in (pj.IvanBench(), pj.BafumbaBench(), pj.ChenBench()):
        obs = bench.observer()
        est = obs(v, 0.01 * v, 1e-3)
        assert ("force" in type(obs).estimates) == (est.force is not None), type(obs).__name__
        assert fitting.default_predictor(obs).outputs == type(obs).estimates
