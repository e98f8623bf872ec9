"""The composed actuator: hysteresis → creep → dynamics → displacement, plus charge and current."""

import contextlib
import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.signal
from jax.flatten_util import ravel_pytree

import piezojax as pj
from piezojax._hysteresis.prandtl_ishlinskii import PrandtlIshlinskii

DT = 1e-3
N = 1500
T = np.arange(N) * DT
V = 10 * np.sin(2 * np.pi * 2 * T) + 3 * np.sin(2 * np.pi * 7 * T) + 2.0  # starts at 2 V: a charging step

W, R, W0 = np.array([0.4, 0.25, 0.1]), np.array([0.5, 2.0, 5.0]), 1.0
K, TAU = np.array([5.0, 20.0]), np.array([0.05, 0.5])
GAIN, OMEGA, ZETA = 2e-6, 2 * np.pi * 30, 0.3
CP, COUPLING = 1.7e-9, 3e-4


@eqx.filter_jit
def _simulate(act, v, dt, hold):
    return act.simulate(v, dt, hold=hold)


def simulate(act, v, dt=DT, hold="zoh"):
    """Compiled simulate with a traced `dt` (one compile per structure and shape)."""
    return _simulate(act, jnp.asarray(v), jnp.asarray(dt), hold)


def make_actuator(smoothing=0.0, structure="parallel", creep=None):
    return pj.Actuator(
        PrandtlIshlinskii(W, R, w0=W0, smoothing=smoothing),
        pj.KelvinVoigtCreep(K, TAU, k0=None) if creep is None else creep,
        pj.StableTransferFunction(GAIN, omega=[OMEGA], zeta=[ZETA]),
        capacitance=CP,
        coupling=COUPLING,
        structure=structure,
    )


# independent references: numpy play recursion and scipy.signal.lsim


def pi_numpy(v, w=W, r=R, w0=W0):
    p = np.zeros_like(r)
    out = np.empty_like(v)
    for k, vk in enumerate(v):
        p = np.maximum(vk - r, np.minimum(vk + r, p))
        out[k] = w0 * vk + w @ p
    return out


def lsim(num, den, u, interp=False):
    return scipy.signal.lsim((num, den), u, np.arange(len(u)) * DT, interp=interp)[1]


def kv_numpy(u, interp=False):
    return sum(lsim([1 / k], [tau, 1.0], u, interp) for k, tau in zip(K, TAU))


def dyn_numpy(u, interp=False):
    return lsim([GAIN * OMEGA**2], [1.0, 2 * ZETA * OMEGA, OMEGA**2], u, interp)


def charge_and_current(delta):
    q = CP * V + COUPLING * delta
    return q, np.diff(q, prepend=0.0) / DT


def test_parallel_actuator_equals_hand_composition():
    out = simulate(make_actuator(), V)
    drive = pi_numpy(V) + kv_numpy(V)  # δ = G[H[V] + C[V]]
    delta = dyn_numpy(drive)
    np.testing.assert_allclose(out.displacement, delta, rtol=0, atol=1e-10 * np.abs(delta).max())
    q, i = charge_and_current(delta)
    np.testing.assert_allclose(out.charge, q, rtol=0, atol=1e-10 * np.abs(q).max())
    np.testing.assert_allclose(out.current, i, rtol=0, atol=1e-9 * np.abs(i).max())
    # the sampled current integrates back to the charge exactly, and starts with the electrode charging step
    np.testing.assert_allclose(np.cumsum(out.current) * DT, out.charge, rtol=0, atol=1e-12 * np.abs(q).max())
    assert float(out.current[0]) == pytest.approx(CP * V[0] / DT, rel=1e-12)


def test_series_actuator_with_log_creep_equals_hand_composition():
    creep = pj.LogarithmicCreep(gamma=0.02, t0=0.01)
    act = make_actuator(structure="series", creep=creep)
    out = simulate(act, V, hold="foh")
    drive = np.asarray(jax.jit(lambda c, u: c.simulate(u, DT, hold="foh"))(creep, pi_numpy(V)))  # δ = G[C[H[V]]]
    # the creep stage itself against its defining superposition (ramp-in increments), spot-checked at one sample
    h = pi_numpy(V)
    k = 700
    means = [np.mean(1 + 0.02 * np.log10(np.maximum(np.linspace(m * DT, (m + 1) * DT, 2001), 0.01) / 0.01))
             for m in range(k + 1)]
    by_hand = h[0] * (1 + 0.02 * np.log10(max(k * DT, 0.01) / 0.01)) + sum(
        (h[j] - h[j - 1]) * means[k - j] for j in range(1, k + 1)
    )
    assert drive[k] == pytest.approx(by_hand, rel=1e-6)
    delta = dyn_numpy(drive, interp=True)
    np.testing.assert_allclose(out.displacement, delta, rtol=0, atol=1e-10 * np.abs(delta).max())
    np.testing.assert_allclose(out.charge, charge_and_current(delta)[0], rtol=1e-12, atol=1e-22)
    np.testing.assert_allclose(jax.jit(lambda a: a.drive(V, DT, hold="foh"))(act), drive, rtol=1e-12, atol=1e-12)


def test_missing_blocks_are_identities():
    ramp = 5.0 * T
    bare = pj.Actuator(capacitance=2e-9)  # δ = V, q = C V
    out = jax.jit(lambda a: a.simulate(ramp, DT))(bare)
    np.testing.assert_allclose(out.displacement, ramp, rtol=0, atol=0)
    np.testing.assert_allclose(out.charge, 2e-9 * ramp, rtol=1e-15)
    np.testing.assert_allclose(out.current[1:], 2e-9 * 5.0, rtol=1e-9)  # i = C dV/dt for a ramp
    # a linear system given as the creep is wrapped as LinearCreep
    act = pj.Actuator(creep=pj.StableTransferFunction(0.1, poles=[-1.0]))
    assert isinstance(act.creep, pj.LinearCreep)


def jac_vs_fd(fn, model, rel=1e-5):
    """jacfwd wrt every inexact array leaf of `model`, and a 4-point central finite-difference Jacobian."""
    params, static = eqx.partition(model, eqx.is_inexact_array)
    flat, unravel = ravel_pytree(params)
    f = jax.jit(lambda p: fn(eqx.combine(unravel(p), static)))
    jac = np.asarray(jax.jit(jax.jacfwd(f))(flat))
    fd = np.zeros_like(jac)
    for i in range(flat.shape[0]):
        h = rel * (abs(float(flat[i])) or 1.0)  # a parameter at 0 (the offset) gets an absolute step
        e = jnp.zeros_like(flat).at[i].set(h)
        d1 = np.asarray(f(flat + e)) - np.asarray(f(flat - e))
        d2 = np.asarray(f(flat + 2 * e)) - np.asarray(f(flat - 2 * e))
        fd[:, i] = (8 * d1 - d2) / (12 * h)
    return jac, fd


def test_jacfwd_wrt_all_parameters_matches_fd():
    act = make_actuator(smoothing=0.05)
    v = jnp.asarray(V[:300])

    def outputs(a):
        out = a.simulate(v, DT)
        # scaled to O(1) so one tolerance fits all three channels
        return jnp.concatenate([out.displacement / 1e-5, out.charge / 1e-8, out.current / 1e-5])

    jac, fd = jac_vs_fd(outputs, act)
    # PI: 3 weights, 3 thresholds, w0, smoothing; KV: 2 + 2; G: gain, omega, zeta; capacitance, coupling, offset
    assert jac.shape == (900, 18)
    scale = np.abs(fd).max(axis=0)
    assert np.all(scale > 0)  # every parameter moves some output
    np.testing.assert_allclose(jac / scale, fd / scale, rtol=0, atol=1e-6)


def test_vmap_over_experiments_and_actuators(rng):
    act = make_actuator()
    batch = np.stack([V, 0.5 * V, V[::-1].copy(), rng.standard_normal(N)])
    outs = jax.jit(jax.vmap(lambda v: act.simulate(v, DT)))(batch)
    assert outs.displacement.shape == (4, N)
    for b in range(4):
        single = simulate(act, batch[b])
        np.testing.assert_allclose(outs.displacement[b], single.displacement, rtol=1e-13, atol=1e-22)
        np.testing.assert_allclose(outs.current[b], single.current, rtol=1e-13, atol=1e-20)
    # a population of actuators (different capacitances) on one record
    acts = jax.vmap(lambda c: eqx.tree_at(lambda a: a.capacitance, act, c))(jnp.array([1e-9, 2e-9]))
    qs = jax.jit(jax.vmap(lambda a: a.simulate(V, DT).charge))(acts)
    np.testing.assert_allclose(qs[1] - qs[0], 1e-9 * V, rtol=1e-9)


@contextlib.contextmanager
def raises_runtime(match):
    """An error raised while running compiled code (eqx.error_if), whose message (anywhere in the chain) matches."""
    with pytest.raises(Exception) as info:
        yield
    texts, e = [], info.value
    while e is not None:
        texts.append(str(e))
        e = e.__cause__ or e.__context__
    assert re.search(match, "\n".join(texts)), texts


def test_bad_input():
    act = pj.Actuator(capacitance=1e-9)
    with pytest.raises(ValueError, match="v_in"):
        act.simulate(jnp.zeros(0), DT)
    with pytest.raises(ValueError, match="v_in"):
        act.simulate(jnp.zeros((3, 10)), DT)
    with pytest.raises(ValueError, match="dt"):
        act.simulate(jnp.ones(10), -1e-3)
    with pytest.raises(ValueError, match="hold"):
        act.simulate(jnp.ones(10), DT, hold="spline")
    with raises_runtime("`v_in` contains NaN"):
        jax.jit(lambda v: act.simulate(v, DT))(jnp.array([0.0, jnp.nan]))
    with raises_runtime("dt"):
        jax.jit(lambda dt: act.simulate(jnp.ones(4), dt))(0.0)
    with pytest.raises(ValueError, match="capacitance"):
        pj.Actuator(capacitance=-1e-9)
    with pytest.raises(ValueError, match="coupling"):
        pj.Actuator(coupling=np.inf)
    with pytest.raises(ValueError, match="structure"):
        pj.Actuator(structure="feedback")
    with pytest.raises(ValueError, match="creep"):
        pj.Actuator(creep=0.1)
    with pytest.raises(ValueError, match="hysteresis"):
        pj.Actuator(hysteresis=pj.KelvinVoigtCreep([1.0], [1.0]))
    with pytest.raises(ValueError, match="dynamics"):
        pj.Actuator(dynamics=pj.KelvinVoigtCreep([1.0], [1.0]))
    bad = eqx.tree_at(lambda a: a.capacitance, act, jnp.asarray(-1.0))
    with raises_runtime("capacitance"):
        jax.jit(lambda a: a.simulate(jnp.ones(4), DT))(bad)
