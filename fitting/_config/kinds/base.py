"""The contract of a block kind (`BlockKind`), the data its starts read (`StartData`) and the registry of
block kinds.


A kind is a `BlockKind` subclass registered with `register_kind`. It must define (abstract): the table it belongs to
(`hysteresis`, `creep` or `dynamics`), its name (`kind = "..."` in that table), its options (`Options`, a frozen
dataclass of its keys, `kinds/options.py`) and how they are validated (`parse`), its parameters (`parameters`),
placeholder values (`placeholder`, enough to rebuild the structure of a fitted model), data-driven initial values
(`start`), the block (`build`) and the constraints its parameters are fitted under (`constraints`). Defaults cover
the rest: which parameters a forward simulation needs (`required`: all), the parameters fitted by default
(`default_free`: all), the relative cost (1), and the hooks to re-seed, swap or move elements (none). The generic
configuration code (`fitting._config`) names no kind: it looks each one up here, so a new kind is one class in one
file:

```python
class WeightedPlayKind(fitting.BlockKind):      # a hysteresis kind: y = w P_r[v], for a user's own block class
    table, name = "hysteresis", "weighted_play"

    @dataclasses.dataclass(frozen=True)
    class Options(fitting.HysteresisOptions):   # its keys (and the table's: the output polynomial)
        weight: float | None = None
        threshold: float | None = None

    def parse(self, t, raw):
        return self.Options(weight=t.number("weight"), threshold=t.number("threshold", positive=True))
    def parameters(self, o): return ("weight", "threshold")
    def placeholder(self, o): return {"weight": 1.0, "threshold": 1.0}
    def start(self, o, data): return {"weight": data.static_gain(), "threshold": 0.1 * data.max_input()}
    def build(self, o, v, config): return MyWeightedPlay(v["weight"], v["threshold"])
    def constraints(self, o): return {"threshold": pj.Positive}

fitting.register_kind(WeightedPlayKind())       # now `[hysteresis] kind = "weighted_play"` works
```

The whole model (which blocks it has, its state and outputs) is a `ModelKind` (`kinds/models.py`).
"""

import abc
import dataclasses
import warnings
from collections.abc import Mapping
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from piezojax import PiezojaxValueError
from piezojax.internal import MAX_ROWS, row_subset

from ..._initialise import cold_start_actuator
from ..table import SURROGATE_PLAYS, ConfigTable, StartWarning, chord
from .options import TABLE_OPTIONS, KindOptions, common_keys

# ------------------------------------------------------------------------------------------------ starts


class StartData:
    """What a kind's `start` may use: the data, and the quantities every start needs, computed once.

    **Fields:** `config` (the `ModelConfig`), `dataset` (the `fitting.Dataset`).
    """

    def __init__(self, config, dataset, use_cold_start: bool = True):
        self.config, self.dataset = config, dataset
        self._records = None
        self._cold = None if use_cold_start else False

    def records(self) -> list[tuple[np.ndarray, np.ndarray, float]]:
        """`(v_in, y, dt)` per usable experiment, `y` the output of hysteresis + creep in the model's units (the
        displacement of an actuator, quasi-static; the model kind's `records`). Raises when there are none, or when
        every voltage is zero."""
        if self._records is None:
            recs = self.config.model_kind.records(self.config, self.dataset)
            if not max(float(np.max(np.abs(v))) for v, _, _ in recs) > 0:
                raise PiezojaxValueError("every 'v_in' column is identically zero: no initial values can be "
                                         "identified")
            self._records = recs
        return self._records

    def rows(self) -> list:
        """The rows a start's least squares use in each record: every row, or a fixed random subset of at most
        `MAX_ROWS` (200000) in all for longer records (`row_subset`)."""
        return row_subset([y.size for _, y, _ in self.records()], MAX_ROWS)

    def sampled(self, per_record) -> np.ndarray:
        """Per-record arrays (first axis: the record's samples) at `rows`, concatenated."""
        return np.concatenate([np.asarray(a)[k] for a, k in zip(per_record, self.rows())])

    def sampled_inputs(self) -> np.ndarray:
        """`inputs` at `rows`."""
        return self.sampled([v for v, _, _ in self.records()])

    def sampled_outputs(self) -> np.ndarray:
        """`outputs` at `rows`."""
        return self.sampled([y for _, y, _ in self.records()])

    def inputs(self) -> np.ndarray:
        """Every record's voltage, concatenated."""
        return np.concatenate([v for v, _, _ in self.records()])

    def outputs(self) -> np.ndarray:
        """Every record's `y` (see `records`), concatenated."""
        return np.concatenate([y for _, y, _ in self.records()])

    def max_input(self) -> float:
        """The largest |v_in| of the records."""
        return float(np.max(np.abs(self.inputs())))

    def static_gain(self) -> float:
        """Least-squares slope of `y` against the voltage (through the origin)."""
        return chord(self.inputs(), self.outputs())

    def dt(self) -> float:
        """The shortest sampling interval of the dataset."""
        return min(e.dt for e in self.dataset)

    def span(self) -> float:
        """The duration of the longest record."""
        return max(e.n * e.dt for e in self.dataset)

    @property
    def unit_drive(self) -> bool:
        """True when the creep acts on the voltage itself, ahead of the dynamics' gain (an actuator without
        hysteresis, where the dynamics carry the scale from volts to metres)."""
        return self.config.hysteresis_kind.empty and self.config.model_kind.scale_in_dynamics

    def cold_start(self):
        """`fitting.cold_start_actuator`'s joint start of every block, when each configured block is in its family
        (each kind's `cold_start_args`; a hysteresis kind outside it is replaced by a PI surrogate of
        `SURROGATE_PLAYS` plays), else `None`. Computed once."""
        if self._cold is None:
            self._cold = False
            cfg = self.config
            if self.dataset is not None and cfg.model_kind.cold_start:
                args = {}
                for table in ("hysteresis", "creep", "dynamics"):
                    kind = cfg.kind(table)
                    a = kind.cold_start_args(cfg.options(table), cfg)
                    if a is None and table == "hysteresis" and not kind.empty:
                        # another hysteresis family: a PI surrogate carries the joint start of creep and dynamics,
                        # and the hysteresis kind starts from the surrogate's output (`for_table`)
                        a = {"n_plays": SURROGATE_PLAYS}
                    if a is None:
                        return None
                    args.update(a)
                ds = [e for e in self.dataset if e.has("displacement")]
                if ds and args.get("n_plays"):
                    self._cold = cold_start_actuator(
                        ds, args["n_plays"], args.get("creep_order", 0), args.get("dynamics_order", 0),
                        structure=args.get("structure", "parallel"), creep=args.get("creep", "kelvin_voigt"),
                        constrained=False)
        return self._cold if self._cold is not False else None

    def for_table(self, table: str) -> "StartData":
        """The data a block kind of `table` starts from: with a joint cold start, a hysteresis kind sees the cold
        start's hysteresis output as its records (free of creep, dynamics, offset and noise), every other table
        the data themselves."""
        cold = self.cold_start()
        if table != "hysteresis" or cold is None or cold.hysteresis is None:
            return self
        recs = self.records()
        view = StartData(self.config, self.dataset, use_cold_start=False)
        view._records = [(v, np.asarray(_hysteresis_output(cold.hysteresis, jnp.asarray(v))), dt)
                         for v, _, dt in recs]
        return view


@jax.jit
def _hysteresis_output(hysteresis, v):
    return hysteresis(v)


# ------------------------------------------------------------------------------------------------ block kinds


def check_class_attributes(cls: type, names: tuple[str, ...]) -> None:
    """Refuse to instantiate `cls` while it leaves one of the abstract class attributes `names` undefined."""
    missing = [n for n in names if not any(n in vars(k) for k in cls.__mro__)]
    if missing:
        raise TypeError(f"Can't instantiate abstract class {cls.__name__} without the class attribute(s) "
                        f"{', '.join(missing)}")


class BlockKind(abc.ABC):
    """One kind of model block a CONFIG table can name (`[hysteresis] kind = "prandtl_ishlinskii"`).

    A concrete kind sets the abstract class attributes and defines the abstract methods; the other methods are
    defaults that fit most kinds, and the hooks at the end act only for kinds that opt in. `o` is the kind's options
    as `parse` returned them (an instance of `Options`), `v` the values of its parameters (explicit from the file,
    else from `start` or `placeholder`).

    **Abstract class attributes:**

    - `table`: `"hysteresis"`, `"creep"` or `"dynamics"`.
    - `name`: the kind's name in the table.
    - `Options`: the options' class, a frozen dataclass subclassing the table's (`fitting.HysteresisOptions`,
      `fitting.CreepOptions`, else `fitting.KindOptions`), one field per key (a parameter not given: `None`).

    **Class attributes with defaults:**

    - `keys`: the keys the kind accepts besides `kind` and the table's common keys (the output polynomial's for
      hysteresis, `structure` for creep): default, the fields `Options` adds to the table's.
    - `empty`: the kind is "no block" (`"none"`).
    - `structures`: creep only: the structures it may be used in (`"series"`, `"parallel"`), the first the default;
      `structure_note`: the error message for another structure (default: the allowed ones).
    - `lag_gains`: for a block of first-order lags (its `time_constants`) whose output is linear in their gains $c_j$
      given the rest of the model: the parameter that holds the gains (through `gains` / `from_gains`), so that
      `ModelConfig.relocated_lags` can move the lags after a fit; `max_total_gain`: a bound on the gains' sum (a
      lag creep's fractions stay below 1). `None` (default): the kind's lags are not moved.
    - `element_parameters`: the parameters of the block's elements (for plays: weights and thresholds) that must
      both be fitted for `ModelConfig.reseeded` to re-seed or swap them; `None` (default): it does neither.
    """

    table: ClassVar[str]
    name: ClassVar[str]
    Options: ClassVar[type[KindOptions]]
    empty: ClassVar[bool] = False
    structures: ClassVar[tuple[str, ...]] = ("parallel", "series")
    structure_note: ClassVar[str] = ""
    lag_gains: ClassVar[str | None] = None
    max_total_gain: ClassVar[float] = np.inf
    element_parameters: ClassVar[tuple[str, str] | None] = None

    def __new__(cls, *args, **kwargs):
        check_class_attributes(cls, ("table", "name", "Options"))
        return super().__new__(cls)

    @property
    def keys(self) -> tuple[str, ...]:
        """The fields `Options` adds to its table's options class (a kind may set `keys` instead)."""
        common = common_keys(self.table)
        return tuple(f.name for f in dataclasses.fields(self.Options) if f.name not in common)

    # -------------------------------------------------------------------------------------------- what every kind says

    @abc.abstractmethod
    def parse(self, t: ConfigTable, raw: Mapping) -> KindOptions:
        """The validated options of the table `t` (`raw`: the whole CONFIG, for keys that depend on other tables),
        an `Options`: parameter values the file does not give are `None`. The table's common keys are read by the
        configuration, not here."""

    @abc.abstractmethod
    def parameters(self, o) -> tuple[str, ...]:
        """The names of the block's parameters (fields of `o`, given by the file or `None`)."""

    @abc.abstractmethod
    def placeholder(self, o) -> dict:
        """Values of the right shapes for every parameter, without data."""

    @abc.abstractmethod
    def start(self, o, data: StartData) -> dict:
        """Data-driven initial values for every parameter (called when the file leaves some out)."""

    @abc.abstractmethod
    def build(self, o, v: dict, config) -> eqx.Module | None:
        """The block (`None` for an empty kind)."""

    @abc.abstractmethod
    def constraints(self, o) -> dict[str, type]:
        """Attribute of the block (a dotted path for a nested one, `"system.poles"`) → the `pj.AbstractReparam` it is
        fitted under (e.g. `{"weights": pj.Positive}`; `{}`: none)."""

    # -------------------------------------------------------------------------------------------- common defaults

    def required(self, o) -> tuple[str, ...]:
        """The parameters a forward simulation needs from the file (default: all)."""
        return self.parameters(o)

    def default_free(self, o, config) -> tuple[str, ...]:
        """Attributes fitted when `[fit] free` is not given (default: every parameter)."""
        return self.parameters(o)

    def data_derived(self, o, config) -> tuple[str, ...]:
        """Values that a fit, when the file omits them, sets from its data and keeps fixed (a scale, a grid): a
        forward simulation needs them, and a fit reports them (`derived_value`; default: none)."""
        return ()

    def derived_value(self, o, key: str, block):
        """The value of `key` (one of `data_derived`) in the built `block`, as the file would give it (default: the
        block's leaf of that name, a float)."""
        return float(np.asarray(getattr(block, key)))

    def cost(self, o) -> int:
        """Relative cost per sample (the Bouc–Wen RK4 substeps), for the fit's memory estimate (default: 1)."""
        return 1

    def optional_start(self, o, data: StartData) -> dict:
        """Values for the parameters a forward simulation does not need, when only those are missing (default:
        `start`; kinds whose `start` needs more data than these override it)."""
        return self.start(o, data)

    def values(self, o, data: StartData | None) -> dict:
        """Explicit values where the file gives them, the rest from the cold start, `start` (`optional_start` when
        only optional parameters are missing) or `placeholder` (no data)."""
        names = self.parameters(o)
        out = {k: getattr(o, k) for k in names}
        if any(x is None for x in out.values()):
            made = None
            if data is None:
                made = self.placeholder(o)
            elif all(getattr(o, k) is not None for k in self.required(o)):
                made = self.optional_start(o, data)
            else:
                cold = data.cold_start()
                if cold is not None:
                    made = self.from_cold_start(o, getattr(cold, self.table))
                if made is None:
                    made = self._safe_start(o, data.for_table(self.table))
            out = {k: (made[k] if out[k] is None else out[k]) for k in names}
        return out

    # -------------------------------------------------------------------------------------------- optional hooks

    def cold_start_args(self, o, config) -> dict | None:
        """Arguments of `fitting.cold_start_actuator` when this block is in its family (PI hysteresis — another
        hysteresis kind gets a PI surrogate —, Kelvin–Voigt creep in series or parallel, lag creep, none, even-order
        all-pole dynamics), else `None` (default)."""
        return None

    def from_cold_start(self, o, block) -> dict | None:
        """The parameter values in the cold start's block (`None`, default: use `start`'s rules)."""
        return None

    def swap_form(self, block):
        r"""The block's elements as `(weights, thresholds, stops)`: a sum of weighted plays $\sum_i w_i P_{r_i}$
        (`stops` False) or stops $\sum_i w_i (v - P_{r_i}[v])$ (True), the output linear in the weights, of which
        `ModelConfig.reseeded` may move one where the residual needs it (`fitting._config._play_swap`); `None`
        (default): it moves none."""
        return None

    def from_swap_form(self, block, weights, thresholds):
        """`block` with the elements `(weights, thresholds)` of `swap_form` (for a kind that defines `swap_form`)."""
        raise NotImplementedError(f"the {self.table} kind {self.name!r} has no `swap_form`")

    def reseed(self, o, block, max_input: float, place=None):
        """After a fit: `block` with its dead elements (that the fit left with no effect) moved to where they can
        act, or `None` when none is dead or the kind does not re-seed (default). `place`: see `_reseed_plays`.
        `ModelConfig.reseeded` calls it only for a kind that names its `element_parameters`."""
        return None

    def gains(self, values):
        """The lags' gains $c_j$ from the values of the parameter `lag_gains` (default: the values themselves);
        elementwise, in NumPy or JAX."""
        return values

    def from_gains(self, gains):
        """The values of the parameter `lag_gains` for the gains $c_j$ (the inverse of `gains`); elementwise."""
        return gains

    def _safe_start(self, o, data: StartData) -> dict:
        """`start`, or, when it fails on usable data, the placeholder values with a `StartWarning` (a start must not
        end the run: the fit may still get there)."""
        data.records()  # unusable data (no displacement, zero voltage) is the user's error, raised as such
        try:
            made = self.start(o, data)
            bad = [k for k, x in made.items() if not np.all(np.isfinite(np.asarray(x, float)))]
            if bad:
                raise FloatingPointError(f"non-finite {', '.join(bad)}")
            return made
        except Exception as e:  # noqa: BLE001 - any failure of a heuristic falls back to the placeholder
            warnings.warn(f"[{self.table}] {self.name}: the data-driven start failed ({type(e).__name__}: {e}); "
                          "starting from the placeholder values", StartWarning, stacklevel=3)
            return self.placeholder(o)


_KINDS: dict[tuple[str, str], BlockKind] = {}
BLOCK_TABLES = ("hysteresis", "creep", "dynamics")
DEFAULT_KIND = {"hysteresis": "none", "creep": "none", "dynamics": "transfer_function"}


def register_kind(kind: BlockKind, *, replace: bool = False) -> BlockKind:
    """Make a block kind available to CONFIG files (`[<kind.table>] kind = "<kind.name>"`).

    **Arguments:**

    - `kind`: an instance of a `BlockKind` subclass.
    - `replace`: allow replacing a registered kind of the same table and name (otherwise an error).

    **Returns:** `kind`.
    """
    if not isinstance(kind, BlockKind):
        raise PiezojaxValueError(f"`kind` must be a fitting.BlockKind instance, got {type(kind).__name__}")
    if kind.table not in BLOCK_TABLES:
        raise PiezojaxValueError(f"`kind.table` must be one of {', '.join(BLOCK_TABLES)}, got {kind.table!r}")
    if not isinstance(kind.name, str) or not kind.name:
        raise PiezojaxValueError(f"`kind.name` must be a non-empty string, got {kind.name!r}")
    base = TABLE_OPTIONS[kind.table]
    if not (isinstance(kind.Options, type) and issubclass(kind.Options, base)
            and "__dataclass_fields__" in vars(kind.Options)):
        raise PiezojaxValueError(f"`kind.Options` must be a frozen dataclass subclassing fitting.{base.__name__} "
                                 f"(decorated with @dataclasses.dataclass(frozen=True)), got {kind.Options!r}")
    if (kind.table, kind.name) in _KINDS and not replace:
        raise PiezojaxValueError(f"a {kind.table} kind named {kind.name!r} is already registered "
                                 "(pass replace=True to replace it)")
    _KINDS[kind.table, kind.name] = kind
    return kind


def unregister_kind(table: str, name: str) -> None:
    """Remove a registered block kind (for tests and interactive sessions)."""
    _KINDS.pop((table, name), None)


def registered_kinds(table: str) -> tuple[str, ...]:
    """The kind names a table accepts, in registration order."""
    return tuple(n for t, n in _KINDS if t == table)


def get_kind(table: str, name: str) -> BlockKind:
    return _KINDS[table, name]


class _NoBlock(BlockKind):
    """No block (`kind = "none"`): no keys of its own, no parameters; `Options`: the table's options class."""

    empty = True

    def parse(self, t, raw):
        return self.Options()

    def parameters(self, o):
        return ()

    def placeholder(self, o):
        return {}

    def start(self, o, data):
        return {}

    def build(self, o, v, config):
        return None

    def constraints(self, o):
        return {}
