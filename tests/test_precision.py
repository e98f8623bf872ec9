"""Matrix products at the full precision of their dtype on every backend.

JAX's default precision lets a GPU multiply float32 matrices (and convolve float32 arrays) in TF32, a 10-bit
mantissa: measured on an H200, the PI operator's float32 Jacobian came out up to 3e-4 relative from the same Jacobian
by autodiff through the scan (`tests/test_fast_jacobians.py::test_pi_jacobian_float32` failed there). The CPU
computes every precision the same way, so these tests read the traced programs instead: every `dot_general` and
`conv_general_dilated` of the models' simulations and derivatives, of `fitting`'s normal equations and trust-region
step, and of the NARX network must ask for HIGHEST precision.
"""

import types

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _jaxpr_helpers import reduced_precision_products

import fitting
import piezojax as pj
from piezojax._dtypes import cast_module, matmul

DT = 1e-3
V = 40.0 * np.sin(np.linspace(0.0, 6.0 * np.pi, 1500)) * np.linspace(1.0, 0.3, 1500)
PI = pj.PrandtlIshlinskii(np.array([0.4, 0.25, 0.1]), np.array([0.0, 2.0, 5.0]), w0=1.0)
DYN = pj.StableTransferFunction(2e-6, omega=[2 * np.pi * 30], zeta=[0.3])

# name -> (model, how the input is held between samples)
MODELS = {
    # the measured actuator's structure (experiments/configs/piezo_150v_pi.toml)
    "series polynomial PI, lag creep, resonance, prehistory": (pj.Actuator(
        pj.OutputPolynomial(PI, [0.05, -0.02], scale=10.0), pj.LagCreep([0.3], [0.02]), DYN, structure="series",
        prehistory=-30.0, offset=1e-6,
    ), "zoh"),
    # dynamics with three real zeros (two share a section: a polynomial product)
    "parallel Gaussian Preisach, Kelvin-Voigt creep, dynamics with zeros": (pj.Actuator(
        pj.GaussianPreisach(0.02, 8.0, 6.0, w0=0.9, r_max=20.0, n=12), pj.KelvinVoigtCreep([5.0, 20.0], [0.05, 0.5]),
        pj.StableTransferFunction(2e-6, [2 * np.pi * 30], [0.3], [-40.0], zeros=[-60.0, -90.0, -200.0]),
        capacitance=1e-9, coupling=1e-3,
    ), "zoh"),
    # dynamics with a coefficient numerator (the denominator's polynomial products) and a first-order hold
    "Maxwell slip, linear creep, dynamics with a numerator, first-order hold": (pj.Actuator(
        pj.MaxwellSlip(np.array([1.0, 0.5, 0.2]), np.array([0.5, 2.0, 6.0])),
        pj.LinearCreep(pj.TransferFunction([0.2, 1.0], [0.1, 1.0])),
        pj.StableTransferFunction(2e-6, [2 * np.pi * 30, 2 * np.pi * 90], [0.3, 0.05], [-50.0],
                                  num=[1.0, 380.0, 24000.0]),
        coupling=1e-3,
    ), "foh"),
}


def _tangents(model):
    return jax.tree_util.tree_map(lambda x: jnp.ones_like(x) if eqx.is_inexact_array(x) else None, model)


@pytest.mark.parametrize("scans", ["never", "always"])
@pytest.mark.parametrize("name", list(MODELS))
def test_every_matrix_product_of_a_model_and_its_derivatives_is_at_full_precision(name, scans):
    model, hold = MODELS[name]
    model = cast_module(model, jnp.float32)
    v = jnp.asarray(V, jnp.float32)

    def displacement(m):
        return m.simulate(v, jnp.float32(DT), hold=hold).displacement

    def tangent(m):
        return eqx.filter_jvp(displacement, (m,), (_tangents(m),))

    previous = pj.set_parallel_scans(scans)
    try:
        programs = {"simulation": eqx.filter_make_jaxpr(displacement)(model)[0],
                    "directional derivative": eqx.filter_make_jaxpr(tangent)(model)[0],
                    "gradient": eqx.filter_make_jaxpr(eqx.filter_grad(lambda m: jnp.sum(displacement(m))))(model)[0]}
    finally:
        pj.set_parallel_scans(previous)
    for what, closed in programs.items():
        assert reduced_precision_products(closed) == [], what


def test_fitting_normal_equations_and_trust_region_step_are_at_full_precision():
    from fitting._solver import TrustRegionDescent

    model, _ = MODELS["series polynomial PI, lag creep, resonance, prehistory"]
    y = np.asarray(model.simulate(V, DT).displacement)
    data = fitting.Dataset([fitting.Experiment.from_arrays(v_in=V, dt=DT, displacement=y, name="e")])
    problem = fitting.Problem(model, data, free=["hysteresis", "creep", "dynamics.omega", "offset", "prehistory"])
    u = problem.u0
    assert reduced_precision_products(jax.make_jaxpr(problem.core.normal_equations)(u)) == []
    p = u.shape[0]

    def trust_region_step(h, g):
        return TrustRegionDescent().step(jnp.asarray(1.0), jnp.ones(p), jnp.asarray(0.0),
                                         types.SimpleNamespace(h=h, g=g), y.size)

    assert reduced_precision_products(jax.make_jaxpr(trust_region_step)(jnp.eye(p), jnp.ones(p))) == []


def test_narx_network_simulation_and_gradient_are_at_full_precision():
    net = cast_module(pj.NarxNetwork(jax.random.key(0), hidden=6, output_lags=2, input_lags=2), jnp.float32)
    x = jnp.asarray(np.sin(np.linspace(0.0, 10.0, 300)), jnp.float32)
    assert reduced_precision_products(eqx.filter_make_jaxpr(lambda n: n.simulate(x))(net)[0]) == []
    grad = eqx.filter_grad(lambda n: jnp.sum(n.simulate(x) ** 2))
    assert reduced_precision_products(eqx.filter_make_jaxpr(grad)(net)[0]) == []


def test_the_check_finds_default_precision_products_and_convolutions():
    """The check itself: a plain `@` or `jnp.polymul` of float32 arrays is reported, `matmul` is not."""
    from piezojax._dtypes import polymul

    a, b = jnp.ones((4, 3), jnp.float32), jnp.ones(3, jnp.float32)
    assert len(reduced_precision_products(jax.make_jaxpr(lambda a, b: a @ b)(a, b))) == 1
    assert reduced_precision_products(jax.make_jaxpr(matmul)(a, b)) == []
    assert len(reduced_precision_products(jax.make_jaxpr(jnp.polymul)(b, b))) == 1
    assert reduced_precision_products(jax.make_jaxpr(polymul)(b, b)) == []
