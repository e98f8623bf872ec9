"""Play and stop operators: closed forms, rate independence, the smooth relaxation, gradients at ties, bad input."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from hypothesis.extra.numpy import arrays

import piezojax as pj
from piezojax._hysteresis.play import clip_stop, play_step

N = 24  # fixed signal length for the property tests: one compilation per function


def refine(v, k, fractions):
    """Insert `k` points on each straight segment of the path 0 -> v[0] -> v[1] ...; return (fine, index of v)."""
    corners = np.concatenate([[0.0], np.asarray(v)])
    fine, idx = [], []
    for i in range(len(corners) - 1):
        a, b = corners[i], corners[i + 1]
        fine.extend(a + (b - a) * np.sort(fractions[i]))
        fine.append(b)
        idx.append(len(fine) - 1)
    return np.asarray(fine), np.asarray(idx)


def play_closed_form_triangle(v, r, peak, trough):
    """Play output by hand on 0 -> peak (rising), -> trough (falling), -> back up (rising), for r < |trough| < peak."""
    out = np.empty_like(v)
    leg = 0
    for k, x in enumerate(v):
        if leg == 0 and k > 0 and x < v[k - 1]:
            leg = 1
        if leg == 1 and x > v[k - 1]:
            leg = 2
        if leg == 0:
            out[k] = max(x - r, 0.0)  # initial loading from the demagnetised state
        elif leg == 1:
            out[k] = min(peak - r, x + r)  # reversal at the peak
        else:
            out[k] = max(trough + r, x - r)  # reversal at the trough
    return out


_play = jax.jit(lambda r, s, v: pj.PlayOperator(r, s)(v))
_stop = jax.jit(lambda r, s, v: pj.StopOperator(r, s)(v))


def test_play_on_triangle_equals_closed_form():
    thresholds = np.array([0.0, 0.3, 0.8, 1.5])
    v = np.concatenate([np.linspace(0, 2.0, 21)[1:], np.linspace(2.0, -1.7, 38)[1:], np.linspace(-1.7, 1.2, 30)[1:]])
    y = np.asarray(pj.PlayOperator(thresholds)(v))
    assert y.shape == (v.size, thresholds.size)
    for i, r in enumerate(thresholds):
        np.testing.assert_allclose(y[:, i], play_closed_form_triangle(v, r, 2.0, -1.7), atol=1e-13)
    # the stop operator is the input minus the play, and stays within [-r, r]
    z = np.asarray(pj.StopOperator(thresholds)(v))
    np.testing.assert_allclose(z, v[:, None] - y, atol=1e-13)
    assert np.all(np.abs(z) <= thresholds + 1e-15)


def test_scalar_threshold_and_docstring_examples():
    np.testing.assert_allclose(pj.StopOperator(1.0)(jnp.array([0.5, 2.0, 1.0])), [0.5, 1.0, 0.0])
    y = pj.PlayOperator(0.5)(jnp.array([1.0, 2.0, 1.0, 0.0, 1.0]))
    assert y.shape == (5,)
    np.testing.assert_allclose(y, [0.5, 1.5, 1.5, 0.5, 0.5])
    np.testing.assert_allclose(play_step(jnp.zeros(3), 0.4, jnp.array([0.0, 0.2, 1.0]), 0.0), [0.0, 0.2, 0.4])


def test_smooth_ramp_equals_closed_form_flow():
    # dz/dv = 1 up to r - eps, then (r - z)/eps: z = r - eps exp(-(v - r + eps)/eps) beyond.
    r, s = 0.8, 0.25
    eps = s * r
    v = np.linspace(0.0, 2.0, 401)[1:]
    z_exact = np.where(v <= r - eps, v, r - eps * np.exp(-(v - r + eps) / eps))
    for stride in (1, 40):  # the same ramp with 400 samples and with 10 samples
        z = np.asarray(pj.StopOperator(r, s)(v[stride - 1 :: stride]))
        np.testing.assert_allclose(z, z_exact[stride - 1 :: stride], rtol=0, atol=1e-14)


@settings(max_examples=25)
@given(
    v=arrays(np.float64, N, elements=st.floats(-3, 3)),
    fractions=arrays(np.float64, (N, 2), elements=st.floats(0.01, 0.99)),
    smoothing=st.sampled_from([0.0, 0.05, 0.3]),
)
def test_rate_independence(v, fractions, smoothing):
    """Inserting samples on the straight path between samples changes nothing at the original samples."""
    thresholds = jnp.array([0.0, 0.2, 0.7, 1.9])
    fine, idx = refine(v, 2, fractions)
    y = _play(thresholds, smoothing, jnp.asarray(v))
    y_fine = _play(thresholds, smoothing, jnp.asarray(fine))
    np.testing.assert_allclose(y_fine[idx], y, rtol=0, atol=1e-12)


def test_ten_times_finer_sampling_changes_less_than_half_percent():
    """Issue property (b) for the recommended fitting smoothing 0.1 (it is in fact exact to rounding)."""
    t = np.linspace(0.0, 1.0, 201)
    t_fine = np.linspace(0.0, 1.0, 2001)
    path = lambda t: 2.0 * np.sin(2 * np.pi * 3 * t) * np.exp(-t)  # noqa: E731
    # the coarse signal and the piecewise-linear path through it, sampled 10x finer
    v = path(t)
    v_fine = np.interp(t_fine, t, v)
    op = pj.PlayOperator(jnp.array([0.1, 0.5, 1.0]), smoothing=0.1)
    y, y_fine = np.asarray(op(v)), np.asarray(op(v_fine))[::10]
    change = np.max(np.abs(y - y_fine)) / (y.max() - y.min())
    assert change < 5e-3
    assert change < 1e-12


def test_smooth_converges_to_exact():
    rng = np.random.default_rng(0)
    v = jnp.asarray(np.cumsum(rng.normal(0, 0.3, 300)))
    thresholds = jnp.array([0.2, 0.6, 1.0])
    exact = np.asarray(pj.StopOperator(thresholds)(v))
    errors = []
    for s in (0.3, 0.1, 0.01, 0.001):
        err = np.max(np.abs(np.asarray(pj.StopOperator(thresholds, s)(v)) - exact), axis=0)
        assert np.all(err <= s * np.asarray(thresholds) + 1e-12)  # within eps = s r of the exact operator
        errors.append(err.max())
    assert errors == sorted(errors, reverse=True) and errors[-1] < 1e-3


def test_zero_smoothing_is_bitwise_exact_and_traced_smoothing_matches():
    rng = np.random.default_rng(1)
    v = jnp.asarray(rng.uniform(-2, 2, 50))
    thresholds = jnp.array([0.0, 0.5, 1.0])
    y = np.zeros((50, 3))
    prev = np.zeros(3)
    for k, x in enumerate(np.asarray(v)):
        prev = np.maximum(x - np.asarray(thresholds), np.minimum(x + np.asarray(thresholds), prev))
        y[k] = prev
    np.testing.assert_allclose(pj.PlayOperator(thresholds)(v), y, rtol=0, atol=1e-15)
    np.testing.assert_allclose(_play(thresholds, 0.0, v), y, rtol=0, atol=1e-15)  # traced smoothing = 0
    # a traced smoothing does not recompile when it changes
    _play(thresholds, 0.2, v)
    size = _play._cache_size()
    _play(thresholds, 0.3, v)
    assert _play._cache_size() == size


def test_gradient_trap_zero_threshold_is_identity():
    """A play with r = 0 on a signal that starts at 0 and holds values: dy/dv = identity (jnp.clip would give 0.75)."""
    v = jnp.array([0.0, 0.0, 0.5, 0.5, 0.5, -0.2, -0.2])
    for smoothing in (0.0, 0.1):
        f = lambda v: pj.PlayOperator(0.0, smoothing)(v)  # noqa: E731
        np.testing.assert_allclose(f(v), v)
        np.testing.assert_allclose(jax.jacfwd(f)(v), np.eye(7), atol=1e-15)
        np.testing.assert_allclose(jax.jacrev(f)(v), np.eye(7), atol=1e-15)
        np.testing.assert_allclose(jax.grad(lambda v: jnp.sum(f(v)))(v), np.ones(7), atol=1e-15)


def test_gradient_when_signal_starts_exactly_on_threshold():
    r = 0.5
    v = np.array([0.5, 0.9, 0.3])
    f = lambda v: pj.PlayOperator(r)(v)  # noqa: E731
    jac = np.asarray(jax.jacfwd(f)(jnp.asarray(v)))
    h = 1e-6
    fd = np.stack([(np.asarray(f(v + h * e)) - np.asarray(f(v - h * e))) / (2 * h) for e in np.eye(3)], -1)
    np.testing.assert_allclose(jac, fd, atol=1e-8)
    assert jac[0, 0] == pytest.approx(0.5)  # the mean of the one-sided derivatives 0 and 1
    np.testing.assert_allclose(jax.jacrev(f)(jnp.asarray(v)), jac, atol=1e-15)


@settings(max_examples=30)
@given(
    z=st.floats(-0.9, 0.9),
    delta=st.floats(-2, 2).filter(lambda d: abs(d) > 1e-3),
    r=st.floats(0.95, 2.0),
    s=st.floats(0.02, 0.9),
    direction=arrays(np.float64, 4, elements=st.floats(-1, 1)),
)
def test_play_step_jvp_matches_finite_differences(z, delta, r, s, direction):
    """The hand-written JVP of the smooth step (flow of an autonomous ODE) against a central difference."""
    x = np.array([z * r, delta, r, s])
    f = lambda p: play_step(p[0], p[1], p[2], p[3])  # noqa: E731
    _, tangent = jax.jvp(f, (jnp.asarray(x),), (jnp.asarray(direction),))
    h = 1e-6
    fd = (float(f(jnp.asarray(x + h * direction))) - float(f(jnp.asarray(x - h * direction)))) / (2 * h)
    assert float(tangent) == pytest.approx(fd, abs=2e-6 * (1 + 1 / s))


def test_play_step_at_zero_increment_takes_mean_slope():
    # z in the upper boundary layer: increasing slope (r - z)/eps, decreasing slope 1
    r, s, z = 1.0, 0.2, 0.9
    d_dd = jax.grad(play_step, argnums=1)(jnp.asarray(z), jnp.asarray(0.0), jnp.asarray(r), jnp.asarray(s))
    assert float(d_dd) == pytest.approx(0.5 * ((r - z) / (s * r) + 1.0))
    h = 1e-7
    fd = (play_step(z, h, r, s) - play_step(z, -h, r, s)) / (2 * h)
    assert float(d_dd) == pytest.approx(float(fd), abs=1e-6)


def test_clip_stop_tie_rules():
    grad = jax.grad(clip_stop, argnums=(0, 1, 2))
    # inside, outside, single tie with motion, double tie at r = 0
    assert [float(g) for g in grad(0.1, 0.2, 1.0)] == [1.0, 1.0, 0.0]
    assert [float(g) for g in grad(0.5, 0.7, 1.0)] == [0.0, 0.0, 1.0]
    assert [float(g) for g in grad(0.2, 0.8, 1.0)] == [0.5, 0.5, 0.5]
    assert [float(g) for g in grad(0.0, 0.0, 0.0)] == [1.0, 0.0, 0.0]


def test_jit_vmap_float32_and_shapes():
    rng = np.random.default_rng(2)
    batch = jnp.asarray(rng.uniform(-1, 1, (3, 20)))
    op = pj.PlayOperator(jnp.array([0.1, 0.4]), smoothing=0.1)
    out = jax.vmap(op)(batch)
    assert out.shape == (3, 20, 2)
    np.testing.assert_allclose(out[1], op(batch[1]), atol=1e-15)
    np.testing.assert_allclose(jax.jit(jax.vmap(op))(batch), out, atol=1e-15)
    op32 = pj.PlayOperator(jnp.array([0.1, 0.4], jnp.float32), smoothing=0.1)
    y32 = op32(batch[0].astype(jnp.float32))
    assert y32.dtype == jnp.float32
    np.testing.assert_allclose(y32, out[0], atol=1e-5)
    stop32 = pj.StopOperator(jnp.float32(0.3))
    assert stop32(jnp.ones(4, jnp.float32)).dtype == jnp.float32
    # the final state continues a signal exactly
    state, y_a = op.scan(batch[0, :10])
    _, y_b = op.scan(batch[0, 10:], state)
    np.testing.assert_allclose(jnp.concatenate([y_a, y_b]), out[0], atol=1e-15)


def test_bad_input():
    with pytest.raises(ValueError, match="thresholds"):
        pj.PlayOperator(jnp.array([0.5, -0.1]))
    with pytest.raises(ValueError, match="thresholds"):
        pj.StopOperator(jnp.ones((2, 2)))
    with pytest.raises(ValueError, match="smoothing"):
        pj.PlayOperator(0.5, smoothing=-0.1)
    with pytest.raises(ValueError, match="smoothing"):
        pj.PlayOperator(0.5, smoothing=jnp.ones(2))
    op = pj.PlayOperator(0.5)
    with pytest.raises(ValueError, match="signal"):
        op(jnp.ones((3, 2)))
    with pytest.raises(ValueError, match="signal"):
        op(jnp.ones(0))
    with pytest.raises(Exception, match="signal"):
        op(jnp.array([0.0, jnp.nan, 1.0]))
    with pytest.raises(Exception, match="signal"):
        jax.jit(lambda v: op(v))(jnp.array([0.0, jnp.nan, 1.0]))
    with pytest.raises(Exception, match="thresholds"):
        _play(jnp.array([0.5, -0.1]), 0.0, jnp.ones(N))  # traced thresholds: eqx.error_if
    with pytest.raises(Exception, match="smoothing"):
        _play(jnp.array([0.5]), -0.1, jnp.ones(N))
    assert isinstance(eqx.filter_jit(op)(jnp.ones(3)), jax.Array)
