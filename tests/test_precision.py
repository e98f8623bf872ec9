"""Matrix products at the full precision of their dtype on every backend.

JAX's default precision lets a GPU multiply float32 matrices in TF32 (a 10-bit mantissa): measured on an H200, the
PI operator's float32 Jacobian came out 3e-4 relative from the same product at full precision
(`tests/test_fast_jacobians.py::test_pi_jacobian_float32` failed there). The CPU computes every precision the same
way, so these tests read the traced programs instead: every `dot_general` of a model's simulation and of its
derivatives must ask for HIGHEST precision.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _jaxpr_helpers import reduced_precision_products

import piezojax as pj
from piezojax._dtypes import cast_module

DT = 1e-3
V = 40.0 * np.sin(np.linspace(0.0, 6.0 * np.pi, 1500)) * np.linspace(1.0, 0.3, 1500)
PI = pj.PrandtlIshlinskii(np.array([0.4, 0.25, 0.1]), np.array([0.0, 2.0, 5.0]), w0=1.0)
DYN = pj.StableTransferFunction(2e-6, omega=[2 * np.pi * 30], zeta=[0.3])

MODELS = {
    # the measured actuator's structure (experiments/configs/piezo_150v_pi.toml)
    "series polynomial PI, lag creep, resonance, prehistory": pj.Actuator(
        pj.OutputPolynomial(PI, [0.05, -0.02], scale=10.0), pj.LagCreep([0.3], [0.02]), DYN, structure="series",
        prehistory=-30.0, offset=1e-6,
    ),
    "parallel Gaussian Preisach, Kelvin-Voigt creep": pj.Actuator(
        pj.GaussianPreisach(0.02, 8.0, 6.0, w0=0.9, r_max=20.0, n=12), pj.KelvinVoigtCreep([5.0, 20.0], [0.05, 0.5]),
        DYN, capacitance=1e-9, coupling=1e-3,
    ),
    "Maxwell slip, linear creep": pj.Actuator(
        pj.MaxwellSlip(np.array([1.0, 0.5, 0.2]), np.array([0.5, 2.0, 6.0])),
        pj.LinearCreep(pj.TransferFunction([0.2, 1.0], [0.1, 1.0])), DYN, coupling=1e-3,
    ),
}


def _tangents(model):
    return jax.tree_util.tree_map(lambda x: jnp.ones_like(x) if eqx.is_inexact_array(x) else None, model)


@pytest.mark.parametrize("scans", ["never", "always"])
@pytest.mark.parametrize("name", list(MODELS))
def test_every_matrix_product_of_a_model_and_its_derivatives_is_at_full_precision(name, scans):
    model = cast_module(MODELS[name], jnp.float32)
    v = jnp.asarray(V, jnp.float32)

    def displacement(m):
        return m.simulate(v, jnp.float32(DT)).displacement

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


def test_the_check_finds_a_default_precision_product():
    """The check itself: a plain `@` of float32 arrays is reported, `piezojax._dtypes.matmul` is not."""
    from piezojax._dtypes import matmul

    a, b = jnp.ones((4, 3), jnp.float32), jnp.ones(3, jnp.float32)
    assert len(reduced_precision_products(jax.make_jaxpr(lambda a, b: a @ b)(a, b))) == 1
    assert reduced_precision_products(jax.make_jaxpr(matmul)(a, b)) == []
