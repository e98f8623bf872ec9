import equinox as eqx
import hypothesis.extra.numpy as hnp
import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given

import piezojax as pj

finite = st.floats(-30.0, 30.0, allow_nan=False)


@given(hnp.arrays(np.float64, st.integers(1, 20), elements=finite))
def test_ordered_positive_maps_any_vector_to_strictly_ascending_positive(raw):
    r = np.asarray(pj.OrderedPositive(raw).unwrap())
    assert np.all(r > 0.0)
    assert np.all(np.diff(r) > 0.0)


@given(hnp.arrays(np.float64, st.integers(1, 20), elements=st.floats(1e-3, 50.0)))
def test_ordered_positive_round_trip(gaps):
    value = np.cumsum(gaps)
    wrapped = pj.OrderedPositive.from_value(value)
    np.testing.assert_allclose(wrapped.unwrap(), value, rtol=1e-10)


@given(hnp.arrays(np.float64, st.integers(1, 10), elements=st.floats(1e-6, 1e3)))
def test_positive_round_trip_and_positivity(value):
    wrapped = pj.Positive.from_value(value)
    np.testing.assert_allclose(wrapped.unwrap(), value, rtol=1e-9)



@given(hnp.arrays(np.float64, st.integers(1, 10), elements=finite))
def test_positive_is_positive_for_any_raw(raw):
    assert np.all(np.asarray(pj.Positive(raw).unwrap()) > 0)


def test_bounded_round_trip_and_range():
    value = jnp.array([0.1, 0.5, 0.99])
    wrapped = pj.Bounded.from_value(value, 0.0, 1.0)
    np.testing.assert_allclose(wrapped.unwrap(), value, rtol=1e-12)
    extreme = pj.Bounded(jnp.array([-20.0, 20.0]), 0.0, 1.0).unwrap()
    assert np.all((np.asarray(extreme) > 0.0) & (np.asarray(extreme) < 1.0))


def test_bad_values_are_named():
    with pytest.raises(ValueError, match="strictly ascending"):
        pj.OrderedPositive.from_value(jnp.array([0.2, 0.1]))
    with pytest.raises(ValueError, match="strictly ascending"):
        pj.OrderedPositive.from_value(jnp.array([0.0, 0.1]))  # r = 0 is reserved for the linear term
    with pytest.raises(ValueError, match="positive"):
        pj.Positive.from_value(jnp.array([1.0, -1.0]))
    with pytest.raises(ValueError, match="inside"):
        pj.Bounded.from_value(jnp.array([2.0]), 0.0, 1.0)
    with pytest.raises(ValueError, match="low"):
        pj.Bounded(jnp.array([0.0]), 1.0, 0.0)


class _Toy(eqx.Module):
    weights: jax.Array
    thresholds: jax.Array


def test_constrain_unwrap_and_gradient_through_softplus():
    toy = _Toy(jnp.array([1.0, 2.0]), jnp.array([0.5, 1.5]))
    params = pj.constrain(toy, lambda m: m.weights, pj.Positive)
    params = pj.constrain(params, lambda m: m.thresholds, pj.OrderedPositive)
    back = pj.unwrap(params)
    np.testing.assert_allclose(back.weights, toy.weights, rtol=1e-12)
    np.testing.assert_allclose(back.thresholds, toy.thresholds, rtol=1e-12)

    def f(p):
        m = pj.unwrap(p)
        return jnp.sum(m.weights * m.thresholds)

    g = jax.grad(f)(params)
    # d/d raw_w of w * r = r * sigmoid(raw_w); thresholds: r_i = cumsum(softplus(raw_r))
    sig = jax.nn.sigmoid
    np.testing.assert_allclose(g.weights.raw, toy.thresholds * sig(params.weights.raw), rtol=1e-10)
    expected = jnp.array([3.0, 2.0]) * sig(params.thresholds.raw)  # d/d gap_j = sum_{i>=j} w_i
    np.testing.assert_allclose(g.thresholds.raw, expected, rtol=1e-10)
    jax.jit(pj.unwrap)(params)  # usable under jit


def test_a_reparametrised_model_asks_to_be_unwrapped():
    model = pj.constrain(pj.Actuator(pj.PrandtlIshlinskii(jnp.ones(3), jnp.array([1.0, 2.0, 3.0]), w0=1.0)),
                         lambda m: m.hysteresis.thresholds, pj.OrderedPositive)
    with pytest.raises(pj.PiezojaxValueError, match=r"Actuator holds reparametrised .*OrderedPositive.*pj.unwrap"):
        model.simulate(jnp.ones(10), 1e-3)
    assert jnp.all(jnp.isfinite(pj.unwrap(model).simulate(jnp.ones(10), 1e-3).displacement))
