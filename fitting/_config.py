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
import math
import os
import tomllib
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import piezojax as pj
from piezojax._checks import PiezojaxValueError

from . import _nonlinear_kinds  # noqa: F401 - registers the [model] kinds
from ._data import CHANNELS, parse_columns, parse_units
from ._kinds import (
    DEFAULT_KIND,
    DUPLICATE_THRESHOLD,
    MAX_POLYNOMIAL,
    TINY,
    BlockKind,
    ConfigTable,
    StartData,
    f64,
    finite_number,
    get_kind,
    registered_kinds,
)
from ._model_kinds import ACTUATOR, ModelKind, get_model_kind, model_kinds
from ._predict import predict

TABLES = ("hysteresis", "creep", "dynamics", "charge", "state", "observer", "model", "data", "fit")
MODEL_TABLES = ("observer", "model")  # the tables naming a whole-model kind (none: `pj.Actuator`)

MAX_STEPS = 100_000
MAX_LEVELS = 10
MAX_WEIGHT = 1e20  # a channel weight beyond it squares past float64 with the residuals it scales
_POLYNOMIAL_KEYS = ("polynomial", "coefficients", "polynomial_scale")
_FIT_KEYS = ("free", "weights", "smoothing", "max_steps", "targets", "method")
_DATA_KEYS = ("units", "columns", "group", "sample_rate", "ignore_extra")
_WEIGHT_MODES = ("range", "noise")


class StartWarning(UserWarning):
    """One of the data-driven starts failed and another was used."""


def _parse_polynomial(t: ConfigTable) -> dict:
    """The output polynomial's keys, common to every hysteresis kind."""
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
      `hysteresis_options`, `creep_options`, `dynamics_options` (see `fitting.BlockKind`).
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
    hysteresis_options: dict
    creep: str
    creep_options: dict
    dynamics: str
    dynamics_options: dict
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

    def options(self, table: str) -> dict:
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
        return self.dynamics_options.get("order", 0)

    @property
    def polynomial(self) -> int:
        """The degree of the hysteresis' output polynomial (0: none)."""
        return self.hysteresis_options.get("polynomial", 0)

    @property
    def creep_structure(self) -> str:
        """`"series"` (the creep after the hysteresis) or `"parallel"` (beside it, driven by the voltage): the
        file's `structure`, else the creep kind's default."""
        return self.creep_options.get("structure", self.kind("creep").structures[0])

    def _block_path(self, table: str) -> str:
        """Where a block's parameters are: `hysteresis.hysteresis` for the operator inside an output polynomial."""
        return "hysteresis.hysteresis" if table == "hysteresis" and self.polynomial else table

    def _block_tables(self) -> tuple[str, ...]:
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
        return max([self.kind(t).cost(self.options(t)) for t in self._block_tables()] + [self.model_kind.cost(self)])

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
        for table in self._block_tables():
            where = self._block_path(table)
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
        for table in self._block_tables():
            o = self.options(table)
            out += [f"[{table}] {k}" for k in self.kind(table).required(o) if o.get(k) is None]
            if table == "hysteresis" and self.polynomial and o.get("coefficients") is None:
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
        return "hysteresis.scale" if table is None else f"{self._block_path(table)}.{key}"

    def derived_values(self, model) -> dict:
        """The values of `data_derived` in `model` (unwrapped), by their CONFIG names, as CONFIG would give them."""
        out = {}
        for label, (table, key) in self._derived().items():
            if table is None:  # the output polynomial's scale
                out[label] = float(np.asarray(model.hysteresis.scale))
                continue
            block = model
            for name in self._block_path(table).split("."):
                block = getattr(block, name)
            out[label] = self.kind(table).derived_value(self.options(table), key, block)
        return out

    def _derived(self) -> dict[str, tuple[str | None, str]]:
        out = {}
        if self.polynomial and self.hysteresis_options.get("polynomial_scale") is None:
            out["[hysteresis] polynomial_scale"] = (None, "polynomial_scale")
        for table in self._block_tables():
            o = self.options(table)
            for k in self.kind(table).data_derived(o, self):
                if o.get(k) is None:
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
            return self._constrain(self._assemble(None))
        return self.starts(dataset)[0]

    def starts(self, dataset) -> list:
        """Every data-driven start of the model, the one closest to the data first, each reparametrised as `build`
        returns it: the kinds' rule-based starts, and, where the blocks allow it, the joint cold start
        (`fitting.cold_start_actuator`; a PI surrogate for other hysteresis families). Each has the same structure,
        so they can be fitted together (`fitting.fit(starts[0], ..., starts=starts)`): closest to the data is not
        always the start that converges best. A cold start that fails (a degenerate record) is left out with a
        `StartWarning`."""
        models = [self._assemble(StartData(self, dataset, use_cold_start=False))]
        if self.model_kind.cold_start:
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
        return [self._constrain(m) for m in models]

    def reseeded(self, model, dataset, free, fit_args: Mapping | None = None) -> tuple[object, int] | None:
        """The fitted `model` with the hysteresis kind's dead elements re-seeded (`BlockKind.reseed`), reparametrised
        as `build` returns it, and how many moved; `None` when none is dead, the kind does not re-seed, or `free`
        does not fit both the weights and the thresholds of the hysteresis. With `fit_args` (the `predictor`,
        `targets` and `weights` of the fit) freed plays go where the residual needs them (`_residual_thresholds`),
        else to the widest gaps between the live thresholds; and when none is dead, one live element of a kind that
        swaps elements (`BlockKind.swap_form`: plays, Maxwell-slip elements) moves where the residual needs it if
        that lowers the cost (`_play_swap`). Before all of these, with `fit_args`, plays (not stops) may all be
        placed anew where the residual needs them (`_play_replace`); then `None` also means none moved."""
        kind = self.hysteresis_kind
        if "hysteresis" not in self._block_tables() or kind.empty or kind.element_parameters is None:
            return None
        where = self._block_path("hysteresis")
        if not _all_fitted(where, kind.element_parameters, free):
            return None
        plain = pj.unwrap(model)
        get = _getter(where.split("."))
        block = get(plain)
        vmax = max(float(np.max(np.abs(np.asarray(e.v_in)))) for e in dataset)
        place = None
        if fit_args is not None:
            def place(thresholds, weights, n):
                return _residual_thresholds(plain, get, where, dataset, fit_args, thresholds, weights, n, vmax)
        new, lin = (None, None) if fit_args is None else _play_replace(plain, get, where, dataset, fit_args, vmax,
                                                                       kind)
        if new is None:
            new = kind.reseed(self.hysteresis_options, block, vmax, place)
        if new is None and fit_args is not None:
            new = _play_swap(plain, get, where, dataset, fit_args, vmax, kind, lin)
        if new is None:
            return None
        before, after = kind.swap_form(block), kind.swap_form(new)
        old = np.asarray(before[1] if before else block.thresholds, float)
        now = np.asarray(after[1] if after else new.thresholds, float)
        moved = int(np.sum(np.min(np.abs(now[:, None] - old[None, :]), axis=1) > 1e-9 * vmax))
        return self._constrain(eqx.tree_at(get, plain, new)), moved

    def relocated_lags(self, model, dataset, free, fit_args: Mapping) -> tuple[object, int] | None:
        r"""The fitted `model` with its creep lags moved to the time constants the residual needs (`_lag_search`,
        the other parameters held; for creep kinds with `BlockKind.lag_gains`: Kelvin–Voigt and lag creep),
        reparametrised as `build` returns it, and how many lags moved; `None` when the creep kind has no such lags,
        `free` does not fit both their gains and time constants, or no set of time constants on the search grid
        lowers the cost by more than `RELOCATE_GAIN` of it and than a regressor of pure noise would. `fit_args`: the
        `predictor`, `targets` and `weights` of the fit.

        A fit can end with its lags in the wrong basin: measured on `experiments.plant_study`'s Bouc–Wen draw 5
        (true lags 0.198 s and 1.65 s), both starts ended with one lag near 1.04 s carrying most of the creep and
        the other at 0.093 s with a sixth of the true gain; the search put them at 0.23 and 1.79 s (linear cost
        prediction 38 % lower) and the fit from there reached the truth's cost (training 1.00x the noise, from
        1.57x)."""
        if "creep" not in self._block_tables():
            return None
        kind = self.kind("creep")
        if kind.lag_gains is None:
            return None
        where = self._block_path("creep")
        if not _all_fitted(where, (kind.lag_gains, "time_constants"), free):
            return None
        plain = pj.unwrap(model)
        get = _getter(where.split("."))
        found = _lag_search(plain, get, where, kind, dataset, fit_args)
        if found is None:
            return None
        gains, taus, moved = found
        block = get(plain)
        leaf = getattr(block, kind.lag_gains)
        new = eqx.tree_at(lambda b: (getattr(b, kind.lag_gains), b.time_constants), block,
                          (jnp.asarray(kind.from_gains(gains), leaf.dtype),
                           jnp.asarray(taus, block.time_constants.dtype)))
        return self._constrain(eqx.tree_at(get, plain, new)), moved

    def _assemble(self, data: StartData | None):
        blocks = {"hysteresis": None, "creep": None, "dynamics": None}
        for table in self._block_tables():
            kind, o = self.kind(table), self.options(table)
            block = kind.build(o, kind.values(o, data), self)
            if table == "hysteresis" and block is not None and self.polynomial:
                coefficients = o.get("coefficients")
                coefficients = np.zeros(self.polynomial - 1) if coefficients is None else coefficients
                block = pj.OutputPolynomial(block, f64(coefficients), f64(self._polynomial_scale(data)))
            blocks[table] = block
        return self.model_kind.build(self, blocks, data)

    def _polynomial_scale(self, data: StartData | None) -> float:
        """The output polynomial's scale: explicit, else the largest deviation of the quasi-static output from its
        mean (so the coefficients are of order one), else 1."""
        s = self.hysteresis_options.get("polynomial_scale")
        if s is not None:
            return s
        if data is None:
            return 1.0
        dev = max(float(np.max(np.abs(y - np.mean(y)))) for _, y, _ in data.records())
        return dev if dev > 0 else 1.0

    def _constrain(self, model):
        for table in self._block_tables():
            where = self._block_path(table).split(".")
            for attr, reparam in self.kind(table).constraints(self.options(table)).items():
                model = pj.constrain(model, _getter(where + attr.split(".")), _off_the_bound(reparam))
        for attr, reparam in self.model_kind.constraints(self).items():
            model = pj.constrain(model, _getter([attr]), _off_the_bound(reparam))
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
RESEED_GRID, RESEED_MEMORY = 64, 2**27


class _PlayWeights:
    r"""The fitted model's live plays (`thresholds`, `weights`) and candidate plays of weight 0 evenly on
    $(0, \max|v|)$ (at most `RESEED_GRID`, fewer on long records, see `RESEED_MEMORY`; less those within
    `DUPLICATE_THRESHOLD` of a live one), linearised together in their weights: $J^\top J$ and $J^\top r$ of the
    fit's weighted residual, formed as a fit's step forms them, with unit columns (so that no choice depends on the
    weights' scales). `decrease(t)` is what refitting the weights of the plays `t` (positions in `r`, the sorted
    thresholds) by linear least squares, the others held, takes off the sum of squares in the Gauss–Newton model
    (exact where the blocks after the hysteresis are linear), with the weights' changes; `live` and `candidates`
    are positions in `r`. `empty` when no candidate is left or the linearisation is not finite. With `stops`, the
    block is a sum of stops $\sum_i k_i S_{r_i}[v] = \sum_i k_i (v - P_{r_i}[v])$ (Maxwell slip; `weights` the
    $k_i$): it is linearised as the same operator in PI form (`as_prandtl_ishlinskii`: $w_0 = \sum k_i$, weights
    $-k_i$), and each stop's column is $w_0$'s less its play's."""

    def __init__(self, plain, get, where: str, dataset, fit_args: Mapping, thresholds, weights, vmax: float,
                 stops: bool = False):
        from ._problem import Problem

        tol = DUPLICATE_THRESHOLD * vmax
        samples = sum(e.n for e in dataset)
        size = int(min(RESEED_GRID, max(8, RESEED_MEMORY // (8 * samples) - len(thresholds))))
        self.spacing = vmax / size
        grid = (np.arange(size) + 0.5) / size * vmax
        grid = grid[np.min(np.abs(grid[:, None] - np.asarray(thresholds)[None, :]), axis=1) > tol]
        self.empty = grid.size == 0
        if self.empty:
            return
        r = np.r_[np.asarray(thresholds, float), grid]
        w = np.r_[np.asarray(weights, float), np.zeros(grid.size)]
        order = np.argsort(r)
        self.r, self.w = r[order], w[order]
        block = get(plain)
        if stops:
            block = block.as_prandtl_ishlinskii(0.0)
        sign = -1.0 if stops else 1.0
        trial = eqx.tree_at(lambda b: (b.weights, b.thresholds), block,
                            (jnp.asarray(sign * self.w, block.weights.dtype),
                             jnp.asarray(self.r, block.thresholds.dtype)))
        free = [f"{where}.weights"] + ([f"{where}.w0"] if stops else [])
        problem = Problem(eqx.tree_at(get, plain, trial), dataset, predictor=fit_args.get("predictor"),
                          targets=fit_args.get("targets"), weights=fit_args.get("weights", "range"),
                          free=free, scales="value")
        res, g, h = (np.asarray(x, float) for x in problem.normal_equations(problem.u0))
        if not (np.all(np.isfinite(g)) and np.all(np.isfinite(h))):
            self.empty = True
            return
        scales = np.asarray(problem.scales, float)
        g, h = g / scales, h / np.outer(scales, scales)  # in the weights themselves
        if stops:  # each stop's column: w0's less its play's
            names = problem.parameter_names()
            i0 = names.index(f"{where}.w0")
            plays_at = [j for j in range(len(names)) if j != i0]
            t = np.zeros((len(plays_at), len(names)))
            t[:, i0], t[np.arange(len(plays_at)), plays_at] = 1.0, -1.0
            g, h = t @ g, t @ h @ t.T
        # unit columns: the choice does not depend on the weights' scales; a weight changes by step / d
        self.d = np.sqrt(np.maximum(np.diag(h), TINY))
        self.g, self.h = g / self.d, h / np.outer(self.d, self.d)
        self.sse = float(np.sum(np.square(res)))
        position = np.empty_like(order)
        position[order] = np.arange(order.size)
        self.live = list(position[: len(thresholds)])
        self.candidates = list(position[len(thresholds):])
        # a play must explain more than a regressor of pure noise would: 25 sigma^2 (5 sigma), sigma^2 estimated
        # from what no combination of the live and candidate plays explains
        unexplained = max(self.sse - self.decrease(list(range(order.size)))[0], 0.0)
        self.floor = 25.0 * unexplained / max(problem.num_residuals - order.size, 1)

    def nonnegative(self) -> np.ndarray:
        r"""The weights of every play of `r` (live and candidate) that minimise the sum of squares of the
        Gauss–Newton model subject to weights $\ge 0$ (non-negative least squares: most come out 0). In the unit
        columns' coordinates $y = d\,w$ the model is
        $\mathrm{sse} + 2g^\top(y - y_0) + (y - y_0)^\top H (y - y_0) = \|A y - b\|^2 + \mathrm{const}$ with
        $H = A^\top A$, $A = \Lambda^{1/2}V^\top$ from $H = V\Lambda V^\top$ (eigenvalues below $10^{-12}$ of the
        largest set to that: candidate columns can be nearly dependent) and $b = A y_0 - \Lambda^{-1/2}V^\top g$."""
        import scipy.optimize

        lam, vec = np.linalg.eigh(self.h)
        lam = np.maximum(lam, 1e-12 * max(float(lam[-1]), TINY))
        a = np.sqrt(lam)[:, None] * vec.T
        c = (vec.T @ self.g) / np.sqrt(lam)
        return scipy.optimize.nnls(a, a @ (self.w * self.d) - c, maxiter=50 * self.h.shape[0])[0] / self.d

    def decrease(self, t, without=None):
        """`without`: a play (not in `t`) whose weight is set to 0, the plays `t` refitted with it removed."""
        t = list(t)

        def refit(g):  # the steps of the plays `t` minimising the Gauss-Newton model with gradient `g`
            return -np.linalg.solve(self.h[np.ix_(t, t)] + 1e-10 * np.eye(len(t)), g) if t else np.zeros(0)

        if without is None:
            step = refit(self.g[t])
            return -float(self.g[t] @ step), step
        # the sum of squares |r + J delta|^2 = sse + 2 g.delta + delta.H.delta with delta_i = -a (play i's weight,
        # in the unit columns' coordinates, to 0), minimised over delta_t
        i = without
        assert i not in t
        a = self.w[i] * self.d[i]
        g = self.g[t] - a * self.h[t, i]
        step = refit(g)
        return 2 * a * float(self.g[i]) - a * a * float(self.h[i, i]) - float(g @ step), step


def _residual_thresholds(plain, get, where: str, dataset, fit_args: Mapping, thresholds, weights, n: int,
                         vmax: float) -> list[float]:
    r"""Up to `n` thresholds for freed plays, chosen where the fit's residual needs them: the live plays
    (`thresholds`, `weights`) and the candidate plays of `_PlayWeights` are linearised together in their weights,
    and candidates are chosen greedily, each the one whose weight, fitted jointly with the live and chosen ones by
    linear least squares, lowers the cost most while the new plays' weights come out positive (orthogonal matching
    pursuit on the normal equations). Fewer than `n` when fewer candidates would each lower the sum of squares by
    more than $25\hat\sigma^2$ (what a regressor of pure noise would explain, at 5 sigma; $\hat\sigma^2$ from the
    part of the residual that no combination of the live and candidate plays explains)."""
    lin = _PlayWeights(plain, get, where, dataset, fit_args, thresholds, weights, vmax)
    if lin.empty:
        return []
    live = lin.live
    chosen: list[int] = []
    for _ in range(n):
        base = lin.decrease(live + chosen)[0]  # `live` is never empty (`_reseed_plays`)
        best, best_gain = None, lin.floor
        for j in lin.candidates:
            if j in chosen:
                continue
            total, step = lin.decrease(live + chosen + [j])
            if np.all(step[len(live):] > 0) and total - base > best_gain:  # the new plays' weights all grow
                best, best_gain = j, total - base
        if best is None:
            break
        chosen.append(best)
    return [float(lin.r[j]) for j in chosen]


# a live play whose removal costs least is swapped: the SWAP_CANDIDATES cheapest to remove are tried
SWAP_CANDIDATES = 8


def _play_swap(plain, get, where: str, dataset, fit_args: Mapping, vmax: float, kind: BlockKind,
               lin: "_PlayWeights | None" = None):
    r"""The fitted model's plays with one moved where the residual needs it, or `None`: every live play none of
    whose neighbours is dead (`_reseed_plays` found none) can still sit in a worse basin than another threshold
    (measured on a numpy plant of 5 plays at 10-95 V fitted with 5 plays: true 45 and 70 V ended at 44 and 51 V,
    1.41x the noise in training and up to 1.96x held out, converged; with 8 plays the fit reached 1.0x). Given the
    thresholds, the output is linear in the weights (`_PlayWeights`): for each of the `SWAP_CANDIDATES` live plays
    whose removal costs least and each candidate threshold, the weights of the set with that play swapped for the
    candidate are refitted by linear least squares; the best set, with positive weights, is taken when it lowers
    the sum of squares below the live plays' own refit by more than `RELOCATE_GAIN` of it and than a regressor of
    pure noise would ($25\hat\sigma^2$). The swapped plays start at those refitted weights. The kind gives its
    elements as weighted plays or stops (`BlockKind.swap_form`; `None`: it swaps none) and builds the block back.
    `lin`: that linearisation when already formed (`_play_replace` forms the same one for plays)."""
    block = get(plain)
    form = kind.swap_form(block)
    if form is None:
        return None
    if lin is None:
        lin = _PlayWeights(plain, get, where, dataset, fit_args, np.asarray(form[1], float),
                           np.asarray(form[0], float), vmax, form[2])
    if lin.empty:
        return None
    live = lin.live
    base = lin.decrease(live)[0]
    loss = [base - lin.decrease([j for j in live if j != i], without=i)[0] for i in live]
    best, best_gain = None, max(RELOCATE_GAIN * (lin.sse - base), lin.floor)
    for i in [live[k] for k in np.argsort(loss)[:SWAP_CANDIDATES]]:
        kept = [j for j in live if j != i]
        for c in lin.candidates:
            total, step = lin.decrease(kept + [c], without=i)
            weights = lin.w[kept + [c]] + step / lin.d[kept + [c]]
            if np.all(weights > 0) and total - base > best_gain:
                best, best_gain = (kept + [c], weights), total - base
    if best is None:
        return None
    chosen, weights = best
    order = np.argsort(lin.r[chosen])
    return kind.from_swap_form(block, weights[order], lin.r[chosen][order])


def _play_clusters(r: np.ndarray, w: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray] | None:
    """`n` plays from the non-negative weights `w` of plays at the sorted thresholds `r`: from the plays of weight
    above 1 % of the largest (the `n` largest if fewer are), the two neighbours whose merging moves the least
    weighted spread (Ward's criterion, $\frac{w_a w_b}{w_a + w_b}(r_a - r_b)^2$) are merged into one play at their
    weighted mean threshold with their summed weight (a play's output is continuous in its threshold), until `n`
    are left. `None` when fewer than `n` plays have weight."""
    top = float(np.max(w, initial=0.0))
    on = np.flatnonzero(w > 1e-12 * max(top, 1e-300))
    if on.size < n:
        return None
    strong = on[w[on] >= 0.01 * top]
    on = strong if strong.size >= n else np.sort(on[np.argsort(w[on])[::-1][:n]])
    centres, weights = list(r[on].astype(float)), list(w[on].astype(float))
    while len(centres) > n:
        a, b, c = np.asarray(weights[:-1]), np.asarray(weights[1:]), np.diff(centres)
        k = int(np.argmin(a * b / (a + b) * c**2))
        m = weights[k] + weights[k + 1]
        centres[k:k + 2] = [(weights[k] * centres[k] + weights[k + 1] * centres[k + 1]) / m]
        weights[k:k + 2] = [m]
    return np.asarray(centres), np.asarray(weights)


def _play_replace(plain, get, where: str, dataset, fit_args: Mapping, vmax: float, kind: BlockKind):
    r"""The fitted model's plays all placed anew where the residual needs them, or `None`. A fit can end with its
    plays in another basin than the data's best, every play a little off, so that no single play gains by moving
    (`_play_swap` finds nothing): measured on `experiments.plant_study`'s draws with six plays between 2 and 48 V,
    fits ended with every threshold 3-4 V above the truth's (training 1.01x the noise, 342 sigma^2 above the
    truth's sum of squares), or with two plays merged and the others shifted (735 sigma^2 above). Given the other
    parameters, the output is linear in the weights (`_PlayWeights`), and non-negative least squares over the live
    and candidate plays (`_PlayWeights.nonnegative`) puts weight in groups around the plant's thresholds, which are
    merged into as many plays as the block has (`_play_clusters`). The set is taken when its weights,
    refitted by linear least squares at the new thresholds, come out positive and lower the sum of squares below
    the live plays' own refit by more than a regressor of pure noise would ($25\hat\sigma^2$: the set has as many
    parameters as the fitted one, so any significant decrease is worth the fit from it); the plays start at those
    weights. Plays (not stops: Maxwell slip keeps `_play_swap`). Returns `(block or None, the linearisation at the
    fitted plays or None)`, the second for `_play_swap`, which needs the same."""
    block = get(plain)
    form = kind.swap_form(block)
    if form is None or form[2]:
        return None, None
    w, r = np.asarray(form[0], float), np.asarray(form[1], float)
    lin = _PlayWeights(plain, get, where, dataset, fit_args, r, w, vmax)
    if lin.empty:
        return None, lin
    base = lin.sse - lin.decrease(lin.live)[0]
    found = _play_clusters(lin.r, lin.nonnegative(), r.size)
    if found is None:
        return None, lin
    r_new, w_new = found
    if np.all(np.abs(r_new - r) <= lin.spacing):  # every play where it was (to the candidates' resolution)
        return None, lin
    placed = kind.from_swap_form(block, w_new, r_new)
    new_form = kind.swap_form(placed)
    at = _PlayWeights(eqx.tree_at(get, plain, placed), get, where, dataset, fit_args, np.asarray(new_form[1], float),
                      np.asarray(new_form[0], float), vmax)
    if at.empty:
        return None, lin
    total, step = at.decrease(at.live)
    weights = at.w[at.live] + step / at.d[at.live]
    if not np.all(weights > 0) or base - (at.sse - total) <= lin.floor:
        return None, lin
    return kind.from_swap_form(block, weights, at.r[at.live]), lin


# creep time constants searched after a fit (`ModelConfig.relocated_lags`): LAG_GRID candidates log-spaced over
# [5 dt, the longest record] (fewer on long records, see RESEED_MEMORY); every set of as many as the creep has lags
# is scored when there are at most LAG_COMBINATIONS sets, else lags are swapped one at a time from the fitted ones
LAG_GRID, LAG_COMBINATIONS = 32, 20000
# a relocation must lower the cost by more than this fraction of it (and than noise would)
RELOCATE_GAIN = 1e-3


def _lag_search(plain, get, where: str, kind: BlockKind, dataset, fit_args: Mapping):
    r"""New time constants and gains for the creep lags of the fitted model `plain` (its block at `get`, at path
    `where`, of the creep kind `kind`), or `None`. Given the rest of the model, the output is linear in the lags'
    gains (`BlockKind.lag_gains`) — Kelvin–Voigt $c_j = 1/k_j$ (in parallel, $\delta = G[h + \sum_j c_j
    L_{\tau_j}[v]]$; in series, $\delta = G[(1 + \sum_j c_j L_{\tau_j})[h]]$), a lag creep's fractions
    ($(1 - \sum_j a_j + \sum_j a_j L_{\tau_j})[h]$) — so one linearisation in the gains of the fitted lags and of
    `LAG_GRID` candidate lags
    (log-spaced over $[5\,dt_{min}, T_{max}]$, at a negligible gain) gives the exact weighted sum of squares of any
    set of them with its gains refitted by linear least squares, the other parameters held. Every set of as many
    lags as the block has is scored (by single swaps from the fitted set when there are more than
    `LAG_COMBINATIONS`), keeping those whose gains come out positive (summing below `kind.max_total_gain`); the best is
    returned as `(gains, time_constants, moved)` (`moved`: lags not at a fitted time constant) when it lowers the
    sum of squares — the fit's, or the fitted lags' with their gains refitted where that is lower, so that what
    refitting the gains alone would gain does not count as a move — by more than `RELOCATE_GAIN` of it and more than
    $25\hat\sigma^2$ (a regressor of pure noise
    explains $\hat\sigma^2$; $\hat\sigma^2$ from what no combination of the lags explains)."""
    from itertools import combinations

    from ._problem import Problem

    block = get(plain)
    name = kind.lag_gains
    leaf = getattr(block, name)
    tau = np.asarray(block.time_constants, float)
    m = tau.size
    c_now = np.asarray(kind.gains(np.asarray(leaf, float)), float)
    if m == 0 or not (np.all(np.isfinite(c_now)) and np.all(c_now > 0) and np.all(tau > 0)):
        return None
    dt = min(float(e.dt) for e in dataset)
    longest = max(e.n * float(e.dt) for e in dataset)
    # fewer candidates on long records: the lags' outputs (8 bytes per sample each) within RESEED_MEMORY, as the
    # plays' (measured on a 1e6-sample record: 34 lags raised the fit's peak from 1.7 to 2.9 GB, 16 to 1.87)
    samples = sum(e.n for e in dataset)
    grid = np.geomspace(5 * dt, longest, int(min(LAG_GRID, max(8, RESEED_MEMORY // (8 * samples) - m))))
    grid = grid[np.min(np.abs(np.log(grid[:, None] / tau[None, :])), axis=1) > 1e-3]
    # candidates at a negligible gain, within a bounded sum (a lag creep's fractions summing to nearly 1)
    room = kind.max_total_gain - float(np.sum(c_now))
    eps = 1e-9 * max(float(np.sum(c_now)), TINY) if not np.isfinite(room) else min(
        1e-9 * max(float(np.sum(c_now)), TINY), 0.5 * room / max(grid.size, 1))
    if not eps > 0:
        return None
    c0 = np.r_[c_now, np.full(grid.size, eps)]
    taus = np.r_[tau, grid]
    trial = eqx.tree_at(lambda b: (getattr(b, name), b.time_constants), block,
                        (jnp.asarray(kind.from_gains(c0), leaf.dtype), jnp.asarray(taus, block.time_constants.dtype)))
    problem = Problem(eqx.tree_at(get, plain, trial), dataset, predictor=fit_args.get("predictor"),
                      targets=fit_args.get("targets"), weights=fit_args.get("weights", "range"),
                      free=[f"{where}.{name}"], scales=np.ones(c0.size))
    res, g, h = (np.asarray(x, float) for x in problem.normal_equations(problem.u0))
    # from the parameter's values to the gains (elementwise): dr/dc = dr/dtheta dtheta/dc
    f = np.asarray(jax.jvp(kind.from_gains, (jnp.asarray(c0),), (jnp.ones(c0.size),))[1], float)
    g, h = g * f, h * np.outer(f, f)
    if not (np.all(np.isfinite(res)) and np.all(np.isfinite(g)) and np.all(np.isfinite(h))):
        return None
    # the sum of squares with every gain 0, and its gradient there: sse(c) = base + 2 gb.c + c'Hc, exactly
    base = float(res @ res) - 2 * float(g @ c0) + float(c0 @ h @ c0)
    gb = g - h @ c0
    d = np.sqrt(np.maximum(np.diag(h), TINY))
    hn = h / np.outer(d, d)

    def sse(sets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # per set (rows of column indices): sse, gains
        hs = hn[sets[:, :, None], sets[:, None, :]] + 1e-12 * np.eye(sets.shape[1])
        gs = (gb / d)[sets]
        with np.errstate(all="ignore"):
            y = -np.linalg.solve(hs, gs[..., None])[..., 0]
        out = base + np.einsum("si,si->s", gs, y)
        gains = y / d[sets]
        ok = np.all(gains > 0, axis=1) & (np.sum(gains, axis=1) < kind.max_total_gain) & np.isfinite(out)
        return np.where(ok, out, np.inf), gains

    fitted = np.arange(m)
    sse_now = base + 2 * float(gb[fitted] @ c_now) + float(c_now @ h[np.ix_(fitted, fitted)] @ c_now)
    refitted = float(sse(fitted[None])[0][0])  # the fitted lags with their gains refitted: not a move
    reference = min(sse_now, refitted) if np.isfinite(refitted) else sse_now
    if math.comb(c0.size, m) <= LAG_COMBINATIONS:
        sets = np.array(list(combinations(range(c0.size), m)))
        scores, gains = sse(sets)
        j = int(np.argmin(scores))
        best, best_sse, best_gains = sets[j], float(scores[j]), gains[j]
    else:  # swap one lag at a time, the best swap first, while one lowers the sum of squares
        best, best_sse, best_gains = fitted, sse_now, c_now
        for _ in range(4 * m):
            trials = np.array([np.r_[np.delete(best, p), q] for p in range(m) for q in range(c0.size)
                               if q not in best])
            scores, gains = sse(trials)
            j = int(np.argmin(scores))
            if not scores[j] < best_sse:
                break
            best, best_sse, best_gains = trials[j], float(scores[j]), gains[j]
    gn = gb / d
    unexplained = max(base - float(gn @ np.linalg.lstsq(hn, gn, rcond=None)[0]), 0.0)
    sigma2 = unexplained / max(problem.num_residuals - c0.size, 1)
    moved = int(np.sum(best >= m))
    if not moved or not reference - best_sse > max(RELOCATE_GAIN * reference, 25 * sigma2):
        return None
    order = np.argsort(taus[best])
    return best_gains[order], taus[best][order], moved


def _all_fitted(where: str, attrs, free) -> bool:
    """Whether `free` selects every attribute `attrs` of the block at path `where`."""
    from ._problem import matches

    return all(any(matches(f"{where}.{a}", p) for p in free) for a in attrs)


def _getter(path: list[str]):
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


def parse_config(text: str, source: str = "config") -> ModelConfig:
    """Parse and validate a model configuration from TOML text.

    **Arguments:**

    - `text`: the TOML text.
    - `source`: the name used in error messages (the file name).

    **Returns:** a `ModelConfig`. Any problem — TOML syntax, unknown table, key or kind, wrong type, wrong length —
    raises a one-line `PiezojaxValueError` naming the file, the table and key, and the allowed values.

    ```python
    cfg = parse_config('[hysteresis]\\nkind = "prandtl_ishlinskii"\\nplays = 8\\n[dynamics]\\norder = 2\\n')
    model = pj.unwrap(cfg.build(dataset))
    ```
    """
    if not isinstance(text, str):
        raise PiezojaxValueError(f"{source}: `text` must be the TOML text (a str; read a file with "
                                 f"`fitting.load_config`), got {type(text).__name__}")
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise PiezojaxValueError(f"{source}: not valid TOML ({' '.join(str(e).split())})") from e
    unknown = [k for k in raw if k not in TABLES]
    if unknown:
        raise PiezojaxValueError(
            f"{source}: unknown table or key [{unknown[0]}]; allowed tables: {', '.join(f'[{t}]' for t in TABLES)}"
        )
    for name, data in raw.items():
        if not isinstance(data, Mapping):
            raise PiezojaxValueError(f"{source}: {name} must be a table ([{name}]), got a {type(data).__name__}")
    if not any(k in raw for k in ("hysteresis", "creep", "dynamics") + MODEL_TABLES):
        raise PiezojaxValueError(
            f"{source}: no model blocks; give at least one of [hysteresis], [creep], [dynamics], [observer] or [model]"
        )

    # the model kind: the observer or model that [observer] / [model] names, else the actuator
    named = [t for t in MODEL_TABLES if t in raw]
    if len(named) > 1:
        raise PiezojaxValueError(f"{source}: [observer] and [model] both name a whole model; keep one")
    if named:
        table = named[0]
        model = _kind(source, table, raw[table], model_kinds(table))
        mkind = get_model_kind(model)
        mt = ConfigTable(source, table, raw[table], mkind.keys, model)
    else:
        model, mkind, mt = ACTUATOR.name, ACTUATOR, None
    for t in ("hysteresis", "creep", "dynamics", "charge", "state"):
        if t in raw and t not in mkind.tables + mkind.blocks:
            raise PiezojaxValueError(
                f"{source}: [{t}] is not used by the {mkind.name.replace('_', ' ')} model (kind {model!r}); remove "
                f"it, or remove [{mkind.table}] for an actuator model")

    # the blocks, each parsed by its kind
    kinds, opts = {}, {}
    for table in ("hysteresis", "creep", "dynamics"):
        if table not in mkind.blocks:  # a block the model does not have
            kinds[table] = DEFAULT_KIND[table]
            opts[table] = {"order": 0, "zero_pairs": 0, "real_zeros": 0} if table == "dynamics" else {}
            continue
        data = raw.get(table, {"kind": DEFAULT_KIND[table]} if table != "dynamics" else {"order": 0})
        if table == "dynamics" and isinstance(data, Mapping) and "kind" not in data:
            data = {**data, "kind": DEFAULT_KIND[table]}
        name = _kind(source, table, data, registered_kinds(table))
        kind = get_kind(table, name)
        common = (_POLYNOMIAL_KEYS if not kind.empty else ()) if table == "hysteresis" else (
            ("structure",) if table == "creep" and not kind.empty else ())
        t = ConfigTable(source, table, data, kind.keys + common, name)
        o = kind.parse(t, raw)
        if table == "hysteresis" and not kind.empty:
            o.update(_parse_polynomial(t))
        if table == "creep" and not kind.empty:
            structure = t.string("structure", ("series", "parallel"))
            allowed = [s for s in kind.structures if s in mkind.structures]
            if structure is not None and structure not in allowed or not allowed:
                if structure is not None and structure not in kind.structures:
                    raise t.error(kind.structure_note or f"a {name!r} creep supports only structure = "
                                  f"{' or '.join(map(repr, kind.structures))}", "structure")
                raise t.error(f"the {mkind.name.replace('_', ' ')} model adds its creep in "
                              f"{' or '.join(mkind.structures)} (paper 001's eq. 4 for the observer); use a kind that "
                              f"supports it, without another `structure`", "structure" if structure else "kind")
            if structure is not None:
                o["structure"] = structure
        kinds[table], opts[table] = name, o
    h_kind = kinds["hysteresis"]
    model_options = mkind.parse(mt, raw, source)
    if mkind.table is None and kinds["creep"] == "none" and h_kind == "none" and opts["dynamics"].get("order", 0) == 0:
        raise PiezojaxValueError(f"{source}: every block is 'none': the model has no parameters")
    outputs_of = ModelConfig(text="", source=source, hysteresis=h_kind, hysteresis_options=opts["hysteresis"],
                             creep=kinds["creep"], creep_options=opts["creep"], dynamics=kinds["dynamics"],
                             dynamics_options=opts["dynamics"], model=model, model_options=model_options, free=None,
                             weights="range", smoothing=None, max_steps=1, targets=None).outputs

    # fit options
    ft = ConfigTable(source, "fit", raw.get("fit", {}), _FIT_KEYS)
    if "kind" in ft.data:
        raise ft.error(f"unknown key 'kind'; allowed keys: {', '.join(_FIT_KEYS)}", "kind")
    free = ft.data.get("free")
    if free is not None:
        if not (isinstance(free, list) and free and all(isinstance(p, str) and p for p in free)):
            raise ft.error(f"must be a non-empty list of parameter paths (e.g. \"hysteresis.weights\"), got {free!r}",
                           "free")
        free = tuple(free)
    weights = ft.data.get("weights", "range")
    if isinstance(weights, str):
        if weights not in _WEIGHT_MODES:
            raise ft.error(f"unknown value {weights!r}; allowed values: \"range\", \"noise\" or a table "
                           "{channel = weight}", "weights")
    elif isinstance(weights, Mapping):
        bad = [c for c in weights if c not in CHANNELS]
        if bad:
            raise ft.error(f"unknown channel {bad[0]!r}; allowed channels: {', '.join(CHANNELS)}", "weights")
        for c, w in weights.items():
            if not (finite_number(w) and 0 < w <= MAX_WEIGHT):
                raise ft.error(f"weight of {c!r} must be a number > 0 and <= {MAX_WEIGHT:g}, got {w!r}", "weights")
        weights = {c: float(w) for c, w in weights.items()}
    else:
        raise ft.error(f"must be \"range\", \"noise\" or a table {{channel = weight}}, got {weights!r}", "weights")
    smoothing = ft.data.get("smoothing")
    if smoothing is not None:
        if not (isinstance(smoothing, list) and smoothing and all(
                finite_number(s) and s >= 0
                for s in smoothing)):
            raise ft.error(f"must be a non-empty list of numbers >= 0 (continuation levels), got {smoothing!r}",
                           "smoothing")
        if h_kind == "none":
            raise ft.error("continuation needs a hysteresis block with smoothing", "smoothing")
        if len(smoothing) > MAX_LEVELS:
            raise ft.error(f"at most {MAX_LEVELS} continuation levels, got {len(smoothing)}", "smoothing")
        smoothing = tuple(float(s) for s in smoothing)
    max_steps = ft.integer("max_steps", 500, minimum=1, maximum=MAX_STEPS)
    method = ft.string("method", ("levenberg_marquardt", "trust_region"), "levenberg_marquardt")
    targets = ft.data.get("targets")
    if targets is not None:
        outputs = outputs_of
        if not (isinstance(targets, list) and targets and all(isinstance(c, str) for c in targets)):
            raise ft.error(f"must be a non-empty list of channel names, got {targets!r}", "targets")
        bad = [c for c in targets if c not in outputs]
        if bad:
            raise ft.error(f"the model does not predict {bad[0]!r}; it predicts: {', '.join(outputs)}", "targets")
        targets = tuple(targets)
    if isinstance(weights, dict) and targets is not None:
        lacking = [c for c in targets if c not in weights]
        if lacking:
            raise ft.error(f"no weight for the target channel {lacking[0]!r}", "weights")

    # data options
    dtab = ConfigTable(source, "data", raw.get("data", {}), _DATA_KEYS)
    if "kind" in dtab.data:
        raise dtab.error(f"unknown key 'kind'; allowed keys: {', '.join(_DATA_KEYS)}", "kind")
    data: dict[str, Any] = {}
    for key, example in (("units", '{displacement = "um"}'), ("columns", '{u = "v_in", y = "displacement"}')):
        value = dtab.data.get(key)
        if value is None:
            continue
        if not isinstance(value, Mapping):
            raise dtab.error(f"must be a table, e.g. {example}, got {value!r}", key)
        (parse_units if key == "units" else parse_columns)(value, f"{source}: [data] {key}")
        data[key] = {str(k): v for k, v in value.items()}
    if "group" in dtab.data:
        if not isinstance(dtab.data["group"], str) or not dtab.data["group"]:
            raise dtab.error(f"must be the name of an HDF5 group (or .mat struct), got {dtab.data['group']!r}", "group")
        data["group"] = dtab.data["group"]
    fs = dtab.number("sample_rate", None, positive=True)
    if fs is not None:
        data["sample_rate"] = fs
    if "ignore_extra" in dtab.data:
        if not isinstance(dtab.data["ignore_extra"], bool):
            raise dtab.error(f"must be true or false, got {dtab.data['ignore_extra']!r}", "ignore_extra")
        data["ignore_extra"] = dtab.data["ignore_extra"]

    cfg = ModelConfig(
        text=text, source=source, hysteresis=h_kind, hysteresis_options=opts["hysteresis"], creep=kinds["creep"],
        creep_options=opts["creep"], dynamics=kinds["dynamics"], dynamics_options=opts["dynamics"], model=model,
        model_options=model_options, free=free, weights=weights, smoothing=smoothing, max_steps=max_steps,
        targets=targets, method=method, data=data,
    )
    if free is not None:
        from ._problem import matches, parameter_paths

        values = parameter_paths(cfg.build(None))
        paths = list(values)
        # without a [charge] table the actuator's capacitance and coupling act on no predicted channel
        no_charge = cfg.model_kind is ACTUATOR and cfg.charge is None
        charge_only = ("capacitance", "coupling") if no_charge else ()
        listed = [p for p in paths if p not in charge_only]
        for sel in free:
            matched = [p for p in paths if matches(p, sel)]
            if not matched:
                raise ft.error(f"unknown parameter path {sel!r}; the model's parameters: {', '.join(listed)}", "free")
            if sel in charge_only:
                raise ft.error(f"{sel!r} acts only on the charge and current, which this model does not predict: add "
                               "a [charge] table to fit it", "free")
            if all(jnp.size(values[p]) == 0 for p in matched):
                # e.g. `dynamics.poles` of a model with pole pairs only: nothing to fit
                sized = ", ".join(p for p in listed if jnp.size(values[p]) > 0)
                raise ft.error(f"{sel!r} has no entries in this model (its sizes come from the block tables); the "
                               f"model's parameters with entries: {sized}", "free")
    return cfg


def load_config(path: str | os.PathLike) -> ModelConfig:
    """Read and validate a TOML model configuration file (see `parse_config`).

    **Arguments:**

    - `path`: the `.toml` file.

    **Returns:** a `ModelConfig`; unreadable files and invalid content raise a one-line `PiezojaxValueError`.

    ```python
    cfg = load_config("pi_creep.toml"); init = cfg.build(fitting.Dataset.from_files(["run1.csv"]))
    ```
    """
    p = Path(os.fspath(path)).expanduser()
    if not p.exists():
        raise PiezojaxValueError(f"configuration file {str(p)!r} does not exist")
    if p.is_dir():
        raise PiezojaxValueError(f"configuration file {str(p)!r} is a directory")
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise PiezojaxValueError(f"cannot read configuration file {str(p)!r}: {e}") from e
    return parse_config(text, source=str(p))
