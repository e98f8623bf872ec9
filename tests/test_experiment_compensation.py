"""`experiments.compensation` with small settings: the study on library-built actuators (the fits it runs on the
measured record are the command line's, tested elsewhere)."""

import json

import jax.numpy as jnp
import numpy as np

import piezojax as pj
from experiments import compensation


def _truth():
    pi = pj.PrandtlIshlinskii(jnp.array([4.5e-8, 3e-8, 3e-8]), jnp.array([0.0, 30.0, 70.0]), w0=9e-8)
    return pj.Actuator(pi, pj.LagCreep([0.3], [0.5]), pj.StableTransferFunction(1.0, omega=[2 * np.pi * 900.0],
                       zeta=[0.1]), structure="series", offset=-1e-7, prehistory=-60.0)


def test_compensation_study_ranks_the_methods():
    truth = _truth()
    wrong = pj.Actuator(pj.PrandtlIshlinskii(jnp.array([5e-8, 2.7e-8, 3.2e-8]), jnp.array([0.0, 28.0, 72.0]),
                                             w0=9.3e-8), truth.creep, truth.dynamics, structure="series",
                        offset=-1e-7, prehistory=-60.0)
    v = jnp.linspace(-150, 150, 2000)
    k, b = np.polyfit(np.asarray(v), np.asarray(truth.simulate(v, compensation.DT).displacement), 1)
    rows = compensation.study(truth, {"model": wrong, "truth": truth}, (k, b), middle=0.0, frequencies=(2.0, 10.0),
                              seconds=1.2, score_from=0.7, iterations=12)
    table = {(r["model"], r["method"], r["frequency_hz"]): r["rms_um"] for r in rows}
    assert len(rows) == 12
    for f in (2.0, 10.0):
        # the truth's own whole inverse is exact up to its low-pass; every inverse beats the plain gain
        assert table["truth", "whole-actuator inverse", f] < 0.01
        assert table["truth", "whole-actuator inverse", f] < table["truth", "hysteresis inverse", f]
        assert table["truth", "hysteresis inverse", f] < table["truth", "plain gain", f]
        assert table["model", "whole-actuator inverse", f] < table["model", "plain gain", f]
    assert all(-150.0 <= r["v_min"] <= r["v_max"] <= 150.0 for r in rows)


def test_an_interrupted_fit_is_not_reused(tmp_path):
    """The command line saves an interrupted fit's last parameters (code 'interrupted'): the experiment refits
    it rather than compensate with it."""
    assert not compensation.reusable(tmp_path / "missing")
    for code, ok in (("interrupted", False), ("not_converged", True), ("converged", True)):
        out = tmp_path / code
        out.mkdir()
        (out / "model.eqx").write_bytes(b"")
        (out / "result.json").write_text(json.dumps({"code": code}))
        assert compensation.reusable(out) is ok
    (tmp_path / "converged" / "result.json").write_text("{not json")
    assert not compensation.reusable(tmp_path / "converged")
