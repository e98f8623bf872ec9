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

from ._data import CHANNELS, parse_columns, parse_units

HYSTERESIS_KINDS = ("prandtl_ishlinskii", "bouc_wen", "maxwell_slip", "none")
CREEP_KINDS = ("kelvin_voigt", "logarithmic", "lag", "none")
OBSERVER_KINDS = ("current_integration",)
DYNAMICS_ORDERS = (0, 1, 2, 3, 4)
TABLES = ("hysteresis", "creep", "dynamics", "charge", "state", "observer", "data", "fit")

# Upper bounds on the sizes a CONFIG may ask for, checked before any work: beyond them the initialisation (dense
# NNLS over plays x samples) or the fit's memory grows past what the method is meant for.
MAX_PLAYS = 100
MAX_ELEMENTS = 100
MAX_CREEP_ORDER = 10
MAX_SUBSTEPS = 64
MAX_STEPS = 100_000
MAX_LEVELS = 10
MAX_POLYNOMIAL = 6
MAX_WEIGHT = 1e20  # a channel weight beyond it squares past float64 with the residuals it scales


def _finite_number(x) -> bool:
    """A TOML number (not a bool) that is finite as a float (an integer of 400 digits is not)."""
    if isinstance(x, bool) or not isinstance(x, int | float):
        return False
    try:
        return math.isfinite(float(x))
    except OverflowError:
        return False

# keys allowed per table (and per kind), besides `kind`
_POLYNOMIAL_KEYS = ("polynomial", "coefficients", "polynomial_scale")
_HYSTERESIS_KEYS = {
    "prandtl_ishlinskii": ("plays", "smoothing", "weights", "thresholds", "w0") + _POLYNOMIAL_KEYS,
    "bouc_wen": ("smoothing", "A", "beta", "gamma", "n", "d", "method", "substeps") + _POLYNOMIAL_KEYS,
    "maxwell_slip": ("elements", "smoothing", "stiffness", "breakaway") + _POLYNOMIAL_KEYS,
    "none": (),
}
_CREEP_KEYS = {
    "kelvin_voigt": ("order", "stiffnesses", "time_constants", "structure"),
    "logarithmic": ("gamma", "t0", "gain", "structure"),
    "lag": ("lags", "fractions", "time_constants", "structure"),
    "none": (),
}
_STATE_KEYS = ("offset", "prehistory")
_DYNAMICS_KEYS = ("order", "gain", "omega", "zeta", "poles")
_CHARGE_KEYS = ("capacitance", "coupling")
_OBSERVER_REQUIRED = (
    "integrator_capacitance",
    "reference_capacitance",
    "leakage_resistance",
    "force_sensitivity",
    "displacement_coefficient",
    "stiffness",
)
_OBSERVER_KEYS = _OBSERVER_REQUIRED + ("bias_current", "capacitance_p", "filter_cutoff")
_FIT_KEYS = ("free", "weights", "smoothing", "max_steps", "targets", "method")
_DATA_KEYS = ("units", "columns", "group", "sample_rate", "ignore_extra")
_WEIGHT_MODES = ("range", "noise")


class StartWarning(UserWarning):
    """One of the data-driven starts failed and another was used."""


class _Negative(pj.AbstractReparam):
    r"""Elementwise negative parameter (real poles of the dynamics): $x = -\mathrm{softplus}(\mathrm{raw}) < 0$."""

    raw: jax.Array = eqx.field(converter=jnp.asarray)

    @classmethod
    def from_value(cls, value) -> "_Negative":
        value = jnp.asarray(value)
        return cls(pj.inv_softplus(-value))

    def unwrap(self) -> jax.Array:
        return -pj.softplus(self.raw)


# ------------------------------------------------------------------------------------------------ parsing helpers


class _Table:
    """One TOML table with the file name and table name for error messages."""

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
        where = f"[{self.name}] {key}" if key else f"[{self.name}]"
        return PiezojaxValueError(f"{self.source}: {where}: {msg}")

    def has(self, key: str) -> bool:
        return key in self.data

    def number(self, key: str, default=None, *, positive=False, nonnegative=False, nonzero=False):
        if key not in self.data:
            return default
        x = self.data[key]
        if not _finite_number(x):
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
        if not isinstance(x, list) or not all(
            _finite_number(v) for v in x
        ):
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
        self, size_key: str, default_size: int, maximum: int, specs: dict[str, dict]
    ) -> tuple[int, list]:
        """A block of `size_key` elements (at most `maximum`) and its per-element vectors `specs` (name → `vector`
        options): the size is given, or taken from the vectors given (which must agree), else `default_size`."""
        n = self.integer(size_key, None, minimum=1, maximum=maximum)
        vectors = [self.vector(name, n, **opts) for name, opts in specs.items()]
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
    - `hysteresis`, `creep`: kinds (`"none"` for no block) with their validated options in `hysteresis_options` /
      `creep_options`; `dynamics_order`, `dynamics_options`; `charge` (the `[charge]` options, or `None`);
      `observer` (the `[observer]` options, or `None` for a `pj.Actuator`).
    - `free`, `weights`, `smoothing`, `max_steps`, `targets`, `method`: the `[fit]` options (`free=None`: the default
      set of `default_free`; `method`: `fitting.solve`'s, default `"levenberg_marquardt"`).
    - `state`: the `[state]` options of an actuator: `offset` and `prehistory`, each `True` (in the model, start
      from the data), `False` (not in the model) or a number (in the model, this start value). Default: the offset
      in the model, no prehistory.
    - `data`: the `[data]` options for reading the files — `units`, `columns`, `group`, `sample_rate`,
      `ignore_extra`, as the keyword arguments of `fitting.load_experiment` (only those the file gives).
    """

    text: str
    source: str
    hysteresis: str
    hysteresis_options: dict
    creep: str
    creep_options: dict
    dynamics_order: int
    dynamics_options: dict
    charge: dict | None
    observer: dict | None
    free: tuple[str, ...] | None
    weights: Any
    smoothing: tuple[float, ...] | None
    max_steps: int
    targets: tuple[str, ...] | None
    method: str = "levenberg_marquardt"
    data: dict = dataclasses.field(default_factory=dict)
    state: dict = dataclasses.field(default_factory=dict)

    # -------------------------------------------------------------------------------------------- structure

    @property
    def is_observer(self) -> bool:
        return self.observer is not None

    @property
    def polynomial(self) -> int:
        """The degree of the hysteresis' output polynomial (0: none)."""
        return self.hysteresis_options.get("polynomial", 0)

    @property
    def creep_structure(self) -> str:
        """`"series"` (the creep after the hysteresis) or `"parallel"` (beside it, driven by the voltage)."""
        return self.creep_options.get("structure", "series" if self.creep == "lag" else "parallel")

    def _offset(self):
        return False if self.is_observer else self.state.get("offset", True)

    def _prehistory(self):
        return False if self.is_observer else self.state.get("prehistory", False)

    def _operator_path(self) -> str:
        """The path of the hysteresis operator's parameters: `hysteresis` (`hysteresis.hysteresis` inside an output
        polynomial)."""
        return "hysteresis.hysteresis" if self.polynomial else "hysteresis"

    def _operator(self, m):
        return m.hysteresis.hysteresis if self.polynomial else m.hysteresis

    @property
    def outputs(self) -> tuple[str, ...]:
        """The channels the model predicts: `displacement` (and `charge`, `current` with a `[charge]` table) for an
        actuator; `displacement`, `force` for the observer."""
        if self.is_observer:
            return ("displacement", "force")
        return ("displacement", "charge", "current") if self.charge is not None else ("displacement",)

    @property
    def inputs(self) -> tuple[str, ...]:
        """Measured channels the model reads besides `t` and `v_in` (`v_out` for the observer)."""
        return ("v_out",) if self.is_observer else ()

    def predictor(self):
        """The built-in `fitting.Predictor` for this model (`actuator_predictor()` or `observer_predictor()`); the
        channels to use are `outputs` (an actuator without `[charge]` predicts zero charge)."""
        from ._predict import actuator_predictor, observer_predictor

        return observer_predictor(force=True) if self.is_observer else actuator_predictor()

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
        """The parameters fitted when `[fit] free` is not given: every parameter of the configured blocks except
        those a convention fixes (they would duplicate another parameter's effect): the dynamics' DC `gain`, the
        logarithmic creep's `gain` (only $g\\gamma$ is identifiable in parallel with the hysteresis), the hysteresis
        `smoothing` (a continuation setting), the Bouc–Wen exponent `n` with the closed-form method (it has no
        effect there), and the observer's circuit constants (capacitances, leakage, bias, `capacitance_p`, filter
        cutoff: identified from the circuit, and scaling all of them with $\\beta$ and the operators leaves the
        estimates unchanged)."""
        paths: list[str] = []
        h, hp = self.hysteresis, self._operator_path()
        if h == "prandtl_ishlinskii":
            paths += [f"{hp}.weights", f"{hp}.thresholds", f"{hp}.w0"]
        elif h == "bouc_wen":
            paths += [f"{hp}.A", f"{hp}.beta", f"{hp}.gamma", f"{hp}.d"]
            if self._bouc_wen_method() == "rk4":
                paths.append(f"{hp}.n")
        elif h == "maxwell_slip":
            paths += [f"{hp}.stiffness", f"{hp}.breakaway"]
        if self.polynomial:
            paths.append("hysteresis.coefficients")
        if self.creep == "kelvin_voigt":
            paths += ["creep.stiffnesses", "creep.time_constants"]
        elif self.creep == "logarithmic":
            paths += ["creep.gamma", "creep.t0"]
        elif self.creep == "lag":
            paths += ["creep.fractions", "creep.time_constants"]
        if self.is_observer:
            paths += ["force_sensitivity", "displacement_coefficient", "stiffness"]
            if h == "none":
                paths.append("capacitance_p")
            return tuple(paths)
        if h == "none":
            paths.append("dynamics.gain")
        n2, n1 = divmod(self.dynamics_order, 2)
        if n2:
            paths += ["dynamics.omega", "dynamics.zeta"]
        if n1:
            paths.append("dynamics.poles")
        if self.charge is not None:
            paths += ["capacitance", "coupling"]
        if self._offset() is not False:
            paths.append("offset")
        if self._prehistory() is not False:
            paths.append("prehistory")
        return tuple(paths)

    def fit_free(self, targets: tuple[str, ...] | None = None) -> list[str]:
        """`[fit] free`, else `default_free()` (without `capacitance`/`coupling` when `targets` has neither
        `charge` nor `current`: the displacement does not depend on them)."""
        if self.free is not None:
            return list(self.free)
        free = list(self.default_free())
        if targets is not None and not {"charge", "current"} & set(targets):
            free = [p for p in free if p not in ("capacitance", "coupling")]
        return free

    def _bouc_wen_method(self) -> str:
        o = self.hysteresis_options
        if o.get("method") is not None:
            return o["method"]
        smooth = o.get("smoothing", 0.0) != 0 or any(s != 0 for s in (self.smoothing or ()))
        return "closed_form" if (o.get("n") in (None, 1.0) and not smooth) else "rk4"

    # -------------------------------------------------------------------------------------------- building

    def missing_values(self) -> list[str]:
        """The parameters the file does not give explicitly (`"[hysteresis] thresholds"`, ...)."""
        out = []
        for table, opts, keys in self._value_keys():
            out += [f"[{table}] {k}" for k in keys if opts.get(k) is None]
        return out

    def _value_keys(self):
        h = {
            "prandtl_ishlinskii": ("weights", "thresholds", "w0"),
            "bouc_wen": ("A", "beta", "gamma", "d"),
            "maxwell_slip": ("stiffness", "breakaway"),
            "none": (),
        }[self.hysteresis]
        c = {"kelvin_voigt": ("stiffnesses", "time_constants"), "logarithmic": ("gamma", "t0"),
             "lag": ("fractions", "time_constants"), "none": ()}[self.creep]
        if self.polynomial:
            h = h + ("coefficients",)
        out = [("hysteresis", self.hysteresis_options, h), ("creep", self.creep_options, c)]
        if self.is_observer:
            return out
        n2, n1 = divmod(self.dynamics_order, 2)
        d = (("omega", "zeta") if n2 else ()) + (("poles",) if n1 else ())
        out.append(("dynamics", self.dynamics_options, d))
        if self.charge is not None:
            out.append(("charge", self.charge, ("capacitance", "coupling")))
        if self._prehistory() is True:
            out.append(("state", {"prehistory": None}, ("prehistory",)))
        return out

    def build(self, dataset=None, *, require_values: bool = False):
        """The model this configuration describes, with its constrained parameters reparametrised for fitting.

        **Arguments:**

        - `dataset`: a `fitting.Dataset` to draw initial values from where the file gives none (PI by
          `fitting.cold_start_actuator` or `pj.pi_cold_start`, the other blocks by simple rules, see the README).
          `None`: placeholders of the right shapes (enough for `fitting.load_model(folder, like=...)`).
        - `require_values`: raise if any parameter is not given explicitly (forward simulation).

        **Returns:** the reparametrised model (`pj.unwrap` it to use it). Constraints: PI `weights`, `w0`,
        Maxwell-slip `stiffness`/`breakaway`, Bouc–Wen `A`, `beta`, `n`, creep `stiffnesses`/`time_constants`/`t0`,
        dynamics `omega`/`zeta`, observer `force_sensitivity`/`stiffness`: positive; PI `thresholds`: ascending
        and positive; real `poles`: negative.
        """
        if require_values:
            missing = self.missing_values()
            if missing:
                raise PiezojaxValueError(
                    f"{self.source}: forward simulation needs every parameter value; missing: {', '.join(missing)}"
                )
        model = self._assemble(_InitialValues(self, dataset, use_cold_start=False))
        if dataset is not None:
            # two data-driven starts for PI + Kelvin–Voigt + even-order dynamics: keep the one closer to the data;
            # the cold start failing (a degenerate record) leaves the rule-based start, with a warning
            try:
                values = _InitialValues(self, dataset)
                other = self._assemble(values) if values._cold_start() is not None else None
            except PiezojaxValueError as e:
                warnings.warn(f"{self.source}: the data-driven cold start failed ({e}); starting from the simple "
                              "rules instead", StartWarning, stacklevel=2)
                other = None
            if other is not None and _start_error(other, dataset) < _start_error(model, dataset):
                model = other
            model = self._start_state(model, dataset)
        return self._constrain(model)

    def _start_state(self, model, dataset):
        """Data-driven starts of the actuator's offset (the mean residual) and prehistory (the best of a grid of
        excursions from -max|v| to max|v|, each with its offset), where the file gives no number."""
        offset, pre = self._offset(), self._prehistory()
        if self.is_observer or (offset is not True and pre is not True):
            return model
        recs = [e for e in dataset if e.has("displacement")]
        if not recs:
            return model
        sim = _displacement

        def with_offset(m):
            if offset is not True:
                return m
            res = np.concatenate([np.asarray(e["displacement"]) - np.asarray(sim(m, jnp.asarray(e.v_in),
                                                                                   jnp.asarray(e.dt)))
                                  for e in recs])
            b = float(np.mean(res)) if np.all(np.isfinite(res)) else 0.0
            return eqx.tree_at(lambda a: a.offset, m, jnp.asarray(b + float(m.offset), m.offset.dtype))

        if pre is not True:
            return with_offset(model)
        vmax = max(float(np.max(np.abs(e.v_in))) for e in recs)
        best, best_err = None, np.inf
        for u in vmax * np.linspace(-1.0, 1.0, 9):
            cand = with_offset(eqx.tree_at(lambda a: a.prehistory, model, jnp.asarray(u, model.prehistory.dtype)))
            err = _start_error(cand, recs)
            if best is None or err < best_err:
                best, best_err = cand, err
        return best

    def _assemble(self, values: "_InitialValues"):
        f64 = lambda x: jnp.asarray(np.asarray(x, np.float64))  # noqa: E731
        ho = self.hysteresis_options
        smoothing = ho.get("smoothing", 0.0)
        hyst = self._assemble_operator(values, f64, ho, smoothing)
        if hyst is not None and self.polynomial:
            coefficients = ho.get("coefficients")
            coefficients = np.zeros(self.polynomial - 1) if coefficients is None else coefficients
            hyst = pj.OutputPolynomial(hyst, f64(coefficients), f64(values.polynomial_scale()))
        creep = None
        if self.creep == "kelvin_voigt":
            v = values.creep()
            creep = pj.KelvinVoigtCreep(f64(v["stiffnesses"]), f64(v["time_constants"]),
                                        k0=None if self.creep_structure == "parallel" else f64(1.0))
        elif self.creep == "logarithmic":
            v = values.creep()
            creep = pj.LogarithmicCreep(f64(v["gamma"]), f64(v["t0"]), gain=f64(v["gain"]),
                                        instantaneous=self.creep_structure == "series")
        elif self.creep == "lag":
            v = values.creep()
            creep = pj.LagCreep(f64(v["fractions"]), f64(v["time_constants"]))
        if self.is_observer:
            o = self.observer
            fc = o.get("filter_cutoff")
            cp = o.get("capacitance_p")
            if cp is None:
                cp = values.observer_capacitance() if self.hysteresis == "none" else 0.0
            return pj.ForceDisplacementObserver(
                f64(o["integrator_capacitance"]), f64(o["reference_capacitance"]), f64(o["leakage_resistance"]),
                f64(o.get("bias_current", 0.0)), f64(o["force_sensitivity"]), f64(o["displacement_coefficient"]),
                f64(o["stiffness"]), capacitance_p=f64(cp), hysteresis=hyst, creep=creep,
                filter_cutoff=None if fc is None else f64(fc),
            )
        dyn = None
        if self.dynamics_order or self.hysteresis == "none":
            # without hysteresis the dynamics' DC gain is the only scale from volts to metres (order 0: a gain)
            v = values.dynamics()
            dyn = pj.StableTransferFunction(f64(values.dynamics_gain()), omega=f64(v["omega"]), zeta=f64(v["zeta"]),
                                            poles=f64(v["poles"]))
        cap = coup = 0.0
        if self.charge is not None:
            cap, coup = values.charge()
        offset, pre = self._offset(), self._prehistory()
        offset = 0.0 if isinstance(offset, bool) else offset
        pre = None if pre is False else (0.0 if pre is True else pre)
        return pj.Actuator(hyst, creep, dyn, capacitance=f64(cap), coupling=f64(coup), structure=self.creep_structure,
                           offset=f64(offset), prehistory=None if pre is None else f64(pre))

    def _assemble_operator(self, values, f64, ho, smoothing):
        hyst = None
        if self.hysteresis == "prandtl_ishlinskii":
            v = values.hysteresis()
            hyst = pj.PrandtlIshlinskii(f64(v["weights"]), f64(v["thresholds"]), w0=f64(v["w0"]),
                                        smoothing=f64(smoothing))
        elif self.hysteresis == "bouc_wen":
            v = values.hysteresis()
            n = 1.0 if ho.get("n") is None else ho["n"]
            hyst = pj.BoucWen(f64(v["A"]), f64(v["beta"]), f64(v["gamma"]), f64(n), f64(v["d"]),
                              smoothing=f64(smoothing), method=self._bouc_wen_method(),
                              substeps=ho.get("substeps", 8))
        elif self.hysteresis == "maxwell_slip":
            v = values.hysteresis()
            hyst = pj.MaxwellSlip(f64(v["stiffness"]), f64(v["breakaway"]), smoothing=f64(smoothing))
        return hyst

    def _constrain(self, model):
        c = pj.constrain
        h, H = self.hysteresis, self._operator
        if h == "prandtl_ishlinskii":
            model = c(model, lambda m: H(m).weights, pj.Positive)
            model = c(model, lambda m: H(m).w0, pj.Positive)
            model = c(model, lambda m: H(m).thresholds, pj.OrderedPositive)
        elif h == "bouc_wen":
            model = c(model, lambda m: H(m).A, pj.Positive)
            model = c(model, lambda m: H(m).beta, pj.Positive)
            model = c(model, lambda m: H(m).n, pj.Positive)
        elif h == "maxwell_slip":
            model = c(model, lambda m: H(m).stiffness, pj.Positive)
            model = c(model, lambda m: H(m).breakaway, pj.Positive)
        if self.creep == "kelvin_voigt":
            model = c(model, lambda m: m.creep.stiffnesses, pj.Positive)
            model = c(model, lambda m: m.creep.time_constants, pj.Positive)
        elif self.creep == "logarithmic":
            model = c(model, lambda m: m.creep.t0, pj.Positive)
        elif self.creep == "lag":
            model = c(model, lambda m: m.creep.fractions, pj.Fractions)
            model = c(model, lambda m: m.creep.time_constants, pj.Positive)
        if self.is_observer:
            model = c(model, lambda m: m.force_sensitivity, pj.Positive)
            model = c(model, lambda m: m.stiffness, pj.Positive)
            return model
        n2, n1 = divmod(self.dynamics_order, 2)
        if n2:
            model = c(model, lambda m: m.dynamics.omega, pj.Positive)
            model = c(model, lambda m: m.dynamics.zeta, pj.Positive)
        if n1:
            model = c(model, lambda m: m.dynamics.poles, _Negative)
        return model


# ------------------------------------------------------------------------------------------------ initial values


def _chord(v: np.ndarray, y: np.ndarray) -> float:
    """Least-squares slope of y against v through the origin."""
    den = float(np.dot(v, v))
    return float(np.dot(v, y)) / den if den > 0 else 1.0


@eqx.filter_jit
def _displacement(model, v, dt):
    """An actuator's displacement, compiled once per model structure and record length (not once per call)."""
    return model.simulate(v, dt).displacement


def _start_error(model, dataset) -> float:
    """Sum over experiments of the squared displacement error of an actuator, relative to the displacement range."""
    sim = _displacement
    total = 0.0
    for e in dataset:
        if e.has("displacement"):
            y = np.asarray(e["displacement"])
            err = np.asarray(sim(model, jnp.asarray(e.v_in), jnp.asarray(e.dt))) - y
            total += float(np.sum((err / max(float(np.ptp(y)), np.finfo(float).tiny)) ** 2))
    return total if np.isfinite(total) else np.inf


class _InitialValues:
    """Explicit values from the file, else data-driven initial values (`dataset`), else placeholders."""

    def __init__(self, config: ModelConfig, dataset, use_cold_start: bool = True):
        self.config, self.dataset = config, dataset
        self._cold = None if use_cold_start else False
        self._records_cache = None

    # ---- data

    def _records(self):
        """(v_in, y, dt) per experiment, y the output of hysteresis + creep in the model's units: the displacement
        for an actuator (quasi-static, G(0) = 1), the charge less β·force for the observer."""
        if self._records_cache is not None:
            return self._records_cache
        cfg, recs = self.config, []
        if cfg.is_observer:
            o = cfg.observer
            plain = pj.ForceDisplacementObserver(
                o["integrator_capacitance"], o["reference_capacitance"], o["leakage_resistance"],
                o.get("bias_current", 0.0), o["force_sensitivity"], o["displacement_coefficient"], o["stiffness"])
            for e in self.dataset:
                if not e.has("v_out"):
                    continue
                q = np.asarray(plain.compensated_charge(jnp.asarray(e.v_in), jnp.asarray(e["v_out"]), e.dt))
                if e.has("force"):
                    q = q - o["force_sensitivity"] * np.asarray(e["force"])
                recs.append((np.asarray(e.v_in), q, e.dt))
            if not recs:
                raise PiezojaxValueError(
                    "initial values for the observer's operators need data files with a 'v_out' column "
                    "(or give the values explicitly in the configuration)")
        else:
            recs = [(np.asarray(e.v_in), np.asarray(e["displacement"]), e.dt) for e in self.dataset
                    if e.has("displacement")]
            if not recs:
                raise PiezojaxValueError(
                    "data-driven initial values need data files with a 'displacement' column "
                    "(or give every parameter value explicitly in the configuration)")
        if not max(float(np.max(np.abs(v))) for v, _, _ in recs) > 0:
            raise PiezojaxValueError("every 'v_in' column is identically zero: no initial values can be identified")
        self._records_cache = recs
        return recs

    def _cold_start(self):
        """`fitting.cold_start_actuator` where the configuration is its family (PI + Kelvin–Voigt or no creep +
        even-order dynamics), else None."""
        cfg = self.config
        if self._cold is not None:
            return self._cold if isinstance(self._cold, pj.Actuator) else None
        self._cold = False
        if (self.dataset is None or cfg.is_observer or cfg.hysteresis != "prandtl_ishlinskii"
                or cfg.creep not in ("kelvin_voigt", "none") or cfg.creep_structure != "parallel"
                or cfg.dynamics_order % 2):
            return None
        try:
            from ._initialise import cold_start_actuator
        except ImportError:  # pragma: no cover - the initialiser is optional
            return None
        order = cfg.creep_options.get("order", 1) if cfg.creep == "kelvin_voigt" else 0
        ds = [e for e in self.dataset if e.has("displacement")]
        if not ds:
            return None
        self._cold = pj.unwrap(cold_start_actuator(ds, cfg.hysteresis_options.get("plays", 10), order,
                                                   cfg.dynamics_order, constrained=False))
        return self._cold

    def _explicit_or(self, opts: dict, keys: tuple[str, ...], make):
        """Explicit values where given, the rest from `make()` (called only if something is missing)."""
        out = {k: opts.get(k) for k in keys}
        if any(v is None for v in out.values()):
            made = make()
            out = {k: (made[k] if out[k] is None else out[k]) for k in keys}
        return out

    # ---- blocks

    def hysteresis(self) -> dict:
        cfg, o = self.config, self.config.hysteresis_options
        kind = cfg.hysteresis
        if kind == "prandtl_ishlinskii":
            n = o.get("plays", 10)

            def make():
                if self.dataset is None:
                    return {"weights": np.full(n, 0.1), "thresholds": np.arange(1.0, n + 1), "w0": 1.0}
                cold = self._cold_start()
                if cold is not None:
                    h = cold.hysteresis
                    return {"weights": np.asarray(h.weights), "thresholds": np.asarray(h.thresholds),
                            "w0": float(h.w0)}
                recs = self._records()
                pi = pj.pi_cold_start([v for v, _, _ in recs], [y for _, y, _ in recs], n)
                w = np.asarray(pi.weights)
                top = max(float(np.max(np.abs(np.r_[w, float(pi.w0)]))), np.finfo(float).tiny)
                return {"weights": np.maximum(w, 1e-3 * top), "thresholds": np.asarray(pi.thresholds),
                        "w0": max(float(pi.w0), 1e-3 * top)}

            return self._explicit_or(o, ("weights", "thresholds", "w0"), make)
        if kind == "maxwell_slip":
            n = o.get("elements", 8)

            def make():
                if self.dataset is None:
                    return {"stiffness": np.ones(n), "breakaway": np.arange(1.0, n + 1)}
                import scipy.optimize

                recs = self._records()
                vmax = max(float(np.max(np.abs(v))) for v, _, _ in recs)
                # thresholds up to 1.2 max|v|: the widest elements stay elastic (the linear part of the response)
                r = 1.2 * vmax * np.arange(1, n + 1) / n
                play = pj.PlayOperator(jnp.asarray(r))
                a = np.concatenate([v[:, None] - np.asarray(play(jnp.asarray(v))) for v, _, _ in recs])
                y = np.concatenate([y for _, y, _ in recs])
                sign = 1.0 if _chord(np.concatenate([v for v, _, _ in recs]), y) >= 0 else -1.0
                k, _ = scipy.optimize.nnls(a, sign * y)
                k = np.maximum(k, 1e-3 * max(float(k.max()), np.finfo(float).tiny))
                return {"stiffness": k, "breakaway": k * r}

            return self._explicit_or(o, ("stiffness", "breakaway"), make)
        if kind == "bouc_wen":

            def make():
                if self.dataset is None:
                    return {"A": 0.1, "beta": 0.01, "gamma": 0.01, "d": 1.0}
                recs = self._records()
                v = np.concatenate([v for v, _, _ in recs])
                y = np.concatenate([y for _, y, _ in recs])
                a = _chord(v, y)
                A = max(0.2 * abs(a), np.finfo(float).tiny)
                z_max = 0.05 * float(np.ptp(y)) / abs(a) * A if np.ptp(y) > 0 else A
                beta = A / (2 * max(z_max, np.finfo(float).tiny))
                bw = pj.BoucWen(A, beta, beta, output="z")
                z = np.concatenate([np.asarray(bw(jnp.asarray(vv))) for vv, _, _ in recs])
                d = float(np.dot(v, y + z) / np.dot(v, v))
                return {"A": A, "beta": beta, "gamma": beta, "d": d}

            return self._explicit_or(o, ("A", "beta", "gamma", "d"), make)
        raise AssertionError(kind)

    def creep(self) -> dict:
        cfg, o = self.config, self.config.creep_options
        if cfg.creep == "kelvin_voigt":
            n = o.get("order", 1)

            def make():
                if self.dataset is None:
                    return {"stiffnesses": np.full(n, 10.0), "time_constants": np.geomspace(1.0, 10.0, n)}
                cold = self._cold_start()
                if cold is not None and cold.creep is not None:
                    return {"stiffnesses": np.asarray(cold.creep.stiffnesses),
                            "time_constants": np.asarray(cold.creep.time_constants)}
                recs = self._records()
                dt = min(d for _, _, d in recs)
                span = max(v.size * d for v, _, d in recs)
                # one lag at a tenth of the longest record, or n lags from 1/100 to 1/3 of it
                taus = (np.array([span / 10]) if n == 1 else np.geomspace(span / 100, span / 3, n))
                taus = np.maximum(taus, 5 * dt)
                v = np.concatenate([v for v, _, _ in recs])
                gain = abs(_chord(v, np.concatenate([y for _, y, _ in recs])))
                if cfg.hysteresis == "none" and not cfg.is_observer:
                    gain = 1.0  # the creep acts on the voltage before the dynamics' gain
                # each lag starts at 1 % of the static gain
                return {"stiffnesses": np.full(n, 1.0 / max(0.01 * gain, np.finfo(float).tiny)),
                        "time_constants": taus}

            return self._explicit_or(o, ("stiffnesses", "time_constants"), make)
        if cfg.creep == "logarithmic":

            def make():
                if self.dataset is None:
                    return {"gamma": 0.01, "t0": 1.0, "gain": 1.0}
                recs = self._records()
                dt = min(d for _, _, d in recs)
                v = np.concatenate([v for v, _, _ in recs])
                gain = _chord(v, np.concatenate([y for _, y, _ in recs]))
                if cfg.hysteresis == "none" and not cfg.is_observer:
                    gain = 1.0
                return {"gamma": 0.01, "t0": 10 * dt, "gain": gain}

            out = self._explicit_or(o, ("gamma", "t0"), make)
            if o.get("gain") is not None:
                out["gain"] = o["gain"]
            else:
                out["gain"] = make()["gain"]
            return out
        if cfg.creep == "lag":
            n = o.get("lags", 1)

            def make():
                if self.dataset is None:
                    return {"fractions": np.full(n, 0.1 / n), "time_constants": np.geomspace(1e-2, 1.0, n)}
                dt = min(e.dt for e in self.dataset)
                span = max(e.n * e.dt for e in self.dataset)
                # 20 % of the response lagging, split evenly; lags from 50 samples to a tenth of the longest record
                lo = 50 * dt
                taus = np.array([lo]) if n == 1 else np.geomspace(lo, max(span / 10, 2 * lo), n)
                return {"fractions": np.full(n, 0.2 / n), "time_constants": taus}

            return self._explicit_or(o, ("fractions", "time_constants"), make)
        raise AssertionError(cfg.creep)

    def polynomial_scale(self) -> float:
        """The output polynomial's scale: explicit, else the largest deviation of the measured output from its
        mean (so the coefficients are of order one), else 1."""
        s = self.config.hysteresis_options.get("polynomial_scale")
        if s is not None:
            return s
        if self.dataset is None:
            return 1.0
        ys = [y for _, y, _ in self._records()]
        dev = max(float(np.max(np.abs(y - np.mean(y)))) for y in ys)
        return dev if dev > 0 else 1.0

    def dynamics(self) -> dict:
        cfg, o = self.config, self.config.dynamics_options
        n2, n1 = divmod(cfg.dynamics_order, 2)

        def make():
            if self.dataset is None:
                return {"omega": np.geomspace(1e3, 1e4, n2) if n2 else np.zeros(0),
                        "zeta": np.full(n2, 0.5), "poles": np.full(n1, -1e3)}
            cold = self._cold_start()
            if cold is not None and cold.dynamics is not None and n1 == 0:
                return {"omega": np.asarray(cold.dynamics.omega), "zeta": np.asarray(cold.dynamics.zeta),
                        "poles": np.zeros(0)}
            dt = min(e.dt for e in self.dataset)
            # rule of thumb: modes at 1/10 (and 1/4) of the sampling rate, damping 0.5, a real pole at 1/10
            nyquist = 0.5 / dt
            omega = 2 * np.pi * nyquist * np.array([0.2, 0.5])[:n2]
            return {"omega": omega, "zeta": np.full(n2, 0.5), "poles": np.full(n1, -2 * np.pi * 0.2 * nyquist)}

        out = self._explicit_or(o, ("omega", "zeta", "poles"), make)
        for k in ("omega", "zeta", "poles"):
            if out[k] is None:
                out[k] = np.zeros(0)
        if n1 == 0:
            out["poles"] = np.zeros(0)
        if n2 == 0:
            out["omega"] = out["zeta"] = np.zeros(0)
        return out

    def _static_gain(self) -> float:
        recs = self._records()
        return _chord(np.concatenate([v for v, _, _ in recs]), np.concatenate([y for _, y, _ in recs]))

    def dynamics_gain(self) -> float:
        """The dynamics' DC gain: explicit, else 1 (the scale sits in the hysteresis), else (no hysteresis) the
        least-squares slope of the displacement against the voltage."""
        g = self.config.dynamics_options.get("gain")
        if g is not None:
            return g
        if self.config.hysteresis != "none" or self.dataset is None:
            return 1.0
        return self._static_gain()

    def observer_capacitance(self) -> float:
        """$C_P$ of an observer without hysteresis operator: the slope of the compensated charge against $V$."""
        return 1e-9 if self.dataset is None else max(self._static_gain(), np.finfo(float).tiny)

    def charge(self) -> tuple[float, float]:
        o = self.config.charge
        cap, coup = o.get("capacitance"), o.get("coupling")
        if cap is not None and coup is not None:
            return cap, coup
        if self.dataset is None:
            return (1e-9 if cap is None else cap), (0.0 if coup is None else coup)
        # q = C v + T δ by least squares over the experiments that measured the charge (and the displacement)
        rows, rhs = [], []
        for e in self.dataset:
            if not e.has("charge"):
                continue
            q = np.asarray(e["charge"])
            d = np.asarray(e["displacement"]) if e.has("displacement") else np.zeros_like(q)
            if cap is not None:
                q = q - cap * np.asarray(e.v_in)
            if coup is not None:
                q = q - coup * d
            cols = ([] if cap is not None else [np.asarray(e.v_in)]) + ([] if coup is not None else [d])
            rows.append(np.column_stack(cols))
            rhs.append(q)
        if not rows:
            raise PiezojaxValueError(
                f"{self.config.source}: [charge]: give 'capacitance' and 'coupling' explicitly, or fit on data "
                "files with a 'charge' column")
        coef = np.linalg.lstsq(np.concatenate(rows), np.concatenate(rhs), rcond=None)[0]
        i = 0
        if cap is None:
            cap, i = max(float(coef[0]), 0.0), 1
        if coup is None:
            coup = float(coef[i])
        return cap, coup


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
    if not any(k in raw for k in ("hysteresis", "creep", "dynamics", "observer")):
        raise PiezojaxValueError(
            f"{source}: no model blocks; give at least one of [hysteresis], [creep], [dynamics] or [observer]"
        )

    # hysteresis
    h_raw = raw.get("hysteresis", {"kind": "none"})
    h_kind = _kind(source, "hysteresis", h_raw, HYSTERESIS_KINDS)
    ht = _Table(source, "hysteresis", h_raw, _HYSTERESIS_KEYS[h_kind], h_kind)
    ho: dict[str, Any] = {}
    if h_kind != "none":
        ho["smoothing"] = ht.number("smoothing", 0.0, nonnegative=True)
    if h_kind == "prandtl_ishlinskii":
        n, (w, r) = ht.sized_vectors("plays", 10, MAX_PLAYS, {"weights": dict(positive=True),
                                                    "thresholds": dict(positive=True, ascending=True)})
        ho.update(plays=n, weights=w, thresholds=r, w0=ht.number("w0", None, positive=True))
    elif h_kind == "maxwell_slip":
        n, (k, f) = ht.sized_vectors("elements", 8, MAX_ELEMENTS, {"stiffness": dict(positive=True),
                                                      "breakaway": dict(positive=True)})
        ho.update(elements=n, stiffness=k, breakaway=f)
    elif h_kind == "bouc_wen":
        ho.update(A=ht.number("A", None, positive=True), beta=ht.number("beta", None, positive=True),
                  gamma=ht.number("gamma", None), n=ht.number("n", None, positive=True), d=ht.number("d", None),
                  method=ht.string("method", ("closed_form", "rk4")),
                  substeps=ht.integer("substeps", 8, minimum=1, maximum=MAX_SUBSTEPS))
        if ho["method"] == "closed_form" and ho["n"] not in (None, 1.0):
            raise ht.error(f"method 'closed_form' needs n = 1, got n = {ho['n']}", "method")
        if ho["method"] == "closed_form" and ho["smoothing"] != 0:
            raise ht.error("method 'closed_form' needs smoothing = 0 (use method = 'rk4')", "method")
    if h_kind != "none":
        degree = ht.integer("polynomial", 0, minimum=0, maximum=MAX_POLYNOMIAL)
        if degree == 1:
            raise ht.error("the output polynomial's degree must be 0 (none) or 2 and above: degree 1 would duplicate "
                           "the operator's gain", "polynomial")
        for key in ("coefficients", "polynomial_scale"):
            if degree == 0 and key in ht.data:
                raise ht.error("needs an output polynomial (polynomial = 2 or more)", key)
        if degree:
            ho["polynomial"] = degree
            ho["coefficients"] = ht.vector("coefficients", degree - 1)
            ho["polynomial_scale"] = ht.number("polynomial_scale", None, positive=True)

    # creep
    c_raw = raw.get("creep", {"kind": "none"})
    c_kind = _kind(source, "creep", c_raw, CREEP_KINDS)
    ct = _Table(source, "creep", c_raw, _CREEP_KEYS[c_kind], c_kind)
    co: dict[str, Any] = {}
    if c_kind == "kelvin_voigt":
        n, (k, tau) = ct.sized_vectors("order", 1, MAX_CREEP_ORDER, {"stiffnesses": dict(positive=True),
                                                     "time_constants": dict(positive=True)})
        co.update(order=n, stiffnesses=k, time_constants=tau)
    elif c_kind == "logarithmic":
        co.update(gamma=ct.number("gamma", None), t0=ct.number("t0", None, positive=True),
                  gain=ct.number("gain", None))
    elif c_kind == "lag":
        n, (alpha, tau) = ct.sized_vectors("lags", 1, MAX_CREEP_ORDER, {"fractions": dict(positive=True),
                                                     "time_constants": dict(positive=True)})
        if alpha is not None and sum(alpha) >= 1:
            raise ct.error(f"the fractions must add up to less than 1 (the rest responds at once), got {sum(alpha)}",
                           "fractions")
        co.update(lags=n, fractions=alpha, time_constants=tau)
    if c_kind != "none":
        structure = ct.string("structure", ("series", "parallel"))
        if structure is not None:
            co["structure"] = structure
        if c_kind == "lag" and structure == "parallel":
            raise ct.error("a 'lag' creep is DC-normalised (its gain is 1): it belongs in series after the hysteresis; "
                           "use 'kelvin_voigt' for creep in parallel", "structure")
        if "observer" in raw and (c_kind == "lag" or structure == "series"):
            raise ct.error("the observer adds its creep in parallel to the hysteresis (paper 001's eq. 4); use "
                           "'kelvin_voigt' or 'logarithmic' without `structure`", "structure" if structure else "kind")

    # observer or actuator
    observer = None
    if "observer" in raw:
        o_raw = raw["observer"]
        o_kind = _kind(source, "observer", o_raw, OBSERVER_KINDS)
        ot = _Table(source, "observer", o_raw, _OBSERVER_KEYS, o_kind)
        for t in ("dynamics", "charge"):
            if t in raw:
                raise PiezojaxValueError(
                    f"{source}: [{t}] is not used by the observer (kind {o_kind!r}); remove it, or remove [observer] "
                    "for an actuator model")
        missing = [k for k in _OBSERVER_REQUIRED if k not in ot.data]
        if missing:
            raise ot.error(f"missing key(s) {', '.join(missing)} (the circuit and beam constants)")
        observer = {"kind": o_kind}
        for k in _OBSERVER_KEYS:
            positive = k not in ("bias_current", "displacement_coefficient", "capacitance_p")
            observer[k] = ot.number(k, None, positive=positive, nonnegative=k == "capacitance_p",
                                    nonzero=k == "displacement_coefficient")
        observer = {k: v for k, v in observer.items() if v is not None}
    d_raw = raw.get("dynamics", {"order": 0})
    dt_ = _Table(source, "dynamics", d_raw, _DYNAMICS_KEYS)
    if "kind" in dt_.data:
        raise dt_.error("unknown key 'kind'; the dynamics are set by `order`", "kind")
    order = dt_.integer("order", None, allowed=DYNAMICS_ORDERS)
    if order is None:
        raise dt_.error(f"missing; allowed values: {', '.join(map(str, DYNAMICS_ORDERS))}", "order")
    n2, n1 = divmod(order, 2)
    for k, n in (("omega", n2), ("zeta", n2), ("poles", n1)):
        if n == 0 and k in dt_.data:
            raise dt_.error(f"not used with order = {order}", k)
    do = {
        "gain": dt_.number("gain", None, nonzero=True),
        "omega": dt_.vector("omega", n2, positive=True),
        "zeta": dt_.vector("zeta", n2, positive=True),
        "poles": dt_.vector("poles", n1, negative=True),
    }
    do = {k: v for k, v in do.items() if v is not None}
    charge = None
    if "charge" in raw:
        cht = _Table(source, "charge", raw["charge"], _CHARGE_KEYS)
        charge = {"capacitance": cht.number("capacitance", None, nonnegative=True),
                  "coupling": cht.number("coupling", None)}
    state: dict[str, Any] = {}
    if "state" in raw:
        st = _Table(source, "state", raw["state"], _STATE_KEYS)
        if "kind" in st.data:
            raise st.error(f"unknown key 'kind'; allowed keys: {', '.join(_STATE_KEYS)}", "kind")
        if observer is not None:
            raise PiezojaxValueError(f"{source}: [state] (offset, prehistory) is not available for the observer yet")
        for key in _STATE_KEYS:
            if key not in st.data:
                continue
            value = st.data[key]
            if not (isinstance(value, bool) or _finite_number(value)):
                raise st.error(f"must be true (fitted from the data), false (none) or a number (its start value), "
                               f"got {value!r}", key)
            state[key] = value if isinstance(value, bool) else float(value)
        if state.get("prehistory", False) is not False and h_kind == "none":
            raise st.error("a prehistory sets the hysteresis' remanent state; the model has no hysteresis",
                           "prehistory")
    if observer is None and c_kind == "none" and h_kind == "none" and order == 0:
        raise PiezojaxValueError(f"{source}: every block is 'none': the model has no parameters")

    # fit options
    ft = _Table(source, "fit", raw.get("fit", {}), _FIT_KEYS)
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
            if not (_finite_number(w) and 0 < w <= MAX_WEIGHT):
                raise ft.error(f"weight of {c!r} must be a number > 0 and <= {MAX_WEIGHT:g}, got {w!r}", "weights")
        weights = {c: float(w) for c, w in weights.items()}
    else:
        raise ft.error(f"must be \"range\", \"noise\" or a table {{channel = weight}}, got {weights!r}", "weights")
    smoothing = ft.data.get("smoothing")
    if smoothing is not None:
        if not (isinstance(smoothing, list) and smoothing and all(
                _finite_number(s) and s >= 0
                for s in smoothing)):
            raise ft.error(f"must be a non-empty list of numbers >= 0 (continuation levels), got {smoothing!r}",
                           "smoothing")
        if h_kind == "none":
            raise ft.error("continuation needs a hysteresis block with smoothing", "smoothing")
        if len(smoothing) > MAX_LEVELS:
            raise ft.error(f"at most {MAX_LEVELS} continuation levels, got {len(smoothing)}", "smoothing")
        smoothing = tuple(float(s) for s in smoothing)
    max_steps = ft.integer("max_steps", 200, minimum=1, maximum=MAX_STEPS)
    method = ft.string("method", ("levenberg_marquardt", "trust_region"), "levenberg_marquardt")
    targets = ft.data.get("targets")
    if targets is not None:
        outputs = ("displacement", "force") if observer is not None else (
            ("displacement", "charge", "current") if charge is not None else ("displacement",))
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
    dtab = _Table(source, "data", raw.get("data", {}), _DATA_KEYS)
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
        text=text, source=source, hysteresis=h_kind, hysteresis_options=ho, creep=c_kind, creep_options=co,
        dynamics_order=order, dynamics_options=do, charge=charge, observer=observer, free=free, weights=weights,
        smoothing=smoothing, max_steps=max_steps, targets=targets, method=method, data=data, state=state,
    )
    if ho.get("smoothing", 0.0) != 0 and h_kind == "bouc_wen" and cfg._bouc_wen_method() != "rk4":
        raise ht.error("smoothing needs method = 'rk4'", "smoothing")
    if free is not None:
        from ._problem import _matches, parameter_paths

        paths = list(parameter_paths(cfg.build(None)))
        for sel in free:
            if not any(_matches(p, sel) for p in paths):
                raise ft.error(f"unknown parameter path {sel!r}; the model's parameters: {', '.join(paths)}", "free")
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
