"""Starts for every configurable structure, checked on the independent plain-NumPy plant of
`experiments.plant_study` (issue 14): the series cold start, the resonance from ringing after steps, the Bouc–Wen
grid start, fallbacks, several starts fitted together, and a reduced run of the study through the command line."""

import warnings

import jax
import numpy as np
import pytest

import fitting
import piezojax as pj
from experiments import plant_study as ps
from fitting._config import StartData, StartWarning, parse_config
from fitting._config.kinds.hysteresis import BoucWenKind, _bouc_wen_grid
from fitting._config.model_config import _start_error


@pytest.fixture(scope="module")
def pi_truth():
    return ps.draw_truth("pi", np.random.default_rng(3))


@pytest.fixture(scope="module")
def pi_records(pi_truth):
    """The study's two training records (halved) of a PI plant, with 0.2 % noise."""
    rng = np.random.default_rng(11)
    sig = ps.signals(0.5)
    exps = []
    for name in ("train_triangles", "train_steps"):
        v = sig[name]
        y = ps.plant(pi_truth, v)
        y = y + 2e-3 * np.ptp(y) * rng.standard_normal(y.size)
        exps.append(fitting.Experiment.from_arrays(t=np.arange(v.size) * ps.DT, v_in=v, displacement=y, name=name))
    return fitting.Dataset(exps)


def test_plain_plant_agrees_with_library(pi_truth):
    """The study's plant (plain loops, exact ZOH of the whole linear part) and `pj.Actuator` (series structure,
    creep and dynamics sampled one after the other) are two implementations of one model: they agree to far below
    the study's noise (0.1 % of the range at least)."""
    v = ps.signals(0.5)["train_steps"]
    y = ps.plant(pi_truth, v)
    model = pj.Actuator(
        pj.PrandtlIshlinskii(pi_truth["weights"], pi_truth["thresholds"], w0=pi_truth["w0"]),
        pj.KelvinVoigtCreep(1.0 / pi_truth["creep_gains"], pi_truth["taus"], k0=1.0),
        pj.StableTransferFunction(1.0, omega=[2 * np.pi * pi_truth["f_res"]], zeta=[pi_truth["zeta"]]),
        structure="series",
    )
    err = np.asarray(model.simulate(jax.numpy.asarray(v), ps.DT).displacement) - y
    assert np.max(np.abs(err)) < 5e-4 * np.ptp(y)
    assert np.sqrt(np.mean(err**2)) < 1e-4 * np.ptp(y)


def test_series_cold_start(pi_truth, pi_records):
    """`structure="series"`: the resonance from the ringing after the steps, creep gains relative to the
    instantaneous response (dimensionless), and the same start as a lag creep (DC-normalised)."""
    kv = pj.unwrap(fitting.cold_start_actuator(pi_records, 6, 2, 2, structure="series"))
    assert kv.structure == "series" and float(kv.creep.k0) == 1.0
    f = float(kv.dynamics.omega[0]) / (2 * np.pi)
    assert abs(f / pi_truth["f_res"] - 1) < 0.03
    assert abs(float(kv.dynamics.zeta[0]) / pi_truth["zeta"] - 1) < 0.3
    total = float(np.sum(1.0 / kv.creep.stiffnesses))
    assert 0.5 < total / np.sum(pi_truth["creep_gains"]) < 2  # dimensionless, of the right size (the fit refines)
    # the start is already close: a few per cent of the range, against 0.2 % noise
    assert _start_error(kv, pi_records) < 30 * sum(e.n for e in pi_records) * (2e-3) ** 2

    lag = pj.unwrap(fitting.cold_start_actuator(pi_records, 6, 2, 2, structure="series", creep="lag"))
    assert isinstance(lag.creep, pj.LagCreep)
    np.testing.assert_allclose(float(np.sum(lag.creep.fractions)), total / (1 + total), rtol=1e-9)
    for e in pi_records:  # the same response: the lag form only moves the scale into the hysteresis
        np.testing.assert_allclose(np.asarray(lag.simulate(e.v_in, e.dt).displacement),
                                   np.asarray(kv.simulate(e.v_in, e.dt).displacement), rtol=1e-7,
                                   atol=1e-9 * np.ptp(e["displacement"]))
    with pytest.raises(pj.PiezojaxValueError, match="structure"):
        fitting.cold_start_actuator(pi_records, 6, 2, structure="serial")
    with pytest.raises(pj.PiezojaxValueError, match="lag"):
        fitting.cold_start_actuator(pi_records, 6, 2, structure="parallel", creep="lag")


def test_resonance_from_steps_with_offset_and_misfit(pi_truth):
    """Only held steps, a sensor offset of half the range and a hysteresis the PI start cannot match exactly
    (Bouc–Wen): the high-passed ARX candidates still find the ringing."""
    bw = ps.draw_truth("bouc_wen", np.random.default_rng(5))
    v = ps.signals(0.5)["train_steps"]
    y = ps.plant(bw, v)
    y = y + 0.5 * np.ptp(y) + 1e-3 * np.ptp(y) * np.random.default_rng(2).standard_normal(y.size)
    exp = fitting.Experiment.from_arrays(t=np.arange(v.size) * ps.DT, v_in=v, displacement=y)
    m = pj.unwrap(fitting.cold_start_actuator([exp], 8, 2, 2, structure="series"))
    assert abs(float(m.dynamics.omega[0]) / (2 * np.pi * bw["f_res"]) - 1) < 0.03


def test_bouc_wen_grid_start():
    """The Bouc–Wen start (a grid of beta, gamma/beta with A, d by least squares) reproduces a Bouc–Wen loop
    to a few per cent of its range, from one record."""
    bw = ps.draw_truth("bouc_wen", np.random.default_rng(8))
    v = ps.signals(0.5)["train_triangles"]
    y = ps.SCALE * ps.bouc_wen(v, bw["A"], bw["beta"], bw["gamma"], bw["d"])
    exp = fitting.Experiment.from_arrays(t=np.arange(v.size) * ps.DT, v_in=v, displacement=y)
    config = parse_config('[hysteresis]\nkind = "bouc_wen"\n[dynamics]\norder = 0\n')
    kind = BoucWenKind()
    o = config.options("hysteresis")
    s = kind.start(o, StartData(config, fitting.Dataset([exp])))
    model = kind.build(o, s, config)
    err = np.asarray(model(jax.numpy.asarray(v))) - y
    assert np.sqrt(np.mean(err**2)) < 0.03 * np.ptp(y)
    assert s["A"] > 0 and s["beta"] + s["gamma"] > 0


def test_bouc_wen_grid_in_blocks():
    """The grid start's operator outputs, stepped block by block (a padded last block) and kept at a subset of
    rows, equal the whole record's outputs at those rows."""
    v = ps.signals(0.5)["train_triangles"][:3001]
    beta, gamma = np.array([0.01, 0.03, 0.02]), np.array([0.005, -0.01, 0.0])
    whole = np.stack([np.asarray(pj.BoucWen(1.0, b, g, output="z")(jax.numpy.asarray(v))) for b, g in zip(beta, gamma)])
    rows = np.sort(np.random.default_rng(0).choice(v.size, 700, replace=False))
    for k in (slice(None), rows):
        z = _bouc_wen_grid(jax.numpy.asarray(beta), jax.numpy.asarray(gamma), v, k, block=512)
        np.testing.assert_allclose(z, whole[:, k], rtol=1e-12, atol=1e-12 * np.max(np.abs(whole)))
    assert np.ptp(whole) > 0


def test_lazy_dense_design_equals_the_design():
    """The cold start's dense design, made block by block each time it is read (`_LazyDesign`), passes through the
    dynamics to the same columns at the least-squares rows as the whole design, bit for bit."""
    from fitting._initialise import _design, _LazyDesign, _through

    sig = ps.signals(0.5)
    recs = [(sig[name][:n], None, ps.DT) for name, n in (("train_triangles", 2500), ("train_steps", 1800))]
    r, taus = np.linspace(1.0, 90.0, 37), np.geomspace(5 * ps.DT, 2.0, 21)  # 3 groups of plays, 2 of lags
    rows = [np.sort(np.random.default_rng(i).choice(v.size, 600, replace=False)) for i, (v, _, _) in enumerate(recs)]
    for omega, zeta in ((None, None), (np.array([2 * np.pi * 300.0]), np.array([0.1]))):
        whole = _through([_design(v, dt, r, taus) for v, _, dt in recs], recs, omega, zeta, rows)
        lazy = _through([_LazyDesign(v, dt, r, taus) for v, _, dt in recs], recs, omega, zeta, rows)
        assert whole.shape == (1200, 1 + r.size + taus.size)
        np.testing.assert_array_equal(lazy, whole)


def test_failed_start_falls_back_with_warning(pi_records, monkeypatch):
    """A start heuristic that raises on usable data gives the placeholder values with a StartWarning; the build
    does not fail."""
    def broken(self, o, data):
        raise np.linalg.LinAlgError("singular")

    monkeypatch.setattr(BoucWenKind, "start", broken)
    config = parse_config('[hysteresis]\nkind = "bouc_wen"\n[dynamics]\norder = 0\n')
    with pytest.warns(StartWarning, match="bouc_wen: the data-driven start failed.*singular"):
        model = pj.unwrap(config.build(pi_records))
    assert float(model.hysteresis.A) == pytest.approx(BoucWenKind().placeholder({})["A"], rel=1e-12)


def test_starts_share_structure_and_fit_together(pi_records):
    """`ModelConfig.starts`: the rule-based and the cold start, closest to the data first, fitted together under
    vmap; the result lists both. With a fitted prehistory, so that the series creep starts settled at the remanent
    output (its settled gain's derivatives were once NaN, and every start stopped at a non-finite Jacobian)."""
    config = parse_config('[hysteresis]\nkind = "bouc_wen"\n[creep]\nkind = "kelvin_voigt"\nstructure = "series"\n'
                          'order = 2\n[dynamics]\norder = 2\n[state]\nprehistory = true\n')
    with warnings.catch_warnings():
        warnings.simplefilter("error", StartWarning)
        starts = config.starts(pi_records)
    assert len(starts) == 2
    assert jax.tree_util.tree_structure(starts[0]) == jax.tree_util.tree_structure(starts[1])
    errors = [_start_error(pj.unwrap(m), pi_records) for m in starts]
    assert errors[0] <= errors[1]
    # series creep gains are dimensionless in both (relative to the instantaneous response), not metres per volt
    for m in starts:
        assert np.all(np.asarray(pj.unwrap(m).creep.stiffnesses) < 1e6)
    targets = config.fit_targets(pi_records)
    res = fitting.fit(starts[0], pi_records, predictor=config.predictor(), targets=targets,
                      free=config.fit_free(targets), starts=starts, max_steps=5, progress=False, kink_restarts=0)
    assert len(res.starts) == 2 and sum(s["best"] for s in res.starts) == 1
    assert res.code != "nonfinite_initial" and res.cost < res.initial_cost, res.reason


def test_plant_study_reduced():
    """The study through the command line on one draw per case with halved records: the in-class PI model and
    the Bouc–Wen model of a Bouc–Wen plant reach the noise on records they never saw."""
    summary = ps.main(["--draws", "1", "--cases", "pi,bw", "--seconds", "0.5", "--seed", "1"])
    for case in ("pi", "bw"):  # every fit ran to its outputs (exit 0 or 1) and predicts to the noise
        assert summary[case]["worst"] <= 1.5 and summary[case]["crashed"] == 0


def test_identification_plants_agree_with_library():
    """The identification case's plants, written without piezojax code: Maxwell slip (plain stop loops) with two
    resonances, and a play plant with parallel creep and a delay of a whole number of samples, each against
    `pj.Actuator` of the same blocks; every plant of `IDENTIFY` gives finite records."""
    v = ps.signals(0.5)["train_steps"]
    ms = ps.draw_identification_truth("maxwell_slip", "series", 2, False, np.random.default_rng(3))
    y = ps.plant(ms, v)
    model = pj.Actuator(
        pj.MaxwellSlip(ms["stiffnesses"], ms["stiffnesses"] * ms["thresholds"]),
        pj.KelvinVoigtCreep(1.0 / ms["creep_gains"], ms["taus"], k0=1.0),
        pj.StableTransferFunction(1.0, omega=2 * np.pi * np.array([ms["f_res"], ms["f_res2"]]),
                                  zeta=[ms["zeta"], ms["zeta2"]]),
        structure="series",
    )
    err = np.asarray(model.simulate(jax.numpy.asarray(v), ps.DT).displacement) - y
    assert np.max(np.abs(err)) < 5e-4 * np.ptp(y)
    play = ps.draw_identification_truth("play", "parallel", 1, False, np.random.default_rng(4))
    play["delay"] = 2 * ps.DT
    y = ps.plant(play, v)
    model = pj.Actuator(
        pj.PrandtlIshlinskii(play["weights"], play["thresholds"], w0=0.0),
        pj.KelvinVoigtCreep(1.0 / (play["creep_gains"] * ps.SCALE), play["taus"], k0=None),
        pj.StableTransferFunction(1.0, omega=[2 * np.pi * play["f_res"]], zeta=[play["zeta"]]),
        delay=pj.Delay(2 * ps.DT),
    )
    err = np.asarray(model.simulate(jax.numpy.asarray(v), ps.DT).displacement) - y
    assert np.max(np.abs(err)) < 5e-4 * np.ptp(y)
    for i, spec in enumerate(ps.IDENTIFY):
        truth = ps.draw_identification_truth(*spec, np.random.default_rng(i))
        assert np.all(np.isfinite(ps.plant(truth, v[:2000]))), spec
