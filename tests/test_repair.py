"""Starts that move: a fit whose start (or stopping point) has a non-finite model next to it is repaired — the point
moved to a near one where the model is finite and fitted again — and the report says so; a point that cannot be
repaired is reported as left. The models are built to be non-finite next to their start: a square root of a
parameter started at zero (its derivative infinite there, NaN on one side), of its absolute value (finite on both
sides, the derivative infinite), and of minus its square (finite only at the start)."""

import dataclasses
import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fitting
import piezojax as pj
from fitting import parse_config

DT = 1e-3
T = np.arange(1500) * DT
V = 60 * np.sin(2 * np.pi * 2 * T) * np.exp(-0.6 * T) + 10 * np.sin(2 * np.pi * 7 * T)
FORMS = {"edge": lambda e: jnp.sqrt(e), "abs": lambda e: jnp.sqrt(jnp.abs(e)), "point": lambda e: jnp.sqrt(-e * e)}


class EdgeGain(pj.AbstractHysteresisCell):
    """y = w v + 1e-6 f(e) (v / 60)^2, f one of `FORMS` (memoryless; a cell so that the CONFIG can name it)."""

    weight: jax.Array
    edge: jax.Array
    form: str = eqx.field(static=True, default="edge")
    smoothing: jax.Array = pj.setting(default_factory=lambda: jnp.zeros(()))

    def init(self):
        return jnp.zeros(())

    def step(self, state, v):
        return state, self.weight * v + 1e-6 * FORMS[self.form](self.edge) * (v / 60.0) ** 2

    def check(self):
        return self


class EdgeGainKind(fitting.BlockKind):
    """The block above as a CONFIG kind whose data-driven start puts `edge` at 0, where the model is not finite
    next to it."""

    table, name = "hysteresis", "edge_gain"

    @dataclasses.dataclass(frozen=True)
    class Options(fitting.HysteresisOptions):
        weight: float | None = None
        edge: float | None = None

    def parse(self, t, raw):
        return self.Options(weight=t.number("weight"), edge=t.number("edge"))

    def parameters(self, o):
        return ("weight", "edge")

    def placeholder(self, o):
        return {"weight": 1.0, "edge": 1.0}

    def start(self, o, data):
        return {"weight": data.static_gain(), "edge": 0.0}

    def build(self, o, v, config):
        return EdgeGain(jnp.asarray(v["weight"], float), jnp.asarray(v["edge"], float))

    def constraints(self, o):
        return {}


def _records(form="edge"):
    truth = pj.Actuator(EdgeGain(jnp.asarray(2e-7), jnp.asarray(0.25), form=form), offset=1e-7)
    y = np.asarray(truth.simulate(jnp.asarray(V), DT).displacement)
    y = y + 1e-9 * np.random.default_rng(0).standard_normal(y.size)
    return fitting.Dataset([fitting.Experiment.from_arrays(t=T, v_in=V, displacement=y, name="r")])


@pytest.fixture
def edge_gain():
    kind = fitting.register_kind(EdgeGainKind())
    try:
        yield kind
    finally:
        fitting.unregister_kind("hysteresis", "edge_gain")


def test_a_configs_start_on_the_edge_of_the_models_domain_is_repaired_fitted_and_reported(edge_gain, tmp_path):
    ds = _records()
    cfg = parse_config('[hysteresis]\nkind = "edge_gain"\n', "edge.toml")
    # as it was: both starts (rule-based and cold) stay where they are, the Jacobian not finite there
    start = cfg.build(ds)
    plain = fitting.Problem(start, ds, predictor=cfg.predictor(), free=cfg.fit_free(("displacement",)))
    assert not np.all(np.isfinite(np.asarray(plain.normal_equations(plain.u0)[1])))
    cal = fitting.calibrate(cfg, ds, progress=False)
    result = cal.result
    assert result.success, result.reason
    (note,) = result.repairs
    assert note.startswith("the fit stopped at its start (nonfinite_initial): the model is not finite next to the "
                           "point (along hysteresis.edge): moved hysteresis.edge from 0 to ")
    assert note.endswith(", kept)") and "fitted again from there (successful, cost " in note
    moved_to = float(note.split("from 0 to ")[1].split(";")[0])
    assert 0 < moved_to <= 1.0  # to the side where the model is defined, within the largest move
    fitted = pj.unwrap(result.model).hysteresis
    assert float(fitted.edge) == pytest.approx(0.25, rel=2e-3)
    assert float(fitted.weight) == pytest.approx(2e-7, rel=1e-4)
    assert "start repaired: the fit stopped at its start" in cal.report()
    cal.save(tmp_path / "fit", figures=False)
    assert json.loads((tmp_path / "fit" / "result.json").read_text())["repairs"] == [note]


@pytest.mark.parametrize("form", ["abs", "point"])
def test_a_start_with_an_infinite_derivative_is_moved_and_one_finite_only_at_itself_is_reported_left(form):
    ds = _records("abs")
    start = pj.Actuator(EdgeGain(jnp.asarray(2.2e-7), jnp.asarray(0.0), form=form), offset=0.0)
    result = fitting.fit(start, ds, max_steps=200, progress=False)
    (note,) = result.repairs
    if form == "abs":
        # finite on both sides of the start: the Jacobian's NaN does not say which parameter, each is tried alone
        assert "the model's Jacobian is not finite at the point: moved hysteresis.edge from 0 to " in note
        assert result.success, result.reason
        assert abs(float(pj.unwrap(result.model).hysteresis.edge)) == pytest.approx(0.25, rel=2e-3)
    else:
        assert not result.success and result.code == "nonfinite_initial"
        assert note.endswith("the model is not finite next to the point (along hysteresis.edge), and no move of one "
                             "parameter (by up to max(1, |u|) in the solver's scaled units) made it finite: left as it "
                             "was")
        with pytest.raises(fitting.FitError):  # `throw` after the repair was tried
            fitting.fit(start, ds, max_steps=200, progress=False, throw=True)
