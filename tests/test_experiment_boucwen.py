"""`python -m experiments.boucwen_benchmark --quick --test FILE` end to end, and its fitting problem."""

import json

import h5py
import jax.numpy as jnp
import numpy as np
import pytest

import fitting
import piezojax as pj
from experiments import _command as exp_command, boucwen_benchmark as exp

FS = 750.0
DT = 1 / FS

needs_data = pytest.mark.skipif(not exp.DATA.exists(), reason=f"benchmark data not found: {exp.DATA}")


# ---------------------------------------------------------------------------------------------------------------
# The fitting problem (the simulator itself, `BoucWenOscillator.simulate(method="rk4")`, is tested with the model).


@needs_data
def test_problem_jacobian_matches_finite_differences():
    """The Jacobian the fit uses (forward mode through the predictor, `pj.Positive` and RK4) against central
    differences of the residuals, in the problem's scaled parameters, on 300 samples with 2 sub-steps."""
    d = exp.load_train()
    data = fitting.Dataset([fitting.Experiment.from_arrays(v_in=d["u"][:300], dt=DT, displacement=d["y"][:300])])
    model = exp.oscillator(1.8, 40.0, 5.5e4, 5.5e4, 1500.0, 0.4, -0.3)
    problem = fitting.Problem(model, data, predictor=exp.periodic_response(2, 100), free=list(exp.FREE),
                              scales="value")
    assert problem.parameter_names() == list(exp.FREE)
    u = problem.u0 * jnp.array([1.02, 1.1, 0.98, 1.01, 1.3, 0.8])
    jac = np.asarray(problem.jacobian_t(u)).T
    eps = 1e-6
    for i in range(u.shape[0]):
        e = jnp.zeros(u.shape[0]).at[i].set(eps)
        fd = (np.asarray(problem.residuals(u + e)) - np.asarray(problem.residuals(u - e))) / (2 * eps)
        np.testing.assert_allclose(jac[:, i], fd, rtol=1e-4, atol=1e-6 * np.max(np.abs(fd)))


def test_periodic_response_warmup():
    """The predictor's warm-up: the periodic input from rest `warmup` samples before the record's first sample,
    i.e. samples -warmup..-1 (of the periodic continuation) drive the model first; only the record is returned."""
    n = 200
    t = np.arange(n) * DT
    u = 30 * np.sin(2 * np.pi * 3 * FS / n * t) + 20 * np.cos(2 * np.pi * 11 * FS / n * t)
    bw = pj.BoucWenOscillator(**exp.NOMINAL)
    data = fitting.ExperimentArrays(t=jnp.asarray(t), dt=jnp.asarray(DT), v_in=jnp.asarray(u), channels={})
    scale = np.abs(exp.simulate(bw, u, FS, 2)).max()
    for warmup in (0, n, 2 * n, 50):
        shifted = np.concatenate([u[n - warmup % n :], u[: n - warmup % n]])  # starts at sample -warmup
        ref = exp.simulate(bw, np.tile(shifted, 3), FS, 2)[warmup : warmup + n]
        y = np.asarray(exp.periodic_response(2, warmup)(bw, data)["displacement"])
        np.testing.assert_allclose(y, ref, rtol=0, atol=1e-12 * scale, err_msg=f"warmup {warmup}")


# ---------------------------------------------------------------------------------------------------------------
# Data handling and the linear start.


@needs_data
def test_linear_start_and_noise_level():
    """The linear fit sees the total small-amplitude stiffness (~k + alpha), and the noise estimate is the data's."""
    d = exp.load_train()
    y_avg = np.mean([d["y"][p * exp.PERIOD : (p + 1) * exp.PERIOD] for p in exp.FIT_PERIODS], axis=0)
    lin = exp.linear_fit(d["u"][: exp.PERIOD], y_avg, d["fs"])
    assert 1.0 < lin["m"] < 4.0 and 0 < lin["c"] and 5e4 < lin["k"] < 2e5, lin
    assert 4 < lin["band_hz"][0] < 6 and 149 < lin["band_hz"][1] < 151
    assert 6e-6 < exp.noise_level(d["y"]) < 9e-6


def test_file_errors(tmp_path):
    """Missing file, group or dataset, and NaN: one line naming the file and what is missing."""
    with pytest.raises(exp.BenchmarkFileError, match="file not found"):
        exp.read_group(tmp_path / "none.h5", "multisine")
    path = tmp_path / "t.h5"
    with h5py.File(path, "w") as f:
        f["other/u"] = np.zeros(4)
    with pytest.raises(exp.BenchmarkFileError, match="neither group 'multisine' nor 'sinesweep'"):
        exp.load_test(path)
    with h5py.File(path, "w") as f:
        f["multisine/u"] = np.zeros((8, 1))
    with pytest.raises(exp.BenchmarkFileError, match="'multisine' has no dataset 'y'"):
        exp.load_test(path)
    with h5py.File(path, "w") as f:
        f["sinesweep/u"] = np.zeros(8)
        f["sinesweep/y"] = np.zeros(7)
    with pytest.raises(exp.BenchmarkFileError, match="'sinesweep/y' has 7 samples"):
        exp.load_test(path)
    with h5py.File(path, "w") as f:
        f["sinesweep/u"] = np.zeros(8)
        f["sinesweep/y"] = np.full(8, np.nan)
    with pytest.raises(exp.BenchmarkFileError, match="NaN"):
        exp.load_test(path)
    # the command line turns it into one error line (before any fitting)
    with h5py.File(path, "w") as f:
        f["other/u"] = np.zeros(4)
    with pytest.raises(exp.BenchmarkFileError, match=r"t\.h5: neither group") as info:
        exp.main(["--test", str(path), "--out", str(tmp_path / "out")])
    assert "\n" not in str(info.value)
    assert not (tmp_path / "out").exists()
    code = exp_command.run(lambda: exp.main(["--test", str(path), "--out", str(tmp_path / "out")]), "boucwen")
    assert code == 2 and not (tmp_path / "out").exists()


# ---------------------------------------------------------------------------------------------------------------
# End to end.


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    if not exp.DATA.exists():
        pytest.skip(f"benchmark data not found: {exp.DATA}")
    folder = tmp_path_factory.mktemp("boucwen")
    test_file = folder / "test.h5"
    # A synthetic test file (nominal parameters, diffrax adaptive, noise 7.3e-6 m); a short sweep keeps it fast.
    exp.make_synthetic_test(test_file, sweep_samples=1500)
    out = folder / "results"
    report = exp.main(["--quick", "--test", str(test_file), "--out", str(out)])
    return out, report, test_file


def test_quick_run_outputs(quick_run):
    out, report, _ = quick_run
    scores = json.loads((out / "test_rmse.json").read_text())
    assert set(scores) == {"multisine_rmse", "sinesweep_rmse"}
    assert (out / "validation.png").stat().st_size > 10_000
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["quick"] is True
    assert metrics["test"] == scores
    assert metrics["metrics"]["validation_samples"] == "32768..40959"
    assert metrics["metrics"]["train_samples"] == "8192..32767"
    # nothing temporary left behind
    assert sorted(p.name for p in out.iterdir()) == [fitting.files.MARKER, "metrics.json", "test_rmse.json",
                                                      "validation.png"]


def test_quick_run_errors_at_noise_level(quick_run):
    """A broken fit fails these: the linear start leaves ~2e-4 m, 30x the noise (7.3e-6 m)."""
    out, report, _ = quick_run
    m = report["metrics"]
    noise = m["noise_level"]
    assert 6e-6 < noise < 9e-6
    assert m["train_rmse"] < 1.1 * noise and m["validation_rmse"] < 1.1 * noise, m
    scores = report["test"]
    for key in ("multisine_rmse", "sinesweep_rmse"):
        assert np.isfinite(scores[key]) and 5e-6 < scores[key] < 1.2 * exp.NOISE_DEFAULT, scores
    # against the noise-free synthetic outputs: far below the noise and the best published 1.87e-5 m
    extra = report["test_extra"]
    assert extra["multisine_rmse_vs_clean"] < 2e-6 and extra["sinesweep_rmse_vs_clean"] < 2e-6, extra
    assert extra["multisine_last_period_change_rms"] < 1e-9


def test_quick_run_recovers_parameters(quick_run):
    """Started from data-only guesses, the fit lands on the benchmark's (unused) nominal values."""
    _, report, _ = quick_run
    p = report["parameters"]
    start = report["fit_info"]["start"]
    nominal = {**exp.NOMINAL, "beta*gamma": 800.0, "beta*delta": -1100.0}
    for name in ("m", "c", "k", "alpha", "beta*gamma", "beta*delta"):
        assert p[name] == pytest.approx(nominal[name], rel=0.05), (name, p[name])
    # and the start was not the answer
    assert abs(start["c"] / nominal["c"] - 1) > 0.5 and start["beta*delta"] == 0.0


def test_rk4_matches_diffrax(quick_run):
    """At the nominal parameters, the experiment's RK4 simulators against the synthetic file's noise-free outputs
    (diffrax Tsit5, adaptive, rtol=1e-8): steady multisine period (3 periods from rest) and sine sweep from rest.
    Measured (max / RMS, m): multisine 1.4e-6 / 2.7e-7 with 4 sub-steps, 5.9e-7 / 7.3e-8 with 8, 1.3e-7 / 1.6e-8
    with 16 (about second order: the vector field has kinks at zero velocity and z = 0)."""
    _, _, test_file = quick_run
    test = exp.load_test(test_file)
    bw = pj.BoucWenOscillator(**exp.NOMINAL)
    ms, sw = test["multisine"], test["sinesweep"]
    errs = {}
    for s in (4, 8):
        y_ms, change = exp.simulate_multisine(bw, ms["u"], FS, s, 3)
        y_sw = exp.simulate_transient(bw, sw["u"], FS, s)
        errs[s] = np.array([np.max(np.abs(y_ms - ms["y_clean"])), np.max(np.abs(y_sw - sw["y_clean"])),
                            exp.rmse(y_ms, ms["y_clean"]), exp.rmse(y_sw, sw["y_clean"])])
        assert change < 1e-9  # periods 2 and 3 agree: the transient from rest has died
    assert np.all(errs[4] < [2e-6, 2e-6, 4e-7, 4e-7]), errs
    assert np.all(errs[8] < [8e-7, 8e-7, 1.2e-7, 1.2e-7]), errs
    assert np.all(errs[8] < errs[4] / 2), errs  # converges to the diffrax solution
    assert np.std(ms["y_clean"]) > 3e-4 and np.std(sw["y_clean"]) > 1e-4  # real responses
