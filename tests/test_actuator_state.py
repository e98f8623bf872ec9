"""Initial state, offset and composable blocks of the actuator: prehistory, hysteresis state, settled creep and
dynamics, the lag creep with feed-through and the output polynomial. References: numpy play recursions and
`scipy.signal.lsim` started from the equilibrium state."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.signal

import fitting
import piezojax as pj

DT = 1e-3
N = 800
T = np.arange(N) * DT
# at rest for 0.1 s, then a sine: the remanent state shows before the drive starts
V = np.where(T < 0.1, 0.0, 40 * np.sin(2 * np.pi * 3 * (T - 0.1)) + 5 * np.sin(2 * np.pi * 11 * T))
W, R, W0 = np.array([0.4, 0.25, 0.1]), np.array([5.0, 20.0, 35.0]), 1.0
OMEGA, ZETA = 2 * np.pi * 40, 0.2


def pi_numpy(v, p=None):
    p = np.zeros_like(R) if p is None else p.copy()
    out = np.empty_like(v)
    for k, vk in enumerate(v):
        p = np.maximum(vk - R, np.minimum(vk + R, p))
        out[k] = W0 * vk + W @ p
    return out, p


def lsim_settled(num, den, u, u_r):
    """Output of num/den for the held input `u`, settled at the input `u_r` before the record (scipy)."""
    A, B, C, D = scipy.signal.tf2ss(num, den)
    x0 = -np.linalg.solve(A, B[:, 0]) * u_r
    _, y, _ = scipy.signal.lsim((A, B, C, D), u, T[: u.size], X0=x0, interp=False)
    return y


def pi():
    return pj.PrandtlIshlinskii(W, R, w0=W0)


def dynamics():
    return pj.StableTransferFunction(1.0, omega=[OMEGA], zeta=[ZETA])


@pytest.mark.parametrize("u_p", [-50.0, 30.0, 0.0])
def test_prehistory_matches_independent_reference(u_p):
    act = pj.Actuator(pi(), None, dynamics(), offset=2.5, prehistory=u_p)
    x = np.asarray(act.simulate(jnp.asarray(V), DT).displacement)
    _, p = pi_numpy(np.array([u_p, 0.0]))
    h, _ = pi_numpy(V, p)
    h_r = W @ p  # the remanent output at V = 0
    ref = 2.5 + lsim_settled([OMEGA**2], [1, 2 * ZETA * OMEGA, OMEGA**2], h, h_r)
    np.testing.assert_allclose(x, ref, rtol=0, atol=1e-9 * np.ptp(ref))
    # before the drive the output sits at the remanent value plus the offset
    np.testing.assert_allclose(x[:50], 2.5 + h_r, atol=1e-12)
    state, hr = act.initial_state()
    np.testing.assert_allclose(float(hr), h_r, atol=1e-12)


def test_demagnetised_preisach_starts_settled_at_its_output_at_zero():
    # a demagnetised Preisach operator's output at V = 0 is c + sum mu_i R_i, not 0 here: before the record the
    # dynamics sat at it (the voltage had been 0 long enough), so nothing rings at t = 0
    op = pj.Preisach.uniform(-45.0, 45.0, 3, mu=jnp.array([0.9, 0.1, 0.3, 0.2, 0.5, 0.05]), offset=0.3)
    assert not op.rests_at_zero and pi().rests_at_zero
    alpha, beta, mu = (np.asarray(x) for x in (op.alpha, op.beta, op.mu))
    relays = -np.sign(alpha + beta)  # the staircase alpha + beta = 0
    h, prev = np.empty_like(V), 0.0
    for k, vk in enumerate(V):
        # a relay with alpha = beta reached exactly takes the direction of travel (unchanged at rest)
        up = (vk > alpha) | ((vk == alpha) & ((alpha > beta) | (vk > prev)))
        down = (vk < beta) | ((vk == beta) & ((alpha > beta) | (vk < prev)))
        relays, prev = np.where(up, 1.0, np.where(down, -1.0, relays)), vk
        h[k] = 0.3 + mu @ relays
    h_r = 0.3 + mu @ -np.sign(alpha + beta)
    assert abs(h_r) > 0.2
    act = pj.Actuator(op, None, dynamics(), offset=2.5)
    x = np.asarray(act(V, DT).displacement)
    ref = 2.5 + lsim_settled([OMEGA**2], [1, 2 * ZETA * OMEGA, OMEGA**2], h, h_r)
    np.testing.assert_allclose(x, ref, rtol=0, atol=1e-9 * np.ptp(ref))
    np.testing.assert_allclose(x[:50], 2.5 + h_r, atol=1e-12)  # at rest before the drive
    assert float(act.initial_state()[1]) == pytest.approx(h_r, abs=1e-12)
    # the same with the demagnetised state given explicitly, and with creep in series (settled at h_r too)
    given = pj.Actuator(op, None, dynamics(), offset=2.5, hysteresis_state=op.init())
    np.testing.assert_allclose(given(V, DT).displacement, x, atol=1e-12)
    series = pj.Actuator(op, pj.LagCreep([0.3], [0.05]), dynamics(), structure="series")
    np.testing.assert_allclose(series(V, DT).displacement[:50], h_r, atol=1e-12)


def test_explicit_state_equals_prehistory_and_rest_is_default():
    state, _ = pi().scan(jnp.asarray([-50.0, 0.0]))
    a = pj.Actuator(pi(), None, dynamics(), prehistory=-50.0)
    b = pj.Actuator(pi(), None, dynamics(), hysteresis_state=state)
    np.testing.assert_allclose(a(V, DT).displacement, b(V, DT).displacement, atol=1e-12)
    # the demagnetised state given explicitly is the default (from rest)
    c = pj.Actuator(pi(), None, dynamics(), hysteresis_state=pi().init())
    d = pj.Actuator(pi(), None, dynamics())
    np.testing.assert_allclose(c(V, DT).displacement, d(V, DT).displacement, atol=1e-12)
    assert d.initial_state()[0] is None and float(d.initial_state()[1]) == 0.0


def test_series_lag_creep_and_polynomial_match_reference():
    alpha, tau = 0.3, 0.02
    coeff, scale = np.array([0.05, -0.02]), 30.0
    act = pj.Actuator(pj.OutputPolynomial(pi(), coeff, scale), pj.LagCreep([alpha], [tau]), dynamics(),
                      structure="series", prehistory=-45.0, offset=-1.0)
    x = np.asarray(act(V, DT).displacement)
    _, p = pi_numpy(np.array([-45.0, 0.0]))
    h, _ = pi_numpy(V, p)

    def poly(y):
        return y + scale * (coeff[0] * (y / scale) ** 2 + coeff[1] * (y / scale) ** 3)

    g, g_r = poly(h), poly(W @ p)
    # creep: (1 - α) + α / (τ s + 1), settled at g_r; then the resonance settled at the creep's settled output g_r
    c = (1 - alpha) * g + alpha * lsim_settled([1 / tau], [1.0, 1 / tau], g, g_r)
    ref = -1.0 + lsim_settled([OMEGA**2], [1, 2 * ZETA * OMEGA, OMEGA**2], c, g_r)
    np.testing.assert_allclose(x, ref, rtol=0, atol=1e-9 * np.ptp(ref))


def test_charge_excludes_the_sensor_offset():
    a = pj.Actuator(pi(), None, dynamics(), capacitance=1e-9, coupling=1e-3, prehistory=-50.0)
    b = eqx.tree_at(lambda m: m.offset, a, jnp.asarray(7.0))
    oa, ob = a(V, DT), b(V, DT)
    np.testing.assert_allclose(ob.displacement - oa.displacement, 7.0)
    np.testing.assert_array_equal(oa.charge, ob.charge)
    # at rest before the drive: no current (the remanent displacement's charge is the starting point)
    np.testing.assert_allclose(oa.current[:50], 0.0, atol=1e-15)


def test_gradients_of_offset_and_prehistory_match_finite_differences():
    act = pj.Actuator(pi(), pj.LagCreep([0.2], [0.03]), dynamics(), structure="series", offset=0.5,
                      prehistory=-43.0)
    v = jnp.asarray(V)

    def loss(off, pre):
        m = eqx.tree_at(lambda m: (m.offset, m.prehistory), act, (off, pre))
        return jnp.sum(m(v, DT).displacement ** 2)

    g = jax.jit(jax.grad(loss, argnums=(0, 1)))(jnp.asarray(0.5), jnp.asarray(-43.0))
    for i, (x0, h) in enumerate(((0.5, 1e-4), (-43.0, 1e-3))):
        args = [jnp.asarray(0.5), jnp.asarray(-43.0)]
        up, dn = list(args), list(args)
        up[i], dn[i] = jnp.asarray(x0 + h), jnp.asarray(x0 - h)
        fd = (loss(*up) - loss(*dn)) / (2 * h)
        np.testing.assert_allclose(g[i], fd, rtol=1e-6)
    assert float(g[1]) != 0.0  # the prehistory moves the output


def test_vmap_over_prehistories():
    act = pj.Actuator(pi(), None, dynamics(), prehistory=0.0)
    pres = jnp.asarray([-50.0, 0.0, 50.0])
    out = jax.vmap(lambda u: eqx.tree_at(lambda m: m.prehistory, act, u)(jnp.asarray(V), DT).displacement)(pres)
    for k, u in enumerate(np.asarray(pres)):
        np.testing.assert_allclose(out[k], pj.Actuator(pi(), None, dynamics(), prehistory=u)(V, DT).displacement,
                                   atol=1e-12)
    assert out[0, 0] < 0 < out[2, 0]  # remanence of the sign of the excursion


def test_creep_settled_initial_state():
    u = jnp.asarray(V + 3.0)
    kv = pj.KelvinVoigtCreep([5.0, 20.0], [0.05, 0.5], k0=2.0)
    y = np.asarray(kv.simulate(u, DT, u0=3.0))
    # reference: each lag settled at 3, the instantaneous part follows the input
    ref = np.asarray(u) / 2.0
    for k, tau in ((5.0, 0.05), (20.0, 0.5)):
        ref = ref + lsim_settled([1 / tau], [1.0, 1 / tau], np.asarray(u), 3.0) / k
    np.testing.assert_allclose(y, ref, atol=1e-12)
    assert float(kv.settled_gain()) == pytest.approx(0.5 + 0.2 + 0.05)
    lin = pj.LinearCreep(pj.StableTransferFunction(2.0, poles=[-10.0]))
    assert float(lin.settled_gain()) == pytest.approx(2.0)
    np.testing.assert_allclose(lin.simulate(jnp.full(50, 3.0), DT, u0=3.0), 6.0, atol=1e-12)
    log = pj.LogarithmicCreep(0.1, 0.01)
    np.testing.assert_allclose(log.simulate(jnp.full(20, 2.0), DT, u0=2.0), 2.0, atol=1e-12)


def test_lag_creep_step_response_and_fractions():
    c = pj.LagCreep([0.1, 0.2], [0.01, 0.1])
    y = np.asarray(c.simulate(jnp.ones(N), DT))
    np.testing.assert_allclose(y, 1 - 0.1 * np.exp(-T / 0.01) - 0.2 * np.exp(-T / 0.1), atol=1e-12)
    np.testing.assert_allclose(c.step_response(T), y, atol=1e-12)
    assert float(c.instantaneous_gain()) == pytest.approx(0.7) and float(c.settled_gain()) == 1.0
    f = pj.Fractions.from_value(jnp.asarray([0.1, 0.2]))
    np.testing.assert_allclose(f.unwrap(), [0.1, 0.2], atol=1e-14)
    raw = jnp.asarray([30.0, -5.0, 2.0])
    x = np.asarray(pj.Fractions(raw).unwrap())
    assert np.all(x > 0) and x.sum() < 1
    with pytest.raises(pj.PiezojaxValueError, match="fractions"):
        pj.LagCreep([0.6, 0.5], [0.1, 0.2])
    with pytest.raises(pj.PiezojaxValueError, match="same shape"):
        pj.LagCreep([0.1], [0.1, 0.2])
    with pytest.raises(pj.PiezojaxValueError, match="sum < 1"):
        pj.Fractions.from_value(jnp.asarray([0.5, 0.5]))


def test_equilibrium_state_holds_constant_output():
    G = pj.StableTransferFunction(3.0, omega=[OMEGA], zeta=[ZETA], poles=[-20.0])
    y = np.asarray(G.simulate(jnp.full(200, 2.0), DT, x0=G.equilibrium_state(2.0)))
    np.testing.assert_allclose(y, 6.0, rtol=1e-12)


def test_output_polynomial_and_smoothing_continuation():
    op = pj.OutputPolynomial(pj.PrandtlIshlinskii(W, R, w0=W0, smoothing=0.1), [0.05], 10.0)
    v = jnp.asarray(V)
    h = np.asarray(op.hysteresis(v))
    np.testing.assert_allclose(op(v), h + 10.0 * 0.05 * (h / 10.0) ** 2, atol=1e-12)
    # three coefficients (powers 2 to 4): each power with its own coefficient
    quartic = pj.OutputPolynomial(op.hysteresis, [0.05, -0.02, 0.01], 10.0)
    x = h / 10.0
    np.testing.assert_allclose(quartic(v), h + 10.0 * (0.05 * x**2 - 0.02 * x**3 + 0.01 * x**4), rtol=1e-13,
                               atol=1e-12)
    # the continuation reaches the wrapped operator's smoothing
    assert float(fitting.set_smoothing(op, 0.0).hysteresis.smoothing) == 0.0
    jac = jax.jacfwd(lambda m: m(v))(op)
    assert jac.coefficients.shape == (N, 1) and np.all(np.isfinite(jac.hysteresis.weights))
    with pytest.raises(pj.PiezojaxValueError, match="scale"):
        pj.OutputPolynomial(op.hysteresis, [0.1], 0.0)
    with pytest.raises(pj.PiezojaxValueError, match="hysteresis"):
        pj.OutputPolynomial(dynamics(), [0.1])


def test_scaled_hysteresis_is_the_operator_times_its_gain():
    inner = pj.PrandtlIshlinskii(W, R, w0=W0)
    op = pj.ScaledHysteresis(inner, 2.5e-9)
    v = jnp.asarray(V)
    ref = pi_numpy(V)[0]
    np.testing.assert_allclose(op(v), 2.5e-9 * ref, rtol=1e-12, atol=1e-22)
    # the state is the inner operator's: a record split in two continues where it stopped
    state, first = op.scan(v[:50])
    np.testing.assert_allclose(jnp.concatenate([first, op.scan(v[50:], state)[1]]), op(v), rtol=1e-12, atol=1e-22)
    assert float(fitting.set_smoothing(pj.ScaledHysteresis(inner, 1.0), 0.2).hysteresis.smoothing) == 0.2
    # derivatives through the inner operator's own (hand-derived) path equal finite differences of the thresholds
    jac = jax.jit(jax.jacfwd(lambda m: m(v)))(op)
    np.testing.assert_allclose(jac.gain, ref, rtol=1e-12)
    h = 1e-6
    for i in range(len(R)):
        bump = lambda d: np.asarray(eqx.tree_at(lambda m: m.hysteresis.thresholds, op,  # noqa: E731
                                                op.hysteresis.thresholds.at[i].add(d))(v))
        np.testing.assert_allclose(jac.hysteresis.thresholds[:, i], (bump(h) - bump(-h)) / (2 * h),
                                   rtol=1e-5, atol=1e-14)
    batched = jax.vmap(lambda g: pj.ScaledHysteresis(inner, g)(v))(jnp.array([1.0, -2.0]))
    np.testing.assert_allclose(batched[1], -2.0 * batched[0], rtol=1e-12)
    # a Python gain takes the operator's dtype, strongly typed (no float64 promotion, no retrace on a swap)
    inner32 = pj.PrandtlIshlinskii(W.astype(np.float32), R.astype(np.float32), w0=np.float32(W0))
    op32 = pj.ScaledHysteresis(inner32, 2.0)
    assert op32.gain.dtype == np.float32 and not op32.gain.weak_type
    assert op32(v.astype(np.float32)).dtype == np.float32
    # a wrapped Bouc-Wen runs its own sub-stepped loop: the same output as the operator times the gain
    bw = pj.BoucWen(1.0, 0.5, 0.2, n=1.5, method="rk4", substeps=4)
    np.testing.assert_allclose(pj.ScaledHysteresis(bw, 3.0)(v), 3.0 * bw(v), rtol=1e-13, atol=1e-13)
    with pytest.raises(pj.PiezojaxValueError, match="gain"):
        pj.ScaledHysteresis(inner, float("nan"))
    with pytest.raises(pj.PiezojaxValueError, match="hysteresis"):
        pj.ScaledHysteresis(dynamics(), 1.0)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(prehistory=1.0, hysteresis=None), "no hysteresis"),
        (dict(hysteresis_state=(0.0, [1.0, 2.0])), "leaf 1 must have shape"),
        (dict(hysteresis_state=(0.0,)), "structure"),
        (dict(prehistory=float("nan")), "prehistory"),
        (dict(offset=float("inf")), "offset"),
    ],
)
def test_bad_state_arguments_are_named(kwargs, match):
    kw = {"hysteresis": pi(), **kwargs}
    with pytest.raises(pj.PiezojaxValueError, match=match):
        pj.Actuator(kw.pop("hysteresis"), None, dynamics(), **kw)


# ---------------------------------------------------------------------------------------------- the observer


def _observer(**kw):
    # paper 001's observer with a PI charge operator (weights in C/V) and no creep
    pi_q = pj.PrandtlIshlinskii(W * 1e-9, R, w0=W0 * 1e-9)
    return pj.ForceDisplacementObserver(100e-9, 1.74e-9, 1e12, 0.0, 1.03e-6, -4e-3, 150.0, hysteresis=pi_q, **kw)


def test_observer_prehistory_and_offset_match_independent_reference():
    v_out = 0.05 * np.sin(2 * np.pi * 2 * T) - 0.02 * V
    plain = _observer()
    u_p, b = -45.0, 3e-6
    est = _observer(prehistory=u_p, offset=b)(jnp.asarray(V), jnp.asarray(v_out), DT)
    q = np.asarray(plain.compensated_charge(jnp.asarray(V), jnp.asarray(v_out), DT))
    _, p = pi_numpy(np.array([u_p, 0.0]))
    h, _ = pi_numpy(V, p)
    q_v = 1e-9 * (h - W @ p)  # the integrator reads the operator's change from the end of the excursion
    force_ref = (q - q_v) / 1.03e-6
    np.testing.assert_allclose(np.asarray(est.force), force_ref, rtol=1e-10, atol=1e-12 * np.ptp(force_ref))
    ref = plain(jnp.asarray(V), jnp.asarray(v_out), DT)
    delta_ref = np.asarray(ref.displacement) - (force_ref - np.asarray(ref.force)) / 150.0 + b
    np.testing.assert_allclose(np.asarray(est.displacement), delta_ref, rtol=0, atol=1e-9 * np.ptp(delta_ref))
    # differentiable in both, under jit
    g = jax.jit(jax.grad(lambda m: jnp.sum(m(jnp.asarray(V), jnp.asarray(v_out), DT).force)))(
        _observer(prehistory=u_p, offset=b))
    assert np.isfinite(float(g.prehistory)) and float(g.prehistory) != 0.0
    with pytest.raises(pj.PiezojaxValueError, match="`prehistory` sets the remanent state of `hysteresis`"):
        pj.ForceDisplacementObserver(100e-9, 1.74e-9, 1e12, 0.0, 1.03e-6, -4e-3, 150.0, prehistory=1.0)


def test_observer_state_in_config_is_fitted_and_started_from_data():
    truth = _observer(prehistory=-50.0, offset=2e-6)
    q = 1e-9 * pi_numpy(V, pi_numpy(np.array([-50.0, 0.0]))[1])[0] - 1e-9 * W @ pi_numpy(np.array([-50.0, 0.0]))[1]
    plain = _observer()
    # v_out such that the compensated charge equals the operator's (no external force): Q = -C v_out + C_R v - leak
    leak = np.asarray(plain.compensated_charge(jnp.asarray(V), jnp.zeros_like(jnp.asarray(V)), DT))
    v_out = (leak - q) / 100e-9
    est = truth(jnp.asarray(V), jnp.asarray(v_out), DT)
    np.testing.assert_allclose(np.asarray(est.force), 0.0, atol=1e-9)
    ds = fitting.Dataset([fitting.Experiment.from_arrays(t=T, v_in=V, v_out=v_out, name="r",
                                                         displacement=np.asarray(est.displacement))])
    text = ('[observer]\nkind = "current_integration"\nintegrator_capacitance = 100e-9\n'
            'reference_capacitance = 1.74e-9\n'
            'leakage_resistance = 1e12\nforce_sensitivity = 1.03e-6\ndisplacement_coefficient = -4e-3\n'
            'stiffness = 150.0\n[hysteresis]\nkind = "prandtl_ishlinskii"\nplays = 3\n'
            f'weights = {(W * 1e-9).tolist()}\nthresholds = {R.tolist()}\nw0 = {W0 * 1e-9}\n'
            '[state]\nprehistory = true\noffset = true\n')
    cfg = fitting.parse_config(text, "obs.toml")
    assert cfg.default_free()[-2:] == ("offset", "prehistory")
    start = pj.unwrap(cfg.build(ds))
    assert isinstance(start, pj.ForceDisplacementObserver)
    # the grid point nearest -50 (steps of max|v| / 4) and the offset of that start
    assert float(start.prehistory) == pytest.approx(-np.max(np.abs(V)), rel=1e-12)
    result = fitting.fit(cfg.build(ds), ds, predictor=cfg.predictor(), targets=("displacement",),
                         free=["offset", "prehistory"], max_steps=100)
    fitted = pj.unwrap(result.model)
    assert float(fitted.prehistory) == pytest.approx(-50.0, rel=1e-3)
    assert float(fitted.offset) == pytest.approx(2e-6, rel=1e-3)
    # the observer's default: no offset (the estimate of paper 001)
    plain_cfg = fitting.parse_config(text.replace("[state]\nprehistory = true\noffset = true\n", ""), "obs.toml")
    assert "offset" not in plain_cfg.default_free()
