"""End-to-end check of `python -m experiments.piezo_150v_1hz --quick` on the measured ±150 V, 1 Hz actuator record."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from experiments import piezo_150v_1hz as exp

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(not exp.DATA.exists(), reason=f"data file not found: {exp.DATA}")


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
    for name in ("metrics.json", "table.txt", "loops.png", "time_series.png"):
        assert (out / name).stat().st_size > 0, name
    # no temporary folder left next to the output
    assert not [p for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.")]
    # progress and the final table are printed
    assert "stage 1" in stdout and "test RMSE" in stdout
    assert (out / "table.txt").read_text().strip() in stdout


def test_errors_finite_and_small(quick_run):
    out, _ = quick_run
    report = json.loads((out / "metrics.json").read_text())
    data = exp.load_data()
    test_range = float(np.ptp(data["x"][data["t"] >= exp.T_SPLIT]))
    assert set(report["metrics"]) == {"PI", "BW", "MS"}
    assert report["quick"] is True
    for name, m in report["metrics"].items():
        for key, value in m.items():
            assert np.isfinite(value), (name, key)
        # The test displacement spans ≈ 39 µm; the rest noise is ≈ 0.05 µm (0.13 %).
        assert m["test_nrmse"] < 0.01, (name, m)  # < 1 % out of sample, well inside the 5 % bound
        assert m["test_rmse_um"] < 0.2, (name, m)
        assert m["train_no_ring_rmse_um"] < 0.2, (name, m)
        # NRMSE = RMSE / range of the measured test displacement
        assert m["test_rmse_um"] / m["test_nrmse"] == pytest.approx(test_range, rel=1e-9)
    # the fitted lag and resonance are physical
    for name, p in report["parameters"].items():
        assert 1e-5 < p["lag_time_constant_s"] < 0.2, (name, p)
        assert 500 < p["resonance_hz"] < 2500, (name, p)


def test_load_data_checks_the_file(tmp_path):
    data = exp.load_data()
    assert len(data["t"]) == 50_001
    assert data["dt"] == pytest.approx(2e-4, rel=1e-3)
    assert data["t_jump"] == pytest.approx(3.2572, abs=1e-3)
    with pytest.raises(FileNotFoundError, match="not found"):
        exp.load_data(tmp_path / "missing.csv")
    bad = tmp_path / "bad.csv"
    bad.write_text(",0,1.0,0\n,0.0002,nan,0\n,0.0004,1.0,0\n")
    with pytest.raises(ValueError, match="displacement"):
        exp.load_data(bad)
    uneven = tmp_path / "uneven.csv"
    uneven.write_text(",0,1.0,0\n,0.0002,1.0,0\n,0.0009,1.0,0\n")
    with pytest.raises(ValueError, match="time"):
        exp.load_data(uneven)
