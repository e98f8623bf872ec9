"""Preisach operator: hand computation, demagnetised state, return-point memory, wiping-out,
congruency, rate independence, the relay = sign(play - middle) identity, the smooth relaxation,
derivatives, and bad
input."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _jaxpr_helpers import runs_outside_cond
from hypothesis import given, settings, strategies as st

import piezojax as pj
from piezojax._hysteresis.play import PlayOperator
from piezojax._hysteresis.preisach import Preisach

LEVELS = 8
LENGTH = 12
INSERT = 9  # 10x finer sampling of the same path
RECOMMENDED = 1.0 / LEVELS  # half the threshold spacing 2 / LEVELS


@eqx.filter_jit
def run_scan(op, v, state):
    return op.scan(v, state)


def run(op, v):
    return run_scan(op, v, op.init())[1]


def grid(smoothing=0.0, mu=None):
    return Preisach.uniform(-1.0, 1.0, LEVELS, mu=mu, smoothing=smoothing)


def random_weights(seed=0):
    return jnp.asarray(np.random.default_rng(seed).uniform(0.1, 1.0, LEVELS * (LEVELS + 1) // 2))


def test_exported():
    assert pj.Preisach is Preisach


def test_hand_computation_three_relays():
    # relays (alpha, beta, mu): (1, -1, 1), (2, 0, 2), (0.5, 0.5, 4); offset 0.25
    op = Preisach([1.0, 2.0, 0.5], [-1.0, 0.0, 0.5], [1.0, 2.0, 4.0], offset=0.25)
    # demagnetised: alpha + beta = 0, 2, 1 -> relays 0, -1, -1
    assert np.allclose(op.relays(op.init()), [0.0, -1.0, -1.0])
    v = jnp.asarray([0.2, 0.6, 1.5, 2.5, 0.3, -0.5, -1.5, 0.0, 0.5, 0.4])
    # 0.2: none switch               -> 0 - 2 - 4 = -6
    # 0.6: R3 up                     -> 0 - 2 + 4 = 2
    # 1.5: R1 up                     -> 1 - 2 + 4 = 3
    # 2.5: R2 up                     -> 1 + 2 + 4 = 7
    # 0.3: R3 down                   -> 1 + 2 - 4 = -1
    # -0.5: R2 down (v <= 0)         -> 1 - 2 - 4 = -5
    # -1.5: R1 down                  -> -1 - 2 - 4 = -7
    # 0.0: none                      -> -7
    # 0.5: R3 (alpha = beta) going up -> +1: -1 - 2 + 4 = 1
    # 0.4: R3 down                   -> -7
    expected = np.array([-6, 2, 3, 7, -1, -5, -7, -7, 1, -7]) + 0.25
    assert np.allclose(run(op, v), expected, rtol=0, atol=1e-14)


def test_uniform_grid_and_demagnetised_state():
    op = grid()
    m = LEVELS * (LEVELS + 1) // 2
    assert op.alpha.shape == (m,) and np.all(op.alpha >= op.beta)
    assert np.isclose(float(op.alpha.max()), 1 - 1 / LEVELS) and np.isclose(
        float(op.beta.min()), -1 + 1 / LEVELS
    )
    relays = np.asarray(op.relays(op.init()))
    s = np.asarray(op.alpha + op.beta)
    assert np.all(relays[s < 0] == 1) and np.all(relays[s > 0] == -1)
    assert np.sum(s == 0) == LEVELS // 2 and np.all(
        relays[s == 0] == 0
    )  # anti-diagonal exactly at 0
    # the demagnetised output of a symmetric grid with symmetric weights is 0
    assert abs(float(run(op, jnp.zeros(LENGTH))[0])) < 1e-15


def input_paths(min_value=-1.3, max_value=1.3, size=LENGTH):
    return st.lists(st.floats(min_value, max_value), min_size=size, max_size=size).map(np.array)


@settings(max_examples=40)
@given(
    history=input_paths(),
    a=st.floats(-1.3, 1.3),
    fb=st.floats(0.0, 1.0),
    wiggle=input_paths(0.0, 1.0, 4),
)
def test_return_point_memory(history, a, fb, wiggle):
    """After the history reaches v_a from the previous extremum v_p, a loop v_a -> v_b -> v_a with
    v_b between v_p
    and v_a (and any wiggles inside [v_b, v_a]) restores the relay state exactly."""
    v_p = history[-1]
    v_b = a + fb * (v_p - a)
    lo, hi = min(a, v_b), max(a, v_b)
    loop = np.concatenate([[v_b], lo + wiggle * (hi - lo), [v_b, a]])
    path = np.concatenate([history, [a], loop])
    op = grid(mu=random_weights())
    state, y = run_scan(op, jnp.asarray(path), op.init())
    before, _ = run_scan(
        op, jnp.asarray(np.concatenate([history, [a], np.full(loop.size, a)])), op.init()
    )
    assert np.array_equal(np.asarray(op.relays(state)), np.asarray(op.relays(before)))
    assert float(y[-1]) == float(y[LENGTH])


@settings(max_examples=40)
@given(history=input_paths(), top=st.floats(0.0, 0.5))
def test_wiping_out(history, top):
    """A new global maximum wipes out all memory except the global minimum: the state after H + [M]
    with
    M >= max(H) equals the state after [min(H), M]."""
    m_max = max(history.max(), 0.0) + top
    path = np.concatenate([history, [m_max]])
    short = np.concatenate([np.full(LENGTH - 1, history.min()), [history.min(), m_max]])
    op = grid()
    s1, _ = run_scan(op, jnp.asarray(path), op.init())
    s2, _ = run_scan(op, jnp.asarray(short), op.init())
    assert np.array_equal(np.asarray(op.relays(s1)), np.asarray(op.relays(s2)))


@settings(max_examples=25)
@given(h1=input_paths(), h2=input_paths(), lo=st.floats(-0.9, 0.0), width=st.floats(0.2, 0.9))
def test_congruent_minor_loops(h1, h2, lo, width):
    """Minor loops between the same extrema are congruent (equal up to a shift) whatever the
    history."""
    hi = lo + width
    loop = np.concatenate([[hi, lo], np.linspace(lo, hi, 8)[1:], np.linspace(hi, lo, 8)[1:]])
    op = grid(mu=random_weights(1))
    y1 = np.asarray(run(op, jnp.asarray(np.concatenate([h1, loop]))))[LENGTH + 1 :]
    y2 = np.asarray(run(op, jnp.asarray(np.concatenate([h2, loop]))))[LENGTH + 1 :]
    shift = y1 - y2
    assert np.max(np.abs(shift - shift[0])) < 1e-12


def refine(v, fracs):
    v = np.asarray(v)
    prev = np.concatenate([[0.0], v[:-1]])
    inner = prev[:, None] + fracs * (v - prev)[:, None]
    return np.concatenate([inner, v[:, None]], axis=1).reshape(-1)


fractions = st.lists(st.floats(0.001, 0.999), min_size=INSERT, max_size=INSERT).map(
    lambda f: np.sort(np.array(f))
)


@settings(max_examples=30)
@given(v=input_paths(), fracs=fractions)
def test_rate_independence_exact_and_smooth(v, fracs):
    """The same piecewise-linear path sampled 10x finer gives the same output at the original
    samples."""
    fine = jnp.asarray(refine(v, fracs))
    for s in (0.0, RECOMMENDED):
        op = grid(smoothing=s, mu=random_weights())
        y = np.asarray(run(op, jnp.asarray(v)))
        y_fine = np.asarray(run(op, fine))[INSERT :: INSERT + 1]
        assert np.max(np.abs(y - y_fine)) < 1e-12


def test_relay_equals_sign_of_play_minus_middle():
    """R_{alpha,beta}[v] = sign(P_r[v] - m), r = (alpha - beta)/2, m = (alpha + beta)/2, away from
    exact ties."""
    op = grid()
    rng = np.random.default_rng(5)
    v = jnp.asarray(np.concatenate([[0.0], rng.uniform(-1.3, 1.3, 199)]))
    r = np.asarray(0.5 * (op.alpha - op.beta))
    mid = np.asarray(0.5 * (op.alpha + op.beta))
    plays = np.asarray(PlayOperator(jnp.asarray(r))(v))  # (time, relays)
    relays = np.asarray(jax.lax.scan(lambda s, x: (op.step(s, x)[0],) * 2, op.init(), v)[1])[
        :, 1 : 1 + r.size
    ]
    gap = plays - mid
    away = np.abs(gap) > 1e-9
    assert np.mean(away) > 0.9
    assert np.array_equal(relays[away], np.sign(gap[away]))
    # at the start (v = 0, P = 0) the anti-diagonal relays are 0 in both forms
    assert np.array_equal(relays[0][mid == 0], np.zeros(np.sum(mid == 0)))
    # an exact tie: the input reaches alpha exactly. The relay is +1, sign(P - m) is 0: the identity
    # needs no ties.
    one = Preisach([0.5], [-0.1], [1.0])
    assert float(run(one, jnp.asarray([0.5]))[0]) == 1.0
    assert abs(float(PlayOperator(0.3)(jnp.asarray([0.5]))[0]) - 0.2) < 1e-15


def test_smooth_form_converges_to_exact():
    """Inputs on the lattice k h (thresholds sit at (k + 1/2) h) are h/2 from every threshold."""
    h = 2.0 / LEVELS
    rng = np.random.default_rng(2)
    v = jnp.asarray(h * rng.integers(-5, 6, 60).astype(float))
    mu = random_weights()
    exact = np.asarray(run(grid(mu=mu), v))
    span = float(jnp.sum(mu)) * 2
    errors = [
        np.max(np.abs(np.asarray(run(grid(s, mu), v)) - exact)) / span
        for s in (0.08, 0.04, 0.02, 0.01)
    ]
    assert all(e1 > e2 for e1, e2 in zip(errors, errors[1:]))
    assert errors[0] > 1e-3  # smoothing changes the operator
    assert errors[-1] < 1e-6
    # at the recommended smoothing (half the threshold spacing) on a random input: a few % of the
    # range
    v_rand = jnp.asarray(rng.uniform(-1.2, 1.2, 60))
    err_rec = np.max(
        np.abs(
            np.asarray(run(grid(RECOMMENDED, mu), v_rand)) - np.asarray(run(grid(mu=mu), v_rand))
        )
    )
    assert 1e-3 < err_rec / span < 0.1


def _jac_and_fd(f, x, h=1e-6):
    jac = np.asarray(jax.jit(jax.jacfwd(f))(x))
    fd = np.stack(
        [(np.asarray(f(x + h * e)) - np.asarray(f(x - h * e))) / (2 * h) for e in np.eye(x.size)],
        -1,
    )
    return jac, fd


@pytest.mark.parametrize("smoothing", [0.0, RECOMMENDED])
def test_derivative_wrt_weights_vs_finite_differences(smoothing):
    v = jnp.asarray(np.sin(np.linspace(0.1, 4 * np.pi, LENGTH)) * 1.2)
    base = grid(smoothing)

    def f(mu):
        return run(eqx.tree_at(lambda p: p.mu, base, mu), v)

    jac, fd = _jac_and_fd(f, random_weights())
    assert np.allclose(jac, fd, rtol=1e-7, atol=1e-9)
    assert np.max(np.abs(jac)) > 0.5


def test_smooth_derivatives_wrt_input_and_thresholds_vs_finite_differences():
    op = grid(RECOMMENDED, random_weights())
    v0 = jnp.asarray(np.sin(np.linspace(0.1, 4 * np.pi, LENGTH)) * 1.2)
    jac, fd = _jac_and_fd(lambda v: run(op, v), v0)
    assert np.allclose(jac, fd, rtol=1e-5, atol=1e-7)
    assert np.all(np.diag(jac) > 0)  # increasing input raises the output of a positive-weight grid
    grad = jax.jit(jax.grad(lambda v: jnp.sum(op(v) ** 2)))(v0)
    assert np.allclose(np.asarray(grad), 2 * np.asarray(run(op, v0)) @ jac, rtol=1e-10, atol=1e-12)

    off = np.nonzero(np.asarray(op.alpha > op.beta))[
        0
    ]  # perturbing a diagonal alpha down would make alpha < beta

    def f(alpha_off):
        return run(eqx.tree_at(lambda p: p.alpha, op, op.alpha.at[off].set(alpha_off)), v0)

    jac_a, fd_a = _jac_and_fd(f, op.alpha[off])
    assert np.allclose(jac_a, fd_a, rtol=1e-5, atol=1e-7)
    assert np.max(np.abs(jac_a)) > 1e-2


def test_vmap_float32_and_state_continuation():
    op = grid(mu=random_weights())
    rng = np.random.default_rng(0)
    batch = jnp.asarray(rng.uniform(-1.3, 1.3, (3, LENGTH)))
    y = jax.vmap(lambda s: op(s))(batch)
    for i in range(3):
        assert np.array_equal(np.asarray(y[i]), np.asarray(run(op, batch[i])))
    half = LENGTH // 2
    s1, y1 = run_scan(op, batch[0, :half], op.init())
    _, y2 = run_scan(op, batch[0, half:], s1)
    assert np.allclose(np.concatenate([y1, y2]), y[0], rtol=0, atol=1e-14)
    op32 = Preisach.uniform(
        -1.0, 1.0, LEVELS, mu=random_weights().astype(jnp.float32), smoothing=jnp.float32(0.05)
    )
    y32 = op32(batch[0].astype(jnp.float32))
    assert y32.dtype == jnp.float32
    y64 = run(grid(0.05, random_weights()), batch[0])
    assert np.allclose(np.asarray(y32), np.asarray(y64), atol=1e-5)


def test_stacked_operators_skip_the_smooth_plays_and_a_mixed_stack_is_each_operators_own():
    """Under `vmap` over stacked operators whose smoothings are all 0, the smooth plays (`tanh`) run only inside
    the step's `cond` (a mapped predicate ran them at every sample); a stack mixing smoothings gives each
    operator's own output and derivatives."""
    mu = jnp.stack([random_weights(), 0.5 * random_weights()])
    v = jnp.asarray(np.random.default_rng(2).uniform(-1.3, 1.3, LENGTH))

    def out(mu, s):
        return Preisach.uniform(-1.0, 1.0, LEVELS, mu=mu, smoothing=s)(v)

    assert not runs_outside_cond(jax.make_jaxpr(jax.vmap(out))(mu, jnp.zeros(2)), "tanh")
    stack = jax.jit(jax.vmap(out))
    jac_stack = jax.jit(jax.jacfwd(jax.vmap(out)))
    one, jac_one = jax.jit(out), jax.jit(jax.jacfwd(out))
    for s in (jnp.array([0.0, 0.0]), jnp.array([0.0, 0.05]), jnp.array([0.05, 0.05])):
        y, jac = stack(mu, s), jac_stack(mu, s)
        for i in range(2):
            np.testing.assert_allclose(y[i], one(mu[i], s[i]), rtol=1e-13, atol=1e-13)
            np.testing.assert_allclose(jac[i, :, i], jac_one(mu[i], s[i]), rtol=1e-12, atol=1e-13)


def test_bad_input():
    op = grid()
    with pytest.raises(ValueError, match="`signal`.*1-D"):
        op(jnp.zeros((2, 3)))
    with pytest.raises(ValueError, match="`signal` must not be empty"):
        op(jnp.zeros((0,)))
    with pytest.raises(Exception, match="`signal` contains NaN"):
        run(op, jnp.asarray([0.0, jnp.nan] + [0.0] * (LENGTH - 2)))
    with pytest.raises(ValueError, match="`beta` must have the same length as `alpha`"):
        Preisach([1.0, 2.0], [0.0], [1.0, 1.0])
    with pytest.raises(ValueError, match="`mu` must have the same length as `alpha`"):
        Preisach([1.0, 2.0], [0.0, 0.0], [1.0])
    with pytest.raises(ValueError, match="`alpha` must be 1-D"):
        Preisach(jnp.ones((2, 2)), [0.0, 0.0], [1.0, 1.0])
    with pytest.raises(ValueError, match="`alpha` must be >= `beta`.*relay 1"):
        Preisach([1.0, 0.0], [0.0, 0.5], [1.0, 1.0])
    with pytest.raises(
        Exception, match="`alpha` must be >= `beta`"
    ):  # traced thresholds: eqx.error_if

        @jax.jit
        def f(alpha):
            return Preisach(alpha, jnp.asarray([0.0, 0.5]), jnp.ones(2))(jnp.ones(3))

        f(jnp.asarray([1.0, 0.0])).block_until_ready()
    with pytest.raises(ValueError, match="`smoothing` must be finite and >= 0"):
        Preisach([1.0], [0.0], [1.0], smoothing=-0.1)
    with pytest.raises(ValueError, match="`n` must be a positive int"):
        Preisach.uniform(-1.0, 1.0, 0)
    with pytest.raises(ValueError, match="`v_min` must be < `v_max`"):
        Preisach.uniform(1.0, -1.0, 4)
    with pytest.raises(ValueError, match="`state` must have shape"):
        op.scan(jnp.ones(3), jnp.zeros(3))
