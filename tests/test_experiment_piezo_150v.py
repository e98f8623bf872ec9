"""End-to-end check of `python -m experiments.piezo_150v_1hz --quick` on the measured ±150 V, 1 Hz actuator record,
and of the library blocks it builds its models from."""

import json
import os
import subprocess
import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

import fitting
import piezojax as pj
from experiments import piezo_150v_1hz as exp

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(not exp.DATA.exists(), reason=f"data file not found: {exp.DATA}")

# Test RMSE [µm] of the --quick run (5 elements, 15 steps per stage, 250 Hz, no full-rate stage), measured on 2 cores:
# PI 0.072-0.074, Bouc-Wen 0.062, Maxwell slip 0.074-0.080 (the full run: 0.058, 0.061, 0.062). Bounds ~15 % above.
QUICK_TEST_RMSE_UM = {"PI": 0.085, "BW": 0.072, "MS": 0.092}


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    """Run the experiment once with reduced settings in a subprocess (so the CLI's own JAX flags apply)."""
    out = tmp_path_factory.mktemp("piezo") / "results"
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run(
        [sys.executable, "-m", "experiments.piezo_150v_1hz", "--quick", "--out", str(out)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return out, proc.stdout


def test_outputs_written_atomically(quick_run):
    out, stdout = quick_run
    for name in ("metrics.json", "table.txt", "loops.png", "time_series.png", "predictions.npz"):
        assert (out / name).stat().st_size > 0, name
    # no temporary folder left next to the output
    assert not [p for p in out.parent.iterdir() if p.name.startswith(f".{out.name}")]
    # progress of every stage and the final table are printed
    for family in ("PI", "BW", "MS"):
        assert f"[{family} stage 1, 250 Hz]" in stdout
        assert f"[{family} stage 2, +mode, 250 Hz]" in stdout
    assert "stage 3" not in stdout  # --quick keeps the resonance's data-derived start
    assert "test RMSE" in stdout
    assert (out / "table.txt").read_text().strip() in stdout


def test_errors_finite_and_not_degraded(quick_run):
    out, _ = quick_run
    report = json.loads((out / "metrics.json").read_text())
    data = exp.load_data()
    test_range = float(np.ptp(data["x"][data["t"] >= exp.T_SPLIT]))
    assert set(report["metrics"]) == {"PI", "BW", "MS"}
    assert report["quick"] is True and report["settings"]["mode"] is True
    for name, m in report["metrics"].items():
        for key, value in m.items():
            assert np.isfinite(value), (name, key)
        # the test displacement spans ≈ 39 µm; the sensor's noise is ≈ 0.05 µm
        assert m["test_rmse_um"] < QUICK_TEST_RMSE_UM[name], (name, m)
        assert m["test_nrmse"] < 0.0025, (name, m)
        assert m["train_no_ring_rmse_um"] < 0.1, (name, m)
        # NRMSE = RMSE / range of the measured test displacement
        assert m["test_rmse_um"] / m["test_nrmse"] == pytest.approx(test_range, rel=1e-9)
    # every fit stage ran and the fitted lag, mode and resonance are physical
    for name, p in report["parameters"].items():
        info = report["fit_info"][name]
        assert info["stage1"]["steps"] >= 1 and info["stage2_mode"]["steps"] >= 1, (name, info)
        assert info["stage3_dynamics"] is None, (name, info)
        assert 1e-5 < p["lag_time_constant_s"] < 0.2, (name, p)
        assert 0 < p["lag_fraction"] < 1, (name, p)
        assert 0.5 < p["mode_hz"] < 40 and p["mode_zeta"] > 0, (name, p)
        assert 500 < p["resonance_hz"] < 2500 and p["resonance_zeta"] > 0, (name, p)
    # the saved predictions are the evaluated ones
    preds = np.load(out / "predictions.npz")
    test = preds["t"] >= exp.T_SPLIT
    rmse = float(np.sqrt(np.mean((preds["PI"][test] - preds["x"][test]) ** 2)))
    assert rmse == pytest.approx(report["metrics"]["PI"]["test_rmse_um"], rel=1e-9)


def test_maxwell_slip_model_is_its_prandtl_ishlinskii_form():
    """The Maxwell-slip family (parallel structure, linear path -c v, dynamics of DC gain -1 carrying the lag) is
    x = b + L[c v - M[v]], i.e. the series PI model with w0 = c - sum k, weights k and thresholds f / k."""
    rng = np.random.default_rng(0)
    k = jnp.asarray([0.02, 0.05, 0.01])
    f = jnp.asarray([0.4, 2.5, 1.2])  # thresholds f / k = 20, 50, 120 V
    c, lag, offset, pre = 0.17, (0.2, 0.03), -0.08, -120.0
    ms = exp.build_model("MS", pj.MaxwellSlip(k, f), c=c, lag=lag, offset=offset, prehistory=pre)
    pi = exp.build_model("PI", pj.PrandtlIshlinskii(k, f / k, w0=c - jnp.sum(k)), lag=lag, offset=offset,
                         prehistory=pre)
    assert exp.lag_of(ms, "MS") == pytest.approx(lag, rel=1e-12)
    assert exp.lag_of(pi, "PI") == pytest.approx(lag, rel=1e-12)
    t = np.arange(3000) * 1e-3
    v = 150 * np.sin(2 * np.pi * t) * np.minimum(1, t) + rng.normal(0, 1, t.size)
    record = fitting.Experiment.from_arrays(v_in=v, dt=1e-3, displacement=np.zeros_like(v))
    y_ms = fitting.predict(ms, record)["displacement"]
    y_pi = fitting.predict(pi, record)["displacement"]
    assert np.ptp(y_pi) > 10
    np.testing.assert_allclose(y_ms, y_pi, rtol=0, atol=1e-9 * np.ptp(y_pi))
    # the pole pairs added for stages 2 and 3 keep DC gain -1 and the lag's wrapped pole
    params = exp.with_pairs(exp.constrained(ms, "MS"), "MS", [(20.0, 0.5), (6000.0, 0.05)], (20.0, 0.5))
    model = pj.unwrap(params)
    assert float(model.dynamics.dc_gain()) == pytest.approx(-1.0, rel=1e-12)
    assert exp.lag_of(model, "MS") == pytest.approx(lag, rel=1e-9)
    assert isinstance(params.dynamics.poles, pj.Bounded)


def test_decimate_blocks_start_at_the_jump():
    data = exp.load_data()
    record = fitting.Experiment.from_arrays(v_in=data["v"], t=data["t"], displacement=data["x"])
    low = exp.decimate(record, 5, data["t_jump"])
    assert low.dt == pytest.approx(5 * data["dt"], rel=1e-9)
    jump = int(np.argmax(data["v"] != 0))
    k = int(np.argmax(low.v_in != 0))  # the first block with voltage starts at the jump
    assert low.v_in[k] == data["v"][jump + 2] and low.t[k] == pytest.approx(data["t"][jump + 2])
    assert low["displacement"][k] == pytest.approx(np.mean(data["x"][jump : jump + 5]))
    assert low["displacement"][k - 1] == pytest.approx(np.mean(data["x"][jump - 5 : jump]))


def test_load_data_checks_the_file(tmp_path):
    data = exp.load_data()
    assert len(data["t"]) == 50_001
    assert data["dt"] == pytest.approx(2e-4, rel=1e-3)
    assert data["t_jump"] == pytest.approx(3.2572, abs=1e-3)
    with pytest.raises(pj.PiezojaxValueError, match="not found"):
        exp.load_data(tmp_path / "missing.csv")
    bad = tmp_path / "bad.csv"
    bad.write_text(",0,1.0,0\n,0.0002,nan,0\n,0.0004,1.0,0\n")
    with pytest.raises(ValueError, match="displacement"):
        exp.load_data(bad)
    uneven = tmp_path / "uneven.csv"
    uneven.write_text(",0,1.0,0\n,0.0002,1.0,0\n,0.0009,1.0,0\n")
    with pytest.raises(ValueError, match="time"):
        exp.load_data(uneven)
