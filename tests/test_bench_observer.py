"""The observer benchmark in quick mode: the paper-001 observer's Jacobian through the blocks' own paths (modal
Butterworth filter, PI and creep fast paths) equals the one through plain scans of generic components."""

from experiments import bench_observer


def test_library_and_generic_observer_jacobians_agree():
    # measured 5.7e-13 (jacfwd and the engine's J^T); the generic components are set with eqx.tree_at, past the
    # observer's component type check, which once made this benchmark fail
    out = bench_observer.main(["--quick"])
    assert out["agreement"] < 1e-10
