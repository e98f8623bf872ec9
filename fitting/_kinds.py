"""The registry of model-block kinds a CONFIG can name: one class per kind, declaring everything about it.

A kind is a `BlockKind` subclass registered with `register_kind`: the table it belongs to (`hysteresis`, `creep` or
`dynamics`), its name (`kind = "..."` in that table), its keys and how they are validated (`parse`), its parameters
and which of them a forward simulation needs (`parameters`, `required`), placeholder values (`placeholder`, enough
to rebuild the structure of a fitted model), data-driven initial values (`start`), the block (`build`), the
constraints its parameters are fitted under (`constraints`) and the parameters fitted by default (`default_free`).
The generic configuration code (`fitting._config`) names no kind: it looks each one up here, so a new kind is one
class in one file:

```python
class WeightedPlay(fitting.BlockKind):          # a hysteresis kind: y = w P_r[v], for a user's own block class
    table, name, keys = "hysteresis", "weighted_play", ("weight", "threshold")
    def parse(self, t, raw):
        return {"weight": t.number("weight"), "threshold": t.number("threshold", positive=True)}
    def parameters(self, o): return ("weight", "threshold")
    def placeholder(self, o): return {"weight": 1.0, "threshold": 1.0}
    def start(self, o, data): return {"weight": data.static_gain(), "threshold": 0.1 * data.max_input()}
    def build(self, o, v, config): return MyWeightedPlay(v["weight"], v["threshold"])
    def constraints(self, o): return {"threshold": pj.Positive}

fitting.register_kind(WeightedPlay())          # now `[hysteresis] kind = "weighted_play"` works
```

The whole model (which blocks it has, its state and outputs) is a `ModelKind`: `pj.Actuator` when the CONFIG has no
`[observer]` table, else the observer kind it names (`register_model_kind`).
"""

import math
import warnings
from collections.abc import Mapping
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import piezojax as pj
from piezojax._checks import PiezojaxValueError
from piezojax._hysteresis.initialise import MAX_ROWS, columns_at_rows, row_subset

# Upper bounds on the sizes a CONFIG may ask for, checked before any work: beyond them the initialisation (dense
# NNLS over plays x samples) or the fit's memory grows past what the method is meant for.
MAX_PLAYS = 100
MAX_ELEMENTS = 100
MAX_LEVELS_PREISACH = 30
MAX_CREEP_ORDER = 10
MAX_SUBSTEPS = 64
MAX_POLYNOMIAL = 6
DYNAMICS_ORDERS = (0, 1, 2, 3, 4, 5, 6, 7, 8)

TINY = np.finfo(float).tiny
# plays whose thresholds lie closer than this fraction of the largest |input| count as one when re-seeding
DUPLICATE_THRESHOLD = 1e-4
# plays of the PI surrogate that starts creep and dynamics jointly when the hysteresis is of another family
SURROGATE_PLAYS = 10


def finite_number(x) -> bool:
    """A TOML number (not a bool) that is finite as a float (an integer of 400 digits is not)."""
    if isinstance(x, bool) or not isinstance(x, int | float):
        return False
    try:
        return math.isfinite(float(x))
    except OverflowError:
        return False


def chord(v: np.ndarray, y: np.ndarray) -> float:
    """Least-squares slope of y against v through the origin (1 when v is zero)."""
    den = float(np.dot(v, v))
    return float(np.dot(v, y)) / den if den > 0 else 1.0


class Negative(pj.AbstractReparam):
    r"""Elementwise negative parameter (real poles of the dynamics): $x = -\mathrm{softplus}(\mathrm{raw}) < 0$."""

    raw: jax.Array = eqx.field(converter=jnp.asarray)

    @classmethod
    def from_value(cls, value) -> "Negative":
        value = jnp.asarray(value)
        return cls(pj.inv_softplus(-value))

    def unwrap(self) -> jax.Array:
        return -pj.softplus(self.raw)


# ------------------------------------------------------------------------------------------------ one TOML table


class ConfigTable:
    """One TOML table of a CONFIG, with the file and table names for its error messages.

    **Arguments:**

    - `source`: the file name (the start of every error message).
    - `name`: the table's name (`hysteresis`, ...).
    - `data`: the table's contents.
    - `allowed`: the keys allowed besides `kind`; any other key is an error listing them.
    - `kind`: the kind named in the table, for the error message.

    The readers (`number`, `integer`, `string`, `vector`, `sized_vectors`) return `default` (`None`) when the key is
    absent and raise one `PiezojaxValueError` naming the file, table and key otherwise.
    """

    def __init__(self, source: str, name: str, data: Any, allowed: tuple[str, ...], kind: str | None = None):
        self.source, self.name = source, name
        if not isinstance(data, Mapping):
            raise self.error(f"must be a table ([{name}]), got {type(data).__name__}")
        self.data = dict(data)
        unknown = [k for k in self.data if k not in allowed and k != "kind"]
        if unknown:
            what = f" for kind {kind!r}" if kind is not None else ""
            raise self.error(
                f"unknown key {unknown[0]!r}; allowed keys{what}: {', '.join(allowed) if allowed else '(none)'}"
            )

    def error(self, msg: str, key: str | None = None) -> PiezojaxValueError:
        """A `PiezojaxValueError` `"<file>: [<table>] <key>: <msg>"` (to raise)."""
        where = f"[{self.name}] {key}" if key else f"[{self.name}]"
        return PiezojaxValueError(f"{self.source}: {where}: {msg}")

    def has(self, key: str) -> bool:
        return key in self.data

    def number(self, key: str, default=None, *, positive=False, nonnegative=False, nonzero=False):
        if key not in self.data:
            return default
        x = self.data[key]
        if not finite_number(x):
            raise self.error(f"must be a finite number, got {x!r}", key)
        if positive and not x > 0:
            raise self.error(f"must be > 0, got {x!r}", key)
        if nonnegative and not x >= 0:
            raise self.error(f"must be >= 0, got {x!r}", key)
        if nonzero and x == 0:
            raise self.error("must be nonzero", key)
        return float(x)

    def integer(self, key: str, default=None, *, minimum=None, maximum=None, allowed=None):
        if key not in self.data:
            return default
        x = self.data[key]
        if isinstance(x, bool) or not isinstance(x, int):
            raise self.error(f"must be an integer, got {x!r}", key)
        if allowed is not None and x not in allowed:
            raise self.error(f"must be one of {', '.join(map(str, allowed))}; got {x}", key)
        if minimum is not None and x < minimum:
            raise self.error(f"must be >= {minimum}, got {x}", key)
        if maximum is not None and x > maximum:
            raise self.error(f"must be <= {maximum} (the documented upper bound), got {x}", key)
        return x

    def string(self, key: str, allowed: tuple[str, ...], default=None):
        if key not in self.data:
            return default
        x = self.data[key]
        if not isinstance(x, str) or x not in allowed:
            raise self.error(f"unknown value {x!r}; allowed values: {', '.join(allowed)}", key)
        return x

    def vector(self, key: str, length: int | None, *, positive=False, nonnegative=False, negative=False,
               ascending=False):
        if key not in self.data:
            return None
        x = self.data[key]
        if not isinstance(x, list) or not all(finite_number(v) for v in x):
            raise self.error(f"must be a list of finite numbers, got {x!r}", key)
        if length is not None and len(x) != length:
            raise self.error(f"must have {length} entries (from the block's size), got {len(x)}", key)
        if not x:
            raise self.error("must not be empty", key)
        a = np.asarray(x, dtype=np.float64)
        if positive and not np.all(a > 0):
            raise self.error(f"entries must be > 0, got {x}", key)
        if nonnegative and not np.all(a >= 0):
            raise self.error(f"entries must be >= 0, got {x}", key)
        if negative and not np.all(a < 0):
            raise self.error(f"entries must be < 0, got {x}", key)
        if ascending and not np.all(np.diff(a) > 0):
            raise self.error(f"entries must be strictly ascending, got {x}", key)
        return a

    def sized_vectors(
        self, size_key: str, default_size: int, maximum: int, specs: dict[str, dict], *, minimum: int = 1
    ) -> tuple[int, list]:
        """A block of `size_key` elements (`minimum` to `maximum`) and its per-element vectors `specs` (name →
        `vector` options): the size is given, or taken from the vectors given (which must agree), else
        `default_size`."""
        n = self.integer(size_key, None, minimum=minimum, maximum=maximum)
        vectors = [self.vector(name, n, **opts) if n != 0 else self._absent(name, size_key)
                   for name, opts in specs.items()]
        sizes = {len(x) for x in vectors if x is not None}
        if n is None:
            if len(sizes) > 1:
                names = list(specs)
                raise self.error(f"`{names[0]}` and `{names[1]}` must have the same length", names[0])
            n = sizes.pop() if sizes else default_size
            if n > maximum:
                name = next(k for k, x in zip(specs, vectors) if x is not None)
                raise self.error(f"has {n} entries; at most {maximum} (the documented upper bound of "
                                 f"`{size_key}`)", name)
        return n, vectors

    def _absent(self, name: str, size_key: str):
        if name in self.data:
            raise self.error(f"not used with {size_key} = 0", name)
        return None


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
                    from ._initialise import cold_start_actuator

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


class BlockKind:
    """One kind of model block a CONFIG table can name (`[hysteresis] kind = "prandtl_ishlinskii"`).

    Subclasses set the class attributes and override the methods they need; `o` is the kind's options as `parse`
    returned them, `v` the values of its parameters (explicit from the file, else from `start` or `placeholder`).

    **Class attributes:**

    - `table`: `"hysteresis"`, `"creep"` or `"dynamics"`.
    - `name`: the kind's name in the table.
    - `keys`: the keys the kind accepts besides `kind` (and the table's common keys: the output polynomial's for
      hysteresis, `structure` for creep).
    - `empty`: the kind is "no block" (`"none"`).
    - `structures`: creep only: the structures it may be used in (`"series"`, `"parallel"`), the first the default;
      `structure_note`: the error message for another structure (default: the allowed ones).
    - `lag_gains`: for a block of first-order lags (its `time_constants`) whose output is linear in their gains $c_j$
      given the rest of the model: the parameter that holds the gains (through `gains` / `from_gains`), so that
      `ModelConfig.relocated_lags` can move the lags after a fit; `max_total_gain`: a bound on the gains' sum (a
      lag creep's fractions stay below 1). `None` (default): the kind's lags are not moved.
    """

    table: ClassVar[str]
    name: ClassVar[str]
    keys: ClassVar[tuple[str, ...]] = ()
    empty: ClassVar[bool] = False
    structures: ClassVar[tuple[str, ...]] = ("parallel", "series")
    structure_note: ClassVar[str] = ""
    lag_gains: ClassVar[str | None] = None
    max_total_gain: ClassVar[float] = np.inf

    def parse(self, t: ConfigTable, raw: Mapping) -> dict:
        """The validated options of the table `t` (`raw`: the whole CONFIG, for keys that depend on other tables).
        Parameter values the file does not give are `None` (or absent)."""
        return {}

    def parameters(self, o: dict) -> tuple[str, ...]:
        """The names of the block's parameters (keys of `o` when the file gives them)."""
        return ()

    def required(self, o: dict) -> tuple[str, ...]:
        """The parameters a forward simulation needs from the file (default: all)."""
        return self.parameters(o)

    def data_derived(self, o: dict, config) -> tuple[str, ...]:
        """Values that a fit, when the file omits them, sets from its data and keeps fixed (a scale, a grid): a
        forward simulation needs them, and a fit reports them (`derived_value`; default: none)."""
        return ()

    def derived_value(self, o: dict, key: str, block):
        """The value of `key` (one of `data_derived`) in the built `block`, as the file would give it (default: the
        block's leaf of that name, a float)."""
        return float(np.asarray(getattr(block, key)))

    def placeholder(self, o: dict) -> dict:
        """Values of the right shapes for every parameter, without data."""
        return {}

    def start(self, o: dict, data: StartData) -> dict:
        """Data-driven initial values for every parameter (called when the file leaves some out)."""
        return self.placeholder(o)

    def build(self, o: dict, v: dict, config) -> eqx.Module | None:
        """The block (`None` for an empty kind)."""
        return None

    def constraints(self, o: dict) -> dict[str, type]:
        """Attribute of the block (a dotted path for a nested one, `"system.poles"`) → the `pj.AbstractReparam` it is
        fitted under (e.g. `{"weights": pj.Positive}`)."""
        return {}

    def default_free(self, o: dict, config) -> tuple[str, ...]:
        """Attributes fitted when `[fit] free` is not given (default: every parameter)."""
        return self.parameters(o)

    def cold_start_args(self, o: dict, config) -> dict | None:
        """Arguments of `fitting.cold_start_actuator` when this block is in its family (PI hysteresis — another
        hysteresis kind gets a PI surrogate —, Kelvin–Voigt creep in series or parallel, lag creep, none, even-order
        all-pole dynamics), else `None`."""
        return None

    def from_cold_start(self, o: dict, block) -> dict | None:
        """The parameter values in the cold start's block (`None`: use `start`'s rules)."""
        return None

    def cost(self, o: dict) -> int:
        """Relative cost per sample (the Bouc–Wen RK4 substeps), for the fit's memory estimate."""
        return 1

    element_parameters: tuple[str, str] | None = None
    """The parameters of the block's elements (for plays: weights and thresholds) that must both be fitted for
    `ModelConfig.reseeded` to re-seed or swap them; `None`: it does neither."""

    def swap_form(self, block):
        r"""The block's elements as `(weights, thresholds, stops)`: a sum of weighted plays $\sum_i w_i P_{r_i}$
        (`stops` False) or stops $\sum_i w_i (v - P_{r_i}[v])$ (True), the output linear in the weights, of which
        `ModelConfig.reseeded` may move one where the residual needs it (`fitting._config._play_swap`); `None`
        (default): it moves none."""
        return None

    def from_swap_form(self, block, weights, thresholds):
        """`block` with the elements `(weights, thresholds)` of `swap_form`."""
        raise NotImplementedError

    def reseed(self, o: dict, block, max_input: float, place=None):
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

    def optional_start(self, o: dict, data: StartData) -> dict:
        """Values for the parameters a forward simulation does not need, when only those are missing (default:
        `start`; kinds whose `start` needs more data than these override it)."""
        return self.start(o, data)

    def values(self, o: dict, data: StartData | None) -> dict:
        """Explicit values where the file gives them, the rest from the cold start, `start` (`optional_start` when
        only optional parameters are missing) or `placeholder` (no data)."""
        names = self.parameters(o)
        out = {k: o.get(k) for k in names}
        if any(x is None for x in out.values()):
            made = None
            if data is None:
                made = self.placeholder(o)
            elif all(o.get(k) is not None for k in self.required(o)):
                made = self.optional_start(o, data)
            else:
                cold = data.cold_start()
                if cold is not None:
                    made = self.from_cold_start(o, getattr(cold, self.table))
                if made is None:
                    made = self._safe_start(o, data.for_table(self.table))
            out = {k: (made[k] if out[k] is None else out[k]) for k in names}
        return out


    def _safe_start(self, o: dict, data: StartData) -> dict:
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
            from ._config import StartWarning

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


# ---- hysteresis


class _NoBlock(BlockKind):
    empty = True


class NoHysteresis(_NoBlock):
    table, name = "hysteresis", "none"


class _PlaySum(BlockKind):
    """A kind whose block is a sum of weighted plays (`weights`, `thresholds`): re-seeded and swapped as plays."""

    element_parameters = ("weights", "thresholds")

    def swap_form(self, block):
        return block.weights, block.thresholds, False

    def from_swap_form(self, block, weights, thresholds):
        return _with_plays(block, weights, thresholds)

    def reseed(self, o, block, max_input, place=None):
        r"""Dead plays — whose largest possible output on the data, $w_i(\max|v| - r_i)^+$ (a play from rest never
        leaves $[-(\max|v| - r), \max|v| - r]$), is below $10^{-3}$ of the operator's,
        $|w_0|\max|v| + \sum_i w_i(\max|v| - r_i)^+$: a negligible weight, a threshold at or above $\max|v|$ (the
        play never moves), or one just below it (a heavy play that moves by millivolts, measured on the independent
        plant: a weight of 20 nm/V at 99.97 V of 100) — and plays whose thresholds coincide (closer than
        `DUPLICATE_THRESHOLD` of $\max|v|$: the fit pulled them onto one kink of the data; they act as one, so the
        heaviest keeps their summed weight and the others are freed) are moved to new thresholds at 1 % of the live
        plays' mean weight (small, so the re-seeded model starts where the fit ended, and not zero, so the play's
        threshold has a gradient). `place(thresholds, weights, n)` chooses the new thresholds (the command line:
        where the residual needs them, `ModelConfig.reseeded`); without it, or for the plays it leaves, each goes
        in turn to the middle of the widest gap between the thresholds on $[0, \max|v|]$."""
        return _reseed_plays(block, max_input, place)


class PrandtlIshlinskiiKind(_PlaySum):
    """`pj.PrandtlIshlinskii`: `plays` (≤ 100), `weights`, `thresholds`, `w0`, `smoothing`. Start:
    `fitting.cold_start_actuator` in its family, else `pj.pi_cold_start` on the quasi-static output."""

    table, name = "hysteresis", "prandtl_ishlinskii"
    keys = ("plays", "smoothing", "weights", "thresholds", "w0")

    def parse(self, t, raw):
        n, (w, r) = t.sized_vectors("plays", 10, MAX_PLAYS, {"weights": dict(positive=True),
                                                          "thresholds": dict(positive=True, ascending=True)})
        return {"smoothing": t.number("smoothing", 0.0, nonnegative=True), "plays": n, "weights": w,
                "thresholds": r, "w0": t.number("w0", None, positive=True)}

    def parameters(self, o):
        return ("weights", "thresholds", "w0")

    def placeholder(self, o):
        n = o["plays"]
        return {"weights": np.full(n, 0.1), "thresholds": np.arange(1.0, n + 1), "w0": 1.0}

    def start(self, o, data):
        recs = data.records()
        pi = pj.pi_cold_start([v for v, _, _ in recs], [y for _, y, _ in recs], o["plays"])
        w = np.asarray(pi.weights)
        top = max(float(np.max(np.abs(np.r_[w, float(pi.w0)]))), TINY)
        # dead plays revived at 1e-3 of the largest weight: a zero weight is a flat spot of the Positive map
        return {"weights": np.maximum(w, 1e-3 * top), "thresholds": np.asarray(pi.thresholds),
                "w0": max(float(pi.w0), 1e-3 * top)}

    def build(self, o, v, config):
        return pj.PrandtlIshlinskii(f64(v["weights"]), f64(v["thresholds"]), w0=f64(v["w0"]),
                                    smoothing=f64(o["smoothing"]))

    def constraints(self, o):
        return {"weights": pj.Positive, "w0": pj.Positive, "thresholds": pj.OrderedPositive}

    def cold_start_args(self, o, config):
        return {"n_plays": o["plays"]}

    def from_cold_start(self, o, block):
        return {"weights": np.asarray(block.weights), "thresholds": np.asarray(block.thresholds),
                "w0": float(block.w0)}


class PlayKind(_PlaySum):
    r"""Weighted play (backlash) operators without a linear term, $y = \sum_i w_i P_{r_i}[v]$ (`pj.PrandtlIshlinskii`
    with $w_0 = 0$): `plays` (≤ 100, default 1: one backlash), `weights`, `thresholds`, `smoothing`. Start: the
    weights by non-negative least squares on the play outputs for thresholds $c\max|v|\,i/n$, $i = 1 \dots n$, the
    scale $c$ the best of 0.02 to 0.9."""

    table, name = "hysteresis", "play"
    keys = ("plays", "smoothing", "weights", "thresholds")

    def parse(self, t, raw):
        n, (w, r) = t.sized_vectors("plays", 1, MAX_PLAYS, {"weights": dict(positive=True),
                                                         "thresholds": dict(positive=True, ascending=True)})
        return {"smoothing": t.number("smoothing", 0.0, nonnegative=True), "plays": n, "weights": w,
                "thresholds": r}

    def parameters(self, o):
        return ("weights", "thresholds")

    def placeholder(self, o):
        n = o["plays"]
        return {"weights": np.full(n, 0.1), "thresholds": np.arange(1.0, n + 1)}

    def start(self, o, data):
        import scipy.optimize

        n, recs = o["plays"], data.records()
        y = data.sampled_outputs()
        sign = 1.0 if data.static_gain() >= 0 else -1.0
        best = None
        for c in np.geomspace(0.02, 0.9, 10):
            r = c * data.max_input() * np.arange(1, n + 1) / n
            play = pj.PlayOperator(jnp.asarray(r))
            a = data.sampled([np.asarray(play(jnp.asarray(v))).reshape(v.size, n) for v, _, _ in recs])
            a = np.column_stack([a, np.ones(a.shape[0]), -np.ones(a.shape[0])])  # a free offset
            w, res = scipy.optimize.nnls(a, sign * y)
            if best is None or res < best[0]:
                best = (res, w[:n], r)
        _, w, r = best
        w = np.maximum(w, 1e-3 * max(float(w.max()), TINY))
        return {"weights": w, "thresholds": r}

    def build(self, o, v, config):
        return pj.PrandtlIshlinskii(f64(v["weights"]), f64(v["thresholds"]), w0=f64(0.0),
                                    smoothing=f64(o["smoothing"]))

    def constraints(self, o):
        return {"weights": pj.Positive, "thresholds": pj.OrderedPositive}


def _with_plays(block, weights, thresholds):
    return eqx.tree_at(lambda b: (b.weights, b.thresholds), block,
                       (jnp.asarray(weights, block.weights.dtype), jnp.asarray(thresholds, block.thresholds.dtype)))


def _reseed_plays(block, max_input: float, place=None):
    """`block` with its dead and coinciding plays moved (see `_PlaySum.reseed`), or `None`. `place(
    thresholds, weights, n)`, when given, proposes up to `n` thresholds for the freed plays from the live ones
    (`ModelConfig.reseeded`: where the residual needs them); the rest go to the widest gaps."""
    w, r = np.asarray(block.weights, float), np.asarray(block.thresholds, float)
    reach = np.abs(w) * np.maximum(max_input - r, 0.0)
    total = float(np.sum(reach)) + abs(float(block.w0)) * max_input
    dead = reach < 1e-3 * max(total, TINY)
    # plays that share a threshold act as one (their weights add): the heaviest keeps the sum, the others are free
    w = w.copy()
    tol = DUPLICATE_THRESHOLD * max_input
    live = np.flatnonzero(~dead)
    live = live[np.argsort(r[live], kind="stable")]
    groups: list[list[int]] = []
    for i in live:  # each group spans at most `tol` from its lowest threshold
        if groups and r[i] - r[groups[-1][0]] <= tol:
            groups[-1].append(i)
        else:
            groups.append([i])
    for group in map(np.asarray, groups):
        if group.size > 1:
            keep = group[np.argmax(np.abs(w[group]))]
            w[keep] = np.sum(w[group])
            dead[group[group != keep]] = True
    if not dead.any() or dead.all() or not max_input > 0:
        return None
    live_r, live_w, n_free = r[~dead], w[~dead], int(dead.sum())
    proposed: list[float] = []
    for x in [] if place is None else place(live_r, live_w, n_free):  # only thresholds where a new play can act
        x = float(x)
        if (len(proposed) < n_free and np.isfinite(x) and 0 < x < max_input
                and all(abs(x - y) > tol for y in [*live_r, *proposed])):
            proposed.append(x)
    new_r = list(live_r) + proposed
    for _ in range(n_free - len(proposed)):
        pts = np.r_[0.0, np.sort(new_r), max_input]
        i = int(np.argmax(np.diff(pts)))
        new_r.append(0.5 * (pts[i] + pts[i + 1]))
    new_w = np.r_[live_w, np.full(n_free, 0.01 * float(np.mean(live_w)))]
    order = np.argsort(new_r)
    return eqx.tree_at(lambda b: (b.weights, b.thresholds), block,
                       (jnp.asarray(new_w[order], block.weights.dtype),
                        jnp.asarray(np.asarray(new_r)[order], block.thresholds.dtype)))


class BoucWenKind(BlockKind):
    """`pj.BoucWen`: `A`, `beta`, `gamma`, `n`, `d`, `method`, `substeps`, `smoothing`."""

    table, name = "hysteresis", "bouc_wen"
    keys = ("smoothing", "A", "beta", "gamma", "n", "d", "method", "substeps")

    def parse(self, t, raw):
        o = {"smoothing": t.number("smoothing", 0.0, nonnegative=True),
             "A": t.number("A", None, positive=True), "beta": t.number("beta", None, positive=True),
             "gamma": t.number("gamma", None), "n": t.number("n", None, positive=True), "d": t.number("d", None),
             "method": t.string("method", ("closed_form", "rk4")),
             "substeps": t.integer("substeps", 8, minimum=1, maximum=MAX_SUBSTEPS)}
        if o["method"] == "closed_form" and o["n"] not in (None, 1.0):
            raise t.error(f"method 'closed_form' needs n = 1, got n = {o['n']}", "method")
        if o["method"] == "closed_form" and o["smoothing"] != 0:
            raise t.error("method 'closed_form' needs smoothing = 0 (use method = 'rk4')", "method")
        if o["method"] is None:
            levels = raw.get("fit", {}).get("smoothing") if isinstance(raw.get("fit"), Mapping) else None
            smooth = o["smoothing"] != 0 or (isinstance(levels, list) and any(
                finite_number(s) and s != 0 for s in levels))
            o["method"] = "closed_form" if (o["n"] in (None, 1.0) and not smooth) else "rk4"
        return o

    def parameters(self, o):
        return ("A", "beta", "gamma", "n", "d")

    def required(self, o):
        return ("A", "beta", "gamma", "d")

    def placeholder(self, o):
        return {"A": 0.1, "beta": 0.01, "gamma": 0.01, "n": 1.0, "d": 1.0}

    def start(self, o, data):
        r"""For $n = 1$ and $z = A\hat z$, $d\hat z = dv - \beta|dv|\hat z - \gamma\,dv|\hat z|$ does not depend
        on $A$, and $y = d\,v - A\hat z$ is linear in $(d, A)$: a grid of $(\beta, \gamma/\beta)$ (saturation
        after 0.1 to 30 times the voltage span; $\gamma/\beta$ from -0.8 to 0.9, inside the bounded class), each
        with $(d, A)$ and an offset by linear least squares; the best with $A > 0$."""
        recs = data.records()
        span = max(float(np.ptp(v)) for v, _, _ in recs) or data.max_input()
        betas, ratios = np.geomspace(0.1, 30.0, 12) / span, np.linspace(-0.8, 0.9, 8)
        bb, rr = (x.ravel() for x in np.meshgrid(betas, ratios))
        zs = [_bouc_wen_grid(jnp.asarray(bb), jnp.asarray(bb * rr), v, k) for (v, _, _), k in zip(recs, data.rows())]
        v_all, y_all = data.sampled_inputs(), data.sampled_outputs()
        best, best_err = None, np.inf
        for i in range(bb.size):
            z = np.concatenate([zz[i] for zz in zs])
            a = np.column_stack([v_all, -z, np.ones_like(v_all)])
            coef, *_ = np.linalg.lstsq(a, y_all, rcond=None)
            err = float(np.sum((y_all - a @ coef) ** 2))
            if coef[1] > 0 and np.isfinite(err) and err < best_err:
                best, best_err = (float(coef[1]), bb[i], bb[i] * rr[i], float(coef[0])), err
        if best is None:  # no loop in the data: a nearly linear element
            d = chord(v_all, y_all)
            best = (max(1e-3 * abs(d), TINY), 1.0 / span, 0.0, d)
        A, beta, gamma, d = best
        return {"A": A, "beta": beta, "gamma": gamma, "n": 1.0, "d": d}

    def optional_start(self, o, data):
        return self.placeholder(o)  # n = 1, the usual Bouc–Wen choice

    def build(self, o, v, config):
        return pj.BoucWen(f64(v["A"]), f64(v["beta"]), f64(v["gamma"]), f64(v["n"]), f64(v["d"]),
                          smoothing=f64(o["smoothing"]), method=o["method"], substeps=o["substeps"])

    def constraints(self, o):
        return {"A": pj.Positive, "beta": pj.Positive, "n": pj.Positive}

    def default_free(self, o, config):
        # the exponent has no effect in the closed form (n = 1)
        return ("A", "beta", "gamma", "d") + (("n",) if o["method"] == "rk4" else ())

    def cost(self, o):
        return max(1, o["substeps"] // 4)


def _bouc_wen_grid(beta, gamma, v, rows, block: int = 2**16) -> np.ndarray:
    r"""$\hat z$ of a unit-$A$ Bouc–Wen operator ($n = 1$, closed form) for each `(beta, gamma)` pair, at the
    samples `rows` of `v` (a slice or sorted indices): shape `(pairs, rows)`. All pairs are stepped together over
    `block` samples at a time, so that only one block of every pair's output is held: the whole record at once
    was the start's memory peak (96 pairs on a 1e6-sample record: 768 MB)."""
    v = np.asarray(v, float)
    n = v.size
    block = max(1, min(block, n))
    # the last block padded to the block's length (one compiled shape; its padded samples are never kept)
    vp = np.concatenate([v, np.full(-n % block, v[-1])])
    keep = np.arange(n)[rows]
    state = _bouc_wen_init(beta, gamma)
    out = []
    for i in range(0, n, block):
        state, z = _bouc_wen_block(beta, gamma, state, jnp.asarray(vp[i : i + block]))
        sel = keep[(keep >= i) & (keep < i + block)] - i
        out.append(np.asarray(z)[:, sel])
    return np.concatenate(out, axis=1)


def _unit_bouc_wen(beta, gamma):
    return pj.BoucWen(1.0, beta, gamma, output="z")


@jax.jit
def _bouc_wen_init(beta, gamma):
    return jax.vmap(lambda b, g: _unit_bouc_wen(b, g).init())(beta, gamma)


@jax.jit
def _bouc_wen_block(beta, gamma, state, v):
    return jax.vmap(lambda b, g, s: _unit_bouc_wen(b, g).scan(v, s))(beta, gamma, state)


class MaxwellSlipKind(BlockKind):
    """`pj.MaxwellSlip`: `elements` (≤ 100), `stiffness`, `breakaway`, `smoothing`. Start: non-negative least
    squares of the stiffnesses on a uniform grid of slip thresholds up to 1.2 max|v|."""

    table, name = "hysteresis", "maxwell_slip"
    keys = ("elements", "smoothing", "stiffness", "breakaway")

    def parse(self, t, raw):
        n, (k, f) = t.sized_vectors("elements", 8, MAX_ELEMENTS, {"stiffness": dict(positive=True),
                                                               "breakaway": dict(positive=True)})
        return {"smoothing": t.number("smoothing", 0.0, nonnegative=True), "elements": n, "stiffness": k,
                "breakaway": f}

    def parameters(self, o):
        return ("stiffness", "breakaway")

    def placeholder(self, o):
        n = o["elements"]
        return {"stiffness": np.ones(n), "breakaway": np.arange(1.0, n + 1)}

    def start(self, o, data):
        import scipy.optimize

        n, recs = o["elements"], data.records()
        # thresholds up to 1.2 max|v|: the widest elements stay elastic (the linear part of the response)
        r = 1.2 * data.max_input() * np.arange(1, n + 1) / n
        play = pj.PlayOperator(jnp.asarray(r))
        a = data.sampled([v[:, None] - np.asarray(play(jnp.asarray(v))) for v, _, _ in recs])
        y = data.sampled_outputs()
        sign = 1.0 if data.static_gain() >= 0 else -1.0
        k, _ = scipy.optimize.nnls(a, sign * y)
        k = np.maximum(k, 1e-3 * max(float(k.max()), TINY))
        return {"stiffness": k, "breakaway": k * r}

    def build(self, o, v, config):
        return pj.MaxwellSlip(f64(v["stiffness"]), f64(v["breakaway"]), smoothing=f64(o["smoothing"]))

    def constraints(self, o):
        return {"stiffness": pj.Positive, "breakaway": pj.Positive}

    element_parameters = ("stiffness", "breakaway")

    def swap_form(self, block):
        """The elements as stops: stiffness $k_i$ and slip threshold $r_i = f_i/k_i$ (`MaxwellSlip.thresholds`)."""
        return block.stiffness, block.thresholds, True

    def from_swap_form(self, block, weights, thresholds):
        k = jnp.asarray(weights, block.stiffness.dtype)
        return eqx.tree_at(lambda b: (b.stiffness, b.breakaway), block,
                           (k, k * jnp.asarray(thresholds, block.breakaway.dtype)))


class PreisachKind(BlockKind):
    r"""`pj.Preisach.uniform`: `levels` (≤ 30) of a uniform triangular relay grid on `range = [v_min, v_max]`
    (default ±1.05 max|v| of the data), relay weights `mu` (fitted), `smoothing` (relay switching width in volts;
    0 = exact, whose weights still enter linearly). Start: the weights by ridge-regularised linear least squares
    on the relay outputs (the output is linear in them). The switching values stay fixed at the grid."""

    table, name = "hysteresis", "preisach"
    keys = ("levels", "range", "mu", "smoothing")

    def parse(self, t, raw):
        n = t.integer("levels", 8, minimum=1, maximum=MAX_LEVELS_PREISACH)
        rng = t.vector("range", 2, ascending=True)
        mu = t.vector("mu", n * (n + 1) // 2)
        return {"levels": n, "range": None if rng is None else (float(rng[0]), float(rng[1])), "mu": mu,
                "smoothing": t.number("smoothing", 0.0, nonnegative=True)}

    def parameters(self, o):
        return ("mu", "range")

    def required(self, o):
        return ("mu", "range")

    def placeholder(self, o):
        n = o["levels"]
        return {"mu": np.zeros(n * (n + 1) // 2), "range": (-1.0, 1.0)}

    def data_derived(self, o, config):
        return ("range",)

    def derived_value(self, o, key, block):
        # `Preisach.uniform` puts the relays at the centres of n x n cells of side h on [v_min, v_max]: the largest
        # alpha is v_max - h/2, the smallest beta v_min + h/2 (one level: any range with that centre)
        n = o["levels"]
        top, bottom = float(np.max(np.asarray(block.alpha))), float(np.min(np.asarray(block.beta)))
        h = (top - bottom) / (n - 1) if n > 1 else 1.0
        return [bottom - h / 2, top + h / 2]

    def start(self, o, data):
        vmax = 1.05 * data.max_input()
        rng = o["range"] if o["range"] is not None else (-vmax, vmax)
        ones = pj.Preisach.uniform(rng[0], rng[1], o["levels"], smoothing=o["smoothing"])
        eye = jnp.eye(ones.mu.shape[0])
        # the relays' outputs a few at a time (all 55 relays of 10 levels on a 1e6-sample record: a 1.25 GB start)
        cols = np.concatenate([columns_at_rows(lambda j, e, vj=jnp.asarray(v): _relay_outputs(ones, eye[j:e], vj).T,
                                               eye.shape[0], v.size, k)
                               for (v, _, _), k in zip(data.records(), data.rows())])
        y = data.sampled_outputs()
        lam = 1e-8 * float(np.sum(cols**2)) / max(cols.shape[1], 1)
        mu = np.linalg.solve(cols.T @ cols + lam * np.eye(cols.shape[1]), cols.T @ y)
        return {"mu": mu, "range": rng}

    def build(self, o, v, config):
        rng = v["range"]
        return pj.Preisach.uniform(float(rng[0]), float(rng[1]), o["levels"], mu=f64(v["mu"]),
                                   smoothing=f64(o["smoothing"]))

    def default_free(self, o, config):
        return ("mu",)


# ---- creep


class NoCreep(_NoBlock):
    table, name = "creep", "none"

    def cold_start_args(self, o, config):
        return {"creep_order": 0}


def _creep_gain(data: StartData) -> float:
    """The creep's scale: 1 where it acts on a signal in the output's units (in series after the hysteresis, or on
    the voltage ahead of the dynamics' gain), else the static gain from volts to the output."""
    series = data.config.creep_structure == "series" and not data.config.hysteresis_kind.empty
    return 1.0 if data.unit_drive or series else data.static_gain()


@eqx.filter_jit
def _relay_outputs(ones, masks, v):
    """The output of each single relay of the Preisach operator `ones` (one row of `masks` as its `mu`) over `v`."""
    return jax.vmap(lambda m: eqx.tree_at(lambda p: p.mu, ones, m)(v))(masks)


class KelvinVoigtKind(BlockKind):
    """`pj.KelvinVoigtCreep`: `order` lags (≤ 10), `stiffnesses`, `time_constants`; in series with an instantaneous
    compliance 1 (`k0 = 1`), in parallel without."""

    table, name = "creep", "kelvin_voigt"
    keys = ("order", "stiffnesses", "time_constants")
    lag_gains = "stiffnesses"  # the compliances 1/k_j are the gains

    def gains(self, values):
        return 1.0 / values

    def from_gains(self, gains):
        return 1.0 / gains

    def parse(self, t, raw):
        n, (k, tau) = t.sized_vectors("order", 1, MAX_CREEP_ORDER, {"stiffnesses": dict(positive=True),
                                                                  "time_constants": dict(positive=True)})
        return {"order": n, "stiffnesses": k, "time_constants": tau}

    def parameters(self, o):
        return ("stiffnesses", "time_constants")

    def placeholder(self, o):
        n = o["order"]
        return {"stiffnesses": np.full(n, 10.0), "time_constants": np.geomspace(1.0, 10.0, n)}

    def start(self, o, data):
        n, dt, span = o["order"], data.dt(), data.span()
        # one lag at a tenth of the longest record, or n lags from 1/100 to 1/3 of it; each at 1 % of the gain
        taus = np.array([span / 10]) if n == 1 else np.geomspace(span / 100, span / 3, n)
        gain = abs(_creep_gain(data))
        return {"stiffnesses": np.full(n, 1.0 / max(0.01 * gain, TINY)), "time_constants": np.maximum(taus, 5 * dt)}

    def build(self, o, v, config):
        series = config.creep_structure == "series"
        return pj.KelvinVoigtCreep(f64(v["stiffnesses"]), f64(v["time_constants"]), k0=f64(1.0) if series else None)

    def constraints(self, o):
        return {"stiffnesses": pj.Positive, "time_constants": pj.Positive}

    def cold_start_args(self, o, config):
        return {"creep_order": o["order"], "structure": config.creep_structure}

    def from_cold_start(self, o, block):
        if block is None:
            return None
        return {"stiffnesses": np.asarray(block.stiffnesses), "time_constants": np.asarray(block.time_constants)}


class LogarithmicKind(BlockKind):
    """`pj.LogarithmicCreep`: `gamma`, `t0`, `gain` (fixed by default: only $g\\gamma$ is identifiable in parallel
    with the hysteresis)."""

    table, name = "creep", "logarithmic"
    keys = ("gamma", "t0", "gain")

    def parse(self, t, raw):
        return {"gamma": t.number("gamma", None), "t0": t.number("t0", None, positive=True),
                "gain": t.number("gain", None)}

    def parameters(self, o):
        return ("gamma", "t0", "gain")

    def required(self, o):
        return ("gamma", "t0")

    def placeholder(self, o):
        return {"gamma": 0.01, "t0": 1.0, "gain": 1.0}

    def start(self, o, data):
        return {"gamma": 0.01, "t0": 10 * data.dt(), "gain": _creep_gain(data)}

    def optional_start(self, o, data):
        return self.placeholder(o) | {"gain": _creep_gain(data)}

    def data_derived(self, o, config):
        # 1 (the placeholder) only where the creep acts on a signal in the output's units, as `_creep_gain`
        unit = config.hysteresis_kind.empty and config.model_kind.scale_in_dynamics
        series = config.creep_structure == "series" and not config.hysteresis_kind.empty
        return () if unit or series else ("gain",)

    def build(self, o, v, config):
        return pj.LogarithmicCreep(f64(v["gamma"]), f64(v["t0"]), gain=f64(v["gain"]),
                                   instantaneous=config.creep_structure == "series")

    def constraints(self, o):
        return {"t0": pj.Positive}

    def default_free(self, o, config):
        return ("gamma", "t0")


class LagKind(BlockKind):
    """`pj.LagCreep`: `lags` (≤ 10), `fractions` (sum < 1), `time_constants`; DC gain 1, so only in series."""

    table, name = "creep", "lag"
    keys = ("lags", "fractions", "time_constants")
    lag_gains, max_total_gain = "fractions", 1.0
    structures = ("series",)
    structure_note = ("a 'lag' creep is DC-normalised (its gain is 1): it belongs in series after the hysteresis; "
                      "use 'kelvin_voigt' for creep in parallel")

    def parse(self, t, raw):
        n, (alpha, tau) = t.sized_vectors("lags", 1, MAX_CREEP_ORDER, {"fractions": dict(positive=True),
                                                                     "time_constants": dict(positive=True)})
        if alpha is not None and sum(alpha) >= 1:
            raise t.error(f"the fractions must add up to less than 1 (the rest responds at once), got {sum(alpha)}",
                          "fractions")
        return {"lags": n, "fractions": alpha, "time_constants": tau}

    def parameters(self, o):
        return ("fractions", "time_constants")

    def placeholder(self, o):
        n = o["lags"]
        return {"fractions": np.full(n, 0.1 / n), "time_constants": np.geomspace(1e-2, 1.0, n)}

    def start(self, o, data):
        n, lo = o["lags"], 50 * data.dt()
        # 20 % of the response lagging, split evenly; lags from 50 samples to a tenth of the longest record
        taus = np.array([lo]) if n == 1 else np.geomspace(lo, max(data.span() / 10, 2 * lo), n)
        return {"fractions": np.full(n, 0.2 / n), "time_constants": taus}

    def build(self, o, v, config):
        return pj.LagCreep(f64(v["fractions"]), f64(v["time_constants"]))

    def cold_start_args(self, o, config):
        return {"creep_order": o["lags"], "structure": "series", "creep": "lag"}

    def from_cold_start(self, o, block):
        if block is None:
            return None
        return {"fractions": np.asarray(block.fractions), "time_constants": np.asarray(block.time_constants)}

    def constraints(self, o):
        return {"fractions": pj.Fractions, "time_constants": pj.Positive}


class LinearCreepKind(BlockKind):
    r"""`pj.LinearCreep` of a `pj.StableTransferFunction` (paper 001's eq. 9): `order` real poles (≤ 10, `poles`
    < 0 in rad/s), `real_zeros` real zeros (`zeros` < 0) and the DC `gain`. In parallel the creep is strictly proper
    ($h(0^+) = 0$, at most `order - 1` zeros, default `order - 1`); in series it responds at once ($h(0^+) \ne 0$:
    `order` zeros), and its DC `gain` is fixed by default (the hysteresis carries the scale). Start: the
    Kelvin–Voigt creep's start or joint cold start with `order` lags, written as its transfer function ($\sum_i
    c_i/(1 + \tau_i s)$, plus 1 in series): poles $-1/\tau_i$, the zeros of the numerator (real, between them)."""

    table, name = "creep", "linear"
    keys = ("order", "poles", "real_zeros", "zeros", "gain")

    def parse(self, t, raw):
        n, (p,) = t.sized_vectors("order", 1, MAX_CREEP_ORDER, {"poles": dict(negative=True)})
        series = _structure(raw) == "series"
        limit = n if series else n - 1
        m, (z,) = t.sized_vectors("real_zeros", limit, max(limit, 0), {"zeros": dict(negative=True)}, minimum=0)
        if series and m != n:
            raise t.error(f"a creep in series responds at once: it needs as many zeros as poles ({n}), got {m}",
                          "real_zeros" if t.has("real_zeros") else "zeros")
        return {"order": n, "poles": p, "real_zeros": m, "zeros": z, "gain": t.number("gain", None, nonzero=True)}

    def parameters(self, o):
        return ("poles",) + (("zeros",) if o["real_zeros"] else ()) + ("gain",)

    def placeholder(self, o):
        n, m = o["order"], o["real_zeros"]
        return {"poles": -np.geomspace(1.0, 10.0, n), "zeros": -1.5 * np.geomspace(1.0, 10.0, n)[:m], "gain": 1.0}

    def _from_lags(self, o, c: np.ndarray, tau: np.ndarray, series: bool) -> dict:
        r"""Poles, zeros and DC gain of $d + \sum_i c_i/(1 + \tau_i s)$ ($d$ = 1 in series, else 0)."""
        tau = _strictly_ascending_taus(np.asarray(tau, float))
        den = [np.poly1d([t, 1.0]) for t in tau]
        num = np.poly1d([1.0 if series else 0.0])
        for t in tau:
            num = num * np.poly1d([t, 1.0])
        for i, ci in enumerate(c):
            term = np.poly1d([float(ci)])
            for j, d in enumerate(den):
                if j != i:
                    term = term * d
            num = num + term
        zeros = np.sort(np.real(np.roots(num.coeffs)))[::-1] if num.order > 0 else np.zeros(0)
        zeros = np.minimum(zeros, -1e-12)[: o["real_zeros"]]
        m = o["real_zeros"]
        if zeros.size < m:  # more zeros asked than the lags have (a parallel creep with fewer lags' worth)
            zeros = np.r_[zeros, -1.5 / tau[: m - zeros.size]]
        return {"poles": -1.0 / tau, "zeros": zeros, "gain": float(series) + float(np.sum(c))}

    def start(self, o, data):
        kv = KelvinVoigtKind().start({"order": o["order"]}, data)
        series = data.config.creep_structure == "series"
        return self._from_lags(o, 1.0 / kv["stiffnesses"], kv["time_constants"], series)

    def build(self, o, v, config):
        return pj.LinearCreep(pj.StableTransferFunction(f64(v["gain"]), poles=f64(v["poles"]),
                                                        zeros=f64(v.get("zeros", np.zeros(0)))))

    def values(self, o, data):
        out = super().values(o, data)
        out.setdefault("zeros", np.zeros(0))
        return out

    def constraints(self, o):
        return {"system.poles": Negative} | ({"system.zeros": Negative} if o["real_zeros"] else {})

    def default_free(self, o, config):
        series = config.creep_structure == "series"
        return ("system.poles",) + (("system.zeros",) if o["real_zeros"] else ()) + (
            () if series else ("system.gain",))

    def cold_start_args(self, o, config):
        default = o["order"] if config.creep_structure == "series" else o["order"] - 1
        if o["real_zeros"] != default:
            return None
        return {"creep_order": o["order"], "structure": config.creep_structure}

    def from_cold_start(self, o, block):
        if block is None:
            return None
        series = block.k0 is not None
        return self._from_lags(o, 1.0 / np.asarray(block.stiffnesses), np.asarray(block.time_constants), series)


def _structure(raw: Mapping) -> str:
    """The creep structure a CONFIG names (`[creep] structure`, default parallel), before it is validated."""
    c = raw.get("creep", {})
    return c.get("structure", "parallel") if isinstance(c, Mapping) else "parallel"


def _strictly_ascending_taus(tau: np.ndarray) -> np.ndarray:
    """Time constants made distinct (at least 1 % apart), so that the lags' poles and zeros stay apart."""
    tau = np.sort(tau)
    for i in range(1, tau.size):
        tau[i] = max(tau[i], 1.01 * tau[i - 1])
    return tau


# ---- dynamics


class TransferFunctionKind(BlockKind):
    r"""`pj.StableTransferFunction` (the default `[dynamics]` kind): `order` (0–8) poles, `order // 2` pairs
    (`omega`, `zeta`) and `order % 2` real (`poles`); `zero_pairs` (≤ the pole pairs) complex zero pairs
    (`zero_omega`, `zero_zeta`: a mode with an antiresonance, e.g. a low-frequency mode of the mount) and
    `real_zeros` (`zeros`); `gain` (DC gain, default 1). Zero pair $i$ starts at 1.25 $\omega_i$ with $\zeta_i$
    (near the pole pair, so the mode starts weak), real zero $j$ at 1.25 times real pole $j$, further real zeros
    spread from 1.25 to 5 times the fastest pole (distinct, so that they can part)."""

    table, name = "dynamics", "transfer_function"
    keys = ("order", "gain", "omega", "zeta", "poles", "zero_pairs", "zero_omega", "zero_zeta", "real_zeros", "zeros")

    def parse(self, t, raw):
        order = t.integer("order", None, allowed=DYNAMICS_ORDERS)
        if order is None:
            raise t.error(f"missing; allowed values: {', '.join(map(str, DYNAMICS_ORDERS))}", "order")
        n2, n1 = divmod(order, 2)
        for k, n in (("omega", n2), ("zeta", n2), ("poles", n1)):
            if n == 0 and k in t.data:
                raise t.error(f"not used with order = {order}", k)
        m2, (zw, zz) = t.sized_vectors("zero_pairs", 0, n2, {"zero_omega": dict(positive=True), "zero_zeta": {}},
                                       minimum=0)
        m1, (z,) = t.sized_vectors("real_zeros", 0, n1 + 2 * (n2 - m2), {"zeros": {}}, minimum=0)
        return {"order": order, "gain": t.number("gain", None, nonzero=True),
                "omega": t.vector("omega", n2, positive=True), "zeta": t.vector("zeta", n2, positive=True),
                "poles": t.vector("poles", n1, negative=True), "zero_pairs": m2, "zero_omega": zw, "zero_zeta": zz,
                "real_zeros": m1, "zeros": z}

    def parameters(self, o):
        n2, n1 = divmod(o["order"], 2)
        return (("omega", "zeta") if n2 else ()) + (("poles",) if n1 else ()) + (
            ("zero_omega", "zero_zeta") if o["zero_pairs"] else ()) + (("zeros",) if o["real_zeros"] else ()) + (
            "gain",)

    def required(self, o):
        return tuple(p for p in self.parameters(o) if p != "gain")

    def data_derived(self, o, config):
        # without hysteresis the DC gain is the scale from volts to the output, started from the data's (and fitted)
        return ("gain",) if config.hysteresis_kind.empty and config.model_kind.scale_in_dynamics else ()

    def _zeros(self, o, omega, zeta, poles) -> dict:
        m2, m1 = o["zero_pairs"], o["real_zeros"]
        # real zeros at 1.25 times the real poles, then spread (distinct, so that they can part) above the pairs
        near = 1.25 * np.asarray(poles)[:m1]
        top = max([1.0] + [abs(float(x)) for x in np.r_[np.asarray(poles), np.asarray(omega)]])
        extra = -1.25 * top * np.geomspace(1.0, 4.0, max(m1 - near.size, 1))[: m1 - near.size]
        return {"zero_omega": 1.25 * np.asarray(omega)[:m2], "zero_zeta": np.asarray(zeta)[:m2],
                "zeros": np.concatenate([near, extra])}

    def placeholder(self, o):
        n2, n1 = divmod(o["order"], 2)
        out = {"omega": np.geomspace(1e3, 1e4, n2) if n2 else np.zeros(0), "zeta": np.full(n2, 0.5),
               "poles": np.full(n1, -1e3), "gain": 1.0}
        return out | self._zeros(o, _given(o, "omega", out), _given(o, "zeta", out), _given(o, "poles", out))

    def start(self, o, data):
        n2, n1 = divmod(o["order"], 2)
        # rule of thumb: modes at 1/10 (and 1/4, ...) of the sampling rate, damping 0.5, real poles at 1/10
        nyquist = 0.5 / data.dt()
        fractions = np.geomspace(0.2, 0.8, n2) if n2 > 2 else np.array([0.2, 0.5])[:n2]
        out = {"omega": 2 * np.pi * nyquist * fractions, "zeta": np.full(n2, 0.5),
               "poles": -2 * np.pi * 0.2 * nyquist * np.geomspace(1.0, 3.0, n1) if n1 else np.zeros(0),
               "gain": data.static_gain() if data.unit_drive else 1.0}
        return out | self._zeros(o, _given(o, "omega", out), _given(o, "zeta", out), _given(o, "poles", out))

    def optional_start(self, o, data):
        return self.placeholder(o) | {"gain": data.static_gain() if data.unit_drive else 1.0}

    def from_cold_start(self, o, block):
        # only all-pole even orders are in the cold start's family (`cold_start_args`)
        return None if block is None else {"omega": np.asarray(block.omega), "zeta": np.asarray(block.zeta),
                                           "gain": 1.0}

    def values(self, o, data):
        out = super().values(o, data)
        for k in ("omega", "zeta", "poles", "zero_omega", "zero_zeta", "zeros"):
            out.setdefault(k, np.zeros(0))
        return out

    def build(self, o, v, config):
        if not o["order"] and not (config.hysteresis_kind.empty and config.model_kind.scale_in_dynamics):
            return None  # without hysteresis the dynamics' DC gain is the only scale from volts to metres
        return pj.StableTransferFunction(f64(v["gain"]), omega=f64(v["omega"]), zeta=f64(v["zeta"]),
                                         poles=f64(v["poles"]), zeros=f64(v["zeros"]),
                                         zero_omega=f64(v["zero_omega"]), zero_zeta=f64(v["zero_zeta"]))

    def constraints(self, o):
        n2, n1 = divmod(o["order"], 2)
        return ({"omega": pj.Positive, "zeta": pj.Positive} if n2 else {}) | ({"poles": Negative} if n1 else {}) | (
            {"zero_omega": pj.Positive} if o["zero_pairs"] else {})

    def default_free(self, o, config):
        # the DC gain duplicates the scale of the hysteresis; it is the scale when there is no hysteresis
        scale = config.hysteresis_kind.empty and config.model_kind.scale_in_dynamics
        return (("gain",) if scale else ()) + tuple(p for p in self.parameters(o) if p != "gain")

    def cold_start_args(self, o, config):
        if o["order"] % 2 or o["zero_pairs"] or o["real_zeros"]:
            return None
        return {"dynamics_order": o["order"]}


def _given(o: dict, key: str, made: dict) -> np.ndarray:
    return np.asarray(made[key] if o.get(key) is None else o[key])


def f64(x) -> jax.Array:
    """A float64 JAX array of `x` (CONFIG values are float64 whatever the default dtype)."""
    return jnp.asarray(np.asarray(x, np.float64))


for _kind in (PrandtlIshlinskiiKind(), PlayKind(), BoucWenKind(), MaxwellSlipKind(), PreisachKind(), NoHysteresis(),
              KelvinVoigtKind(), LogarithmicKind(), LagKind(), LinearCreepKind(), NoCreep(), TransferFunctionKind()):
    register_kind(_kind)
