"""The observer kinds of the `[observer]` table: papers 001 (current integration), 000 (dynamic impedance)
and 002 (sensor layer)."""

from typing import ClassVar

import jax.numpy as jnp
import numpy as np

import piezojax as pj
from piezojax import PiezojaxValueError

from ..._predict import observer_predictor
from ..table import ConfigTable, f64
from .models import ModelKind, _WithState, parse_state

# ---------------------------------------------------------------------------------------------- observers


class _Observer(ModelKind):
    """A `pj.AbstractObserver`: estimates (`estimates`: displacement, and force where it has one) from the measured
    `v_in` and `v_out`."""

    estimates: ClassVar[tuple[str, ...]] = ("displacement", "force")

    def outputs(self, config):
        return self.estimates

    def inputs(self, config):
        return ("v_out",)

    def predictor(self, config):
        return observer_predictor(force="force" in self.estimates)


_OBSERVER_REQUIRED = (
    "integrator_capacitance",
    "reference_capacitance",
    "leakage_resistance",
    "force_sensitivity",
    "displacement_coefficient",
    "stiffness",
)


class CurrentIntegrationObserver(_WithState, _Observer):
    """`pj.ForceDisplacementObserver`, paper 001's self-sensing observer: displacement and force from `v_in` and
    the measured integrator output `v_out`; `[hysteresis]` and `[creep]` are its charge operators (creep in
    parallel). The circuit constants are fixed by default (scaling all of them with β and the operators leaves the
    estimates unchanged); without hysteresis, `capacitance_p` is fitted."""

    name = "current_integration"
    keys = _OBSERVER_REQUIRED + ("bias_current", "capacitance_p", "filter_cutoff")
    tables = ("state",)
    structures = ("parallel",)
    offset_default = False  # the estimate of paper 001 has none unless asked for

    def parse(self, t, raw, source):
        missing = [k for k in _OBSERVER_REQUIRED if k not in t.data]
        if missing:
            raise t.error(f"missing key(s) {', '.join(missing)} (the circuit and beam constants)")
        out = {}
        for k in self.keys:
            positive = k not in ("bias_current", "displacement_coefficient", "capacitance_p")
            out[k] = t.number(k, None, positive=positive, nonnegative=k == "capacitance_p",
                              nonzero=k == "displacement_coefficient")
        return {k: v for k, v in out.items() if v is not None} | {"state": parse_state(raw, source)}

    def missing(self, config):
        # without hysteresis C_P is the charge's scale, started from the data (the placeholder 1 nF is no value)
        given = config.model_options.get("capacitance_p") is not None
        return ([] if given or not config.hysteresis_kind.empty else ["[observer] capacitance_p"]) + (
            super().missing(config))

    def records(self, config, dataset):
        o = config.model_options
        plain = pj.ForceDisplacementObserver(
            o["integrator_capacitance"], o["reference_capacitance"], o["leakage_resistance"],
            o.get("bias_current", 0.0), o["force_sensitivity"], o["displacement_coefficient"], o["stiffness"])
        recs = []
        for e in dataset:
            if not e.has("v_out"):
                continue
            q = np.asarray(plain.compensated_charge(jnp.asarray(e.v_in), jnp.asarray(e["v_out"]), e.dt))
            if e.has("force"):
                q = q - o["force_sensitivity"] * np.asarray(e["force"])
            recs.append((np.asarray(e.v_in), q, e.dt))
        if not recs:
            raise PiezojaxValueError("initial values for the observer's operators need data files with a 'v_out' "
                                     "column (or give the values explicitly in the configuration)")
        return recs

    def build(self, config, blocks, data):
        o = config.model_options
        fc, cp = o.get("filter_cutoff"), o.get("capacitance_p")
        if cp is None:
            if not config.hysteresis_kind.empty:
                cp = 0.0
            else:  # C_P: the slope of the compensated charge against V
                cp = 1e-9 if data is None else max(data.static_gain(), np.finfo(float).tiny)
        return pj.ForceDisplacementObserver(
            f64(o["integrator_capacitance"]), f64(o["reference_capacitance"]), f64(o["leakage_resistance"]),
            f64(o.get("bias_current", 0.0)), f64(o["force_sensitivity"]), f64(o["displacement_coefficient"]),
            f64(o["stiffness"]), capacitance_p=f64(cp), hysteresis=blocks["hysteresis"], creep=blocks["creep"],
            filter_cutoff=None if fc is None else f64(fc), **self.state_values(config),
        )

    def constraints(self, config):
        return {"force_sensitivity": pj.Positive, "stiffness": pj.Positive}

    def default_free(self, config):
        return ("force_sensitivity", "displacement_coefficient", "stiffness") + (
            ("capacitance_p",) if config.hysteresis_kind.empty else ()) + self.state_free(config)





def _required_numbers(t: ConfigTable, required: tuple[str, ...], optional: dict[str, dict]) -> dict:
    """The observer table's constants: `required` (each > 0 unless `optional` says otherwise) and `optional` (name →
    `ConfigTable.number` options, absent ones left out)."""
    missing = [k for k in required if k not in t.data]
    if missing:
        raise t.error(f"missing key(s) {', '.join(missing)} (the circuit constants)")
    out = {k: t.number(k, None, **optional.get(k, {"positive": True})) for k in required}
    for k, opts in optional.items():
        if k not in required and k in t.data:
            out[k] = t.number(k, None, **opts)
    return out


class _ObserverOffset(_WithState, _Observer):
    """An observer with a displacement `offset` from `[state]` (off unless `offset = true` or a number: the
    estimate of the paper has none); no prehistory (the observer has no hysteresis operator)."""

    tables = ("state",)
    offset_default = False

    def parse(self, t, raw, source):
        return {"state": parse_state(raw, source)}

    def offset_value(self, config) -> dict:
        return {"offset": self.state_values(config)["offset"]}


class DynamicImpedanceKind(_ObserverOffset):
    r"""`pj.DynamicImpedanceObserver`, paper 000's displacement observer from the transimpedance amplifier output
    `v_out`: $\hat\delta = G(s)[\alpha V_{in} + \beta(Q_\delta + \gamma V_{in})]$, with $G$ the `[dynamics]` table (its
    DC gain included: without it the scale of $\alpha$, $\beta$ would be free). Required: `feedback_resistance`
    $R_f$, `capacitance` $C_r$ [F], `alpha`, `beta`; optional `bias_current = 0`, `gamma` (default: fitted from
    0.1 $C_r$). `[state] offset` (displacement offset, off by default). Fitted by default: `gamma`, $G$ and the
    offset when present."""

    name = "dynamic_impedance"
    estimates = ("displacement",)
    keys = ("feedback_resistance", "capacitance", "alpha", "beta", "bias_current", "gamma")
    blocks = ("dynamics",)
    scale_in_dynamics = True

    def parse(self, t, raw, source):
        return _required_numbers(t, ("feedback_resistance", "capacitance", "alpha", "beta"),
                                 {"alpha": {}, "beta": {}, "bias_current": {}, "gamma": {"nonnegative": True}}) | (
            super().parse(t, raw, source))

    def _observer(self, config, dynamics, gamma):
        o = config.model_options
        return pj.DynamicImpedanceObserver(
            f64(o["feedback_resistance"]), f64(o["capacitance"]), f64(gamma), f64(o.get("bias_current", 0.0)),
            f64(o["alpha"]), f64(o["beta"]), dynamics, **self.offset_value(config))

    def _gamma(self, config):
        g = config.model_options.get("gamma")
        return 0.1 * config.model_options["capacitance"] if g is None else g

    def missing(self, config):
        # gamma is fitted from a start of 0.1 C_r, which is no value to simulate with
        given = config.model_options.get("gamma") is not None
        return ([] if given else ["[observer] gamma"]) + super().missing(config)

    def records(self, config, dataset):
        # the transduced force F_t (at the start's gamma) against the displacement: G's static gain is their chord
        obs = self._observer(config, pj.StableTransferFunction(1.0), self._gamma(config))
        recs = [(np.asarray(obs.transduced_force(jnp.asarray(e.v_in), jnp.asarray(e["v_out"]), e.dt)),
                 np.asarray(e["displacement"]), e.dt) for e in dataset if e.has("v_out") and e.has("displacement")]
        if not recs:
            raise PiezojaxValueError("initial values for the observer's dynamics need data files with 'v_out' and "
                                     "'displacement' columns (or give the values explicitly in the configuration)")
        return recs

    def build(self, config, blocks, data):
        return self._observer(config, blocks["dynamics"], self._gamma(config))

    def constraints(self, config):
        # gamma = 0 given explicitly is the static-impedance observer the paper compares against: fixed
        return {} if config.model_options.get("gamma") == 0 else {"gamma": pj.Positive}

    def default_free(self, config):
        return (() if config.model_options.get("gamma") == 0 else ("gamma",)) + self.state_free(config)


class SensorLayerKind(_ObserverOffset):
    r"""`pj.SensorLayerObserver`, paper 002's smart-stack sensing layer: displacement and force from the sensor
    voltage `v_out` ($V_s$) and the drive `v_in` ($V_a$). Required: `d33` [C/N], `amplifier_capacitance` [F], `k_p`,
    `k_s` [N/m]; optional `crosstalk` $p_c$ (default 0). Fitted by default: `d33` (the force scale $d_{33}/C$),
    `k_s` (with $k_p$ fixed, the compliance $1/k_p + 1/k_s$ of the displacement), `crosstalk`, and the displacement
    offset when `[state] offset` asks for one."""

    name = "sensor_layer"
    keys = ("d33", "amplifier_capacitance", "k_p", "k_s", "crosstalk")
    blocks = ()

    def parse(self, t, raw, source):
        return _required_numbers(t, ("d33", "amplifier_capacitance", "k_p", "k_s"), {"crosstalk": {}}) | (
            super().parse(t, raw, source))

    def records(self, config, dataset):
        return []

    def build(self, config, blocks, data):
        o = config.model_options
        return pj.SensorLayerObserver(f64(o["d33"]), f64(o["amplifier_capacitance"]), f64(o["k_p"]), f64(o["k_s"]),
                                      crosstalk=f64(o.get("crosstalk", 0.0)), **self.offset_value(config))

    def constraints(self, config):
        return {"d33": pj.Positive, "k_s": pj.Positive}

    def default_free(self, config):
        return ("d33", "k_s", "crosstalk") + self.state_free(config)


