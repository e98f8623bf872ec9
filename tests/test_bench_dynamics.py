"""`experiments.bench_dynamics --quick` runs and its models agree with the numba loops it times them against."""

import numpy as np
import pytest

pytest.importorskip("numba")

from experiments import bench_dynamics  # noqa: E402


def test_bench_dynamics_quick_agrees_with_numba():
    out = bench_dynamics.main(["--quick"])
    agreement = out["agreement"]
    # the same discrete models: rounding only (the one-loop and block-by-block actuator passes both checked)
    assert agreement["linear"] < 1e-12
    assert agreement["actuator"] < 1e-12
    assert agreement["rule"] < 1e-12
    # forward differences of the numba loop (h = 1e-7 relative): their own truncation and rounding error
    assert agreement["finite_differences"] < 1e-3
    t_one, t_numba = out["actuator"]
    assert np.isfinite(t_one) and np.isfinite(t_numba) and t_one > 0 and t_numba > 0
