"""The calibration benchmark in quick mode: the numba baseline simulates the same model, the engine's Jacobian is the
derivative of its residuals, and both fits get near the noise floor from the same start."""

import pytest

pytest.importorskip("numba")

from experiments import bench_calibration  # noqa: E402


@pytest.fixture(scope="module")
def quick_results():
    # one cold engine fit (no warm repeat) of 20 LM steps and a scipy fit of at most 15 residual evaluations: both
    # are within a few % of the noise floor by then on the quick data (measured: 5.2e-3 and 5.19e-3 against 4.94e-3)
    return bench_calibration.run(quick=True, max_steps=20, warm_run=False, scipy_max_nfev=15)


def test_numba_baseline_is_the_same_model(quick_results):
    # forward outputs (truth and start parameters), relative to the displacement range
    assert quick_results["numba_vs_piezojax_max_rel"] < 1e-9
    # the numpy reparametrisation and the residual vectors agree with the engine's
    assert quick_results["reparam_max_rel"] < 1e-12
    assert quick_results["residual_numba_vs_engine_max"] < 1e-9


def test_engine_jacobian_matches_finite_differences(quick_results):
    # central differences with h = 1e-6 in the scaled parameters: truncation ~1e-12, rounding ~1e-10 relative
    assert quick_results["jacobian_fd_max_col_rel"] < 1e-5


def test_both_fits_reach_the_noise_floor(quick_results):
    floor = quick_results["noise_floor_cost"]
    assert quick_results["initial_cost"] > 50 * floor  # the start is far from the optimum
    for key in ("jax_cost", "scipy_u_cost"):
        assert 0.9 * floor < quick_results[key] < 1.5 * floor, (key, quick_results[key], floor)
    assert quick_results["jax_steps"] <= 20
