"""Prandtl–Ishlinskii operator: hand computation, analytic inverse, memory properties, gradients, bad input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _jaxpr_helpers import loop_under_cond
from hypothesis import given, settings, strategies as st
from hypothesis.extra.numpy import arrays

import piezojax as pj

N = 30  # fixed signal length for the property tests: one compilation per function
N_PLAYS = 5


def _apply(w, r, w0, s, v):
    return pj.PrandtlIshlinskii(w, r, w0, s)(v)


_pi = jax.jit(_apply)
_scan = jax.jit(lambda w, r, w0, v, state: pj.PrandtlIshlinskii(w, r, w0).scan(v, state))
_round_trip = jax.jit(lambda w, r, w0, v: pj.PrandtlIshlinskii(w, r, w0).inverse()(pj.PrandtlIshlinskii(w, r, w0)(v)))
_inverse_first = jax.jit(
    lambda w, r, w0, y: pj.PrandtlIshlinskii(w, r, w0)(pj.PrandtlIshlinskii(w, r, w0).inverse()(y))
)


def random_pi(draw_weights, draw_gaps, w0):
    thresholds = np.cumsum(draw_gaps) - draw_gaps[0]  # starts at 0: a zero threshold is included
    return jnp.asarray(draw_weights), jnp.asarray(thresholds), jnp.asarray(w0)


weights_st = arrays(np.float64, N_PLAYS, elements=st.floats(0.05, 1.5))
gaps_st = arrays(np.float64, N_PLAYS, elements=st.floats(0.05, 0.6))
signal_st = arrays(np.float64, N, elements=st.floats(-3, 3))


def test_hand_computation():
    # P_0.5: [0.5, 1.5, 1.5, 0.5, 0.5], P_1: [0, 1, 1, 1, 1]; H = 0.5 v + 1 P_0.5 + 2 P_1
    pi = pj.PrandtlIshlinskii(jnp.array([1.0, 2.0]), jnp.array([0.5, 1.0]), w0=0.5)
    np.testing.assert_allclose(pi(jnp.array([1.0, 2.0, 1.0, 0.0, 1.0])), [1.0, 4.5, 4.0, 2.5, 3.0], atol=1e-15)


def test_sum_of_play_operators_and_loading_curve():
    rng = np.random.default_rng(0)
    w, r = rng.uniform(-0.5, 1.0, 4), np.array([0.0, 0.3, 0.9, 1.4])
    v = np.cumsum(rng.normal(0, 0.4, 60))
    pi = pj.PrandtlIshlinskii(w, r, w0=0.7)
    plays = np.asarray(pj.PlayOperator(r)(v))
    np.testing.assert_allclose(pi(v), 0.7 * v + plays @ w, atol=1e-13)
    ramp = np.linspace(0, 2.5, 26)
    np.testing.assert_allclose(pi(ramp), pi.loading_curve(ramp), atol=1e-13)


@settings(max_examples=25)
@given(w=weights_st, gaps=gaps_st, w0=st.floats(0.1, 2.0), v=signal_st)
def test_inverse_composed_with_operator_is_identity(w, gaps, w0, v):
    w, r, w0 = random_pi(w, gaps, w0)
    np.testing.assert_allclose(_round_trip(w, r, w0, jnp.asarray(v)), v, rtol=0, atol=1e-9)
    np.testing.assert_allclose(_inverse_first(w, r, w0, jnp.asarray(v)), v, rtol=0, atol=1e-9)


def test_inverse_formula_by_loading_curves_and_involution():
    """The inverse has the inverse loading curve; inverting twice gives the operator back."""
    w, r = jnp.array([0.4, 1.1, 0.2]), jnp.array([0.0, 0.5, 1.3])
    pi = pj.PrandtlIshlinskii(w, r, w0=0.6)
    inv = pi.inverse()
    # by hand: slopes a = [0.6, 1.0, 2.1, 2.3]; r' = [0, 0.6*0.5 + 1.0*0 ..] = cumulative a_{j-1} (r_j - r_{j-1})
    np.testing.assert_allclose(inv.thresholds, [0.0, 0.5, 0.5 + 2.1 * 0.8], atol=1e-15)
    np.testing.assert_allclose(inv.weights, [-0.4 / (1.0 * 0.6), -1.1 / (2.1 * 1.0), -0.2 / (2.3 * 2.1)], atol=1e-15)
    np.testing.assert_allclose(inv.w0, 1 / 0.6)
    v = jnp.linspace(0, 3, 31)
    np.testing.assert_allclose(inv.loading_curve(pi.loading_curve(v)), v, atol=1e-13)
    back = inv.inverse()
    np.testing.assert_allclose(back.weights, w, atol=1e-13)
    np.testing.assert_allclose(back.thresholds, r, atol=1e-13)
    np.testing.assert_allclose(back.w0, 0.6, atol=1e-13)


@settings(max_examples=25)
@given(
    w=weights_st,
    gaps=gaps_st,
    history=arrays(np.float64, 8, elements=st.floats(-3, 3)),
    peak=st.floats(0.1, 3),
    dip=st.floats(0, 1),
    beyond=st.floats(0, 2),
)
def test_return_point_memory_and_wiping_out(w, gaps, history, peak, dip, beyond):
    """After a minor loop v_a -> v_b -> v_a inside the last rising branch, state and output are as before the loop,
    and the rest of the signal sees no trace of it."""
    w, r, w0 = random_pi(w, gaps, 0.8)
    m = history[-1]
    v_a = m + peak  # rising from the last reversal m to v_a
    v_b = v_a - dip * (v_a - m)  # the minor loop stays above the previous reversal point m
    base = np.concatenate([history, [v_a]])
    demagnetised = (jnp.asarray(0.0), jnp.zeros(N_PLAYS))
    state_a, y_a = _scan(w, r, w0, jnp.asarray(base), demagnetised)
    state_loop, y_loop = _scan(w, r, w0, jnp.asarray([v_b, v_a]), state_a)
    assert float(y_loop[-1]) == pytest.approx(float(y_a[-1]), abs=1e-12)
    np.testing.assert_allclose(state_loop[1], state_a[1], atol=1e-12)
    tail = jnp.asarray([v_a + beyond, m - beyond])
    np.testing.assert_allclose(_scan(w, r, w0, tail, state_loop)[1], _scan(w, r, w0, tail, state_a)[1], atol=1e-12)


@settings(max_examples=20)
@given(
    w=weights_st,
    gaps=gaps_st,
    v=signal_st,
    fractions=arrays(np.float64, (N, 3), elements=st.floats(0.01, 0.99)),
    smoothing=st.sampled_from([0.0, 0.1]),
)
def test_rate_independence(w, gaps, v, fractions, smoothing):
    w, r, w0 = random_pi(w, gaps, 0.8)
    corners = np.concatenate([[0.0], v])
    fine = np.concatenate(
        [np.concatenate([a + (b - a) * np.sort(f), [b]]) for a, b, f in zip(corners[:-1], corners[1:], fractions)]
    )
    idx = np.arange(1, N + 1) * 4 - 1
    np.testing.assert_allclose(
        _pi(w, r, w0, smoothing, jnp.asarray(fine))[idx], _pi(w, r, w0, smoothing, jnp.asarray(v)), atol=1e-12
    )


def test_smooth_converges_to_exact():
    rng = np.random.default_rng(1)
    w, r = jnp.asarray(rng.uniform(0.2, 1, 6)), jnp.linspace(0.0, 1.5, 6)
    v = jnp.asarray(np.cumsum(rng.normal(0, 0.3, N)))
    exact = _pi(w, r, 0.5, 0.0, v)
    bound = float(jnp.sum(jnp.abs(w) * r))  # each play is within s r_i of the exact one
    errs = [float(jnp.max(jnp.abs(_pi(w, r, 0.5, s, v) - exact))) for s in (0.2, 0.02, 0.002)]
    for s, e in zip((0.2, 0.02, 0.002), errs):
        assert e <= s * bound + 1e-12
    assert errs[0] > errs[1] > errs[2]


def _fd_jacobian(f, x, h=1e-6, one_sided=()):
    x = np.asarray(x, dtype=np.float64)
    cols = []
    for i in range(x.size):
        e = np.zeros_like(x)
        e.flat[i] = h
        if i in one_sided:
            cols.append((np.asarray(f(jnp.asarray(x + e))) - np.asarray(f(jnp.asarray(x)))) / h)
        else:
            cols.append((np.asarray(f(jnp.asarray(x + e))) - np.asarray(f(jnp.asarray(x - e)))) / (2 * h))
    return np.stack(cols, -1).reshape(np.shape(f(jnp.asarray(x))) + x.shape)


@pytest.mark.parametrize("smoothing", [0.0, 0.15])
def test_gradients_match_finite_differences(smoothing):
    """Input, weights, thresholds (one zero: one-sided difference) and w0; a signal starting exactly on a threshold
    (0.3) and at 0 for the r = 0 play."""
    rng = np.random.default_rng(3)
    v = jnp.asarray(np.concatenate([[0.3], rng.uniform(-2, 2, N - 1)]))
    w = jnp.asarray(rng.uniform(0.2, 1.0, N_PLAYS))
    r = jnp.array([0.0, 0.3, 0.75, 1.2, 1.6])
    w0 = jnp.asarray(0.6)
    jac = jax.jit(jax.jacfwd(_apply, argnums=(0, 1, 2, 3, 4)))(w, r, w0, smoothing, v)
    jac_rev = jax.jit(jax.jacrev(_apply, argnums=(0, 1, 2, 4)))(w, r, w0, smoothing, v)
    for a, b in zip((jac[0], jac[1], jac[2], jac[4]), jac_rev):
        np.testing.assert_allclose(a, b, atol=1e-12)
    tol = dict(rtol=0, atol=1e-6)
    np.testing.assert_allclose(jac[4], _fd_jacobian(lambda x: _pi(w, r, w0, smoothing, x), v), **tol)
    np.testing.assert_allclose(jac[0], _fd_jacobian(lambda x: _pi(x, r, w0, smoothing, v), w), **tol)
    np.testing.assert_allclose(
        jac[1], _fd_jacobian(lambda x: _pi(w, x, w0, smoothing, v), r, one_sided=(0,)), **tol
    )
    np.testing.assert_allclose(jac[2], _fd_jacobian(lambda x: _pi(w, r, x, smoothing, v), w0), **tol)
    if smoothing:
        fd_s = (_pi(w, r, w0, smoothing + 1e-6, v) - _pi(w, r, w0, smoothing - 1e-6, v)) / 2e-6
        np.testing.assert_allclose(jac[3], fd_s, **tol)
    if smoothing == 0:
        # v[0] = 0.3 = r_1 from the demagnetised state: the r = 0 play follows v (slope 1), the r = 0.3 play sits on
        # the tie (mean of the one-sided slopes 0 and 1), the others do not move
        assert float(jac[4][0, 0]) == pytest.approx(0.6 + float(w[0]) + 0.5 * float(w[1]), abs=1e-12)


def test_grad_of_scalar_loss_vmap_jit_float32():
    rng = np.random.default_rng(4)
    batch = jnp.asarray(rng.uniform(-1, 1, (3, N)))
    op = pj.PrandtlIshlinskii(jnp.array([0.5, 0.3]), jnp.array([0.1, 0.4]), w0=1.0)

    def loss(op, v):
        return jnp.sum(op(v) ** 2)

    g = jax.jit(jax.grad(loss))(op, batch[0])
    assert isinstance(g, pj.PrandtlIshlinskii) and g.weights.shape == (2,) and jnp.all(jnp.isfinite(g.thresholds))
    h = 1e-6
    fd = (loss(pj.PrandtlIshlinskii(op.weights, op.thresholds, 1.0 + h), batch[0])
          - loss(pj.PrandtlIshlinskii(op.weights, op.thresholds, 1.0 - h), batch[0])) / (2 * h)
    assert float(g.w0) == pytest.approx(float(fd), rel=1e-6)
    out = jax.jit(jax.vmap(lambda v: op(v)))(batch)
    np.testing.assert_allclose(out[2], op(batch[2]), atol=1e-14)
    op32 = pj.PrandtlIshlinskii(jnp.array([0.5, 0.3], jnp.float32), jnp.array([0.1, 0.4], jnp.float32), w0=1.0)
    y32 = op32(batch[0].astype(jnp.float32))
    assert y32.dtype == jnp.float32 and op32.w0.dtype == jnp.float32
    np.testing.assert_allclose(y32, out[0], atol=1e-5)


def test_stacked_operators_keep_one_loop_and_a_mixed_stack_is_each_operators_own():
    """Under `vmap` over stacked operators (a fleet), the choice between the exact and the general loop stays a
    `cond` while every smoothing is 0 (a mapped predicate ran the general loop too: 4.4x the simulation of a stacked
    model on 2 cores); a stack mixing smoothings runs the general loop, each operator's values and derivatives."""
    w = jnp.array([[1.0, 0.5, 0.3], [0.8, 0.6, 0.2]])
    r = jnp.array([0.0, 0.4, 0.9])
    v = jnp.asarray(2 * np.sin(np.linspace(0, 9, N)))

    def out(w, s):
        return pj.PrandtlIshlinskii(w, r, 0.2, s)(v)

    stack = jax.jit(jax.vmap(out))
    assert loop_under_cond(jax.make_jaxpr(jax.vmap(out))(w, jnp.zeros(2)))
    jac_stack = jax.jit(jax.jacfwd(lambda w, s: jax.vmap(out)(w, s), argnums=(0, 1)))
    one = jax.jit(out)
    jac_one = jax.jit(jax.jacfwd(out, argnums=(0, 1)))
    for s in (jnp.array([0.0, 0.0]), jnp.array([0.0, 0.3])):
        y = stack(w, s)
        jw, js = jac_stack(w, s)  # (2, N, 2, 3) and (2, N, 2)
        for i in range(2):
            np.testing.assert_allclose(y[i], one(w[i], s[i]), rtol=1e-13, atol=1e-13)
            jw_i, js_i = jac_one(w[i], s[i])
            np.testing.assert_allclose(jw[i, :, i], jw_i, rtol=1e-12, atol=1e-13)
            np.testing.assert_allclose(js[i, :, i], js_i, rtol=1e-12, atol=1e-13)
        np.testing.assert_array_equal(jw[0, :, 1], 0.0)


def test_bad_input():
    with pytest.raises(ValueError, match="thresholds"):
        pj.PrandtlIshlinskii(jnp.ones(2), jnp.array([0.5, 0.2]))
    with pytest.raises(ValueError, match="thresholds"):
        pj.PrandtlIshlinskii(jnp.ones(2), jnp.array([0.5, 0.5]))
    with pytest.raises(ValueError, match="thresholds"):
        pj.PrandtlIshlinskii(jnp.ones(2), jnp.array([-0.1, 0.5]))
    with pytest.raises(ValueError, match="weights"):
        pj.PrandtlIshlinskii(jnp.ones(3), jnp.array([0.1, 0.5]))
    with pytest.raises(ValueError, match="weights"):
        pj.PrandtlIshlinskii(jnp.ones((2, 1)), jnp.array([0.1, 0.5]))
    with pytest.raises(ValueError, match="w0"):
        pj.PrandtlIshlinskii(jnp.ones(2), jnp.array([0.1, 0.5]), w0=jnp.ones(2))
    with pytest.raises(ValueError, match="smoothing"):
        pj.PrandtlIshlinskii(jnp.ones(2), jnp.array([0.1, 0.5]), smoothing=-1.0)
    pi = pj.PrandtlIshlinskii(jnp.ones(2), jnp.array([0.1, 0.5]))
    with pytest.raises(ValueError, match="signal"):
        pi(jnp.ones((2, 3)))
    with pytest.raises(ValueError, match="signal"):
        pi(jnp.ones(0))
    with pytest.raises(Exception, match="signal"):
        _pi(pi.weights, pi.thresholds, pi.w0, 0.0, jnp.full(N, jnp.nan))
    with pytest.raises(Exception, match="thresholds"):
        _pi(pi.weights, jnp.array([0.5, 0.1]), pi.w0, 0.0, jnp.ones(N))  # traced: eqx.error_if
    # inverse: smoothed operator, non-positive partial sums
    with pytest.raises(ValueError, match="smoothing"):
        pj.PrandtlIshlinskii(jnp.ones(2), jnp.array([0.1, 0.5]), smoothing=0.1).inverse()
    with pytest.raises(ValueError, match="weights"):
        pj.PrandtlIshlinskii(jnp.array([0.5, -2.0]), jnp.array([0.1, 0.5])).inverse()
    with pytest.raises(ValueError, match="w0"):
        pj.PrandtlIshlinskii(jnp.array([0.5, 2.0]), jnp.array([0.1, 0.5]), w0=0.0).inverse()
    with pytest.raises(Exception, match="weights"):
        _round_trip(jnp.array([0.5, -2.0]), jnp.array([0.1, 0.5]), jnp.asarray(1.0), jnp.ones(N))
