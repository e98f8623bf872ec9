"""Model configurations in TOML: which blocks, their sizes, optional initial values, and the fit options.

A configuration names the blocks of a model (`[hysteresis]`, `[creep]`, `[dynamics]`, `[charge]` for a
`pj.Actuator`; `[observer]` with `[hysteresis]`/`[creep]` for the self-sensing observer of paper 001) and the fit
options (`[fit]`). `ModelConfig.build` turns it into a (reparametrised) model: with explicit values where the file
gives them, data-driven initial values otherwise (`build(dataset)`), or placeholders of the right shapes when only the
structure is needed (to load a fitted model with `fitting.load_model`). Every error is a one-line
`PiezojaxValueError` naming the file, the table and the key, with the allowed values.

The configuration format is documented in the README ("Command line"); `piezojax fit --help` summarises it.
"""

import dataclasses
import warnings
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import piezojax as pj
from piezojax import PiezojaxValueError

from .._predict import predict
from .._problem import matches
from .kinds.base import BlockKind, StartData, get_kind
from .kinds.models import ACTUATOR, ModelKind, get_model_kind
from .kinds.options import CreepOptions, HysteresisOptions, KindOptions
from .table import MAX_POLYNOMIAL, ConfigTable, StartWarning, f64

TABLES = ("hysteresis", "creep", "dynamics", "charge", "state", "input", "observer", "model", "data", "fit")
MODEL_TABLES = ("observer", "model")  # the tables naming a whole-model kind (none: `pj.Actuator`)

MAX_STEPS = 100_000
MAX_LEVELS = 10
MAX_WEIGHT = 1e20  # a channel weight beyond it squares past float64 with the residuals it scales
_FIT_KEYS = ("free", "weights", "smoothing", "max_steps", "targets", "method")
_DATA_KEYS = ("units", "columns", "group", "sample_rate", "ignore_extra")
_WEIGHT_MODES = ("range", "noise")



def _parse_polynomial(t: ConfigTable) -> dict:
    """The output polynomial's keys, common to every hysteresis kind (`HysteresisOptions`): the fields to set."""
    degree = t.integer("polynomial", 0, minimum=0, maximum=MAX_POLYNOMIAL)
    if degree == 1:
        raise t.error("the output polynomial's degree must be 0 (none) or 2 and above: degree 1 would duplicate "
                      "the operator's gain", "polynomial")
    for key in ("coefficients", "polynomial_scale"):
        if degree == 0 and key in t.data:
            raise t.error("needs an output polynomial (polynomial = 2 or more)", key)
    if not degree:
        return {}
    return {"polynomial": degree, "coefficients": t.vector("coefficients", degree - 1),
            "polynomial_scale": t.number("polynomial_scale", None, positive=True)}


def _kind(source: str, name: str, data, kinds: tuple[str, ...]) -> str:
    if not isinstance(data, Mapping):
        raise PiezojaxValueError(f"{source}: [{name}]: must be a table, got {type(data).__name__}")
    if "kind" not in data:
        raise PiezojaxValueError(f"{source}: [{name}] kind: missing; allowed values: {', '.join(kinds)}")
    kind = data["kind"]
    if not isinstance(kind, str) or kind not in kinds:
        raise PiezojaxValueError(f"{source}: [{name}] kind: unknown kind {kind!r}; allowed kinds: {', '.join(kinds)}")
    return kind


# ------------------------------------------------------------------------------------------------ the configuration


@dataclasses.dataclass(frozen=True, eq=False)
class ModelConfig:
    """A parsed and validated model configuration (see `parse_config`).

    **Fields:**

    - `text`: the TOML text it was parsed from (saved next to a fitted model, so the structure can be rebuilt).
    - `source`: the file name used in error messages.
    - `hysteresis`, `creep`, `dynamics`: the kinds of the blocks (`"none"` for no block; the dynamics' default
      `"transfer_function"`, order 0 when the file has no `[dynamics]`), with their validated options in
      `hysteresis_options`, `creep_options`, `dynamics_options`: each the kind's `Options` dataclass (see
      `fitting.BlockKind`), holding the table's common keys too (`fitting.HysteresisOptions`: the output
      polynomial; `fitting.CreepOptions`: the structure).
    - `model`: `"actuator"` (`pj.Actuator`) or the observer kind of `[observer]`; `model_options` its options
      (the actuator's: `charge`, the `[charge]` options or `None`; both: `state`, the `[state]` options).
    - `free`, `weights`, `smoothing`, `max_steps`, `targets`, `method`: the `[fit]` options (`free=None`: the default
      set of `default_free`; `method`: `fitting.solve`'s, default `"levenberg_marquardt"`).
    - `data`: the `[data]` options for reading the files — `units`, `columns`, `group`, `sample_rate`,
      `ignore_extra`, as the keyword arguments of `fitting.load_experiment` (only those the file gives).
    """

    text: str
    source: str
    hysteresis: str
    hysteresis_options: HysteresisOptions
    creep: str
    creep_options: CreepOptions
    dynamics: str
    dynamics_options: KindOptions
    model: str
    model_options: dict
    free: tuple[str, ...] | None
    weights: Any
    smoothing: tuple[float, ...] | None
    max_steps: int
    targets: tuple[str, ...] | None
    method: str = "levenberg_marquardt"
    data: dict = dataclasses.field(default_factory=dict)

    # -------------------------------------------------------------------------------------------- structure

    def kind(self, table: str) -> BlockKind:
        """The registered kind of a block table (`"hysteresis"`, `"creep"`, `"dynamics"`)."""
        return get_kind(table, getattr(self, table))

    def options(self, table: str) -> KindOptions:
        """The options of a block table (`hysteresis_options`, ...)."""
        return getattr(self, f"{table}_options")

    @property
    def hysteresis_kind(self) -> BlockKind:
        return self.kind("hysteresis")

    @property
    def model_kind(self) -> ModelKind:
        return get_model_kind(self.model)

    @property
    def is_observer(self) -> bool:
        return self.model_kind.table == "observer"

    @property
    def observer(self) -> dict | None:
        """The `[observer]` options (`None` for another model)."""
        return self.model_options if self.is_observer else None

    @property
    def charge(self) -> dict | None:
        """The actuator's `[charge]` options (`None`: no charge output)."""
        return self.model_options.get("charge") if self.model_kind is ACTUATOR else None

    @property
    def state(self) -> dict:
        """The `[state]` options (`offset`, `prehistory`)."""
        return self.model_options.get("state", {})

    @property
    def dynamics_order(self) -> int:
        """The order of the dynamics (0: none, or a dynamics kind without an order)."""
        return getattr(self.dynamics_options, "order", 0)

    @property
    def polynomial(self) -> int:
        """The degree of the hysteresis' output polynomial (0: none)."""
        return self.hysteresis_options.polynomial

    @property
    def creep_structure(self) -> str:
        """`"series"` (the creep after the hysteresis) or `"parallel"` (beside it, driven by the voltage): the
        file's `structure`, else the creep kind's default."""
        given = self.creep_options.structure
        return self.kind("creep").structures[0] if given is None else given

    def block_path(self, table: str) -> str:
        """Where a block's parameters are: `hysteresis.hysteresis` for the operator inside an output polynomial."""
        return "hysteresis.hysteresis" if table == "hysteresis" and self.polynomial else table

    def block_tables(self) -> tuple[str, ...]:
        return self.model_kind.blocks

    @property
    def outputs(self) -> tuple[str, ...]:
        """The channels the model predicts: `displacement` (and `charge`, `current` with a `[charge]` table) for an
        actuator; `displacement`, `force` for the observer."""
        return self.model_kind.outputs(self)

    @property
    def inputs(self) -> tuple[str, ...]:
        """Measured channels the model reads besides `t` and `v_in` (`v_out` for the observer)."""
        return self.model_kind.inputs(self)

    def cost(self) -> int:
        """Relative cost per sample of the model (the Bouc–Wen RK4 substeps), for memory estimates."""
        return max([self.kind(t).cost(self.options(t)) for t in self.block_tables()] + [self.model_kind.cost(self)])

    def predictor(self):
        """The built-in `fitting.Predictor` for this model (`actuator_predictor()` or `observer_predictor()`); the
        channels to use are `outputs` (an actuator without `[charge]` predicts zero charge)."""
        return self.model_kind.predictor(self)

    def fit_targets(self, dataset) -> tuple[str, ...]:
        """The target channels for `dataset`: `[fit] targets`, else every channel of `outputs` the data measure."""
        have = set(dataset.channels)
        if self.targets is not None:
            missing = [c for c in self.targets if c not in have]
            if missing:
                raise PiezojaxValueError(f"{self.source}: [fit] targets: no data file has the channel(s) {missing}")
            return self.targets
        targets = tuple(c for c in self.outputs if c in have)
        if not targets:
            raise PiezojaxValueError(
                f"the data have none of the channels the model predicts ({', '.join(self.outputs)}); "
                f"they have: {', '.join(dataset.channels) or 'only t and v_in'}"
            )
        return targets

    def default_free(self) -> tuple[str, ...]:
        """The parameters fitted when `[fit] free` is not given: each block kind's `default_free` (every parameter
        except those a convention fixes because they would duplicate another parameter's effect: the dynamics' DC
        `gain`, the logarithmic creep's `gain`, the Bouc–Wen exponent `n` of the closed form, the Preisach switching
        values; every `smoothing`, a continuation setting), the output polynomial's coefficients, then the model's
        own (`offset`, `prehistory`, `capacitance`, `coupling` of an actuator; the observer's `force_sensitivity`,
        `displacement_coefficient`, `stiffness`, not its circuit constants)."""
        paths: list[str] = []
        for table in self.block_tables():
            where = self.block_path(table)
            paths += [f"{where}.{a}" for a in self.kind(table).default_free(self.options(table), self)]
            if table == "hysteresis" and self.polynomial:
                paths.append("hysteresis.coefficients")
        return tuple(paths) + self.model_kind.default_free(self)

    def fit_free(self, targets: tuple[str, ...] | None = None) -> list[str]:
        """`[fit] free`, else `default_free()` (without `capacitance`/`coupling` when `targets` has neither
        `charge` nor `current`: the displacement does not depend on them)."""
        if self.free is not None:
            return list(self.free)
        return self.model_kind.fit_free(self, list(self.default_free()), targets)

    # -------------------------------------------------------------------------------------------- building

    def missing_values(self) -> list[str]:
        """The parameters the file does not give explicitly (`"[hysteresis] thresholds"`, ...) that a forward
        simulation needs."""
        out = []
        for table in self.block_tables():
            o = self.options(table)
            out += [f"[{table}] {k}" for k in self.kind(table).required(o) if getattr(o, k) is None]
            if table == "hysteresis" and self.polynomial and self.hysteresis_options.coefficients is None:
                out.append("[hysteresis] coefficients")
        out += self.model_kind.missing(self)
        return out + [k for k in self.data_derived() if k not in out]

    def data_derived(self) -> list[str]:
        """The values the file does not give that a fit takes from its data (the output polynomial's
        `polynomial_scale`, a parallel logarithmic creep's `gain`, a Preisach grid's `range`, fixed; the dynamics'
        `gain` without hysteresis, fitted from there), as `"[table] key"`: a fit reports them (`derived_values`;
        `result.json` → `cli.data_derived`), and a forward simulation needs them given."""
        return list(self._derived())

    def derived_path(self, label: str) -> str:
        """The model path of the parameter behind a `data_derived` entry (`"[creep] gain"` → `"creep.gain"`)."""
        table, key = self._derived()[label]
        return "hysteresis.scale" if table is None else f"{self.block_path(table)}.{key}"

    def derived_values(self, model) -> dict:
        """The values of `data_derived` in `model` (unwrapped), by their CONFIG names, as CONFIG would give them."""
        out = {}
        for label, (table, key) in self._derived().items():
            if table is None:  # the output polynomial's scale
                out[label] = float(np.asarray(model.hysteresis.scale))
                continue
            block = model
            for name in self.block_path(table).split("."):
                block = getattr(block, name)
            out[label] = self.kind(table).derived_value(self.options(table), key, block)
        return out

    def _derived(self) -> dict[str, tuple[str | None, str]]:
        out = {}
        if self.polynomial and self.hysteresis_options.polynomial_scale is None:
            out["[hysteresis] polynomial_scale"] = (None, "polynomial_scale")
        for table in self.block_tables():
            o = self.options(table)
            for k in self.kind(table).data_derived(o, self):
                if getattr(o, k) is None:
                    out[f"[{table}] {k}"] = (table, k)
        return out

    def build(self, dataset=None, *, require_values: bool = False):
        """The model this configuration describes, with its constrained parameters reparametrised for fitting.

        **Arguments:**

        - `dataset`: a `fitting.Dataset` to draw initial values from where the file gives none: the first (closest
          to the data) of `starts(dataset)`. `None`: placeholders of the right shapes (enough for
          `fitting.load_model(folder, like=...)`).
        - `require_values`: raise if any parameter a forward simulation needs is not given explicitly.

        **Returns:** the reparametrised model (`pj.unwrap` it to use it), each parameter under its kind's constraint
        (`BlockKind.constraints`, `ModelKind.constraints`).
        """
        if require_values:
            missing = self.missing_values()
            if missing:
                derived = [k for k in missing if k in self._derived()]
                raise PiezojaxValueError(
                    f"{self.source}: forward simulation needs every parameter value; missing: {', '.join(missing)}"
                    + (f" ({', '.join(derived)}: what a fit takes from its data when the file omits it; `piezojax "
                       "fit` reports the value at the end of report.txt and in result.json under cli.data_derived)"
                       if derived else "")
                )
        if dataset is None:
            return self.constrain(self._assemble(None))
        return self.starts(dataset)[0]

    def starts(self, dataset, *, cold_start: bool = True) -> list:
        """Every data-driven start of the model, the one closest to the data first, each reparametrised as `build`
        returns it: the kinds' rule-based starts, and, where the blocks allow it and `cold_start` is true, the joint
        cold start (`fitting.cold_start_actuator`; a PI surrogate for other hysteresis families). Each has the same
        structure, so they can be fitted together (`fitting.fit(starts[0], ..., starts=starts)`): closest to the
        data is not always the start that converges best. A cold start that fails (a degenerate record) is left out
        with a `StartWarning`."""
        models = [self._assemble(StartData(self, dataset, use_cold_start=False))]
        if self.model_kind.cold_start and cold_start:
            try:
                data = StartData(self, dataset)
                if data.cold_start() is not None:
                    models.append(self._assemble(data))
            except PiezojaxValueError as e:
                warnings.warn(f"{self.source}: the data-driven cold start failed ({e}); starting from the simple "
                              "rules instead", StartWarning, stacklevel=2)
        models = [self.model_kind.start_state(self, m, dataset) for m in models]
        if self.model_kind.cold_start and len(models) > 1:
            models.sort(key=lambda m: _start_error(m, dataset, self.predictor()))
        return [self.constrain(m) for m in models]

    def _assemble(self, data: StartData | None):
        blocks = {"hysteresis": None, "creep": None, "dynamics": None}
        for table in self.block_tables():
            kind, o = self.kind(table), self.options(table)
            block = kind.build(o, kind.values(o, data), self)
            if table == "hysteresis" and block is not None and self.polynomial:
                coefficients = self.hysteresis_options.coefficients
                coefficients = np.zeros(self.polynomial - 1) if coefficients is None else coefficients
                block = pj.OutputPolynomial(block, f64(coefficients), f64(self._polynomial_scale(data)))
            blocks[table] = block
        return self.model_kind.build(self, blocks, data)

    def _polynomial_scale(self, data: StartData | None) -> float:
        """The output polynomial's scale: explicit, else the largest deviation of the quasi-static output from its
        mean (so the coefficients are of order one), else 1."""
        s = self.hysteresis_options.polynomial_scale
        if s is not None:
            return s
        if data is None:
            return 1.0
        dev = max(float(np.max(np.abs(y - np.mean(y)))) for _, y, _ in data.records())
        return dev if dev > 0 else 1.0

    def constrain(self, model):
        for table in self.block_tables():
            where = self.block_path(table).split(".")
            for attr, reparam in self.kind(table).constraints(self.options(table)).items():
                model = pj.constrain(model, attribute_getter(where + attr.split(".")), _off_the_bound(reparam))
        for attr, reparam in self.model_kind.constraints(self).items():
            model = pj.constrain(model, attribute_getter(attr.split(".")), _off_the_bound(reparam))
        return model


def _off_the_bound(reparam):
    """`reparam` (a class), wrapping a value that a fitted model may hold at its bound: a positive parameter whose
    softplus underflowed to 0, or ordered ones that underflowed onto their neighbour (a re-seeding round refits from
    such a model, and `from_value` refuses the bound itself) is moved off it by a rounding-size step."""
    if reparam not in (pj.Positive, pj.OrderedPositive):
        return reparam

    def factory(value):
        if isinstance(value, jax.core.Tracer):
            return reparam.from_value(value)
        v = np.asarray(value)
        if not (np.issubdtype(v.dtype, np.floating) and np.all(np.isfinite(v))):
            return reparam.from_value(value)  # refused there, naming `value`
        # a step of rounding size at the value's scale (subnormal steps are flushed to zero in XLA's checks)
        step = np.finfo(v.dtype).eps * max(float(np.max(np.abs(v), initial=0.0)), 1.0)
        lifted = np.where(v == 0, step, v)  # exactly at the bound only: a negative value is still refused
        if reparam is pj.OrderedPositive and lifted.ndim == 1:
            for i in range(1, lifted.size):
                if lifted[i] == lifted[i - 1]:
                    lifted[i] = lifted[i - 1] + step
        return reparam.from_value(jnp.asarray(lifted, v.dtype) if np.any(lifted != v) else value)

    return factory


# candidate thresholds scored when a freed play is placed where the residual needs it: at most RESEED_GRID, fewer on
# long records so that the plays' outputs (live and candidates, 8 bytes per sample each) stay within RESEED_MEMORY
# (measured on one 1e6-sample record: 70 plays raised the peak by 1.2 GB, 33 by 0.32 GB; with the 16 this gives,
# the whole `piezojax fit` peaked at 1.80 GB against 1.77 GB placing by the widest gaps)


def all_fitted(where: str, attrs, free) -> bool:
    """Whether `free` selects every attribute `attrs` of the block at path `where`."""
    return all(any(matches(f"{where}.{a}", p) for p in free) for a in attrs)


def attribute_getter(path: list[str]):
    """A function that reads the attribute at `path` (a list of names) of a model: the `where` of `pj.constrain`."""
    def get(m):
        for name in path:
            m = getattr(m, name)
        return m

    return get


# ------------------------------------------------------------------------------------------------ initial values


def _start_error(model, dataset, predictor=None) -> float:
    """Sum over experiments of the squared displacement error of an actuator (predicted by `predictor`, default the
    built-in one of its type), relative to the displacement range."""
    total = 0.0
    for e in dataset:
        if e.has("displacement"):
            y = np.asarray(e["displacement"])
            err = predict(model, e, predictor=predictor, check_finite=False)["displacement"] - y
            total += float(np.sum((err / max(float(np.ptp(y)), np.finfo(float).tiny)) ** 2))
    return total if np.isfinite(total) else np.inf


# ------------------------------------------------------------------------------------------------ parse
