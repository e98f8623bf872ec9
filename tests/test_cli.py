"""The `piezojax` command line end-to-end: fit on CSV/NPZ/HDF5/.mat files, predict, simulate, bad input, Ctrl-C."""

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import fitting
import piezojax as pj
from fitting._config import parse_config
from fitting.cli import main

DT = 1e-3
ROOT = Path(__file__).resolve().parents[1]

TRUTH = dict(weights=[2.5e-8, 1.5e-8, 1.0e-8], thresholds=[8.0, 20.0, 35.0], w0=1.0e-7, k=1.25e8, tau=0.3,
             omega=2 * np.pi * 40.0, zeta=0.3)

# README example 1: PI + Kelvin–Voigt creep + 2nd-order dynamics for displacement data (initial values from data)
CONFIG = """\
[hysteresis]
kind = "prandtl_ishlinskii"
plays = 3

[creep]
kind = "kelvin_voigt"
order = 1

[dynamics]
order = 2

[fit]
weights = "range"
max_steps = 100
"""

KNOWN = f"""\
[hysteresis]
kind = "prandtl_ishlinskii"
weights = {TRUTH['weights']}
thresholds = {TRUTH['thresholds']}
w0 = {TRUTH['w0']}

[creep]
kind = "kelvin_voigt"
stiffnesses = [{TRUTH['k']}]
time_constants = [{TRUTH['tau']}]

[dynamics]
order = 2
omega = [{TRUTH['omega']}]
zeta = [{TRUTH['zeta']}]
"""


def _truth():
    return pj.Actuator(
        pj.PrandtlIshlinskii(jnp.asarray(TRUTH["weights"]), jnp.asarray(TRUTH["thresholds"]), w0=TRUTH["w0"]),
        pj.KelvinVoigtCreep(jnp.asarray([TRUTH["k"]]), jnp.asarray([TRUTH["tau"]]), k0=None),
        pj.StableTransferFunction(1.0, omega=jnp.asarray([TRUTH["omega"]]), zeta=jnp.asarray([TRUTH["zeta"]])),
    )


def _experiment(i, n, f, noise, name):
    rng = np.random.default_rng(i)
    t = np.arange(n) * DT
    v = (30 + 10 * i) * np.sin(2 * np.pi * f * t) * np.minimum(1, t / 0.2) + 10 * np.sin(2 * np.pi * 3.1 * f * t)
    y = np.asarray(_truth().simulate(jnp.asarray(v), DT).displacement)
    return fitting.Experiment.from_arrays(t=t, v_in=v, displacement=y + noise * rng.standard_normal(n), name=name)


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    files = []
    for i, (suffix, f) in enumerate([(".csv", 2.0), (".npz", 3.0), (".h5", 1.5), (".mat", 2.5)]):
        p = d / f"run{i}{suffix}"
        fitting.save_experiment(_experiment(i, 1500, f, 1e-9, p.stem), p)
        files.append(str(p))
    fitting.save_experiment(_experiment(4, 1500, 1.7, 1e-9, "heldout"), d / "heldout.csv")
    (d / "pi_creep.toml").write_text(CONFIG)
    (d / "known.toml").write_text(KNOWN)
    return d, files


@pytest.fixture(scope="module")
def fitted(work):
    d, files = work
    out = d / "fit"
    rc = main(["fit", str(d / "pi_creep.toml"), *files, "--out", str(out), "--quiet"])
    return rc, out


def test_fit_writes_complete_folder_and_recovers_truth(fitted, work):
    rc, out = fitted
    assert rc == 0
    for name in ("result.json", "model.eqx", "config.toml", "report.txt", "timeseries_run0.png", "loops_run3.png"):
        assert (out / name).is_file(), name
    assert (out / "config.toml").read_text() == CONFIG
    res = json.loads((out / "result.json").read_text())
    assert res["success"] is True and res["code"] == "successful"
    assert set(res["metrics"]) == {"run0", "run1", "run2", "run3"}  # one entry per file, any format
    for m in res["metrics"].values():
        assert set(m) == {"displacement"}
        assert m["displacement"]["rmse"] < 1.5e-9  # the noise level (1e-9)
        assert 0.9 < m["displacement"]["rmse_over_noise"] < 1.1  # the model explains the data to their noise
    assert res["lack_of_fit"] is None
    p = res["parameters"]
    assert all(np.isfinite(v["std_error"]) and v["std_error"] > 0 for v in p.values())
    expect = {
        **{f"hysteresis.thresholds[{i}]": r for i, r in enumerate(TRUTH["thresholds"])},
        **{f"hysteresis.weights[{i}]": w for i, w in enumerate(TRUTH["weights"])},
        "hysteresis.w0": TRUTH["w0"], "creep.stiffnesses[0]": TRUTH["k"], "creep.time_constants[0]": TRUTH["tau"],
        "dynamics.omega[0]": TRUTH["omega"], "dynamics.zeta[0]": TRUTH["zeta"],
    }
    for name, value in expect.items():
        assert abs(p[name]["value"] / value - 1) < 0.02, (name, p[name]["value"], value)
    assert res["cli"]["targets"] == ["displacement"] and len(res["cli"]["data"]) == 4
    # where the command's time went: its phases, compilation taken out of each, adding up to the whole
    t = res["timings"]
    assert list(t) == ["imports", "read", "starts", "steps", "write", "compile", "other", "total"]
    assert all(v >= 0 for v in t.values()) and t["steps"] > 0 and t["compile"] > 0 and t["write"] > 0
    assert sum(v for k, v in t.items() if k != "total") == pytest.approx(t["total"], abs=0.01)
    assert t["steps"] + t["compile"] <= t["total"]


def _without_times(value):
    """`value` (parsed JSON) without its wall-clock times."""
    if isinstance(value, dict):
        return {k: _without_times(v) for k, v in value.items()
                if k not in ("seconds", "piezojax_version", "timings")}
    if isinstance(value, list):
        return [_without_times(v) for v in value]
    return value


def test_the_library_pipeline_writes_what_the_command_writes(fitted, work, tmp_path):
    """`fitting.calibrate` + `Calibration.save` is `piezojax fit`: the same result.json (times aside), model.eqx,
    report.txt and config.toml, from the same files."""
    rc, out = fitted
    d, files = work
    cal = fitting.calibrate(str(d / "pi_creep.toml"), fitting.Dataset.from_files(files), progress=False)
    assert cal.result.success and rc == 0
    mine = cal.save(tmp_path / "lib", data=files)
    command, library = (json.loads((f / "result.json").read_text()) for f in (out, mine))
    assert _without_times(command) == _without_times(library)
    for name in ("model.eqx", "config.toml", ".piezojax"):
        assert (out / name).read_bytes() == (mine / name).read_bytes(), name
    seconds = re.compile(r", [0-9.]+ s, ")  # the report's time of the fit
    assert seconds.sub("", (out / "report.txt").read_text()) == seconds.sub("", (mine / "report.txt").read_text())
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in mine.iterdir())
    with pytest.raises(pj.PiezojaxValueError, match="max_steps"):
        fitting.calibrate(str(d / "pi_creep.toml"), fitting.Dataset.from_files(files), max_steps=0)


def test_fit_names_a_lack_of_fit(work, tmp_path, capsys):
    """A model without the plant's resonance cannot reach the noise: `lack_of_fit` in result.json, a line in the
    report, and, the creep's structure being left at its default, the other structure named."""
    d, files = work
    (tmp_path / "no_dynamics.toml").write_text(CONFIG.replace("[dynamics]\norder = 2\n", ""))
    capsys.readouterr()
    rc = main(["fit", str(tmp_path / "no_dynamics.toml"), *files[:2], "--out", str(tmp_path / "fit"), "--no-figures",
               "--max-steps", "1000"])
    assert rc == 0
    printed = capsys.readouterr().out
    res = json.loads((tmp_path / "fit" / "result.json").read_text())
    worst = max((m["displacement"]["rmse_over_noise"], name) for name, m in res["metrics"].items())
    assert worst[0] > 1.2
    assert res["lack_of_fit"] == {"rmse_over_noise": worst[0], "experiment": worst[1], "channel": "displacement"}
    assert f"lack of fit: the RMSE is {worst[0]:.2f}x the measurement noise in {worst[1]} (displacement" in printed
    assert 'structure = "series"' in printed
    assert res["cli"]["hints"] and 'structure = \"series\"' in res["cli"]["hints"][0]
    assert (tmp_path / "fit" / "report.txt").read_text().strip() == printed.strip()  # the hint included
    assert (tmp_path / "fit" / "report.txt").read_text().count("lack of fit:") == 1  # said once
    # held out, a record that continues the misfit is named
    rc = main(["predict", str(tmp_path / "fit"), files[2], "--out", str(tmp_path / "pred")])
    assert rc == 0 and "above the noise: the model misses part of this record's displacement" in capsys.readouterr().out


def test_error_metrics_noise_level(rng):
    """`error_metrics`' noise level: the white noise of a smooth measured signal within a few per cent, and its
    ratio to the RMSE; none (None, JSON null) for a record without noise."""
    t = np.arange(20000) * 1e-4
    clean = 3e-6 * np.sin(2 * np.pi * 2 * t) + 1e-6 * np.sign(np.sin(2 * np.pi * 0.7 * t))  # smooth, with steps
    measured = clean + 2e-9 * rng.standard_normal(t.size)
    m = fitting.error_metrics(clean, measured)
    assert m["noise"] == pytest.approx(2e-9, rel=0.05)
    assert m["rmse_over_noise"] == pytest.approx(m["rmse"] / m["noise"], rel=1e-12)
    assert 0.95 < m["rmse_over_noise"] < 1.05
    off = fitting.error_metrics(clean + 1e-8, measured)
    assert off["rmse_over_noise"] > 4
    d2 = np.diff(measured, 2)  # order 2: the second differences' MAD over sqrt(6)
    assert fitting.estimate_noise_std(measured, order=2) == pytest.approx(
        np.median(np.abs(d2 - np.median(d2))) / (0.6745 * np.sqrt(6.0)), rel=1e-12)
    with pytest.raises(pj.PiezojaxValueError, match="order"):
        fitting.estimate_noise_std(measured, order=0)
    noiseless = fitting.error_metrics(clean + 1e-8, clean)  # rounding only
    assert noiseless["noise"] < 1e-15 and noiseless["rmse_over_noise"] is None


def test_lack_of_fit_judges_long_finite_ratios():
    """`lack_of_fit`: the worst finite ratio over records of 1000 samples or more; a NaN (a failed prediction), a
    record without noise (None) or a short record neither hides nor makes one."""
    from fitting._results import lack_of_fit

    def m(ratio, samples=5000):
        return {"rmse_over_noise": ratio, "samples": samples}

    assert lack_of_fit({"a": {"displacement": m(1.1)}}) is None
    assert lack_of_fit({"a": {"displacement": m(float("nan"))}, "b": {"displacement": m(1.5)},
                        "c": {"displacement": m(None)}}) == (1.5, "b", "displacement")
    assert lack_of_fit({"a": {"displacement": m(9.0, samples=200)}, "b": {"force": m(1.3)}}) == (1.3, "b", "force")
    assert lack_of_fit({}) is None


def test_predict_matches_direct_api(fitted, work, capsys):
    rc, out = fitted
    d, _ = work
    pred_dir = d / "pred"
    capsys.readouterr()
    assert main(["predict", str(out), str(d / "heldout.csv"), "--out", str(pred_dir)]) == 0
    printed = capsys.readouterr().out
    # the same numbers by the Python API: rebuild the structure from the saved config, load the fitted values
    model = fitting.load_model(out, like=parse_config((out / "config.toml").read_text()).build(None))
    exp = fitting.load_experiment(d / "heldout.csv")
    y = np.asarray(model.simulate(jnp.asarray(exp.v_in), exp.dt).displacement)
    direct = fitting.error_metrics(y, exp["displacement"])
    got = json.loads((pred_dir / "metrics.json").read_text())["metrics"]["heldout"]["displacement"]
    for k in ("rmse", "nrmse_percent", "max_error_percent"):
        assert got[k] == pytest.approx(direct[k], rel=1e-9)
    assert f"RMSE {direct['rmse']:.6e}" in printed and f"NRMSE {direct['nrmse_percent']:.4f} %" in printed
    assert got["rmse_over_noise"] == pytest.approx(direct["rmse_over_noise"], rel=1e-9)
    assert f"{direct['rmse_over_noise']:.2f}x the noise" in printed
    written = fitting.load_experiment(pred_dir / "heldout.csv")
    np.testing.assert_array_equal(written.t, exp.t)
    np.testing.assert_allclose(written["displacement"], y, rtol=1e-15, atol=0)
    assert direct["nrmse_percent"] < 0.05  # held out: the fitted model generalises


def test_predict_warm_up_estimates_the_records_offset_and_prehistory(fitted, work, capsys):
    # a record from another occasion: the sensor's zero moved by 0.2 um and the actuator was left at the remanent
    # state of an excursion to -25 V (between two plays' thresholds, so the state identifies the excursion)
    rc, out = fitted
    d, _ = work
    rng = np.random.default_rng(7)
    n = 1500
    t = np.arange(n) * DT
    v = 40 * np.sin(2 * np.pi * 1.7 * t) * np.minimum(1, t / 0.2) + 10 * np.sin(2 * np.pi * 5.3 * t)
    truth = eqx.tree_at(lambda a: (a.offset, a.prehistory), _truth(), (jnp.asarray(2e-7), jnp.asarray(-25.0)),
                        is_leaf=lambda x: x is None)
    y = np.asarray(truth.simulate(jnp.asarray(v), DT).displacement) + 1e-9 * rng.standard_normal(n)
    fitting.save_experiment(fitting.Experiment.from_arrays(t=t, v_in=v, displacement=y, name="day2"), d / "day2.csv")
    capsys.readouterr()
    plain, warmed = d / "pred_plain", d / "pred_warm"
    assert main(["predict", str(out), str(d / "day2.csv"), "--out", str(plain)]) == 0
    assert main(["predict", str(out), str(d / "day2.csv"), "--warm-up", "0.4", "--out", str(warmed)]) == 0
    before = json.loads((plain / "metrics.json").read_text())
    after = json.loads((warmed / "metrics.json").read_text())
    assert before["warm_up"] is None
    assert before["metrics"]["day2"]["displacement"]["rmse_over_noise"] > 50  # the offset dominates
    est = after["warm_up"]["records"]["day2"]
    assert after["warm_up"]["seconds"] == 0.4 and est["samples"] == 400
    assert est["offsets"]["displacement"] == pytest.approx(2e-7, abs=5e-9)
    assert est["prehistory"] == pytest.approx(-25.0, abs=1.0)
    assert after["metrics"]["day2"]["displacement"]["rmse_over_noise"] < 1.5  # scored after the window only
    # the same numbers from the library
    fit = fitting.load_fit(out)
    w = fitting.warm_up(fit.model, fitting.load_experiment(d / "day2.csv"), 0.4, predictor=fit.config.predictor())
    assert w.prehistory == pytest.approx(est["prehistory"], rel=1e-12) and w.scored.sum() == n - 400
    written = fitting.load_experiment(warmed / "day2.csv")
    np.testing.assert_allclose(written["displacement"], w.predictions["displacement"], rtol=1e-14, atol=1e-20)
    # a window that leaves nothing to score: one line, exit 2, nothing written
    capsys.readouterr()
    assert main(["predict", str(out), str(d / "day2.csv"), "--warm-up", "1.5", "--out", str(d / "p3")]) == 2
    err = capsys.readouterr().err
    assert "warm-up of 1.5 s" in err and "leaves 0" in err and not (d / "p3").exists()
    with pytest.raises(pj.PiezojaxValueError, match="seconds > 0"):
        fitting.warm_up(fit.model, fitting.load_experiment(d / "day2.csv"), -1.0)


def test_simulate_with_given_parameters(work):
    d, _ = work
    out = d / "sim.npz"
    assert main(["simulate", str(d / "known.toml"), "--input", str(d / "heldout.csv"), "--out", str(out)]) == 0
    sim = fitting.load_experiment(out)
    exp = fitting.load_experiment(d / "heldout.csv")
    truth = np.asarray(_truth().simulate(jnp.asarray(exp.v_in), DT).displacement)
    np.testing.assert_allclose(sim["displacement"], truth, rtol=1e-12, atol=1e-20)


def test_self_sensing_config_builds_the_paper_001_observer(work):
    # README example 2: the observer with PI + Kelvin–Voigt charge operators; simulate against the direct API
    d, _ = work
    cfg_text = """\
[observer]
kind = "current_integration"
integrator_capacitance = 10e-9
reference_capacitance = 1.5e-9
leakage_resistance = 1e11
bias_current = 1e-14
force_sensitivity = 1.03e-6
displacement_coefficient = -4.05e-3
stiffness = 150.0
filter_cutoff = 10.0

[hysteresis]
kind = "prandtl_ishlinskii"
weights = [1e-10, 5e-11]
thresholds = [2.0, 6.0]
w0 = 1.6e-9

[creep]
kind = "kelvin_voigt"
stiffnesses = [2.9e10]
time_constants = [10.0]

[fit]
weights = {displacement = 1e6, force = 1e3}
"""
    cfg = parse_config(cfg_text, "selfsensing.toml")
    assert cfg.outputs == ("displacement", "force") and cfg.inputs == ("v_out",)
    assert cfg.default_free() == ("hysteresis.weights", "hysteresis.thresholds", "hysteresis.w0", "creep.stiffnesses",
                                  "creep.time_constants", "force_sensitivity", "displacement_coefficient", "stiffness")
    (d / "selfsensing.toml").write_text(cfg_text)
    n = 800
    t = np.arange(n) * DT
    v = -20 * np.sin(np.pi * t / 0.8) ** 2
    v_out = 0.1 * np.sin(2 * np.pi * 3 * t) - 0.01 * v
    fitting.save_experiment(fitting.Experiment.from_arrays(t=t, v_in=v, v_out=v_out, name="rec"), d / "rec.h5")
    assert main(["simulate", str(d / "selfsensing.toml"), "--input", str(d / "rec.h5"), "--out",
                 str(d / "est.csv")]) == 0
    est = fitting.load_experiment(d / "est.csv")
    obs = pj.ForceDisplacementObserver(
        10e-9, 1.5e-9, 1e11, 1e-14, 1.03e-6, -4.05e-3, 150.0,
        hysteresis=pj.PrandtlIshlinskii(jnp.asarray([1e-10, 5e-11]), jnp.asarray([2.0, 6.0]), w0=1.6e-9),
        creep=pj.KelvinVoigtCreep(jnp.asarray([2.9e10]), jnp.asarray([10.0]), k0=None), filter_cutoff=10.0)
    direct = obs(jnp.asarray(v), jnp.asarray(v_out), DT)
    np.testing.assert_allclose(est["force"], np.asarray(direct.force), rtol=1e-12, atol=1e-18)
    np.testing.assert_allclose(est["displacement"], np.asarray(direct.displacement), rtol=1e-12, atol=1e-20)


# ---------------------------------------------------------------------------------------------- bad input


def _write_csv(path, header, cols):
    np.savetxt(path, np.column_stack(cols), delimiter=",", header=",".join(header), comments="")


def _bad_cases(d):
    t = np.arange(500) * DT
    v = 30 * np.sin(2 * np.pi * 2 * t)
    x = 1e-8 * v
    _write_csv(d / "nocol.csv", ["t", "displacement"], [t, x])
    t2 = t.copy()
    t2[200:] += 0.3 * DT
    _write_csv(d / "nonuniform.csv", ["t", "v_in", "displacement"], [t2, v, x])
    _write_csv(d / "nan.csv", ["t", "v_in", "displacement"], [t, v, np.where(np.arange(500) == 17, np.nan, x)])
    _write_csv(d / "ok.csv", ["t", "v_in", "displacement"], [t, v, x])
    (d / "badkind.toml").write_text('[hysteresis]\nkind = "stop"\nplays = 3\n')
    (d / "badtable.toml").write_text('[hysteresis]\nkind = "prandtl_ishlinskii"\n[motor]\norder = 2\n')
    (d / "badkey.toml").write_text('[creep]\nkind = "kelvin_voigt"\norder = 1\ntau = [1.0]\n')
    (d / "badorder.toml").write_text('[dynamics]\norder = 9\n')
    (d / "afile").write_text("not a folder\n")
    cfg = str(d / "pi_creep.toml")
    ok = str(d / "ok.csv")
    return {
        "missing column": (["fit", cfg, str(d / "nocol.csv")], "required column(s) ['v_in'] missing"),
        "non-uniform t": (["fit", cfg, str(d / "nonuniform.csv")], "not uniformly sampled"),
        "NaN": (["fit", cfg, str(d / "nan.csv")], "line 19, column 'displacement' holds a non-finite value (nan)"),
        "unknown block kind": (["fit", str(d / "badkind.toml"), ok], "unknown kind 'stop'; allowed kinds"),
        "unknown table": (["fit", str(d / "badtable.toml"), ok], "unknown table or key [motor]"),
        "unknown key": (["fit", str(d / "badkey.toml"), ok], "unknown key 'tau'"),
        "bad order": (["fit", str(d / "badorder.toml"), ok], "order: must be one of 0, 1, 2, 3, 4"),
        "missing data file": (["fit", cfg, str(d / "absent.csv")], "does not exist"),
        "simulate without values": (["simulate", cfg, "--input", ok], "missing: [hysteresis] weights"),
        "predict from a non-fit folder": (["predict", str(d), ok], "is not a folder written by `piezojax fit`"),
    }


@pytest.mark.parametrize("case", ["missing column", "non-uniform t", "NaN", "unknown block kind", "unknown table",
                                  "unknown key", "bad order", "missing data file", "simulate without values",
                                  "predict from a non-fit folder", "unwritable output", "output parent missing",
                                  "output exists"])
def test_bad_input_is_one_line_and_writes_nothing(work, capsys, case):
    d, files = work
    cases = _bad_cases(d)
    if case in cases:
        argv, expected = cases[case]
        out = d / "out_bad.csv" if argv[0] == "simulate" else d / "out_bad"
        argv = argv + ["--out", str(out)]
    else:
        out = {"unwritable output": d / "afile" / "sub", "output parent missing": d / "nowhere" / "sub",
               "output exists": d / "existing_out"}[case]
        (d / "existing_out").mkdir(exist_ok=True)
        (d / "existing_out" / "notes.txt").write_text("not empty\n")  # an empty folder is replaced
        expected = {"unwritable output": "is not a directory", "output parent missing": "does not exist",
                    "output exists": "which already exists: it has no piezojax marker"}[case]
        argv = ["fit", str(d / "pi_creep.toml"), files[0], "--out", str(out)]
    capsys.readouterr()
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("piezojax: error: "), err
    assert expected in lines[0], lines[0]
    assert "Traceback" not in err
    if case != "output exists":
        assert not out.exists()
    assert not list(d.glob(".out_bad*")) and not list(d.glob(".*tmp-*"))  # no temporary left behind


# ---------------------------------------------------------------------------------------------- real processes


def _script():
    exe = shutil.which("piezojax")
    return [exe] if exe else [sys.executable, "-m", "fitting.cli"]


def test_console_script_help_and_error(work, capsys):
    d, _ = work
    _bad_cases(d)  # writes badkind.toml and ok.csv (this test may run before, or apart from, the bad-input ones)
    r = subprocess.run([*_script(), "--help"], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 0
    for word in ("fit", "predict", "simulate", "[hysteresis]", "prandtl_ishlinskii", "[observer]", "[fit]"):
        assert word in r.stdout
    r = subprocess.run([*_script(), "fit", str(d / "badkind.toml"), str(d / "ok.csv"), "--out", str(d / "o")],
                       capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        f"piezojax: error: {d / 'badkind.toml'}: [hysteresis] kind: unknown kind 'stop'; allowed kinds: "
        "prandtl_ishlinskii, play, bouc_wen, maxwell_slip, preisach, none"
    ]
    assert not (d / "o").exists()
    # the same parser in-process: per-command help with examples, one-line usage errors
    for cmd, words in (("fit", ("--out DIR", "--overwrite", "--max-steps", "examples:", "result.json")),
                       ("predict", ("--out OUT", "examples:", "metrics.json")),
                       ("simulate", ("--input FILE", "examples:", "every parameter value"))):
        assert main([cmd, "--help"]) == 0
        help_text = capsys.readouterr().out
        assert all(w in help_text for w in words), (cmd, help_text)
    assert main(["fit", str(d / "pi_creep.toml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("piezojax fit: error: the following arguments are required")
    assert main(["calibrate"]) == 2
    assert "invalid choice: 'calibrate'" in capsys.readouterr().err


def test_ctrl_c_leaves_no_folder_or_a_complete_one(work):
    d, _ = work
    # a long record so that each step takes a while; SIGINT as soon as the first step is reported
    n = 200_000
    t = np.arange(n) * DT
    v = 40 * np.sin(2 * np.pi * 0.7 * t) + 15 * np.sin(2 * np.pi * 3.3 * t)
    y = np.asarray(_truth().simulate(jnp.asarray(v), DT).displacement)
    fitting.save_experiment(fitting.Experiment.from_arrays(t=t, v_in=v, displacement=y, name="long"), d / "long.npz")
    (d / "small.toml").write_text('[hysteresis]\nkind = "prandtl_ishlinskii"\nplays = 2\n[fit]\nmax_steps = 100000\n')
    out = d / "interrupted"
    proc = subprocess.Popen([sys.executable, "-m", "fitting.cli", "fit", str(d / "small.toml"), str(d / "long.npz"),
                             "--out", str(out), "--no-figures"], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    seen = b""
    deadline = time.monotonic() + 300
    try:
        while not re.search(rb"step +\d+ +(best )?cost", seen):  # the first Levenberg–Marquardt step is done
            chunk = os.read(proc.stderr.fileno(), 4096)
            assert chunk, f"process ended before any progress: {seen.decode()}"
            seen += chunk
            assert time.monotonic() < deadline, "no progress within 300 s"
        proc.send_signal(signal.SIGINT)
        _, rest = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    err = (seen + rest).decode()
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    # interrupted inside the Levenberg–Marquardt loop: the last accepted parameters are saved, complete; an
    # interrupt that lands while the first result is being summarised or written leaves nothing
    if out.exists():  # complete: every file, and a summary that says it was interrupted
        for name in ("result.json", "model.eqx", "config.toml", "report.txt"):
            assert (out / name).is_file()
        assert json.loads((out / "result.json").read_text())["code"] == "interrupted"
    assert not list(d.glob(".interrupted*"))


# ---------------------------------------------------------------------------------------------- config parsing


@pytest.mark.parametrize("text, expected", [
    ('[hysteresis]\nkind = "prandtl_ishlinskii"\nplays = 3\nthresholds = [1.0, 2.0]\n',
     "[hysteresis] thresholds: must have 3 entries"),
    ('[hysteresis]\nkind = "prandtl_ishlinskii"\nthresholds = [2.0, 1.0]\n', "strictly ascending"),
    ('[hysteresis]\nkind = "bouc_wen"\nmethod = "closed_form"\nsmoothing = 0.1\n', "needs smoothing = 0"),
    ('[hysteresis]\nkind = "maxwell_slip"\nelements = 0\n', "[hysteresis] elements: must be >= 1"),
    ('[creep]\nkind = "kelvin_voigt"\norder = "two"\n', "[creep] order: must be an integer"),
    ('[dynamics]\norder = 2\npoles = [-1.0]\n', "[dynamics] poles: not used with order = 2"),
    ('[dynamics]\norder = 1\npoles = [1.0]\n', "entries must be < 0"),
    ('[observer]\nkind = "current_integration"\nstiffness = 1.0\n', "missing key(s) integrator_capacitance"),
    ('[observer]\nkind = "luenberger"\n', "unknown kind 'luenberger'; allowed kinds: current_integration"),
    ('[dynamics]\norder = 2\n[fit]\nweights = "max"\n', "[fit] weights: unknown value 'max'"),
    ('[dynamics]\norder = 2\n[fit]\nweights = {strain = 1.0}\n', "unknown channel 'strain'"),
    ('[dynamics]\norder = 2\n[fit]\ntargets = ["force"]\n', "the model does not predict 'force'"),
    ('[dynamics]\norder = 2\n[fit]\nsmoothing = [0.1]\n', "needs a hysteresis block"),
    ('[fit]\nmax_steps = 10\n', "no model blocks"),
    ('[dynamics]\norder = 2\n[fit]\nmethod = "bfgs"\n', "[fit] method: unknown value 'bfgs'"),
    ('hysteresis = 3\n', "hysteresis must be a table"),
    ('[hysteresis]\nkind = "prandtl_ishlinskii"\npolynomial = 1\n', "[hysteresis] polynomial: the output polynomial's"),
    ('[hysteresis]\nkind = "prandtl_ishlinskii"\npolynomial = 7\n', "[hysteresis] polynomial: must be <= 6"),
    ('[hysteresis]\nkind = "prandtl_ishlinskii"\npolynomial = 3\ncoefficients = [0.1]\n',
     "[hysteresis] coefficients: must have 2 entries"),
    ('[hysteresis]\nkind = "prandtl_ishlinskii"\ncoefficients = [0.1]\n', "[hysteresis] coefficients: needs an output"),
    ('[hysteresis]\nkind = "prandtl_ishlinskii"\n[creep]\nkind = "lag"\nlags = 2\nfractions = [0.6, 0.5]\n',
     "[creep] fractions: the fractions must add up to less than 1"),
    ('[hysteresis]\nkind = "prandtl_ishlinskii"\n[creep]\nkind = "lag"\nstructure = "parallel"\n',
     "[creep] structure: a 'lag' creep is DC-normalised"),
    ('[creep]\nkind = "kelvin_voigt"\nstructure = "diagonal"\n', "[creep] structure: unknown value 'diagonal'"),
    ('[dynamics]\norder = 2\n[state]\nprehistory = true\n', "[state] prehistory: a prehistory sets the"),
    ('[hysteresis]\nkind = "prandtl_ishlinskii"\n[state]\noffset = "yes"\n', "[state] offset: must be true"),
    ('[hysteresis]\nkind = "prandtl_ishlinskii"\n[state]\nremanence = 1.0\n',
     "[state]: unknown key 'remanence'; allowed keys: offset, prehistory"),
    ('[dynamics]\norder = 2\n[fit]\nfree = ["dynamics.poles"]\n',
     "[fit] free: 'dynamics.poles' has no entries in this model (its sizes come from the block tables); the model's "
     "parameters with entries: dynamics.gain, dynamics.omega, dynamics.zeta, offset"),
    ('[dynamics]\norder = 2\n[fit]\nfree = ["dynamics.zeta", "capacitance"]\n',
     "[fit] free: 'capacitance' acts only on the charge and current, which this model does not predict: add a "
     "[charge] table"),
    ('[dynamics]\norder = 2\n[fit]\nfree = ["dynamics.bogus"]\n',
     "[fit] free: unknown parameter path 'dynamics.bogus'; the model's parameters: dynamics.gain, dynamics.omega, "
     "dynamics.zeta, dynamics.poles, dynamics.zeros, dynamics.zero_omega, dynamics.zero_zeta, offset"),
])
def test_config_errors_name_table_key_and_allowed_values(text, expected):
    with pytest.raises(pj.PiezojaxValueError) as e:
        parse_config(text, "m.toml")
    msg = str(e.value)
    assert msg.startswith("m.toml") and expected in msg and "\n" not in msg, msg


def test_config_defaults_and_free_sets():
    cfg = parse_config('[hysteresis]\nkind = "prandtl_ishlinskii"\n[dynamics]\norder = 3\n[charge]\n', "m.toml")
    assert cfg.hysteresis_options.plays == 10 and cfg.outputs == ("displacement", "charge", "current")
    assert cfg.default_free() == ("hysteresis.weights", "hysteresis.thresholds", "hysteresis.w0", "dynamics.omega",
                                  "dynamics.zeta", "dynamics.poles", "capacitance", "coupling", "offset")
    assert "capacitance" not in cfg.fit_free(("displacement",)) and "coupling" in cfg.fit_free(("charge",))
    model = pj.unwrap(cfg.build(None))  # placeholders of the configured shapes
    assert model.hysteresis.weights.shape == (10,) and model.dynamics.order == 3 and float(model.dynamics.gain) == 1
    bw = parse_config('[hysteresis]\nkind = "bouc_wen"\n[fit]\nsmoothing = [0.1, 0.0]\n', "m.toml")
    assert bw.hysteresis_options.method == "rk4" and "hysteresis.n" in bw.default_free()
    assert "dynamics.gain" in parse_config('[creep]\nkind = "logarithmic"\n', "m.toml").default_free()
    assert cfg.method == "levenberg_marquardt"


def test_charge_start_from_a_measured_current():
    # records with the current but not the charge: the start integrates it (q_k = dt (i_0 + ... + i_k), the model's
    # definition of the current) and finds C and T by least squares
    pi = pj.PrandtlIshlinskii(jnp.asarray([0.3e-7, 0.2e-7]), jnp.asarray([10.0, 30.0]), w0=jnp.asarray(1e-7))
    truth = pj.Actuator(pi, capacitance=2e-7, coupling=3.0)
    t = np.arange(800) * DT
    v = 50 * np.sin(2 * np.pi * 2 * t) * np.minimum(1.0, t / 0.1)
    out = truth(jnp.asarray(v), DT)
    # the displacement sensor's zero (5 um, the model's offset) enters the displacement, not the charge
    ds = fitting.Dataset([fitting.Experiment.from_arrays(t=t, v_in=v, displacement=np.asarray(out.displacement) + 5e-6,
                                                         current=np.asarray(out.current))])
    start = pj.unwrap(parse_config('[hysteresis]\nkind = "prandtl_ishlinskii"\nplays = 2\n[charge]\n', "m.toml")
                      .build(ds))
    assert float(start.capacitance) == pytest.approx(2e-7, rel=1e-6)
    assert float(start.coupling) == pytest.approx(3.0, rel=1e-6)


def test_config_state_polynomial_and_lag_creep_build_the_composed_actuator():
    text = ('[hysteresis]\nkind = "prandtl_ishlinskii"\nplays = 4\npolynomial = 3\n[creep]\nkind = "lag"\nlags = 2\n'
            '[dynamics]\norder = 2\n[state]\nprehistory = -20.0\noffset = 1e-7\n')
    cfg = parse_config(text, "m.toml")
    assert cfg.creep_structure == "series" and cfg.polynomial == 3
    assert cfg.default_free() == (
        "hysteresis.hysteresis.weights", "hysteresis.hysteresis.thresholds", "hysteresis.hysteresis.w0",
        "hysteresis.coefficients", "creep.fractions", "creep.time_constants", "dynamics.omega", "dynamics.zeta",
        "offset", "prehistory")
    model = pj.unwrap(cfg.build(None))
    assert isinstance(model.hysteresis, pj.OutputPolynomial) and isinstance(model.creep, pj.LagCreep)
    assert model.structure == "series" and float(model.prehistory) == -20.0 and float(model.offset) == 1e-7
    assert model.hysteresis.coefficients.shape == (2,) and model.creep.fractions.shape == (2,)
    # the offset is in the default model (fitted), the prehistory only when asked for; `false` removes both
    plain = parse_config('[hysteresis]\nkind = "prandtl_ishlinskii"\n', "m.toml")
    assert "offset" in plain.default_free() and pj.unwrap(plain.build(None)).prehistory is None
    off = parse_config('[hysteresis]\nkind = "prandtl_ishlinskii"\n[state]\noffset = false\n', "m.toml")
    assert "offset" not in off.default_free()
    # forward simulation needs the prehistory's value when it is `true`
    with pytest.raises(pj.PiezojaxValueError, match=r"\[state\] prehistory"):
        parse_config('[hysteresis]\nkind = "prandtl_ishlinskii"\nweights = [1.0]\nthresholds = [1.0]\nplays = 1\n'
                     'w0 = 1.0\n[state]\nprehistory = true\n', "m.toml").build(None, require_values=True)


def test_scales_taken_from_the_data_are_reported_and_needed_to_simulate(tmp_path, capsys):
    # a parallel logarithmic creep's gain and an output polynomial's scale are fixed at values from the fit's data:
    # a fit reports them, and a forward simulation refuses to guess them (the placeholder gain 1 V/V was 1e5 times
    # the scale of a real actuator's m/V)
    text = ('[hysteresis]\nkind = "prandtl_ishlinskii"\nplays = 2\npolynomial = 2\n[creep]\nkind = "logarithmic"\n'
            '[dynamics]\norder = 0\n')
    cfg = parse_config(text, "m.toml")
    assert cfg.data_derived() == ["[hysteresis] polynomial_scale", "[creep] gain"]
    # series after the hysteresis, the creep acts on the output itself: its gain is 1 by convention, not derived
    series = parse_config(text.replace('"logarithmic"', '"logarithmic"\nstructure = "series"'), "m.toml")
    assert series.data_derived() == ["[hysteresis] polynomial_scale"]
    # without hysteresis the dynamics' gain is the scale from volts to metres, started from the data (and fitted)
    alone = parse_config('[dynamics]\norder = 2\nomega = [900.0]\nzeta = [0.1]\n', "m.toml")
    assert alone.data_derived() == ["[dynamics] gain"] and alone.missing_values() == ["[dynamics] gain"]
    assert alone.derived_path("[dynamics] gain") == "dynamics.gain" and "dynamics.gain" in alone.default_free()
    # a Preisach grid's range: derived from the data's voltage when not given, recovered from the built grid
    for levels, rng in ((6, [-110.0, 95.0]), (1, [-3.0, 5.0])):
        pre = parse_config(f'[hysteresis]\nkind = "preisach"\nlevels = {levels}\n', "m.toml")
        assert pre.data_derived() == ["[hysteresis] range"] and "[hysteresis] range" in pre.missing_values()
        grid = pj.Preisach.uniform(*rng, levels)
        back = pre.derived_values(pj.Actuator(grid))["[hysteresis] range"]
        again = pj.Preisach.uniform(*back, levels)
        np.testing.assert_allclose([again.alpha, again.beta], [grid.alpha, grid.beta], rtol=0, atol=1e-12)
        if levels > 1:
            np.testing.assert_allclose(back, rng, rtol=1e-12)
    given = ('[hysteresis]\nkind = "prandtl_ishlinskii"\nplays = 1\nweights = [1e-8]\nthresholds = [5.0]\n'
             'w0 = 5e-8\npolynomial = 2\ncoefficients = [0.1]\n[creep]\nkind = "logarithmic"\ngamma = 0.01\n'
             't0 = 0.01\n')
    with pytest.raises(pj.PiezojaxValueError, match=r"missing: \[hysteresis\] polynomial_scale, \[creep\] gain.*"
                                                    r"cli\.data_derived"):
        parse_config(given, "m.toml").build(None, require_values=True)
    ok = given.replace("[creep]", "polynomial_scale = 1e-6\n[creep]") + "gain = 2e-7\n"
    model = pj.unwrap(parse_config(ok, "m.toml").build(None, require_values=True))
    assert float(model.creep.gain) == 2e-7 and float(model.hysteresis.scale) == 1e-6
    # the fit's values, in result.json and in the report
    t = np.arange(600) * DT
    v = 40 * np.sin(2 * np.pi * 2 * t)
    x = np.asarray(pj.unwrap(parse_config(ok, "m.toml").build(None))(jnp.asarray(v), DT).displacement)
    _write_csv(tmp_path / "r.csv", ["t", "v_in", "displacement"], [t, v, x])
    (tmp_path / "m.toml").write_text(text)
    out = tmp_path / "fit"
    assert main(["fit", str(tmp_path / "m.toml"), str(tmp_path / "r.csv"), "--out", str(out), "--quiet",
                 "--no-figures", "--max-steps", "3"]) in (0, 1)
    derived = json.loads((out / "result.json").read_text())["cli"]["data_derived"]
    fitted = fitting.load_model(out, like=cfg.build(None))
    assert derived == {"[hysteresis] polynomial_scale": float(fitted.hysteresis.scale),
                       "[creep] gain": float(fitted.creep.gain)}
    assert 1e-9 < derived["[creep] gain"] < 1e-6  # the data's m/V, not the placeholder 1
    report = (out / "report.txt").read_text()
    assert f"[creep] gain = {derived['[creep] gain']!r}" in report
    capsys.readouterr()


def test_config_starts_offset_and_prehistory_from_the_data():
    # a remanent actuator seen by a sensor with an offset: both starts land near the truth
    pi = pj.PrandtlIshlinskii(jnp.asarray([0.3, 0.2]), jnp.asarray([10.0, 30.0]), w0=jnp.asarray(1.0))
    truth = pj.Actuator(pi, offset=5.0, prehistory=-60.0)
    t = np.arange(600) * DT
    v = np.where(t < 0.1, 0.0, 50 * np.sin(2 * np.pi * 4 * t))
    y = np.asarray(truth(jnp.asarray(v), DT).displacement)
    ds = fitting.Dataset([fitting.Experiment.from_arrays(v_in=v, t=t, displacement=y, name="r")])
    cfg = parse_config('[hysteresis]\nkind = "prandtl_ishlinskii"\nplays = 2\nweights = [0.3, 0.2]\n'
                       'thresholds = [10.0, 30.0]\nw0 = 1.0\n[state]\nprehistory = true\n', "m.toml")
    start = pj.unwrap(cfg.build(ds))
    # the grid point nearest -60 (from -max|v| to max|v| in steps of max|v| / 4)
    assert float(start.prehistory) == pytest.approx(-np.max(np.abs(v)))
    assert float(start.offset) == pytest.approx(5.0, abs=0.5)
    assert parse_config('[dynamics]\norder = 2\n[fit]\nmethod = "trust_region"\n', "m.toml").method == "trust_region"


@pytest.mark.slow
def test_shipped_config_calibrates_the_measured_actuator(tmp_path, capsys):
    """The README's example: the shipped CONFIG on the shipped 150 V record, fitted on t < 7 s through `piezojax fit`
    and scored on 7-10 s with the first 7 s as history through `piezojax predict` (measured 0.064 um), which equals
    predicting the rest after the first part as history."""
    data = ROOT / "experiments" / "data" / "piezo_150V_1Hz" / "hysteresis_v_150_1hz.csv"
    config = ROOT / "experiments" / "configs" / "piezo_150v_pi.toml"
    fit_dir, pred_dir = tmp_path / "fit", tmp_path / "held_out"
    assert main(["fit", str(config), str(data), "--window", ":7", "--out", str(fit_dir), "--quiet",
                 "--no-figures"]) == 0  # converged (at a kink of the exact PI)
    summary = json.loads((fit_dir / "result.json").read_text())
    assert summary["cli"]["window"] == ":7" and summary["num_residuals"] == 35_000  # 5 kHz, t < 7 s
    capsys.readouterr()
    assert main(["predict", str(fit_dir), str(data), "--score-from", "7", "--out", str(pred_dir)]) == 0
    scored = json.loads((pred_dir / "metrics.json").read_text())["metrics"]["hysteresis_v_150_1hz"]["displacement"]
    assert f"RMSE {scored['rmse']:.6e}" in capsys.readouterr().out
    pred = np.genfromtxt(pred_dir / "hysteresis_v_150_1hz.csv", delimiter=",", names=True, skip_header=1)
    raw = np.genfromtxt(data, delimiter=",")
    held = raw[:, 1] >= 7.0
    np.testing.assert_allclose(pred["t"], raw[:, 1], atol=1e-6)  # the file rounds its stamps
    # scored here from the raw file (µm), independently of the command's own metric
    rmse_um = 1e6 * np.sqrt(np.mean((pred["displacement"][held] - 1e-6 * raw[held, 2]) ** 2))
    assert scored["samples"] == held.sum() and scored["rmse"] == pytest.approx(1e-6 * rmse_um, rel=1e-6)
    assert rmse_um <= 0.065, rmse_um


def test_timings_take_compilation_out_of_each_phase_once():
    """`fitting._timing.Timings`: overlapping compilation spans (a trace inside a trace) count once, inside a phase
    they are taken out of it, and the phases, `compile` and `other` add up to the whole; a jitted function's first
    call is seen as compilation."""
    import jax
    import jax.numpy as jnp

    from fitting._timing import Timings, phase

    t = Timings(start=100.0)
    t.end = 120.0
    t.add("read", 100.0, 102.0)
    t.add("steps", 105.0, 115.0)
    t.compile_spans += [(106.0, 109.0), (107.0, 108.0), (114.0, 116.0)]  # nested, and past the end of `steps`
    s = t.summary()
    assert s["read"] == 2.0 and s["compile"] == 5.0 and s["steps"] == 10.0 - 4.0
    assert s["other"] == pytest.approx(20.0 - 2.0 - 6.0 - 5.0) and s["total"] == 20.0
    with Timings() as live:
        with phase("steps"):
            jax.jit(lambda x: jnp.sin(x) * 2.5 + 0.125)(jnp.arange(7.0)).block_until_ready()
    assert live.compile_spans and live.summary()["compile"] > 0
