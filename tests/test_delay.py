"""`pj.Delay`, a dead time of fractional samples: against scipy's cubic Hermite interpolant, exact at whole
samples, continuously differentiable in the delay (finite differences), in an `Actuator` and undone by its inverse."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.interpolate

import piezojax as pj

DT = 1e-3
T = np.arange(400) * DT
U = np.sin(2 * np.pi * 3 * T) + 0.4 * np.sin(2 * np.pi * 17 * T + 0.3)


@pytest.mark.parametrize("samples", [0.0, 1.0, 3.0, 0.25, 2.5, 7.8])
def test_delay_is_the_catmull_rom_interpolant_read_late(samples):
    y = np.asarray(pj.Delay(samples * DT)(U, DT))
    # an independent reference: scipy's cubic Hermite spline with central-difference slopes (Catmull-Rom)
    slopes = np.gradient(U, DT)
    spline = scipy.interpolate.CubicHermiteSpline(T, U, slopes)
    inside = slice(int(np.ceil(samples)) + 3, -3)  # away from the held ends, where the slopes are one-sided
    np.testing.assert_allclose(y[inside], spline(T[inside] - samples * DT), rtol=0, atol=1e-12)
    if samples == int(samples):  # a whole number of samples: the samples themselves, the first held before
        k = int(samples)
        np.testing.assert_allclose(y, np.concatenate([np.full(k, U[0]), U[: U.size - k]]), rtol=0, atol=1e-14)


def test_delay_is_differentiable_in_its_time_across_whole_samples():
    def loss(tau):
        return jnp.sum(jnp.sin(pj.Delay(tau)(jnp.asarray(U), DT)) ** 2)

    for tau in [0.4 * DT, 1.0 * DT, 1.0 * DT * (1 - 1e-9), 2.7 * DT]:
        h = 1e-9
        fd = (loss(tau + h) - loss(tau - h)) / (2 * h)
        assert float(jax.grad(loss)(tau)) == pytest.approx(float(fd), rel=1e-5)
    # jit and vmap over delays
    taus = jnp.array([0.0, 1.5 * DT, 3.0 * DT])
    batch = jax.jit(jax.vmap(lambda tau: pj.Delay(tau)(jnp.asarray(U), DT)))(taus)
    np.testing.assert_allclose(batch[2], pj.Delay(3.0 * DT)(U, DT), rtol=0, atol=1e-15)


def test_bad_delays_are_named():
    with pytest.raises(pj.PiezojaxValueError, match="`time`"):
        pj.Delay(-1e-3)
    with pytest.raises(pj.PiezojaxValueError, match="`time` must be a scalar"):
        pj.Delay([1e-3, 2e-3])
    with pytest.raises(pj.PiezojaxValueError, match="`delay` must be a pj.Delay"):
        pj.Actuator(delay=1e-3)


def _actuator(delay=None):
    return pj.Actuator(pj.PrandtlIshlinskii(jnp.array([1.0, 0.5, 0.3]), jnp.array([0.0, 20.0, 40.0])),
                       pj.KelvinVoigtCreep([20.0], [0.2], k0=None),
                       pj.StableTransferFunction(1.0, omega=[2 * np.pi * 80.0], zeta=[0.3]), capacitance=1e-9,
                       coupling=0.1, delay=delay)


def test_an_actuators_delay_reads_its_voltage_late_and_its_inverse_reads_ahead():
    v = 60 - 60 * np.cos(2 * np.pi * 2 * T)
    plain, late = _actuator(), _actuator(pj.Delay(3 * DT))
    shifted = np.concatenate([np.zeros(3), v[:-3]])
    for a, b in zip(jax.tree.leaves(late.simulate(v, DT)), jax.tree.leaves(plain.simulate(shifted, DT))):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-18)
    # a fractional delay, fitted by gradient with the other parameters: its derivative through the whole chain
    def displacement_sum(tau):
        m = eqx.tree_at(lambda a: a.delay.time, late, tau)
        return jnp.sum(m.simulate(v, DT).displacement)

    h = 1e-8
    fd = (displacement_sum(2.5 * DT + h) - displacement_sum(2.5 * DT - h)) / (2 * h)
    assert float(jax.grad(displacement_sum)(2.5 * DT)) == pytest.approx(float(fd), rel=1e-5)
    # the inverse reads the voltage ahead by the delay: tracking as good as without one, far better than ignoring it
    target = plain.simulate(v, DT).displacement
    late = _actuator(pj.Delay(2.4 * DT))

    def error(model, voltage):
        return float(jnp.sqrt(jnp.mean((model.simulate(voltage, DT).displacement - target)[:-5] ** 2)))

    with_delay = error(late, late.inverse(0.0, 200.0)(target, DT))
    without = error(plain, plain.inverse(0.0, 200.0)(target, DT))
    ignored = error(late, plain.inverse(0.0, 200.0)(target, DT))
    assert with_delay < 1.1 * without and ignored > 10 * with_delay
