"""Control: PID, feedforward, NARX network, adaptive inverse controller and the closed-loop simulator."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import piezojax as pj


class FirstOrderPlant(pj.AbstractPlant):
    """x_{k+1} = a x_k + b u_k, y_k = x_k + w_k: written out for the tests."""

    a: jax.Array
    b: jax.Array

    def init(self):
        return jnp.zeros((), self.a.dtype)

    def output(self, state, noise):
        return {"displacement": state + (0.0 if noise is None else noise)}

    def step(self, state, command):
        return self.a * state + self.b * command


def _plant():
    return FirstOrderPlant(jnp.asarray(0.9), jnp.asarray(0.5))


def _pid_by_hand(kp, ki, kd, dt, r, w, a, b, u_min, u_max, tf, tt):
    x, integ, y_prev, d = 0.0, 0.0, None, 0.0  # the derivative starts at rest at the first measurement
    us, ys = [], []
    for k in range(len(r)):
        y = x + w[k]
        e = r[k] - y
        d = (tf * d - kd * (y - (y if y_prev is None else y_prev))) / (tf + dt)
        v = kp * e + integ + d
        u = min(max(v, u_min), u_max)
        integ = integ + ki * dt * e + dt / tt * (u - v)
        y_prev = y
        us.append(u)
        ys.append(y)
        x = a * x + b * u
    return np.array(us), np.array(ys)


def test_pid_derivative_starts_at_the_first_measurement():
    """A plant read at 5 from the start and a reference at 5: a derivative-only PID commands nothing (it had
    kicked on the first sample, from a previous measurement taken as 0); `init(measurement)` still sets it."""
    pid = pj.PID(0.0, 0.0, 0.05, dt=1e-3)
    rec = pj.closed_loop(pid, _plant(), jnp.full(5, 5.0), noise=jnp.full(5, 5.0))
    np.testing.assert_array_equal(rec.control, 0.0)
    state, u = pid.step(pid.init(0.0), 5.0, 5.0)
    assert float(u) == pytest.approx(-0.05 * 5.0 / 2e-3)  # (T_f D - k_d (y - y_prev)) / (T_f + dt), T_f = dt


def test_closed_loop_matches_a_hand_written_loop():
    rng = np.random.default_rng(0)
    n = 200
    r = np.where(np.arange(n) > 20, 3.0, 0.0)
    w = 0.01 * rng.standard_normal(n)
    pid = pj.PID(0.4, 30.0, 0.002, dt=0.01, u_min=-0.8, u_max=0.8, derivative_filter=0.02, tracking_time=0.05)
    rec = pj.closed_loop(pid, _plant(), r, noise=w)
    u, y = _pid_by_hand(0.4, 30.0, 0.002, 0.01, r, w, 0.9, 0.5, -0.8, 0.8, 0.02, 0.05)
    np.testing.assert_allclose(rec.control, u, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(rec.feedback, y, rtol=1e-12, atol=1e-14)
    assert np.any(u == 0.8)  # the limit was reached: the anti-windup path is exercised
    # the replay of the recorded feedback gives the same commands (the controller is a pure cell)
    np.testing.assert_allclose(pid(r, rec.feedback), u, rtol=1e-12, atol=1e-14)
    # settled on the reference despite the saturation, with less overshoot than the same PID without anti-windup
    truth = np.asarray(rec.channels["displacement"]) - w
    windup = eqx.tree_at(lambda p: p.tracking_time, pid, jnp.asarray(1e12))
    truth_windup = np.asarray(pj.closed_loop(windup, _plant(), r, noise=w).channels["displacement"]) - w
    assert abs(truth[-1] - 3.0) < 0.05
    assert truth.max() - 3.0 < 0.5 * (truth_windup.max() - 3.0), (truth.max(), truth_windup.max())


def test_closed_loop_preview_feeds_the_controller_the_reference_ahead():
    rng = np.random.default_rng(1)
    r = np.cumsum(rng.standard_normal(40))
    pid = pj.PID(0.4, 30.0, dt=0.01)
    rec = pj.closed_loop(pid, _plant(), r, preview=3)
    ahead = np.concatenate([r[3:], np.full(3, r[-1])])
    np.testing.assert_allclose(rec.control, pj.closed_loop(pid, _plant(), ahead).control, rtol=1e-12)
    np.testing.assert_array_equal(rec.reference, r)  # the record stays aligned with r_k
    long = pj.closed_loop(pid, _plant(), r[:2], preview=5)  # a preview longer than the reference holds its end
    np.testing.assert_allclose(long.control, pj.closed_loop(pid, _plant(), np.full(2, r[1])).control, rtol=1e-12)
    with pytest.raises(pj.PiezojaxValueError, match="preview"):
        pj.closed_loop(pid, _plant(), r, preview=-1)


def test_closed_loop_vmaps_and_jits_over_controllers_and_references():
    r = jnp.stack([jnp.ones(50), 2 * jnp.ones(50)])
    gains = jnp.asarray([10.0, 20.0])

    @eqx.filter_jit
    def run(ki, ref):
        return pj.closed_loop(pj.PID(0.1, ki, dt=0.01), _plant(), ref).channels["displacement"]

    out = jax.vmap(run)(gains, r)
    for i in range(2):
        np.testing.assert_allclose(out[i], run(gains[i], r[i]), rtol=1e-12)


def _tracking_cost(gains, plant, ref, observer):
    pid = pj.PID(gains[0], gains[1], dt=plant.dt, offset=100.0)
    rec = pj.closed_loop(pid, plant, ref, observer=observer)
    return jnp.mean(((ref - rec.channels["displacement"]) / 1e-6) ** 2)


def test_gradient_through_the_closed_loop_matches_finite_differences():
    bench = pj.ChenBench().ideal()
    plant = bench.plant(dac_bits=0, substeps=2, bias=100.0, settle=0.1)
    t = np.arange(300) * 1e-3
    ref = jnp.asarray(2e-6 * np.sin(2 * np.pi * 5 * t))
    gains = jnp.asarray([2e6, 1.5e9])
    cost = eqx.filter_jit(_tracking_cost)
    g = eqx.filter_jit(jax.grad(_tracking_cost))(gains, plant, ref, bench.observer())
    for i in range(2):
        h = 1e-5 * gains[i]
        e = jnp.zeros(2).at[i].set(h)
        fd = (cost(gains + e, plant, ref, bench.observer()) - cost(gains - e, plant, ref, bench.observer())) / (2 * h)
        np.testing.assert_allclose(g[i], fd, rtol=1e-5)
    assert np.all(np.isfinite(g)) and np.all(g != 0)


def _adaptive_by_hand(W, c, w, b, eta, alpha, u0, su, y0, sy, n_y, n_r, r, y, preview=0):
    """Paper 002's eq. (12)-(19), written out sample by sample (our index reading, see the class docstring); with
    a preview p the reference read at k is aimed at k + p, so the error compares y_k with the one read at k - p."""
    g = lambda z: 1 / (1 + np.exp(-z))  # noqa: E731
    W, c, w, b = W.copy(), c.copy(), w.copy(), float(b)
    dW, dc, dw, db = np.zeros_like(W), np.zeros_like(c), np.zeros_like(w), 0.0
    ys, rs = None, None
    X_prev, O_prev = None, None
    us = []
    for k in range(len(r)):
        yn, rn = (y[k] - y0) / sy, (r[k] - y0) / sy
        if k > 0:
            e = (r[max(k - preview, 0)] - y0) / sy - yn  # eq. (17)
            w_old = w.copy()
            dw = eta * e * O_prev + alpha * dw  # eq. (18)
            db = eta * e + alpha * db
            dc = eta * e * w_old * O_prev * (1 - O_prev) + alpha * dc  # eq. (19), bias input 1
            dW = eta * e * (w_old * O_prev * (1 - O_prev))[:, None] * X_prev[None, :] + alpha * dW
            W, c, w, b = W + dW, c + dc, w + dw, b + db
            ys = [yn] + ys[: n_y - 1]
            rs = [rn] + rs[: n_r - 1]
        else:
            ys, rs = [yn] * n_y, [rn] * n_r
        X = np.array(ys + rs)
        O = g(W @ X + c)  # noqa: E741  eq. (15)
        us.append(u0 + su * (w @ O + b))  # eq. (16)
        X_prev, O_prev = X, O
    return np.array(us), (W, c, w, b)


@pytest.mark.parametrize("preview", [0, 2])
def test_adaptive_update_matches_equations_18_19_written_out(preview):
    rng = np.random.default_rng(3)
    n = 60
    r = 1e-6 * np.sin(np.arange(n) / 5)
    y = 1e-6 * np.sin((np.arange(n) - 1.5) / 5) + 1e-8 * rng.standard_normal(n)
    aic = pj.AdaptiveInverseController(jax.random.key(2), hidden=5, measurement_lags=2, reference_lags=3,
                                       learning_rate=0.3, momentum=0.6, offset=100.0, command_scale=40.0,
                                       output_offset=1e-7, output_scale=2e-6, preview=preview)
    aic = eqx.tree_at(lambda m: (m.output_weights, m.output_bias), aic,
                      (jnp.asarray(rng.standard_normal(5)), jnp.asarray(0.1)))
    u = aic(r, y)
    params = [np.asarray(p) for p in aic.params]
    u_ref, final = _adaptive_by_hand(*params, 0.3, 0.6, 100.0, 40.0, 1e-7, 2e-6, 2, 3, r, y, preview)
    np.testing.assert_allclose(u, u_ref, rtol=1e-12)
    state = aic.init()
    for k in range(n):
        state, _ = aic.step(state, jnp.asarray(r[k]), jnp.asarray(y[k]))
    for got, want in zip(state[0], final, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-14)
    # learning moved the weights; a zero learning rate and momentum leave them where they were
    assert not np.allclose(final[2], params[2])
    frozen = eqx.tree_at(lambda m: (m.learning_rate, m.momentum), aic, (jnp.asarray(0.0), jnp.asarray(0.0)))
    state = frozen.init()
    for k in range(5):
        state, _ = frozen.step(state, jnp.asarray(r[k]), jnp.asarray(y[k]))
    np.testing.assert_array_equal(state[0][2], params[2])


def test_adaptive_inverse_control_tracks_the_chen_stage_better_as_it_learns():
    bench = pj.ChenBench()
    plant = bench.plant(bias=100.0, substeps=4, settle=0.2)
    obs = bench.observer()
    n = 1000
    t = np.arange(n) * 1e-3
    u_open = 100 + (30 * np.sin(2 * np.pi * 3 * t) + 10 * np.sin(2 * np.pi * 13 * t)) * np.minimum(t / 0.3, 1)
    noise = jax.random.normal(jax.random.key(4), (n, 2))
    ch = eqx.filter_jit(lambda p, u, w: p.simulate(u, w))(plant, u_open, noise)
    y_open = jax.vmap(lambda a, b: obs.step((), {"v_in": a, "v_out": b})[1])(ch["v_in"], ch["v_out"])
    base = pj.AdaptiveInverseController(jax.random.key(0), hidden=6, measurement_lags=0, reference_lags=3,
                                        offset=100.0, command_scale=30.0, output_scale=3e-6)
    base = base.fit_output_layer(y_open, u_open)
    ph = (t * 5) % 1
    ref = jnp.asarray(3e-6 * np.where(ph < 0.25, 4 * ph, np.where(ph < 0.75, 2 - 4 * ph, 4 * ph - 4)))

    @eqx.filter_jit
    def error(c):
        rec = pj.closed_loop(c, plant, ref, observer=obs, noise=noise)
        return pj.tracking_error_percent(ref[500:], rec.channels["displacement"][500:])

    fixed = float(error(base))
    adaptive = float(error(eqx.tree_at(lambda m: (m.learning_rate, m.momentum), base,
                                       (jnp.asarray(0.005), jnp.asarray(0.5)))))
    assert adaptive < 0.6 * fixed, (fixed, adaptive)  # measured: 2.70 % fixed, 1.05 % adaptive
    assert adaptive < 2.0


def test_narx_cell_simulation_one_step_and_online_training():
    rng = np.random.default_rng(1)
    n = 400
    x = np.cumsum(rng.standard_normal(n)) * 0.1
    # a plant written without piezojax: y_k = 0.6 y_{k-1} + tanh(x_{k-1})
    y = np.zeros(n)
    for k in range(1, n):
        y[k] = 0.6 * y[k - 1] + np.tanh(x[k - 1])
    net = pj.NarxNetwork(jax.random.key(0), hidden=6, output_lags=1, input_lags=1, output_scale=2.0, input_scale=2.0)
    # the scan of the cell equals the regression form when the model's own outputs are the measured ones
    net = eqx.tree_at(lambda m: m.output_weights, net, jnp.asarray(rng.standard_normal(6)))
    sim = net.simulate(x, y0=y[0])
    np.testing.assert_allclose(net.one_step(x, sim)[1:], sim[1:], rtol=1e-12, atol=1e-12)
    trained = pj.train_narx_online(net, x, y, learning_rate=0.05, momentum=0.5, epochs=30)
    before = np.sqrt(np.mean((np.asarray(net.one_step(x, y)) - y) ** 2))
    after = np.sqrt(np.mean((np.asarray(trained.one_step(x, y)) - y) ** 2))
    assert after < 0.1 * before, (before, after)
    rms_free = lambda m: np.sqrt(np.mean((np.asarray(m.simulate(x, y0=y[0])) - y) ** 2))  # noqa: E731
    assert rms_free(trained) < 0.5 * rms_free(net)


def test_narx_without_output_lags():
    """`output_lags=0`: a static network of the past inputs; its free run is its one-step prediction (the cell had
    shifted an empty output history and failed)."""
    rng = np.random.default_rng(2)
    net = pj.NarxNetwork(jax.random.key(3), hidden=4, output_lags=0, input_lags=2)
    net = eqx.tree_at(lambda m: m.output_weights, net, jnp.asarray(rng.standard_normal(4)))
    x = jnp.asarray(rng.standard_normal(50))
    sim = eqx.filter_jit(net.simulate)(x)
    np.testing.assert_allclose(sim[3:], net.one_step(x, jnp.zeros(50))[3:], rtol=1e-12, atol=1e-14)
    with pytest.raises(pj.PiezojaxValueError, match="`delay` must be an int"):
        pj.NarxNetwork(jax.random.key(0), hidden=3, output_lags=1, input_lags=1, delay=True)


def test_control_bad_input():
    with pytest.raises(pj.PiezojaxValueError, match="u_max"):
        pj.PID(1.0, dt=0.01, u_min=1.0, u_max=0.0)
    with pytest.raises(pj.PiezojaxValueError, match="dt"):
        pj.PID(1.0, dt=0.0)
    with pytest.raises(pj.PiezojaxValueError, match="controller"):
        pj.closed_loop(object(), _plant(), np.ones(3))
    with pytest.raises(pj.PiezojaxValueError, match="feedback"):
        pj.closed_loop(pj.PID(1.0, dt=0.01), _plant(), np.ones(3), feedback="force")
    with pytest.raises(pj.PiezojaxValueError, match="noise"):
        pj.closed_loop(pj.PID(1.0, dt=0.01), _plant(), np.ones(3), noise=np.ones(4))
    with pytest.raises(pj.PiezojaxValueError, match="momentum"):
        pj.AdaptiveInverseController(jax.random.key(0), hidden=3, momentum=1.0)
    with pytest.raises(pj.PiezojaxValueError, match="input_lags"):
        pj.NarxNetwork(jax.random.key(0), hidden=3, output_lags=1, input_lags=0)
    with pytest.raises(pj.PiezojaxValueError, match="`inverse` must be a pj.AbstractCell"):
        pj.InverseFeedforward(lambda y: y)

    class DuckCell(eqx.Module):  # init/step without declaring the interface: refused, naming it
        def init(self):
            return ()

        def step(self, state, x):
            return state, x

    with pytest.raises(pj.PiezojaxValueError, match="`observer` must be a pj.AbstractCell .*got DuckCell"):
        pj.closed_loop(pj.PID(1.0, dt=0.01), _plant(), np.ones(3), observer=DuckCell())

    class Gain(pj.AbstractCell):  # a cell of one's own: the feedback doubled, the inverse halving
        g: float

        def init(self):
            return ()

        def step(self, state, x):
            return state, self.g * (x["displacement"] if isinstance(x, dict) else x)

    pid, ref = pj.PID(1.0, ki=5.0, dt=0.01), np.ones(10)
    same = pj.closed_loop(pid, _plant(), ref, observer=Gain(1.0))
    np.testing.assert_array_equal(np.asarray(same.control), np.asarray(pj.closed_loop(pid, _plant(), ref).control))
    doubled = pj.closed_loop(pid, _plant(), ref, observer=Gain(2.0))
    np.testing.assert_allclose(doubled.feedback, 2 * np.asarray(doubled.channels["displacement"]), rtol=1e-12)
    assert np.ptp(np.asarray(doubled.feedback)) > 0
    ff = pj.InverseFeedforward(Gain(0.5), offset=1.0)
    np.testing.assert_allclose(np.asarray(ff(jnp.array([2.0, 4.0]), jnp.zeros(2))), [2.0, 3.0], rtol=1e-12)


def test_adaptive_offline_start_fits_the_inverse_the_preview_aims_at():
    # a plant that is a gain behind two samples of delay: y_{k+2} = 0.5 (u_k - 100); with preview=2 the network reads
    # r_{k+2} and its offline start is the exact inverse, with preview=1 it must guess u_k from y_{k+1}
    rng = np.random.default_rng(5)
    n = 800
    u = 100 + np.convolve(rng.standard_normal(n + 40), np.ones(40) / 4, mode="valid")[:n]
    y = np.concatenate([np.zeros(2), 0.5e-6 * (u[:-2] - 100)])
    errors = {}
    for preview in (1, 2):
        aic = pj.AdaptiveInverseController(jax.random.key(1), hidden=8, measurement_lags=0, reference_lags=1,
                                           offset=100.0, command_scale=10.0, output_scale=5e-6, preview=preview)
        aic = aic.fit_output_layer(y, u)
        ahead = np.concatenate([y[preview:], np.full(preview, y[-1])])  # what the loop's preview reads
        u_hat = np.asarray(aic(ahead, y))
        errors[preview] = np.sqrt(np.mean((u_hat - u)[10:-10] ** 2)) / np.std(u)
    assert errors[2] < 0.02 < errors[1], errors
    with pytest.raises(pj.PiezojaxValueError, match="preview"):
        pj.AdaptiveInverseController(jax.random.key(1), hidden=2, preview=-1)
    # run in a loop of another preview, its targets would be misaligned: refused, naming both
    with pytest.raises(pj.PiezojaxValueError, match=r"`preview` = 0 differs from the controller's own `preview` = 2"):
        pj.closed_loop(aic, _plant(), np.ones(3))
    with pytest.raises(pj.PiezojaxValueError, match=r"differs from the controller's own `preview` = 2"):
        pj.closed_loop(pj.FeedforwardFeedback(aic, pj.PID(0.1, dt=1e-3, offset=0.0)), _plant(), np.ones(3), preview=1)


def test_network_controllers_name_a_key_that_is_no_key():
    for make in (lambda k: pj.AdaptiveInverseController(k, hidden=4),
                 lambda k: pj.NarxNetwork(k, hidden=4, output_lags=2, input_lags=2)):
        for bad in (0, jnp.zeros(3)):
            with pytest.raises(pj.PiezojaxValueError, match=r"`key` must be one JAX PRNG key"):
                make(bad)
        make(jax.random.key(0))
        make(jax.random.PRNGKey(0))
        with jax.default_prng_impl("rbg"):  # a raw key of another implementation has another length
            make(jax.random.PRNGKey(0))


def test_float32_controllers_stay_float32():
    """Under x64, a PID built from float32 gains keeps its Python-number defaults (offset, limits) in float32, and so
    does a feedforward of a float32 model: the commands come out float32."""
    f32 = np.float32
    pid = pj.PID(f32(0.4), f32(30.0), dt=f32(0.01))
    assert {leaf.dtype for leaf in jax.tree.leaves(pid)} == {jnp.dtype("float32")}
    r = jnp.ones(5, jnp.float32)
    assert pid(r, r).dtype == jnp.float32
    pi32 = pj.PrandtlIshlinskii(jnp.full(2, 0.5, jnp.float32), jnp.asarray([0.1, 0.3], jnp.float32), w0=f32(1.0))
    ff = pj.InverseFeedforward(pi32.inverse(), offset=100.0, reference_scale=1e-6)
    assert ff(r, r).dtype == jnp.float32
