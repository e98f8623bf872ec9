"""Maxwell-slip operator: hand computation, equivalence with Prandtl–Ishlinskii, electrical analogue, gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from hypothesis.extra.numpy import arrays

import piezojax as pj

N = 30
N_ELEMENTS = 4


def _apply(k, f, s, x):
    return pj.MaxwellSlip(k, f, s)(x)


_gms = jax.jit(_apply)
_pi = jax.jit(lambda w, r, w0, s, v: pj.PrandtlIshlinskii(w, r, w0, s)(v))


def test_hand_computation_and_element_saturation():
    # k = [2, 1], f = [1, 2]: thresholds r = f/k = [0.5, 2]; elongations z = [0.25, 0.25] -> F = 0.75, then
    # z = [0.5, 1] -> 2, z = [0.5, 2] -> 3 (both slipping at +f), back to 0: z = [-0.5, -1] -> -2
    gms = pj.MaxwellSlip(jnp.array([2.0, 1.0]), jnp.array([1.0, 2.0]))
    np.testing.assert_allclose(gms(jnp.array([0.25, 1.0, 3.0, 0.0])), [0.75, 2.0, 3.0, -2.0], atol=1e-15)
    np.testing.assert_allclose(gms.thresholds, [0.5, 2.0])
    # far beyond every threshold the force saturates at the total breakaway force, both ways
    np.testing.assert_allclose(gms(jnp.array([10.0, -10.0])), [3.0, -3.0])


@settings(max_examples=20)
@given(
    k=arrays(np.float64, N_ELEMENTS, elements=st.floats(0.1, 5.0)),
    r=arrays(np.float64, N_ELEMENTS, elements=st.floats(0.01, 2.0), unique=True),
    x=arrays(np.float64, N, elements=st.floats(-3, 3)),
    smoothing=st.sampled_from([0.0, 0.1]),
)
def test_equals_prandtl_ishlinskii_stop_form(k, r, x, smoothing):
    """sum_i k_i S_{f_i/k_i}[x] = PI with w0 = sum k_i, weights -k_i and thresholds f_i/k_i (sorted)."""
    f = k * r
    order = np.argsort(r)
    expected = _pi(jnp.asarray(-k[order]), jnp.asarray(r[order]), jnp.asarray(k.sum()), smoothing, jnp.asarray(x))
    got = _gms(jnp.asarray(k), jnp.asarray(f), smoothing, jnp.asarray(x))
    np.testing.assert_allclose(got, expected, atol=1e-11)


def test_electrical_analogue():
    """Input charge q, element stiffness 1/C_i, breakaway voltage v_i, output V_H (paper 003 §3.3.1)."""
    c = jnp.array([2e-6, 5e-6, 1e-5])  # F
    v_break = jnp.array([0.5, 1.0, 2.0])  # V
    gms = pj.MaxwellSlip.electrical(c, v_break)
    np.testing.assert_allclose(gms.stiffness, 1 / c)
    np.testing.assert_allclose(gms.thresholds, c * v_break)  # charge at which element i slips
    q = jnp.linspace(0, 1e-4, 101)[1:]  # C
    vh = gms(q)
    # initial slope sum 1/C_i, final value sum v_i (every element slipping)
    assert float(vh[0]) == pytest.approx(float(q[0] * jnp.sum(1 / c)), rel=1e-12)
    assert float(vh[-1]) == pytest.approx(3.5, rel=1e-12)
    with pytest.raises(ValueError, match="capacitances"):
        pj.MaxwellSlip.electrical(jnp.array([1e-6, -1e-6]), jnp.array([1.0, 1.0]))


@settings(max_examples=15)
@given(
    x=arrays(np.float64, N, elements=st.floats(-3, 3)),
    fractions=arrays(np.float64, (N, 2), elements=st.floats(0.01, 0.99)),
    smoothing=st.sampled_from([0.0, 0.2]),
)
def test_rate_independence(x, fractions, smoothing):
    k, f = jnp.array([1.0, 2.0, 0.5, 3.0]), jnp.array([0.2, 1.0, 0.1, 4.0])
    corners = np.concatenate([[0.0], x])
    fine = np.concatenate(
        [np.concatenate([a + (b - a) * np.sort(q), [b]]) for a, b, q in zip(corners[:-1], corners[1:], fractions)]
    )
    idx = np.arange(1, N + 1) * 3 - 1
    np.testing.assert_allclose(_gms(k, f, smoothing, jnp.asarray(fine))[idx], _gms(k, f, smoothing, jnp.asarray(x)),
                               atol=1e-12)


@pytest.mark.parametrize("smoothing", [0.0, 0.2])
def test_gradients_match_finite_differences(smoothing):
    rng = np.random.default_rng(5)
    x = jnp.asarray(rng.uniform(-2, 2, N))
    k, f = jnp.array([1.0, 2.0, 0.5, 3.0]), jnp.array([0.2, 1.0, 0.1, 4.0])
    jac_k, jac_f, jac_x = jax.jit(jax.jacfwd(_apply, argnums=(0, 1, 3)))(k, f, smoothing, x)
    h = 1e-6

    def fd(fun, p):
        p = np.asarray(p)
        return np.stack([(fun(jnp.asarray(p + h * e)) - fun(jnp.asarray(p - h * e))) / (2 * h) for e in np.eye(p.size)],
                        -1)

    np.testing.assert_allclose(jac_k, fd(lambda p: _gms(p, f, smoothing, x), k), atol=1e-6)
    np.testing.assert_allclose(jac_f, fd(lambda p: _gms(k, p, smoothing, x), f), atol=1e-6)
    np.testing.assert_allclose(jac_x, fd(lambda p: _gms(k, f, smoothing, p), x), atol=1e-6)
    g = jax.grad(lambda k: jnp.sum(_apply(k, f, smoothing, x) ** 2))(k)
    np.testing.assert_allclose(g, 2 * jac_k.T @ _gms(k, f, smoothing, x), rtol=1e-10)


def test_vmap_float32_and_bad_input():
    gms = pj.MaxwellSlip(jnp.array([1.0, 2.0]), jnp.array([0.5, 0.5]), smoothing=0.1)
    batch = jnp.asarray(np.random.default_rng(6).uniform(-1, 1, (2, N)))
    out = jax.vmap(lambda x: gms(x))(batch)
    np.testing.assert_allclose(out[1], gms(batch[1]), atol=1e-14)
    gms32 = pj.MaxwellSlip(jnp.array([1.0, 2.0], jnp.float32), jnp.array([0.5, 0.5], jnp.float32))
    assert gms32(batch[0].astype(jnp.float32)).dtype == jnp.float32
    with pytest.raises(ValueError, match="stiffness"):
        pj.MaxwellSlip(jnp.array([1.0, 0.0]), jnp.array([0.5, 0.5]))
    with pytest.raises(ValueError, match="breakaway"):
        pj.MaxwellSlip(jnp.array([1.0, 1.0]), jnp.array([0.5, -0.5]))
    with pytest.raises(ValueError, match="breakaway"):
        pj.MaxwellSlip(jnp.array([1.0, 1.0]), jnp.array([0.5, 0.5, 1.0]))
    with pytest.raises(ValueError, match="signal"):
        gms(jnp.ones((2, 2)))
    with pytest.raises(Exception, match="stiffness"):
        _gms(jnp.array([1.0, -1.0]), jnp.array([0.5, 0.5]), 0.0, jnp.ones(N))  # traced: eqx.error_if
