"""Parallel-in-time recurrences (`pj.set_parallel_scans`): the associative forms of the exact play/stop operators,
the first-order lags and the discrete linear systems against the sequential scans and plain loops — values,
forward and reverse derivatives — and the per-member NaN refusals a fleet traces its steps with."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import piezojax as pj
from piezojax._checks import PiezojaxValueError, check_value, refusals_as_nan
from piezojax._config import parallel_scans, use_parallel_scan
from piezojax._creep.lags import lag_sum
from piezojax._scans import affine_scan, clamp_scan, matrix_affine_scan


def test_the_associative_forms_match_plain_loops(rng):
    t = 257  # not a power of two
    a, b = rng.uniform(-1, 1, (t, 3)), rng.standard_normal((t, 3))
    x0 = rng.standard_normal(3)
    x, ref = x0, []
    for k in range(t):
        x = a[k] * x + b[k]
        ref.append(x)
    np.testing.assert_allclose(affine_scan(jnp.asarray(a), jnp.asarray(b), jnp.asarray(x0)), ref, rtol=1e-12,
                               atol=1e-12)
    delta = rng.standard_normal((3, 3)) * 0.1 - 0.2 * np.eye(3)
    states, last = matrix_affine_scan(jnp.asarray(delta), jnp.asarray(b), jnp.asarray(x0))
    x, ref = x0, []
    for k in range(t):
        ref.append(x)
        x = x + delta @ x + b[k]
    np.testing.assert_allclose(states, ref, rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(last, x, rtol=1e-11, atol=1e-12)
    lo = rng.standard_normal((t, 2)) - 0.5
    hi = lo + rng.uniform(0, 1, (t, 2))
    y, ref = np.array([5.0, -5.0]), []
    for k in range(t):
        y = np.minimum(np.maximum(y, lo[k]), hi[k])
        ref.append(y)
    np.testing.assert_array_equal(clamp_scan(jnp.asarray(lo), jnp.asarray(hi), jnp.asarray([5.0, -5.0])), ref)


def _both(fn):
    """`fn()` traced sequentially and in parallel in time (fresh `jit`s, so each mode is traced)."""
    out = []
    for mode in ("never", "always"):
        with parallel_scans(mode):
            out.append(fn())
    return out


def _close(a, b, rtol=1e-11):
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        scale = max(float(jnp.max(jnp.abs(x))), 1e-300) if x.size else 1.0
        np.testing.assert_allclose(x, y, rtol=0, atol=rtol * scale)


def test_exact_hysteresis_in_parallel_equals_the_sequential_scan(rng):
    v = np.cumsum(rng.standard_normal(600)) * 3.0
    v[200:240] = v[200]  # a held input: ties at the thresholds
    v = jnp.asarray(v)
    pi = pj.PrandtlIshlinskii(jnp.asarray(rng.uniform(0.01, 0.1, 6)), jnp.array([0.0, 1.0, 2.0, 4.0, 7.0, 11.0]),
                              w0=0.3)
    play = pj.PlayOperator(jnp.array([0.0, 1.0, 2.5]))
    stop = pj.StopOperator(jnp.array([0.5, 3.0]))

    def run():
        out = []
        for op in (pi, play, stop):
            out.append(eqx.filter_jit(lambda m: m(v))(op))
            out.append(eqx.filter_jit(jax.jacfwd(lambda m: m(v)))(op))
        out.append(eqx.filter_jit(jax.grad(lambda m: jnp.sum(m(v) ** 2)))(pi))
        out.append(eqx.filter_jit(jax.jacfwd(lambda x: pi(x)[-4:]))(v))  # input tangents
        state, y = eqx.filter_jit(lambda m: m.scan(v[:300]))(pi)  # continued from a state
        out += [y, eqx.filter_jit(lambda m: m.scan(v[300:], state)[1])(pi)]
        return out

    seq, par = _both(run)
    _close(seq, par)
    # a clamped stop value is exactly +-r in both forms (the derivative rules tell a tie from a clamp by it)
    z_seq, z_par = (np.asarray(x[4]) for x in (seq, par))
    np.testing.assert_array_equal(np.abs(z_par) == stop.thresholds, np.abs(z_seq) == stop.thresholds)
    np.testing.assert_allclose(jnp.concatenate(par[-2:]), par[0], rtol=0, atol=1e-12 * float(jnp.max(par[0])))


@pytest.mark.parametrize("hold", ["zoh", "foh", "interval"])
def test_lags_in_parallel_equal_the_sequential_scan(rng, hold):
    u = jnp.asarray(np.cumsum(rng.standard_normal(500)))
    c, tau = jnp.array([0.5, 2.0]), jnp.array([0.01, 0.5])

    def run():
        f = eqx.filter_jit(lambda c, tau, u: lag_sum(c, tau, u, 1e-3, hold))
        return [f(c, tau, u), eqx.filter_jit(jax.jacfwd(f, argnums=(0, 1, 2)))(c, tau, u),
                eqx.filter_jit(jax.grad(lambda tau: jnp.sum(f(c, tau, u) ** 2)))(tau)]

    _close(*_both(run))


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_linear_systems_in_parallel_equal_the_sequential_scan(rng, hold):
    u = jnp.asarray(np.cumsum(rng.standard_normal(500)))
    # a resonance, a slow mode and a slow real pole (|p| dt = 1e-7: the delta form keeps it)
    g = pj.StableTransferFunction(1.3, omega=jnp.array([2 * np.pi * 400.0, 2 * np.pi * 3.0]),
                                  zeta=jnp.array([0.08, 0.5]), poles=jnp.array([-1e-3]))
    x0 = jnp.array([0.1, 0.2, -0.3, 0.4, 0.5])

    def run():
        f = eqx.filter_jit(lambda g, u, x0: g.simulate(u, 1e-4, x0=x0, hold=hold))
        return [f(g, u, x0), eqx.filter_jit(jax.jacfwd(f, argnums=(0, 1, 2)))(g, u, x0),
                eqx.filter_jit(jax.grad(lambda g: jnp.sum(f(g, u, x0) ** 2)))(g)]

    _close(*_both(run))


def test_a_whole_actuator_in_parallel_equals_the_sequential_one(rng):
    v = jnp.asarray(50 + 40 * np.sin(np.linspace(0, 30, 600)) * np.exp(-np.linspace(0, 2, 600)))
    act = pj.Actuator(pj.PrandtlIshlinskii(jnp.full(5, 0.02), jnp.linspace(0.0, 30.0, 5), w0=0.1),
                      pj.KelvinVoigtCreep(jnp.array([50.0, 20.0]), jnp.array([0.05, 0.5]), k0=None),
                      pj.StableTransferFunction(1e-6, omega=jnp.array([2 * np.pi * 400.0]), zeta=jnp.array([0.05])),
                      capacitance=1.7e-9)

    def run():
        f = eqx.filter_jit(lambda a: a.simulate(v, 1e-4).displacement)
        return [f(act), eqx.filter_jit(jax.jacfwd(f))(act)]

    _close(*_both(run))


def test_the_mode_is_chosen_by_backend_and_length():
    assert not use_parallel_scan(10**6) or jax.default_backend() != "cpu"  # "auto": sequential on the CPU
    with parallel_scans("always"):
        assert use_parallel_scan(3)
    with parallel_scans("never"):
        assert not use_parallel_scan(10**6)
    with pytest.raises(PiezojaxValueError, match="`mode`"):
        pj.set_parallel_scans("sometimes")


def test_refusals_as_nan_refuse_each_batch_member_alone():
    def f(a):
        return check_value(a * jnp.ones(3), a <= 1.0, "`a` must be at most 1")

    with refusals_as_nan():
        out = jax.jit(jax.vmap(f))(jnp.array([0.5, 2.0, 1.0]))
    out = np.asarray(out)
    assert np.all(np.isfinite(out[[0, 2]])) and np.all(np.isnan(out[1]))
    with pytest.raises(Exception, match="at most 1"):  # outside the context: the usual runtime error
        jax.block_until_ready(eqx.filter_jit(jax.vmap(f))(jnp.array([0.5, 2.0])))
    with refusals_as_nan(), pytest.raises(PiezojaxValueError, match="at most 1"):
        f(jnp.asarray(2.0))  # concrete values still raise at once
