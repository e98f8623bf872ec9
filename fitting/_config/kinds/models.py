"""The whole-model kinds of a CONFIG: `pj.Actuator` (no `[observer]` table) and the observers (`[observer] kind`).

A `ModelKind` says which tables the model uses besides its blocks' (the actuator's `[charge]` and `[state]`), how
they are validated, which channels the model predicts and reads, the quasi-static output its hysteresis and creep
are started from, how the blocks are put together, its own constraints, default free set and data-driven state.
The generic configuration code (`fitting._config`) names none of them.
"""

import abc
from collections.abc import Mapping
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import piezojax as pj
from piezojax import PiezojaxValueError

from ..._predict import actuator_predictor, predict
from ..table import ConfigTable, f64, finite_number
from .base import StartData, check_class_attributes


class ModelKind(abc.ABC):
    """A kind of whole model (see the module docstring).

    A concrete model kind sets `name` and defines the abstract methods (`outputs`, `predictor`, `records`,
    `build`); the other methods are defaults. Its options (`ModelConfig.model_options`) are a dict of its tables'
    validated values.

    **Abstract class attribute:** `name`, the kind's name in its table.

    **Class attributes with defaults:**

    - `table`: the CONFIG table naming it (`"observer"`, or `"model"` for a model that is not an observer), or
      `None` for the default model (no such table).
    - `keys`: the keys of that table besides `kind`.
    - `blocks`: the block tables the model is built from (`"hysteresis"`, `"creep"`, `"dynamics"`);
      `tables`: the other tables it uses (an unused table present in the CONFIG is an error).
    - `structures`: the creep structures it supports.
    - `scale_in_dynamics`: without hysteresis, the dynamics' gain carries the scale from volts to the output.
    - `cold_start`: the model is a `pj.Actuator`, so `fitting.cold_start_actuator` applies to it.
    - `input_unit`: the SI unit of what the model reads from `v_in` (a voltage, or the force of a force-driven
      model), for the labels of the files the command line writes.
    """

    table: ClassVar[str | None] = "observer"
    name: ClassVar[str]
    keys: ClassVar[tuple[str, ...]] = ()
    blocks: ClassVar[tuple[str, ...]] = ("hysteresis", "creep")
    tables: ClassVar[tuple[str, ...]] = ()
    structures: ClassVar[tuple[str, ...]] = ("parallel", "series")
    scale_in_dynamics: ClassVar[bool] = False
    cold_start: ClassVar[bool] = False
    input_unit: ClassVar[str] = "V"

    def __new__(cls, *args, **kwargs):
        check_class_attributes(cls, ("name",))
        return super().__new__(cls)

    @abc.abstractmethod
    def outputs(self, config) -> tuple[str, ...]:
        """The channels the model predicts."""

    @abc.abstractmethod
    def predictor(self, config):
        """The `fitting.Predictor` that simulates the model on an experiment."""

    @abc.abstractmethod
    def records(self, config, dataset) -> list[tuple[np.ndarray, np.ndarray, float]]:
        """`(v_in, y, dt)` per experiment: `y` the quasi-static output of hysteresis + creep (for their starts)."""

    @abc.abstractmethod
    def build(self, config, blocks: dict, data: StartData | None):
        """The model from its built `blocks` (table → block or `None`); `data`: the `StartData` of a data-driven
        start, else `None` (placeholders)."""

    def parse(self, t: ConfigTable | None, raw: Mapping, source: str) -> dict:
        """The model's validated options (from its own table `t` and the tables in `tables`; default: none)."""
        return {}

    def inputs(self, config) -> tuple[str, ...]:
        """Measured channels the model reads besides `t` and `v_in` (default: none)."""
        return ()

    def missing(self, config) -> list[str]:
        """Values of the model's own tables a forward simulation needs and the file does not give."""
        return []

    def constraints(self, config) -> dict[str, type]:
        """Attribute of the model → the `pj.AbstractReparam` it is fitted under."""
        return {}

    def default_free(self, config) -> tuple[str, ...]:
        """The model's own parameters fitted by default (after its blocks')."""
        return ()

    def fit_free(self, config, free: list[str], targets) -> list[str]:
        """The default free set for these target channels."""
        return free

    def cost(self, config) -> int:
        """Relative cost per sample of the model's own simulation (e.g. integration substeps), for the fit's memory
        estimate (the blocks' costs are the kinds')."""
        return 1

    def start_state(self, config, model, dataset):
        """Data-driven values of the model's own state parameters (default: none)."""
        return model


_MODEL_KINDS: dict[str, ModelKind] = {}


def register_model_kind(kind: ModelKind, *, replace: bool = False) -> ModelKind:
    """Make a whole-model kind available to CONFIG files (`[observer] kind = "<kind.name>"`, or `[model]` for a
    model that is not an observer). Names are unique across both tables."""
    if not isinstance(kind, ModelKind) or kind.table not in ("observer", "model"):
        raise PiezojaxValueError("`kind` must be a fitting.ModelKind instance with `table` 'observer' or 'model'")
    if kind.name in _MODEL_KINDS and not replace:
        raise PiezojaxValueError(f"a model kind named {kind.name!r} is already registered")
    _MODEL_KINDS[kind.name] = kind
    return kind


def model_kinds(table: str | None = None) -> tuple[str, ...]:
    """The registered whole-model kinds (of one table, `"observer"` or `"model"`, when given)."""
    return tuple(n for n, k in _MODEL_KINDS.items() if table is None or k.table == table)


def get_model_kind(name: str) -> ModelKind:
    return _MODEL_KINDS[name] if name != ActuatorModel.name else ACTUATOR


# ---------------------------------------------------------------------------------------------- state


_STATE_KEYS = ("offset", "prehistory")
_INPUT_KEYS = ("delay",)


def _switches(raw: Mapping, source: str, table: str, keys: tuple[str, ...], *, positive: bool = False
              ) -> tuple[dict, ConfigTable]:
    """A table of switches (`[state]`, `[input]`): each key `true` (in the model, started from the data), `false`
    (not in the model) or a number (in the model, this start value; > 0 with `positive`)."""
    what = "a number of seconds > 0" if positive else "a number"
    st = ConfigTable(source, table, raw.get(table, {}), keys)
    if "kind" in st.data:
        raise st.error(f"unknown key 'kind'; allowed keys: {', '.join(keys)}", "kind")
    out: dict = {}
    for key in keys:
        if key not in st.data:
            continue
        value = st.data[key]
        if not (isinstance(value, bool) or finite_number(value)) or (
                positive and not isinstance(value, bool) and not value > 0):
            raise st.error(f"must be true (fitted from the data), false (none) or {what} (its start value), got "
                           f"{value!r}", key)
        out[key] = value if isinstance(value, bool) else float(value)
    return out, st


def parse_state(raw: Mapping, source: str) -> dict:
    """The `[state]` table: `offset` and `prehistory`, each `True` (in the model, started from the data), `False`
    (not in the model) or a number (in the model, this start value)."""
    if "state" not in raw:
        return {}
    out, st = _switches(raw, source, "state", _STATE_KEYS)
    h = raw.get("hysteresis", {})
    if out.get("prehistory", False) is not False and h.get("kind", "none") == "none":
        raise st.error("a prehistory sets the hysteresis' remanent state; the model has no hysteresis", "prehistory")
    return out


def parse_input(raw: Mapping, source: str) -> dict:
    """The `[input]` table: `delay`, the dead time between the recorded voltage and the one the actuator sees
    (`pj.Delay`): `True` (fitted from a data-driven start), `False` (none) or a number of seconds > 0 (its start: a
    delay fitted under `pj.Positive` cannot leave 0)."""
    return _switches(raw, source, "input", _INPUT_KEYS, positive=True)[0] if "input" in raw else {}


class _WithState(ModelKind):
    """A model with an output `offset` and a hysteresis `prehistory` (`[state]`), both fields of the model."""

    offset_default: ClassVar[bool] = True

    def offset(self, config):
        return config.model_options["state"].get("offset", self.offset_default)

    def prehistory(self, config):
        return config.model_options["state"].get("prehistory", False)

    def state_values(self, config) -> dict:
        """The model's `offset` and `prehistory` arguments (a start of 0 where the data will set them)."""
        offset, pre = self.offset(config), self.prehistory(config)
        return {"offset": f64(0.0 if isinstance(offset, bool) else offset),
                "prehistory": None if pre is False else f64(0.0 if pre is True else pre)}

    def missing(self, config):
        return ["[state] prehistory"] if self.prehistory(config) is True else []

    def displacement(self, config, model, experiment) -> np.ndarray:
        """The model's displacement for one experiment, from rest (`fitting.predict` with the kind's predictor; not
        finite where the model fails there)."""
        return predict(model, experiment, predictor=self.predictor(config), check_finite=False)["displacement"]

    def state_free(self, config) -> tuple[str, ...]:
        return (("offset",) if self.offset(config) is not False else ()) + (
            ("prehistory",) if self.prehistory(config) is not False else ())

    def start_state(self, config, model, dataset):
        """The offset (the mean residual of the displacement) and the prehistory (the best of a grid of excursions
        from -max|v| to max|v|, each with its offset), where the file gives no number."""
        offset, pre = self.offset(config), self.prehistory(config)
        if offset is not True and pre is not True:
            return model
        recs = [e for e in dataset if e.has("displacement") and all(e.has(c) for c in self.inputs(config))]
        if not recs:
            return model
        if pre is not True:
            return self.with_offset(config, model, recs)
        vmax = max(float(np.max(np.abs(e.v_in))) for e in recs)
        best, best_err = None, np.inf
        for u in vmax * np.linspace(-1.0, 1.0, 9):
            cand = eqx.tree_at(lambda a: a.prehistory, model, jnp.asarray(u, model.prehistory.dtype))
            cand = self.with_offset(config, cand, recs)
            err = self.start_error(config, cand, recs)
            if best is None or err < best_err:
                best, best_err = cand, err
        return best

    def with_offset(self, config, model, recs):
        """`model` with its offset started at the mean residual of the displacement over `recs` (where the file
        gives no number)."""
        if self.offset(config) is not True:
            return model
        res = np.concatenate([np.asarray(e["displacement"]) - self.displacement(config, model, e) for e in recs])
        b = float(np.mean(res)) if np.all(np.isfinite(res)) else 0.0
        return eqx.tree_at(lambda a: a.offset, model, jnp.asarray(b + float(model.offset), model.offset.dtype))

    def start_error(self, config, model, recs) -> float:
        """The sum of squared displacement errors over `recs`, each relative to its record's range (inf where not
        finite)."""
        total = sum(float(np.sum(((self.displacement(config, model, e) - np.asarray(e["displacement"]))
                                  / max(float(np.ptp(e["displacement"])), np.finfo(float).tiny)) ** 2))
                    for e in recs)
        return total if np.isfinite(total) else np.inf


# ---------------------------------------------------------------------------------------------- the actuator


_CHARGE_KEYS = ("capacitance", "coupling")


class ActuatorModel(_WithState):
    r"""`pj.Actuator`: the blocks, `[charge]` ($q = C_p V + T\delta$: `capacitance`, `coupling`), `[state]`
    (`offset`, `prehistory`: `true` fitted from a data-driven start, `false` absent, or a number, the start) and
    `[input]` (`delay`, a `pj.Delay` of the voltage, in seconds, the same way)."""

    table, name = None, "actuator"
    blocks = ("hysteresis", "creep", "dynamics")
    tables = ("charge", "state", "input")
    scale_in_dynamics = True
    cold_start = True

    def parse(self, t, raw, source):
        out: dict = {"charge": None, "state": parse_state(raw, source), "input": parse_input(raw, source)}
        if "charge" in raw:
            cht = ConfigTable(source, "charge", raw["charge"], _CHARGE_KEYS)
            out["charge"] = {"capacitance": cht.number("capacitance", None, nonnegative=True),
                             "coupling": cht.number("coupling", None)}
        return out

    def outputs(self, config):
        return ("displacement", "charge", "current") if config.charge is not None else ("displacement",)

    def predictor(self, config):
        return actuator_predictor()

    def records(self, config, dataset):
        recs = [(np.asarray(e.v_in), np.asarray(e["displacement"]), e.dt) for e in dataset if e.has("displacement")]
        if not recs:
            raise PiezojaxValueError("data-driven initial values need data files with a 'displacement' column "
                                     "(or give every parameter value explicitly in the configuration)")
        return recs

    def missing(self, config):
        charge = config.charge or {}
        return [f"[charge] {k}" for k in _CHARGE_KEYS if config.charge is not None and charge.get(k) is None] + (
            super().missing(config)) + (["[input] delay"] if self.delay(config) is True else [])

    def build(self, config, blocks, data):
        cap = coup = 0.0
        if config.charge is not None:
            cap, coup = self._charge(config, data)
        delay = self.delay(config)
        if delay is not False:  # a start of one sample where the data will set it (none: any positive value)
            delay = pj.Delay(f64(delay if delay is not True else data.dt() if data is not None else 1e-6))
        return pj.Actuator(blocks["hysteresis"], blocks["creep"], blocks["dynamics"], capacitance=f64(cap),
                           coupling=f64(coup), structure=config.creep_structure, **self.state_values(config),
                           delay=None if delay is False else delay)

    def delay(self, config):
        """`[input] delay`: `True`, `False` or its start [s]."""
        return config.model_options.get("input", {}).get("delay", False)

    def constraints(self, config):
        return {"delay.time": pj.Positive} if self.delay(config) is not False else {}

    def default_free(self, config):
        return (("capacitance", "coupling") if config.charge is not None else ()) + self.state_free(config) + (
            ("delay.time",) if self.delay(config) is not False else ())

    def start_state(self, config, model, dataset):
        """`_WithState`'s offset and prehistory; then, where `[input] delay = true`, the delay of a grid from a
        quarter of a sample to eight samples whose simulation is closest to the data (the offset started again)."""
        model = super().start_state(config, model, dataset)
        if self.delay(config) is not True:
            return model
        recs = [e for e in dataset if e.has("displacement")]
        if not recs:
            return model
        dt = min(e.dt for e in recs)
        best, best_err = model, np.inf
        for k in (0.25, 0.5, 1.0, 2.0, 3.0, 5.0, 8.0):
            cand = eqx.tree_at(lambda a: a.delay.time, model, jnp.asarray(k * dt, model.delay.time.dtype))
            cand = self.with_offset(config, cand, recs)
            err = self.start_error(config, cand, recs)
            if err < best_err:
                best, best_err = cand, err
        return best

    def fit_free(self, config, free, targets):
        if targets is not None and not {"charge", "current"} & set(targets):
            # the displacement does not depend on them
            free = [p for p in free if p not in ("capacitance", "coupling")]
        return free

    def _charge(self, config, data) -> tuple[float, float]:
        o = config.charge
        cap, coup = o.get("capacitance"), o.get("coupling")
        if cap is not None and coup is not None:
            return cap, coup
        if data is None:
            return (1e-9 if cap is None else cap), (0.0 if coup is None else coup)
        # q = C v + T δ by least squares over the experiments that measured the charge (and the displacement), or
        # the current: the model's i_k = (q_k - q_{k-1})/dt from q_{-1} = 0 at rest, so q_k = dt (i_0 + ... + i_k)
        rows, rhs = [], []
        for e in data.dataset:
            if e.has("charge"):
                q = np.asarray(e["charge"])
            elif e.has("current"):
                q = e.dt * np.cumsum(np.asarray(e["current"]))
            else:
                continue
            d = np.asarray(e["displacement"]) if e.has("displacement") else np.zeros_like(q)
            if cap is not None:
                q = q - cap * np.asarray(e.v_in)
            if coup is not None:
                q = q - coup * d
            cols = ([] if cap is not None else [np.asarray(e.v_in)]) + ([] if coup is not None else [d])
            # and a constant per record: the displacement sensor's offset (T b), the charge at the record's start
            rows.append(np.column_stack(cols + [np.ones_like(q)]))
            rhs.append(q)
        if not rows:
            raise PiezojaxValueError(
                f"{config.source}: [charge]: give 'capacitance' and 'coupling' explicitly, or fit on data "
                "files with a 'charge' or 'current' column")
        k = rows[0].shape[1] - 1
        design = np.zeros((sum(r.shape[0] for r in rows), k + len(rows)))
        at = 0
        for j, r in enumerate(rows):
            design[at: at + r.shape[0], :k], design[at: at + r.shape[0], k + j] = r[:, :k], 1.0
            at += r.shape[0]
        coef = np.linalg.lstsq(design, np.concatenate(rhs), rcond=None)[0]
        i = 0
        if cap is None:
            cap, i = max(float(coef[0]), 0.0), 1
        if coup is None:
            coup = float(coef[i])
        return cap, coup


ACTUATOR = ActuatorModel()
