"""Hand-derived forward sensitivities of the play / Prandtl–Ishlinskii scans against autodiff through the scan.

The fast rule (`stop_scan`, `pi_scan` with `jax.custom_jvp`) must give the same JVP as plain autodiff of the cell
(`_run_autodiff`), including the tie conventions of `clip_stop` (r = 0, inputs arriving at or holding at a threshold),
for the exact and the smooth operator, with input-signal and initial-state tangents, in float32, under `jax.grad`,
`jit` and `vmap`; and central finite differences where the operator is smooth.
"""

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import piezojax as pj

N = 40  # one signal length: one compilation per function
THRESHOLDS = np.array([0.0, 0.25, 0.5, 1.0])  # on the signal grid below: exact ties, and r = 0
ARGS = (0, 1, 2, 3, 4, 5, 6)  # w0, weights, thresholds, smoothing, signal, v0, z0


def tie_signal(rng, n=N, grid=0.25):
    """A piecewise-monotone walk on a grid (steps of 0, ±1, ±2 grid units): holds, reversals and inputs landing
    exactly on the thresholds."""
    steps = rng.choice([-2, -1, 0, 0, 1, 2], size=n)
    return grid * np.cumsum(steps).astype(float)


def smooth_signal(rng, n=N):
    return np.cumsum(rng.normal(0.0, 0.4, n))


def pi_args(rng, smoothing, dtype=np.float64, signal=None):
    w = rng.uniform(0.1, 1.0, THRESHOLDS.size)
    signal = tie_signal(rng) if signal is None else signal
    v0 = 0.25 * rng.integers(-2, 3)  # on the grid: ties from the first step on
    z0 = np.clip(0.25 * rng.integers(-4, 5, THRESHOLDS.size), -THRESHOLDS, THRESHOLDS)  # a valid stop state
    values = (rng.uniform(0.2, 1.0), w, THRESHOLDS, smoothing, signal, v0, z0)
    return tuple(jnp.asarray(x, dtype) for x in values)


def pi_model(run):
    def f(w0, w, r, s, v, v0, z0):
        op, v, state = pj.PrandtlIshlinskii(w, r, w0, s)._prepare(v, (v0, z0))
        state, y = getattr(op, run)(state, v)
        return y, state[1]

    return f


def pi_model_concrete(smoothing):
    """The fast path with a concrete smoothing (the exact/smooth choice is made in Python, no `lax.cond`)."""

    def f(w0, w, r, v, v0, z0):
        op, v, state = pj.PrandtlIshlinskii(w, r, w0, smoothing)._prepare(v, (v0, z0))
        state, y = op._run(state, v)
        return y, state[1]

    return f


FAST = pi_model("_run")
REF = pi_model("_run_autodiff")


@pytest.fixture(scope="module")
def jac():
    return {
        "fast": jax.jit(jax.jacfwd(FAST, ARGS)),
        "ref": jax.jit(jax.jacfwd(REF, ARGS)),
    }


def assert_trees_close(a, b, atol, rtol=0.0):
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        assert x.shape == y.shape and x.dtype == y.dtype
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), atol=atol, rtol=rtol)


@pytest.mark.parametrize("smoothing", [0.0, 0.3])
@pytest.mark.parametrize("kind", ["ties", "random"])
def test_pi_jacobian_equals_autodiff(jac, smoothing, kind):
    # every tangent at once: parameters, smoothing, the input signal and the initial state (v0, z0)
    for seed in range(3):
        rng = np.random.default_rng(seed)
        signal = tie_signal(rng) if kind == "ties" else smooth_signal(rng)
        args = pi_args(rng, smoothing, signal=signal)
        fast, ref = jac["fast"](*args), jac["ref"](*args)
        assert_trees_close(fast, ref, atol=1e-10)
        # non-trivial: the threshold and signal columns are not all zero
        assert np.abs(np.asarray(fast[0][2])).max() > 0.1 and np.abs(np.asarray(fast[0][4])).max() > 0.1


@pytest.mark.parametrize("mode", ["never", "always"])
def test_initial_state_tangents_on_a_measured_signal_equal_autodiff(mode):
    # a fitted prehistory before measured data: tangents of (v0, z0) and the parameters, none of the signal (a
    # symbolic zero), which the fast rule carries as one more row of its one scan (P = dz/dz0, times a factor per
    # threshold) instead of a recurrence per direction; sequential and parallel in time, exact and smooth (traced and
    # concrete smoothing), v0 and z0 alone and together, PI and play operators, forward and reverse mode
    from piezojax._config import parallel_scans

    no_signal = (0, 1, 2, 3, 5, 6)  # w0, weights, thresholds, smoothing, v0, z0
    with parallel_scans(mode):
        fast, ref = (jax.jit(jax.jacfwd(pi_model(run), no_signal)) for run in ("_run", "_run_autodiff"))

        def concrete(smoothing, argnums):  # the exact/smooth choice made in Python (no lax.cond)
            return jax.jit(jax.jacfwd(lambda *a: pi_model_concrete(smoothing)(*a[:3], *a[4:]), argnums))

        def grads(run):
            def loss(v0, z0, w0, w, r, s, v):
                y, z = pi_model(run)(w0, w, r, s, v, v0, z0)
                return jnp.sum(y * jnp.cos(jnp.arange(y.shape[0], dtype=y.dtype))) + jnp.sum(z**2)

            return jax.jit(jax.grad(loss, (0, 1)))

        def play(run):
            def f(r, s, v, v0, z0):
                op, vv, state = pj.PlayOperator(r, s)._prepare(v, (v0, z0))
                state, y = getattr(op, run)(state, vv)
                return y, state[1]

            return jax.jit(jax.jacfwd(f, (0, 1, 3, 4)))

        play_fast, play_ref = play("_run"), play("_run_autodiff")
        grad_fast, grad_ref = grads("_run"), grads("_run_autodiff")
        for seed, smoothing in ((0, 0.0), (1, 0.0), (2, 0.3), (3, 0.05)):
            rng = np.random.default_rng(seed)
            args = pi_args(rng, smoothing, signal=tie_signal(rng) if seed % 2 == 0 else smooth_signal(rng))
            if mode == "always" and smoothing > 0:
                continue  # the parallel form is the exact operator's
            got, want = fast(*args), ref(*args)
            assert_trees_close(got, want, atol=1e-10)
            # non-trivial: the output depends on the initial stop values and input
            assert np.abs(np.asarray(got[0][5])).max() > 0.1 and np.abs(np.asarray(got[0][4])).max() > 0.1
            for argnums, cols in (((5,), (4,)), ((6,), (5,)), ((1, 5, 6), (1, 4, 5))):  # v0 alone, z0 alone, both
                one = concrete(smoothing, argnums)(*args)
                assert_trees_close(one, tuple(tuple(w[c] for c in cols) for w in want), atol=1e-10)
            w0, w, r, s_, v, v0, z0 = args
            assert_trees_close(grad_fast(v0, z0, w0, w, r, s_, v), grad_ref(v0, z0, w0, w, r, s_, v), atol=1e-10)
            a = (args[2], args[3], args[4], args[5], args[6])
            assert_trees_close(play_fast(*a), play_ref(*a), atol=1e-10)


def test_ties_exercise_every_rule(jac):
    # the tie signal hits: r = 0, inputs arriving exactly at +-r, and inputs held at a clamped play
    rng = np.random.default_rng(0)
    args = pi_args(rng, 0.0)
    v = np.concatenate([[float(args[5])], np.asarray(args[4])])
    assert np.any(np.diff(v) == 0) and np.any(np.diff(np.sign(np.diff(v))) != 0)
    w0, w, r, _, signal, v0, z0 = args
    stop = pj.StopOperator(r)
    z = np.asarray(stop.scan(signal, (v0, z0))[1])
    assert np.any(np.abs(z[:, 1:]) == THRESHOLDS[1:])  # clamped plays, some reached exactly
    # the tie rules show in the Jacobian: halves at ties, and the zero-threshold play passes dv fully
    j_y, j_z = jac["fast"](*args)
    assert np.any(np.abs(np.asarray(j_y[2]) / np.asarray(w)) == 0.5)  # dy/dr_i = -w_i dz_i/dr_i = -+w_i/2


@pytest.mark.parametrize("smoothing", [0.0, 0.3])
def test_concrete_smoothing_path_equals_autodiff(jac, smoothing):
    rng = np.random.default_rng(7)
    args = pi_args(rng, smoothing)
    f = jax.jit(jax.jacfwd(pi_model_concrete(smoothing), (0, 1, 2, 3, 4, 5)))
    fast = f(*args[:3], *args[4:])
    ref = jac["ref"](*args)
    ref = jax.tree_util.tree_map(lambda j: j, tuple(tuple(r[i] for i in (0, 1, 2, 4, 5, 6)) for r in ref))
    assert_trees_close(fast, ref, atol=1e-10)


@settings(max_examples=15)
@given(seed=st.integers(0, 2**31 - 1), smoothing=st.sampled_from([0.0, 0.05, 0.5]))
def test_pi_jacobian_property(jac, seed, smoothing):
    rng = np.random.default_rng(seed)
    args = pi_args(rng, smoothing)
    assert_trees_close(jac["fast"](*args), jac["ref"](*args), atol=1e-10)


def test_pi_jacobian_float32():
    rng = np.random.default_rng(3)
    f32 = {run: jax.jit(jax.jacfwd(pi_model(run), ARGS)) for run in ("_run", "_run_autodiff")}
    for smoothing in (0.0, 0.3):
        args = pi_args(rng, smoothing, dtype=np.float32)
        fast, ref = f32["_run"](*args), f32["_run_autodiff"](*args)
        for leaf in jax.tree_util.tree_leaves(fast):
            assert leaf.dtype == jnp.float32
        assert_trees_close(fast, ref, atol=2e-5, rtol=1e-5)


def flat_model(p):
    """y(p) with p = [w0, weights, thresholds, smoothing, signal] flattened (for finite differences)."""
    n = THRESHOLDS.size
    w0, w, r, s, v = p[0], p[1 : 1 + n], p[1 + n : 1 + 2 * n], p[1 + 2 * n], p[2 + 2 * n :]
    return pj.PrandtlIshlinskii(w, r, w0, s)(v)


FLAT_JAC = jax.jit(jax.jacfwd(flat_model))
FLAT_FD = jax.jit(
    lambda p, eye, h: jax.vmap(lambda e: (flat_model(p + h * e) - flat_model(p - h * e)) / (2 * h), out_axes=1)(eye)
)


@pytest.mark.parametrize("smoothing", [0.0, 0.3])
def test_pi_jacobian_central_differences(smoothing):
    # Smooth operator: C^1, so central differences agree to O(h); exact operator on a generic signal (no ties,
    # strictly positive thresholds): piecewise linear, differences exact away from switches.
    rng = np.random.default_rng(11)
    r = np.sort(rng.uniform(0.1, 1.5, THRESHOLDS.size))
    p = jnp.asarray(np.concatenate([[0.6], rng.uniform(0.1, 1.0, r.size), r, [smoothing], smooth_signal(rng)]))
    jac = FLAT_JAC(p)
    h = 1e-6 if smoothing else 1e-8
    s_col = 1 + 2 * r.size
    eye = np.eye(p.size)
    if not smoothing:
        eye[s_col, s_col] = 0.0  # no negative smoothing; d/ds at 0 is defined as 0
    fd = FLAT_FD(p, jnp.asarray(eye), h)
    np.testing.assert_allclose(np.asarray(jac), np.asarray(fd), atol=2e-6 if smoothing else 1e-7)
    assert np.abs(np.asarray(jac)[:, 1 + r.size : 1 + 2 * r.size]).max() > 0.1  # thresholds matter


def test_grad_equals_autodiff_and_transposed_jacobian(jac):
    rng = np.random.default_rng(5)

    def loss(model):
        def f(cy, cz, *a):
            y, z = model(*a)
            return jnp.sum(cy * y) + jnp.sum(cz * z)

        return jax.jit(jax.grad(f, tuple(i + 2 for i in ARGS)))

    grad_fast, grad_ref = loss(FAST), loss(REF)
    for smoothing in (0.0, 0.3):
        args = pi_args(rng, smoothing)
        cy = jnp.asarray(rng.normal(size=N))
        cz = jnp.asarray(rng.normal(size=THRESHOLDS.size))
        g_fast = grad_fast(cy, cz, *args)
        g_ref = grad_ref(cy, cz, *args)
        assert_trees_close(g_fast, g_ref, atol=1e-10)
        j_y, j_z = jac["fast"](*args)
        for i, g in enumerate(g_fast):
            jt = jnp.tensordot(cy, j_y[i], axes=1) + jnp.tensordot(cz, j_z[i], axes=1)
            np.testing.assert_allclose(np.asarray(g), np.asarray(jt), atol=1e-10)


def test_vmap_over_signals_and_parameters(jac):
    rng = np.random.default_rng(9)
    batch = [pi_args(rng, s) for s in (0.0, 0.3, 0.0)]
    stacked = tuple(jnp.stack(x) for x in zip(*batch, strict=True))
    out = jax.jit(jax.vmap(jax.jacfwd(FAST, ARGS)))(*stacked)
    for b, args in enumerate(batch):
        one = jax.tree_util.tree_map(lambda x, b=b: x[b], out)
        assert_trees_close(one, jac["ref"](*args), atol=1e-10)


def test_play_jacobians_equal_autodiff():
    def model(run):
        def f(r, s, v, v0, z0):
            op, vv, state = pj.PlayOperator(r, s)._prepare(v, (v0, z0))
            state, y = getattr(op, run)(state, vv)
            return y, state[1]

        return jax.jit(jax.jacfwd(f, (0, 1, 2, 3, 4)))

    fast, ref = model("_run"), model("_run_autodiff")
    rng = np.random.default_rng(2)
    for smoothing in (0.0, 0.3):
        args = pi_args(rng, smoothing)
        a = (args[2], args[3], args[4], args[5], args[6])
        j_fast = fast(*a)
        assert_trees_close(j_fast, ref(*a), atol=1e-10)
        # the zero-threshold play is the input itself: dP_0/dv = I (not jnp.clip's tie split)
        np.testing.assert_array_equal(np.asarray(j_fast[0][2][:, 0, :]), np.eye(N))
    # a scalar threshold keeps scalar shapes
    j = jax.jacfwd(lambda r: pj.PlayOperator(r, 0.2)(args[4]))(jnp.asarray(0.5))
    j_ref = jax.jacfwd(lambda r: pj.PlayOperator(r, 0.2).scan(args[4])[1])(jnp.asarray(0.5))
    assert j.shape == (N,)
    np.testing.assert_allclose(j, j_ref, atol=1e-12)


def test_actuator_jacobian_equals_autodiff(monkeypatch):
    rng = np.random.default_rng(4)
    act = pj.Actuator(
        pj.PrandtlIshlinskii(jnp.asarray(rng.uniform(0.02, 0.1, 4)), jnp.asarray([0.0, 2.0, 5.0, 9.0]), w0=1.0),
        pj.KelvinVoigtCreep(jnp.asarray([8.0, 25.0]), jnp.asarray([0.01, 0.2]), k0=None),
        pj.StableTransferFunction(jnp.asarray(1e-7), omega=jnp.asarray([2 * np.pi * 200]), zeta=jnp.asarray([0.1])),
        capacitance=jnp.asarray(1.7e-9),
        coupling=jnp.asarray(2e-3),
    )
    v = jnp.asarray(20 * tie_signal(rng))
    params, static = eqx.partition(act, eqx.is_inexact_array)
    flat, unravel = jax.flatten_util.ravel_pytree(params)

    def jacobian():
        def f(p):
            o = eqx.combine(unravel(p), static).simulate(v, 1e-3)
            return o.displacement, o.charge, o.current

        return jax.jit(jax.jacfwd(f))(flat)

    fast = jacobian()
    monkeypatch.setattr(pj.PrandtlIshlinskii, "_run", pj.PrandtlIshlinskii._run_autodiff)
    ref = jacobian()
    for a, b in zip(fast, ref, strict=True):
        scale = np.abs(np.asarray(b)).max(axis=0)
        assert np.all(np.abs(np.asarray(a) - np.asarray(b)) <= 1e-10 * np.maximum(scale, 1e-300))
