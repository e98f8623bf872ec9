"""`pj.Actuator`'s one-loop forward pass: the same outputs as the block-by-block pass, whose derivatives it uses."""

import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import piezojax as pj
from piezojax import _actuator
from piezojax._checks import refusal_mode

DT = 1e-3
N = 400
T = np.arange(N) * DT
V = 12 * np.sin(2 * np.pi * 3 * T) * np.exp(-2 * T) + 4 * np.sin(2 * np.pi * 11 * T) + 1.5

PI = pj.PrandtlIshlinskii(np.array([0.4, 0.25, 0.1]), np.array([0.0, 2.0, 5.0]), w0=1.0)
DYN = pj.StableTransferFunction(2e-6, omega=[2 * np.pi * 30, 2 * np.pi * 90], zeta=[0.3, 0.05])
KV = pj.KelvinVoigtCreep([5.0, 20.0], [0.05, 0.5], k0=None)

CONFIGS = {
    "parallel PI, Kelvin-Voigt, 4th order": pj.Actuator(PI, KV, DYN, capacitance=1.7e-9, coupling=3e-4, offset=1e-6),
    "series scaled PI, lag creep, settled prehistory": pj.Actuator(
        pj.ScaledHysteresis(PI, 0.5), pj.LagCreep([0.1, 0.05], [0.02, 0.3]), DYN, coupling=2e-4,
        structure="series", prehistory=9.0,
    ),
    "series polynomial PI, linear creep, no dynamics, given state": pj.Actuator(
        pj.OutputPolynomial(PI, [0.05], scale=10.0),
        pj.LinearCreep(pj.TransferFunction([0.2, 1.0], [0.1, 1.0])),
        None,
        coupling=1e-3,
        structure="series",
        hysteresis_state=(jnp.asarray(3.0), jnp.asarray([0.0, 1.0, -2.0])),
    ),
    "no hysteresis": pj.Actuator(None, KV, DYN, capacitance=1e-9),
    "no creep, prehistory": pj.Actuator(PI, None, DYN, coupling=1e-3, prehistory=-6.0),
    "Gaussian Preisach, parallel": pj.Actuator(
        pj.GaussianPreisach(0.02, 8.0, 6.0, w0=0.9, r_max=20.0, n=12), KV, DYN, coupling=1e-3
    ),
}


def blocks(act, v, dt=DT, hold="zoh"):
    """The block-by-block pass (the reference, and the derivative rule of the one-loop pass)."""
    m, v, dt = act._prepare(v, dt, hold)
    return _actuator._blocks(m, v, dt, hold, m._initial(v.dtype))


def takes_one_loop(act, v=V, hold="zoh"):
    m, v, _ = act._prepare(v, DT, hold)
    return _actuator._one_loop(m, v, hold)


def assert_outputs_close(out, ref, rtol):
    for name in ("displacement", "charge", "current"):
        a, b = np.asarray(getattr(out, name)), np.asarray(getattr(ref, name))
        scale = max(np.abs(b).max(), 1e-300)
        assert np.abs(a - b).max() <= rtol * scale, (name, np.abs(a - b).max() / scale)


@pytest.mark.parametrize("name", list(CONFIGS))
def test_one_loop_equals_blocks(name):
    act = CONFIGS[name]
    assert takes_one_loop(act)
    out = jax.jit(lambda a, v: a.simulate(v, DT))(act, jnp.asarray(V))
    ref = jax.jit(blocks)(act, jnp.asarray(V))
    assert_outputs_close(out, ref, 1e-13)
    # the reference is not degenerate: hysteresis, creep and dynamics all move the output
    assert np.ptp(np.asarray(ref.displacement)) > 0


def test_one_loop_in_float32():
    act = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32) if eqx.is_inexact_array(x) else x,
                                 CONFIGS["parallel PI, Kelvin-Voigt, 4th order"])
    v = jnp.asarray(V, jnp.float32)
    out = act.simulate(v, jnp.float32(DT))
    assert out.displacement.dtype == jnp.float32
    assert_outputs_close(out, blocks(act, v, jnp.float32(DT)), 1e-5)


def test_blocks_built_from_float32_arrays_stay_float32_with_python_numbers():
    """Under x64, blocks constructed from float32 arrays (with Python numbers and empty defaults beside them) keep
    float32, and so do their outputs for a float32 signal with a Python `dt`."""
    f32 = jnp.float32
    G = pj.StableTransferFunction(f32(1e-6), omega=jnp.array([2e3], f32), zeta=jnp.array([0.1], f32))
    creep = pj.KelvinVoigtCreep(jnp.array([20.0], f32), jnp.array([2.0], f32), k0=None)
    pi = pj.PrandtlIshlinskii(jnp.array([1.0, 2.0], f32), jnp.array([0.0, 1.0], f32), w0=f32(1.0))
    assert {x.dtype for x in jax.tree_util.tree_leaves(G) if eqx.is_array(x)} == {jnp.dtype(f32)}
    v = jnp.linspace(0.0, 3.0, 50, dtype=f32)
    assert creep.simulate(v, 1e-4).dtype == f32
    assert pj.Actuator(pi, creep, G).simulate(v, 1e-4).displacement.dtype == f32
    # without arrays, the default float dtype decides
    assert pj.StableTransferFunction(1e-6, omega=[2e3], zeta=[0.1]).omega.dtype == jnp.zeros(()).dtype


def test_which_chains_take_the_one_loop_pass():
    act = CONFIGS["parallel PI, Kelvin-Voigt, 4th order"]
    assert not takes_one_loop(act, hold="foh")  # the FOH cells would need the next input
    assert not takes_one_loop(eqx.tree_at(lambda a: a.creep, act, pj.LogarithmicCreep(0.02, 1e-3)))
    assert not takes_one_loop(eqx.tree_at(lambda a: a.hysteresis, act, pj.BoucWen(1.0, 0.5, 0.5, 1.0)))
    assert not takes_one_loop(eqx.tree_at(lambda a: a.hysteresis.smoothing, act, jnp.asarray(0.1)))
    with pj._config.parallel_scans("always"):
        assert not takes_one_loop(act)
    # each of these still simulates (block by block) and agrees with its own reference
    foh = act.simulate(V, DT, hold="foh")
    assert_outputs_close(foh, blocks(act, V, hold="foh"), 0.0)


def test_a_users_own_blocks_declare_the_one_loop_pass():
    """Whether a block runs in the one loop is declared by its class (`pj.AbstractFusedHysteresis`,
    `pj.AbstractFusedCreep`), so a user's own blocks take it as the built-in ones do, with the same outputs."""

    class MyPlay(pj.AbstractHysteresisCell, pj.AbstractFusedHysteresis):  # a play of the user's own, by its cell
        r: jax.Array
        smoothing: jax.Array = eqx.field(default_factory=lambda: jnp.asarray(0.0))

        def init(self):
            return jnp.zeros((), self.r.dtype)

        def step(self, y, v):
            y = jnp.clip(y, v - self.r, v + self.r)
            return y, y

        def exact_step(self):
            return self.step

        def check(self):
            return self

    class MyLag(pj.AbstractFusedCreep):  # creep through the user's own first-order lag, given as a state space
        gain: jax.Array
        tau: jax.Array

        def _system(self):
            return pj.StateSpace([[-1 / self.tau]], [1 / self.tau], [self.gain], 0.0)

        def _simulate(self, u, dt, hold):
            return self._system().simulate(u, dt, hold=hold)

        def step_response(self, t):
            return self.gain * (1 - jnp.exp(-jnp.asarray(t) / self.tau))

        def instantaneous_gain(self):
            return jnp.zeros_like(self.gain)

        def settled_gain(self):
            return self.gain

        def check(self):
            return self

        def zoh_cell(self, dt):
            return self._system().discretise(dt, "zoh")

    act = pj.Actuator(MyPlay(jnp.asarray(2.0)), MyLag(jnp.asarray(0.3), jnp.asarray(0.05)), DYN)
    assert takes_one_loop(act)
    assert_outputs_close(act.simulate(V, DT), blocks(act, V), 1e-12)
    # a block that does not declare it runs block by block
    plain = eqx.tree_at(lambda a: a.creep, act, pj.LogarithmicCreep(0.02, 1e-3))
    assert not takes_one_loop(plain)


def test_derivatives_are_the_blocks():
    act = CONFIGS["series scaled PI, lag creep, settled prehistory"]
    # every parameter traced but the smoothing, held at a concrete 0 (a traced one runs block by block)
    spec = jax.tree_util.tree_map(eqx.is_inexact_array, act)
    spec = eqx.tree_at(lambda a: a.hysteresis.hysteresis.smoothing, spec, False)
    params, static = eqx.partition(act, spec)
    flat, unravel = jax.flatten_util.ravel_pytree(params)
    assert takes_one_loop(eqx.combine(params, static))

    def outputs(simulate):
        def f(p):
            o = simulate(eqx.combine(unravel(p), static), jnp.asarray(V))
            return jnp.stack([o.displacement, o.charge, o.current])

        return f

    one_loop = outputs(lambda a, v: a.simulate(v, DT))
    reference = outputs(blocks)
    np.testing.assert_array_equal(jax.jit(jax.jacfwd(one_loop))(flat), jax.jit(jax.jacfwd(reference))(flat))
    # the same loops over the record as the blocks: leaves without a tangent (the signal, dt) stay symbolic zeros
    # for the blocks' rules, which then skip their input-tangent loops
    loops = [len(re.findall(rf"scan\[[^\]]*?length={N}\b", str(jax.make_jaxpr(jax.jacfwd(f))(flat)).replace("\n", " ")))
             for f in (one_loop, reference)]
    assert loops[0] == loops[1] >= 3, loops

    def cost(f):
        return lambda p: jnp.sum(f(p)[0] ** 2) * 1e12

    g, g_ref = jax.jit(jax.grad(cost(one_loop)))(flat), jax.jit(jax.grad(cost(reference)))(flat)
    np.testing.assert_allclose(g, g_ref, rtol=1e-12, atol=0)
    assert np.all(np.isfinite(g)) and np.any(g != 0)
    # the input tangent too (a controller differentiating through the plant)
    dv = jax.jit(jax.grad(lambda v: jnp.sum(act.simulate(v, DT).displacement)))(jnp.asarray(V))
    dv_ref = jax.jit(jax.grad(lambda v: jnp.sum(blocks(act, v).displacement)))(jnp.asarray(V))
    np.testing.assert_allclose(dv, dv_ref, rtol=1e-12, atol=1e-12 * np.abs(dv_ref).max())


def test_traced_smoothing_runs_block_by_block_and_vmap():
    act = CONFIGS["parallel PI, Kelvin-Voigt, 4th order"]
    passes = []

    def simulate(s, v):
        a = eqx.tree_at(lambda a: a.hysteresis.smoothing, act, s)
        passes.append(takes_one_loop(a, v))
        return a.simulate(v, DT)

    # a traced smoothing (as in a fit) keeps the block-by-block pass: one pass compiled, not both
    run = jax.jit(simulate)
    assert_outputs_close(run(jnp.asarray(0.0), jnp.asarray(V)), blocks(act, V), 1e-13)
    smooth = eqx.tree_at(lambda a: a.hysteresis.smoothing, act, jnp.asarray(0.2))
    assert_outputs_close(run(jnp.asarray(0.2), jnp.asarray(V)), blocks(smooth, V), 1e-13)
    assert passes == [False]
    # a batch of records through the one-loop pass
    batch = jnp.stack([jnp.asarray(V), -0.5 * jnp.asarray(V), jnp.zeros(N)])
    out = jax.jit(jax.vmap(lambda v: act.simulate(v, DT)))(batch)
    for i in range(3):
        ref = blocks(act, batch[i])
        np.testing.assert_allclose(out.displacement[i], ref.displacement, rtol=0,
                                   atol=1e-13 * max(np.abs(ref.displacement).max(), 1e-30))


def test_parameter_checks_still_attached():
    act = CONFIGS["parallel PI, Kelvin-Voigt, 4th order"]
    descending = eqx.tree_at(lambda a: a.hysteresis.thresholds, act, jnp.asarray([5.0, 2.0, 0.0]))
    # concrete parameters closed over in `jit` raise at once, as block by block; also in fitting's refusal mode
    with pytest.raises(pj.PiezojaxValueError, match="thresholds"):
        jax.jit(lambda v: descending.simulate(v, DT))(jnp.asarray(V))
    with refusal_mode("nan"), pytest.raises(pj.PiezojaxValueError, match="time_constants"):
        bad_creep = eqx.tree_at(lambda a: a.creep.time_constants, act, jnp.asarray([-0.05, 0.5]))
        jax.jit(lambda v: bad_creep.simulate(v, DT))(jnp.asarray(V))
    # traced: the runtime check
    with pytest.raises(Exception, match="thresholds"):
        jax.block_until_ready(jax.jit(lambda a: a.simulate(jnp.asarray(V), DT))(descending))
    negative = eqx.tree_at(lambda a: a.creep.time_constants, act, jnp.asarray([-0.05, 0.5]))
    with pytest.raises(Exception, match="time_constants"):
        jax.block_until_ready(jax.jit(lambda a: a.simulate(jnp.asarray(V), DT))(negative))
