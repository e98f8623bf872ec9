"""The main command (`python -m experiments.calibrate`) in quick mode, and the staged identification's input checks."""

import json

import numpy as np
import pytest

import fitting
import piezojax as pj
from experiments import calibrate
from piezojax._checks import PiezojaxValueError


def test_calibrate_quick(tmp_path, capsys):
    out = tmp_path / "cal"
    assert calibrate.main(["--quick", "--max-steps", "3", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "force error band" in printed and "displacement RMSE" in printed
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["staged"]) == {"heldout_paper_drive", "heldout_5_15V", "heldout_triangle"}
    for method in ("staged", "joint"):
        for name, r in summary[method].items():
            band = (r["force"]["min_percent"], r["force"]["max_percent"])
            # both observers are usable: errors of a few % of the 1.1 mN maximum force, not tens
            assert -15 < band[0] < 0 < band[1] < 15, (method, name, band)
            assert 0.5e-3 < r["force"]["max_force"] < 1.3e-3  # 1.15 mN at -20 V (paper), less at -15 V
            assert np.isfinite(r["displacement"]["rmse_percent"])
    fit = summary["joint_fit"]
    assert fit["cost"] < fit["initial_cost"] and fit["steps"] == 3
    assert "filter_cutoff" in fit["parameters"]
    # the joint fit improves on the staged one where it was trained (the paper's drive, new noise)
    s, j = summary["staged"]["heldout_paper_drive"], summary["joint"]["heldout_paper_drive"]
    assert j["force"]["rmse_percent"] < s["force"]["rmse_percent"]
    for f in ("table.txt", "report.txt", "heldout_estimates.png", "heldout_force_error.png", "joint/model.eqx",
              "joint/result.json"):
        assert (out / f).exists(), f
    assert [p.name for p in tmp_path.iterdir()] == ["cal"]  # no temporary folder left


def test_staged_needs_v_out():
    exp = fitting.Experiment.from_arrays(dt=1e-3, v_in=np.zeros(100), name="no_vout", displacement=np.zeros(100))
    with pytest.raises(PiezojaxValueError, match="no_vout.*v_out"):
        fitting.staged_ivan2009(pj.IvanBench().observer(), exp, exp)
