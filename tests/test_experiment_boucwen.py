"""`python -m experiments.boucwen_benchmark --quick --test FILE` end to end, and its fixed-step RK4 simulator."""

import json

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import piezojax as pj
from experiments import boucwen_benchmark as exp
from piezojax._nonlinear.fixed_step import rk4_scan, stage_inputs

FS = 750.0
DT = 1 / FS

needs_data = pytest.mark.skipif(not exp.DATA.exists(), reason=f"benchmark data not found: {exp.DATA}")


# ---------------------------------------------------------------------------------------------------------------
# The simulator.


def test_stage_inputs_band_limited():
    """Column 0 holds the samples, the last column the next sample (wrapping), and a sine with a whole number of
    periods in the record is interpolated exactly at the half-step times."""
    n, s = 64, 3
    t = np.arange(n) * DT
    f = 5 * FS / n
    u = np.sin(2 * np.pi * f * t + 0.3)
    tab = np.asarray(stage_inputs(jnp.asarray(u), DT, s))
    assert tab.shape == (n, 2 * s + 1)
    np.testing.assert_allclose(tab[:, 0], u, atol=1e-12)
    np.testing.assert_allclose(tab[:, -1], np.roll(u, -1), atol=1e-12)
    tt = t[:, None] + np.arange(2 * s + 1)[None, :] * DT / (2 * s)
    np.testing.assert_allclose(tab, np.sin(2 * np.pi * f * tt + 0.3), atol=1e-12)
    # transient record: zero padding, so the last sample's end point is u = 0 (the first pad sample)
    tab2 = np.asarray(stage_inputs(jnp.asarray(u), DT, s, periodic=False, pad=8))
    assert tab2.shape == (n, 2 * s + 1)
    assert tab2[-1, -1] == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(ValueError, match="substeps"):
        stage_inputs(jnp.asarray(u), DT, 0)
    with pytest.raises(ValueError, match="`u`"):
        stage_inputs(jnp.zeros((4, 2)), DT, 2)


def test_rk4_fourth_order_on_linear_ode():
    r"""$\dot x = -a x + u$, $u = \sin\omega t$ from rest: exact solution known; RK4 error falls 16x per halving."""
    n, a = 200, 30.0
    w = 2 * np.pi * 10 * FS / n  # 10 periods in the record: the band-limited input is exact
    t = np.arange(n) * DT
    u = np.sin(w * t)
    exact = (a * np.sin(w * t) - w * np.cos(w * t) + w * np.exp(-a * t)) / (a * a + w * w)
    errs = []
    for s in (1, 2, 4):
        _, xs = rk4_scan(lambda x, u_t, _: -a * x + u_t, jnp.zeros(1), stage_inputs(jnp.asarray(u), DT, s), DT)
        errs.append(np.max(np.abs(np.asarray(xs[:, 0]) - exact)))
    assert errs[2] < 1e-7 * np.max(np.abs(exact))
    assert 12 < errs[0] / errs[1] < 20 and 12 < errs[1] / errs[2] < 20, errs
    # jit / grad / jacfwd / vmap: d/da of the final state, three ways, and a batch of two inputs
    table = stage_inputs(jnp.asarray(u), DT, 2)

    def final(a_):
        return rk4_scan(lambda x, u_t, aa: -aa * x + u_t, jnp.zeros(1), table, DT, a_)[0][0]

    g = jax.grad(final)(a)
    assert float(jax.jit(jax.jacfwd(final))(a)) == pytest.approx(float(g), rel=1e-10)
    fd = (float(final(a + 1e-4)) - float(final(a - 1e-4))) / 2e-4
    assert float(g) == pytest.approx(fd, rel=1e-6)
    tables = jnp.stack([table, 2 * table])
    batch = jax.vmap(lambda tb: rk4_scan(lambda x, u_t, _: -a * x + u_t, jnp.zeros(1), tb, DT)[1])(tables)
    np.testing.assert_allclose(np.asarray(batch[1]), 2 * np.asarray(batch[0]), rtol=1e-12, atol=1e-18)


@needs_data
def test_jacobian_matches_finite_differences():
    """jacfwd through the RK4 scan (what LM uses) against central differences, on 300 samples."""
    d = exp.load_train()
    table = stage_inputs(jnp.asarray(d["u"][: exp.PERIOD]), DT, 2)[:300]
    par = exp.Parametrisation(1.8, 40.0, 5.5e4, 5.5e4, 1500.0)

    def f(th):
        return exp.simulate(par.model(th), table, DT)

    th = jnp.array([0.05, 0.1, -0.05, 0.02, 0.4, -0.3])
    jac = np.asarray(jax.jit(jax.jacfwd(f))(th))
    fj = jax.jit(f)
    eps = 1e-6
    for i in range(th.shape[0]):
        e = jnp.zeros(6).at[i].set(eps)
        fd = (np.asarray(fj(th + e)) - np.asarray(fj(th - e))) / (2 * eps)
        np.testing.assert_allclose(jac[:, i], fd, rtol=1e-4, atol=1e-6 * np.max(np.abs(fd)))


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
    with pytest.raises(SystemExit, match=r"^error: .*t\.h5: neither group") as info:
        exp.main(["--test", str(path), "--out", str(tmp_path / "out")])
    assert "\n" not in str(info.value)
    assert not (tmp_path / "out").exists()


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
    assert sorted(p.name for p in out.iterdir()) == ["metrics.json", "test_rmse.json", "validation.png"]


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
