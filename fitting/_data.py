"""Measured experiments, data files and datasets for calibration.

An *experiment* is one record on a uniform time grid: time `t` [s], applied voltage `v_in` [V], and any subset of the
measured channels in `CHANNELS`. A `Dataset` is an ordered collection of experiments of possibly different lengths and
channel sets, with the grouping and padding the calibration engine needs to `vmap` over them.

Data live on the host as read-only float64 numpy arrays: they are loaded and validated once, eagerly, with error
messages naming the file, the column and the row. The engine converts them to JAX arrays (in the dtype it chooses)
when it builds residuals.
"""

import contextlib
import dataclasses
import io
import math
import os
import re
import types
import warnings
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path

import numpy as np

from piezojax._checks import PiezojaxValueError

from .files import atomic_file, atomic_write_bytes

CHANNELS: tuple[str, ...] = ("v_out", "displacement", "force", "charge", "current")
"""Measured channels besides `t` [s] and `v_in` [V], all in SI units:

- `v_out` [V]: output voltage of the sensing circuit (transimpedance amplifier, charge amplifier, sensor layer);
- `displacement` [m]: actuator/stage displacement;
- `force` [N]: force on the actuator (e.g. from a force sensor at the tip);
- `charge` [C]: charge on the piezo electrodes;
- `current` [A]: current into the piezo.
"""

UNITS: Mapping[str, str] = types.MappingProxyType(
    {"t": "s", "v_in": "V", "v_out": "V", "displacement": "m", "force": "N", "charge": "C", "current": "A"}
)

COLUMNS: tuple[str, ...] = ("t", "v_in") + CHANNELS

_QUANTITIES = {"s": "time", "V": "voltage", "m": "length", "N": "force", "C": "charge", "A": "current"}
_PREFIXES = {"k": 1e3, "": 1.0, "m": 1e-3, "u": 1e-6, "µ": 1e-6, "μ": 1e-6, "n": 1e-9, "p": 1e-12}


class UnitWarning(UserWarning):
    """A column's magnitude is implausible for its SI unit (e.g. a displacement spanning metres: probably µm)."""


def unit_scale(column: str, unit: str, where: str = "units") -> float:
    """The factor that converts `column` from `unit` to its SI unit (`UNITS`): `unit_scale("displacement", "um")`
    is 1e-6. Units are the SI unit with an optional prefix k, m, u (or µ), n, p.

    Raises `PiezojaxValueError` naming `where`, the column and the units it takes."""
    if column not in COLUMNS:
        raise PiezojaxValueError(f"{where}: unknown column {column!r}; columns are {list(COLUMNS)}")
    base = UNITS[column]
    if isinstance(unit, str):
        u = unit.strip()
        if u.endswith(base) and u[: len(u) - len(base)] in _PREFIXES:
            return _PREFIXES[u[: len(u) - len(base)]]
    allowed = ", ".join(p + base for p in ("k", "", "m", "u", "n", "p"))
    raise PiezojaxValueError(
        f"{where}: unknown unit {unit!r} for column {column!r}, a {_QUANTITIES[base]}; allowed: {allowed} "
        f"(u or µ for micro)"
    )


def parse_units(units, where: str = "`units`") -> dict[str, float]:
    """Validate a `{column: unit}` mapping (e.g. `{"displacement": "um", "t": "ms"}`); return `{column: scale to
    SI}`. `None` means every column is in SI units."""
    if units is None:
        return {}
    if not isinstance(units, Mapping):
        raise PiezojaxValueError(f"{where} must be a mapping {{column: unit}}, got {type(units).__name__}")
    return {str(k): unit_scale(str(k), v, where) for k, v in units.items()}


# Plausible magnitudes for a piezoelectric actuator in SI units: (column, statistic, upper bound, hint, the unit
# to suggest).
_PLAUSIBLE = (
    ("v_in", "peak", 1e4, "V (kilovolts are the upper end of piezo drives; is it in mV?)", "mV"),
    ("v_out", "peak", 1e4, "V (is it in mV?)", "mV"),
    ("displacement", "range", 1e-2, "m (piezo strokes are below a few millimetres; is it in µm, nm or mm?)", "um"),
    ("force", "peak", 1e5, "N (is it in mN?)", "mN"),
    ("charge", "peak", 1.0, "C (is it in µC or nC?)", "uC"),
    ("current", "peak", 1e2, "A (is it in mA or µA?)", "mA"),
)


def plausibility_warnings(exp: "Experiment", units: Mapping[str, str] | None = None) -> list[str]:
    """Messages for columns of `exp` whose magnitude is implausible in SI units (a record in µm read as metres,
    in mV read as volts, ...); empty if everything looks plausible. `units`: the units declared on loading (a
    column with a declared unit is reported as such, not asked to declare one)."""
    units = dict(units or {})
    out = []
    for col, stat, bound, hint, suggest in _PLAUSIBLE:
        if col not in exp.columns():
            continue
        a = exp[col]
        value = float(np.ptp(a)) if stat == "range" else float(np.max(np.abs(a)))
        if value <= bound:
            continue
        if col in units:
            out.append(f"{exp._label()}: column {col!r}, declared in {units[col]!r}, has a {stat} of {value:.4g} "
                       f"{UNITS[col]} after conversion, implausible for a piezo record — check its declared unit")
        else:
            out.append(
                f"{exp._label()}: column {col!r} has a {stat} of {value:.4g} {hint} — declare the column's unit "
                f"(e.g. units = {{{col} = \"{suggest}\"}} in [data], or --units {col}={suggest})"
            )
    if exp.dt < 1e-8 or exp.dt > 10.0:
        if "t" in units:
            out.append(f"{exp._label()}: sampling step dt = {exp.dt:.4g} s (t declared in {units['t']!r}) is "
                       "implausible for a piezo record — check its declared unit")
        else:
            out.append(
                f"{exp._label()}: sampling step dt = {exp.dt:.4g} s is implausible for a piezo record (is 't' in ms "
                "or µs? declare its unit, e.g. --units t=ms)"
            )
    return out

MAX_MAGNITUDE = 1e30
"""Largest accepted |value| in any column: beyond it, squares and products in the model and the residuals overflow
float64."""

MIN_MAGNITUDE = 1e-30
"""Smallest accepted peak |value| of a column that is not identically zero: below it, squares and products underflow
float64 (no SI signal of a piezo bench comes near it)."""

DT_RTOL = 1e-3
"""Largest accepted deviation of a time step from the typical (median) step, relative to it: max |Δt_k − dt| ≤
DT_RTOL · dt, or two floating-point spacings of the largest |t| (float32 spacings for stamps that are float32 numbers),
whichever is larger. Enough for time stamps
rounded to float32 or stored at epoch scale (1.7e9 s, where float64 resolves 2.4e-7 s); a gap of missing samples or a
change of rate is far above it. Accepted stamps are replaced by the uniform
grid $t_0 + k dt$ through the first and last sample."""

_SLICE_RTOL = 1e-6  # a slice boundary this close (relative to dt) to a sample counts as on it

SUPPORTED_SUFFIXES: tuple[str, ...] = (".csv", ".npz", ".h5", ".hdf5", ".mat")

UNGROUPED_SUFFIXES = (".csv", ".npz")
"""The data formats without groups (read whole): a `group` concerns the others, HDF5 and `.mat`."""


def listed_files(paths: Sequence) -> str:
    """The first three of `paths` for a message: `'a.csv', 'b.csv', 'c.csv', …`."""
    return ", ".join(repr(str(p)) for p in paths[:3]) + (", …" if len(paths) > 3 else "")

FILE_MARKER = "piezojax_output"
"""Name under which `save_experiment(..., marker=...)` records the piezojax command that wrote a file (a variable in
NPZ and .mat files, a root attribute in HDF5, the first comment line in CSV); readers skip it."""


def _readonly(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False  # `a` is the private copy made by `_column`
    return a


def _column(value, label: str, column: str) -> np.ndarray:
    try:
        arr = np.asarray(value)
    except Exception as e:
        raise PiezojaxValueError(f"{label}: column {column!r} is not an array ({type(value).__name__})") from e
    if arr.dtype.kind == "c":
        raise PiezojaxValueError(f"{label}: column {column!r} is complex; expected real numbers")
    if arr.dtype.kind == "b":
        raise PiezojaxValueError(f"{label}: column {column!r} is boolean (True/False); expected real numbers")
    if arr.dtype.kind not in "iuf":
        raise PiezojaxValueError(f"{label}: column {column!r} is not numeric (dtype {arr.dtype})")
    if arr.ndim != 1:
        raise PiezojaxValueError(f"{label}: column {column!r} must be 1-D, got shape {tuple(arr.shape)}")
    return np.array(arr, dtype=np.float64, copy=True)  # private copy: the caller's array may change later


@dataclasses.dataclass(frozen=True, eq=False, repr=False)
class Experiment:
    """One measured record on a uniform time grid: `t` [s], `v_in` [V] and any of the `CHANNELS`.

    $t_k = t_0 + k\\,dt,\\quad k = 0, \\dots, n-1$, with every column of length $n \\ge 2$ and finite.

    Immutable: a frozen dataclass holding read-only float64 numpy arrays. Host data rather than an `eqx.Module`
    because it is loaded and validated once, eagerly (errors name the file, column and row, which needs concrete
    values), and is never differentiated; `Dataset.padded` produces the pytree the engine feeds to `jit`/`vmap`.

    **Arguments:**

    - `t`: sample times [s], strictly increasing and uniform: each step within `DT_RTOL` of the typical one
      (rounded stamps are accepted and replaced by the uniform grid; gaps and jitter beyond that are errors that
      say which).
    - `v_in`: applied voltage [V].
    - `channels`: mapping from names in `CHANNELS` to measured signals (any subset, possibly empty).
    - `name`: the experiment's name (unique inside a `Dataset`).
    - `source`: the file it was loaded from, if any (used in error messages).
    - `scored_from`: a time [s] within the record, or `None` (default): a fit scores only the samples from it on;
      the model still runs over the samples before it, from rest at the record's start, so they are its history
      (`piezojax fit --window START:STOP`). At least 2 samples must be scored.

    **Returns:**

    The validated experiment; bad input raises `PiezojaxValueError` naming the experiment (or file) and the column.

    ```python
    exp = Experiment.from_arrays(v_in=v, dt=1e-3, displacement=x, name="step_50V")
    train, test = exp.slice(0.0, 10.0), exp.slice(10.0, None)
    ```
    """

    t: np.ndarray
    v_in: np.ndarray
    channels: Mapping[str, np.ndarray] = dataclasses.field(default_factory=dict)
    name: str = "experiment"
    source: str | None = None
    scored_from: float | None = None

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise PiezojaxValueError(f"`name` must be a non-empty string, got {self.name!r}")
        label = self._label()
        if not isinstance(self.channels, Mapping):
            raise PiezojaxValueError(f"{label}: `channels` must be a mapping, got {type(self.channels).__name__}")
        unknown = [k for k in self.channels if k not in CHANNELS]
        if unknown:
            raise PiezojaxValueError(
                f"{label}: unknown channel(s) {unknown}; allowed channels are {list(CHANNELS)} (besides 't', 'v_in')"
            )
        cols = {"t": _column(self.t, label, "t"), "v_in": _column(self.v_in, label, "v_in")}
        for k in CHANNELS:
            if k in self.channels:
                cols[k] = _column(self.channels[k], label, k)
        n = cols["t"].shape[0]
        if n < 2:
            raise PiezojaxValueError(f"{label}: column 't' has {n} sample(s); an experiment needs at least 2")
        for k, a in cols.items():
            if a.shape[0] != n:
                raise PiezojaxValueError(
                    f"{label}: column {k!r} has {a.shape[0]} samples but column 't' has {n}; all columns must have "
                    "equal length"
                )
        for k, a in cols.items():
            bad = ~np.isfinite(a)
            if bad.any():
                i = int(np.argmax(bad))
                raise PiezojaxValueError(
                    f"{label}: column {k!r} has a non-finite value ({a[i]}) at row {i} (0-based sample index); "
                    f"{int(bad.sum())} non-finite value(s) in total"
                )
            peak = float(np.max(np.abs(a))) if a.size else 0.0
            if 0 < peak < MIN_MAGNITUDE:
                raise PiezojaxValueError(
                    f"{label}: column {k!r} is at most {peak:.3g} in magnitude; values this small (below "
                    f"{MIN_MAGNITUDE:g}) underflow the model's arithmetic (expected {k!r} in {UNITS[k]}; declare its "
                    "unit if it is not SI)"
                )
            huge = np.abs(a) > MAX_MAGNITUDE
            if huge.any():
                i = int(np.argmax(huge))
                raise PiezojaxValueError(
                    f"{label}: column {k!r} has the value {a[i]:.6g} at row {i}; values beyond ±{MAX_MAGNITUDE:g} "
                    f"overflow the model's arithmetic (expected {k!r} in {UNITS[k]})"
                )
        t = cols["t"]
        d = np.diff(t)
        if not (d > 0).all():
            i = int(np.argmax(~(d > 0)))
            raise PiezojaxValueError(
                f"{label}: column 't' is not strictly increasing: "
                f"t[{i + 1}] = {float(t[i + 1])!r} <= t[{i}] = {float(t[i])!r}"
            )
        step = float(np.median(d))
        dev = np.abs(d - step)
        j = int(np.argmax(dev))
        # a step between rounded stamps is exact to one spacing of their floating-point type at the largest |t|,
        # the median step to another: float64, or float32 for stamps that are all float32 numbers
        top = np.max(np.abs(t))
        single = np.array_equal(t.astype(np.float32).astype(np.float64), t)
        resolution = 2 * float(np.spacing(np.float32(top) if single else top))
        tol = max(DT_RTOL * step, resolution) if resolution < 0.1 * step else DT_RTOL * step
        if dev[j] > tol:
            ratio = d[j] / step
            if ratio > 1.5:
                what = f"a gap: about {round(ratio) - 1} sample(s) missing"
            elif ratio < 0.75:
                what = "samples closer than the typical step (a change of rate, or repeated samples?)"
            else:
                what = (f"jitter of {dev[j] / step:.3g}·dt, more than the {tol / step:.3g}·dt accepted for rounded "
                        "stamps")
            raise PiezojaxValueError(
                f"{label}: column 't' is not uniformly sampled: typical step dt = {step:.6g} s but "
                f"t[{j + 1}] - t[{j}] = {d[j]:.6g} s = {ratio:.4g}·dt at row {j + 1} ({what}); resample the record "
                "onto a uniform grid"
            )
        dt = (t[-1] - t[0]) / (n - 1)
        if np.max(np.abs(d - dt)) > 1e-9 * dt:  # rounded stamps: the grid they stand for
            t = t[0] + dt * np.arange(n, dtype=np.float64)
            t[-1] = cols["t"][-1]
        object.__setattr__(self, "t", _readonly(t))
        if self.scored_from is not None:
            s = self.scored_from
            if isinstance(s, bool) or not isinstance(s, (int, float, np.integer, np.floating)) or not np.isfinite(s):
                raise PiezojaxValueError(f"{label}: `scored_from` must be a finite time in seconds or None, got {s!r}")
            object.__setattr__(self, "scored_from", float(s))
            first = self.first_scored
            if n - first < 2:
                raise PiezojaxValueError(f"{label}: `scored_from` = {float(s):.6g} s leaves {max(n - first, 0)} "
                                         f"scored sample(s) of the record [{t[0]:.6g}, {t[-1]:.6g}] s; at least 2 are "
                                         "needed")
            if first == 0:
                object.__setattr__(self, "scored_from", None)
        object.__setattr__(self, "v_in", _readonly(cols["v_in"]))
        chans = {k: _readonly(cols[k]) for k in CHANNELS if k in cols}
        object.__setattr__(self, "channels", types.MappingProxyType(chans))

    def __reduce__(self):
        # The read-only channel mapping is not picklable itself; rebuild (and revalidate) from plain values.
        return (Experiment, (self.t, self.v_in, dict(self.channels), self.name, self.source, self.scored_from))

    def _label(self) -> str:
        if self.source is not None:
            return f"experiment {self.name!r} (file {self.source!r})"
        return f"experiment {self.name!r}"

    @classmethod
    def from_arrays(
        cls,
        *,
        v_in,
        t=None,
        dt: float | None = None,
        t0: float = 0.0,
        name: str = "experiment",
        source: str | None = None,
        **channels,
    ) -> "Experiment":
        """Build an experiment from arrays, with either the time vector `t` or the step `dt` ($t_k = t_0 + k\\,dt$).

        **Arguments:**

        - `v_in`: applied voltage [V].
        - `t`: sample times [s]; or
        - `dt`: sampling step [s] (with the start time `t0`, default 0).
        - `name`: the experiment's name.
        - `**channels`: measured signals named as in `CHANNELS`; `None` values are skipped.

        **Returns:**

        The validated `Experiment`.

        ```python
        exp = Experiment.from_arrays(v_in=v, dt=1e-4, v_out=vo, force=f, name="contact")
        ```
        """
        label = f"experiment {name!r}"
        if (t is None) == (dt is None):
            raise PiezojaxValueError(f"{label}: pass exactly one of `t` and `dt`")
        if t is None:
            numeric = not isinstance(dt, str | bytes | bool) and np.ndim(dt) == 0
            numeric = numeric and np.issubdtype(np.asarray(dt).dtype, np.number)
            dt_f = float(np.asarray(dt)) if numeric else math.nan
            if not (math.isfinite(dt_f) and dt_f > 0):
                raise PiezojaxValueError(f"{label}: `dt` must be a positive finite scalar, got {dt!r}")
            n = np.shape(v_in)[0] if np.ndim(v_in) >= 1 else 0
            t = float(t0) + dt_f * np.arange(n, dtype=np.float64)
        chans = {k: v for k, v in channels.items() if v is not None}
        return cls(t=t, v_in=v_in, channels=chans, name=name, source=source)

    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.t.shape[0])

    @property
    def first_scored(self) -> int:
        """The index of the first sample a fit scores (`scored_from`; 0 when it is `None`)."""
        if self.scored_from is None:
            return 0
        return int(np.searchsorted(self.t, self.scored_from - _SLICE_RTOL * self.dt, side="left"))

    @property
    def dt(self) -> float:
        """Sampling step [s], $(t_{n-1} - t_0)/(n-1)$."""
        return float((self.t[-1] - self.t[0]) / (self.n - 1))

    @property
    def duration(self) -> float:
        """Time span $t_{n-1} - t_0 = (n-1)\\,dt$ [s]."""
        return float(self.t[-1] - self.t[0])

    @property
    def channel_names(self) -> tuple[str, ...]:
        """The measured channels present, in `CHANNELS` order."""
        return tuple(self.channels)

    def has(self, channel: str) -> bool:
        """Whether `channel` was measured (`'t'` and `'v_in'` always are)."""
        if channel not in COLUMNS:
            raise PiezojaxValueError(f"unknown channel {channel!r}; allowed channels are {list(CHANNELS)}")
        return channel in ("t", "v_in") or channel in self.channels

    def __getitem__(self, column: str) -> np.ndarray:
        """The column `t`, `v_in` or a measured channel, by name."""
        if column == "t":
            return self.t
        if column == "v_in":
            return self.v_in
        if column in self.channels:
            return self.channels[column]
        if column in CHANNELS:
            raise PiezojaxValueError(f"{self._label()} has no channel {column!r}; it has {list(self.channels)}")
        raise PiezojaxValueError(f"unknown column {column!r}; allowed columns are {list(COLUMNS)}")

    def columns(self) -> dict[str, np.ndarray]:
        """All columns by name: `t`, `v_in`, then the measured channels in `CHANNELS` order."""
        return {"t": self.t, "v_in": self.v_in, **self.channels}

    def slice(self, start: float | None = None, stop: float | None = None, name: str | None = None) -> "Experiment":
        """The samples with $start \\le t_k < stop$ (times in seconds, half-open like Python slices).

        Times are kept (not shifted to start at 0). A boundary within $10^{-6}\\,dt$ of a sample counts as on it, so
        `slice(0, 10)` and `slice(10, None)` partition a record exactly even if `t` carries rounding error.

        The second part of a split record continues from the state the first part leaves (hysteresis memory, creep,
        ringing): predict it after the first, `fitting.predict(model, test, history=train)` (`piezojax predict
        --history train.csv`), or predict the whole record and score only its end (`piezojax predict --score-from`),
        not from rest.

        **Arguments:**

        - `start`, `stop`: times in seconds; `None` means the start/end of the record.
        - `name`: name of the result; default `"NAME[start:stop]"`.

        **Returns:**

        A new `Experiment` with at least 2 samples (else `PiezojaxValueError`), scored from `scored_from` where that
        lies after `start`.
        """
        tol = _SLICE_RTOL * self.dt
        i0 = 0 if start is None else int(np.searchsorted(self.t, float(start) - tol, side="left"))
        i1 = self.n if stop is None else int(np.searchsorted(self.t, float(stop) - tol, side="left"))
        if i1 - i0 < 2:
            window = (f"{'its start' if start is None else f't = {float(start):.6g} s'} to "
                      f"{'its end' if stop is None else f't = {float(stop):.6g} s'}")
            raise PiezojaxValueError(
                f"{self._label()}: {window} keeps {max(i1 - i0, 0)} sample(s) of the record "
                f"[{self.t[0]:.6g}, {self.t[-1]:.6g}] s; at least 2 are needed"
            )
        if name is None:
            name = f"{self.name}[{'' if start is None else f'{start:g}'}:{'' if stop is None else f'{stop:g}'}]"
        keep = self.scored_from is not None and i0 < self.first_scored
        return Experiment(
            t=self.t[i0:i1],
            v_in=self.v_in[i0:i1],
            channels={k: v[i0:i1] for k, v in self.channels.items()},
            name=name,
            source=self.source,
            scored_from=self.scored_from if keep else None,
        )

    def __repr__(self) -> str:
        chans = ", ".join(self.channels) or "none"
        scored = "" if self.scored_from is None else f", scored from t = {self.scored_from:.6g} s"
        return f"Experiment({self.name!r}, n={self.n}, dt={self.dt:.6g} s, channels: {chans}{scored})"


# ----------------------------------------------------------------------------------------------------------- loading


def _squeeze_vector(a: np.ndarray) -> np.ndarray:
    # MATLAB stores vectors as n×1 or 1×n (and v7.3 transposes them); accept those, leave other shapes to validation.
    if a.ndim >= 2 and sum(s != 1 for s in a.shape) <= 1:
        return a.reshape(-1)
    return a


def _looks_like_sample_indices(t) -> bool:
    try:
        t = np.asarray(t, dtype=np.float64)
    except (TypeError, ValueError):
        return False
    return t.ndim == 1 and t.size >= 3 and bool(np.all(np.diff(t) == 1.0)) and bool(np.all(t == np.round(t)))


def parse_columns(columns, where: str = "`columns`") -> dict[str, str]:
    """Validate a `{file column: piezojax column}` renaming (e.g. `{"u": "v_in", "y": "displacement"}`; for a CSV file
    without a header, the keys are 1-based positions: `{"2": "t", "4": "v_in"}`)."""
    if columns is None:
        return {}
    if not isinstance(columns, Mapping):
        raise PiezojaxValueError(f"{where} must be a mapping {{file column: column}}, got {type(columns).__name__}")
    out = {str(k): v for k, v in columns.items()}
    for k, v in out.items():
        if not k or not isinstance(v, str) or v not in COLUMNS:
            raise PiezojaxValueError(
                f"{where}: {k!r} = {v!r}: the new name must be one of {list(COLUMNS)}"
            )
    targets = list(out.values())
    dup = sorted({v for v in targets if targets.count(v) > 1})
    if dup:
        raise PiezojaxValueError(f"{where}: several file columns renamed to {dup}")
    return out


def _columns_to_experiment(
    data: Mapping[str, np.ndarray], path: Path, name: str | None, ignore_extra: bool, units=None, columns=None,
    sample_rate: float | None = None,
) -> Experiment:
    src = str(path)
    label = f"file {src!r}"
    data = {k: v for k, v in data.items() if k != FILE_MARKER}
    renames = parse_columns(columns)
    if not any(k.isdigit() for k in data):  # named columns: the field positions of a header-less CSV do not apply
        renames = {k: v for k, v in renames.items() if not k.isdigit()}
    # a file with none of the renamed channels is an input-only file (to predict from): those renames do not apply;
    # a file with some of them must have all (a misspelt name is an error, not a channel silently left out)
    channel_sources = [k for k, v in renames.items() if v in CHANNELS]
    if channel_sources and not any(k in data for k in channel_sources):
        renames = {k: v for k, v in renames.items() if v not in CHANNELS}
    absent = [k for k in renames if k not in data]
    if absent:
        raise PiezojaxValueError(f"{label}: `columns` renames {absent}, which the file does not have; found "
                                 f"{sorted(data)}")
    clash = [v for k, v in renames.items() if v in data and v not in renames]
    if clash:
        raise PiezojaxValueError(f"{label}: `columns` renames a column to {clash[0]!r}, which the file has already")
    data = {renames.get(k, k): v for k, v in data.items()}
    rate_to_check = None
    if sample_rate is not None:
        fs = float(sample_rate) if np.ndim(sample_rate) == 0 else math.nan
        if not (math.isfinite(fs) and fs > 0):
            raise PiezojaxValueError(f"`sample_rate` must be a positive finite number of Hz, got {sample_rate!r}")
        if "t" in data:  # for files without 't'; one with its own times must agree (checked in SI below)
            rate_to_check = fs
        elif "v_in" in data:
            data["t"] = np.arange(np.shape(_squeeze_vector(np.asarray(data["v_in"])))[0], dtype=np.float64) / fs
    missing = [c for c in ("t", "v_in") if c not in data]
    if missing:
        raise PiezojaxValueError(
            f"{label}: required column(s) {missing} missing; found {sorted(data)} "
            f"(expected 't' [s], 'v_in' [V] and any of {list(CHANNELS)}; rename columns with `columns`, or give "
            "`sample_rate` for a file without 't')"
        )
    extra = [k for k in data if k not in COLUMNS]
    if extra and not ignore_extra:
        raise PiezojaxValueError(
            f"{label}: unknown column(s) {extra}; allowed columns are {list(COLUMNS)} (rename them with `columns`, "
            "or skip them with `ignore_extra`: --columns / --ignore-extra on the command line, columns = {...} / "
            "ignore_extra = true in [data])"
        )
    scales = parse_units(units)
    data = dict(data)
    for k, scale in scales.items():
        if k in data and scale != 1.0:
            data[k] = _column(data[k], label, k) * scale
    try:
        exp = Experiment(
            t=data["t"],
            v_in=data["v_in"],
            channels={k: data[k] for k in CHANNELS if k in data},
            name=path.stem if name is None else name,
            source=src,
        )
    except PiezojaxValueError as e:
        if not renames and not any(v != 1.0 for v in scales.values()):
            raise
        positional = path.suffix.lower() == ".csv" and all(k.isdigit() for k in renames)
        notes = [f"{v} = {'field ' + k if positional else f'file column {k!r}'}" for k, v in renames.items()]
        converted = [f"{k} from {units[k]}" for k, v in scales.items() if v != 1.0]
        if converted:
            notes.append(f"converted to SI: {', '.join(converted)}")
        raise PiezojaxValueError(f"{e} ({'; '.join(notes)})") from e
    if rate_to_check is not None and abs(float(exp.dt) * rate_to_check - 1) > 1e-6:
        raise PiezojaxValueError(
            f"{label}: its 't' column is sampled at {1 / float(exp.dt):.6g} Hz, but `sample_rate` = "
            f"{rate_to_check:.6g} Hz was given (for files without 't'); give the file's own rate, or none"
        )
    if "t" not in scales and sample_rate is None and _looks_like_sample_indices(exp.t):
        t = exp.t
        raise PiezojaxValueError(
            f"{label}: column 't' holds sample indices ({t[0]:g}, {t[1]:g}, {t[2]:g}, … in steps of 1), not times in "
            "seconds; write t in seconds, or declare its unit (units = {t = \"ms\"} in [data], --units t=ms; "
            "t = \"s\" if the record really is sampled at 1 Hz)"
        )
    return exp


def _read_csv(path: Path, columns: Mapping[str, str] | None = None) -> dict[str, np.ndarray]:
    text = path.read_text(encoding="utf-8-sig")
    all_lines = text.splitlines()
    lines = [(i + 1, ln) for i, ln in enumerate(all_lines) if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise PiezojaxValueError(f"file {str(path)!r}: no header row (the file is empty or has only comments)")
    head = lines[0][1]
    # Comma by default; tab or semicolon (spreadsheet exports in some locales) when the header uses them instead;
    # runs of spaces (numpy.savetxt's default) when there is none of those.
    delim = next((d for d in (",", "\t", ";") if d in head), None if len(head.split()) > 1 else ",")
    split = lambda row: [h.strip().strip('"').strip("'").strip() for h in row.split(delim)]  # noqa: E731
    nfields = lambda row: len(row.split(delim))  # noqa: E731
    header = split(head)
    usecols = None
    if any(header) and all(_is_number(h) for h in header if h):
        # numpy.savetxt(header=...) writes the column names as a '#' comment: take the comment line just above
        comment = all_lines[lines[0][0] - 2].lstrip() if lines[0][0] >= 2 else ""
        names = split(comment[1:]) if comment.startswith("#") else []
        positions = [k for k in (columns or {}) if k.isdigit()]
        if len(names) == len(header) and all(n and not _is_number(n) for n in names):
            header, lines = names, [(0, "")] + lines
        elif positions:
            # no header: the columns are named by their 1-based positions, and only the named ones are read
            bad = [k for k in positions if not 1 <= int(k) <= len(header)]
            if bad:
                raise PiezojaxValueError(
                    f"file {str(path)!r}: `columns` names position(s) {bad}, but the lines have {len(header)} fields"
                )
            header, lines = [str(i + 1) for i in range(len(header))], [(0, "")] + lines
            usecols = sorted(int(k) - 1 for k in positions)
        else:
            raise PiezojaxValueError(
                f"file {str(path)!r}: no header row: line {lines[0][0]}, the first line that is not a '#' comment, "
                f"holds numbers; the first line must name the columns (t, v_in, {', '.join(CHANNELS)}), or name "
                "them by position (columns = {1 = \"t\", 2 = \"v_in\", ...} in [data], or --columns 1=t,2=v_in,...)"
            )
    if (usecols is None and delim is not None and len(header) > 1 and not header[-1]
            and all(not ln.rsplit(delim, 1)[-1].strip() for _, ln in lines[1:])):
        # every line ends with the delimiter (some spreadsheet exports): no last column
        usecols = list(range(len(header) - 1))
    # a column without a name (e.g. the index pandas' DataFrame.to_csv writes first) is an unknown column, which
    # `ignore_extra` skips
    header = [h or f"(unnamed column {j + 1})" for j, h in enumerate(header)]
    dup = sorted({h for h in header if header.count(h) > 1})
    if dup:
        raise PiezojaxValueError(f"file {str(path)!r}: duplicate column(s) {dup} in header row")
    body = lines[1:]
    width = len(header)
    for lineno, ln in body:
        if nfields(ln) != width:
            raise PiezojaxValueError(
                f"file {str(path)!r}: line {lineno} has {nfields(ln)} fields but the header names {width} columns"
            )
    file_header = header  # numpy's error messages count the file's columns, not the ones read
    if usecols is not None:
        header = [header[j] for j in usecols]
    if not body:
        return {h: np.zeros(0) for h in header}
    try:
        values = np.loadtxt(io.StringIO("\n".join(ln for _, ln in body)), delimiter=delim, ndmin=2, dtype=np.float64,
                            usecols=usecols)
    except ValueError as e:
        # numpy counts the rows it was given from 0 and the columns from 1: name the file's line and column instead
        m = re.search(r"could not convert string '(.*)' to \w+ at row (\d+), column (\d+)", str(e))
        if m and int(m.group(2)) < len(body) and 1 <= int(m.group(3)) <= len(file_header):
            lineno, name = body[int(m.group(2))][0], file_header[int(m.group(3)) - 1]
            where = f"field {name}" if name.isdigit() else f"column {name!r}"  # a file without a header row
            raise PiezojaxValueError(
                f"file {str(path)!r}: cannot parse numbers: line {lineno}, {where} holds {m.group(1)!r}"
            ) from e
        raise PiezojaxValueError(f"file {str(path)!r}: cannot parse numbers ({e})") from e
    # the checks `Experiment` makes by sample index, made here by the file's line, for the columns it will read
    for j, h in enumerate(header):
        name = (columns or {}).get(h, h)
        if name not in COLUMNS:
            continue
        col = values[:, j]
        where = f"field {h}" if h.isdigit() else f"column {h!r}"
        bad = ~np.isfinite(col)
        if bad.any():
            i = int(np.argmax(bad))
            raise PiezojaxValueError(f"file {str(path)!r}: line {body[i][0]}, {where} holds a non-finite value "
                                     f"({col[i]}); {int(bad.sum())} in that column")
        if name == "t" and col.size > 1 and not np.all(np.diff(col) > 0):
            i = int(np.argmax(~(np.diff(col) > 0)))
            later, earlier = float(col[i + 1]), float(col[i])
            raise PiezojaxValueError(f"file {str(path)!r}: {where} (the time) must increase from line to line: line "
                                     f"{body[i + 1][0]} holds {later!r}, line {body[i][0]} {earlier!r}")
    return {h: values[:, j] for j, h in enumerate(header)}


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    with open(path, "rb") as f:
        magic = f.read(6)
    if magic.startswith(b"\x93NUMPY"):
        raise PiezojaxValueError(
            f"file {str(path)!r}: a single .npy array, not an .npz archive of named columns (save with "
            "numpy.savez(path, t=..., v_in=..., ...))"
        )
    if not magic.startswith((b"PK\x03\x04", b"PK\x05\x06")):
        kind = "text" if magic and all(32 <= c < 127 or c in b"\t\r\n" for c in magic) else "something else"
        raise PiezojaxValueError(
            f"file {str(path)!r}: not an .npz archive (those are zip files; this one starts with {magic!r}, "
            f"which looks like {kind}); rename a CSV file to .csv"
        )
    with np.load(path, allow_pickle=False) as z:
        return {k: _squeeze_vector(np.asarray(z[k])) for k in z.files}


def _read_hdf5_group(g, path: Path) -> dict[str, np.ndarray]:
    import h5py

    out = {}
    for k, obj in g.items():
        # Sub-groups and MATLAB's '#refs#'/'#subsystem#' bookkeeping are not columns.
        if not isinstance(obj, h5py.Dataset) or k.startswith("#"):
            continue
        out[k] = _squeeze_vector(np.asarray(obj[()]))
    return out


def _read_hdf5(path: Path, group: str | None) -> dict[str, np.ndarray]:
    import h5py

    with h5py.File(path, "r") as f:
        if group is None:
            out = _read_hdf5_group(f, path)
            groups = sorted(k for k, v in f.items() if isinstance(v, h5py.Group) and not k.startswith("#"))
            if not out and groups:
                raise PiezojaxValueError(f"file {str(path)!r}: no datasets at the root; name the group holding the "
                                         f"columns (`group`, --group): groups at the root: {groups}")
            return out
        if group not in f or not isinstance(f[group], h5py.Group):
            groups = sorted(k for k, v in f.items() if isinstance(v, h5py.Group))
            raise PiezojaxValueError(f"file {str(path)!r}: no group {group!r}; groups at the root: {groups}")
        return _read_hdf5_group(f[group], path)


def _read_mat(path: Path, group: str | None) -> dict[str, np.ndarray]:
    import h5py
    import scipy.io

    if h5py.is_hdf5(path):  # MATLAB v7.3 files are HDF5
        return _read_hdf5(path, group)
    raw = scipy.io.loadmat(path, squeeze_me=False)
    if group is not None:
        # A struct variable holding the columns as fields (data.t, data.v_in, ...).
        s = raw.get(group)
        if s is None or s.dtype.names is None or s.size != 1:
            structs = sorted(k for k, v in raw.items() if not k.startswith("__") and v.dtype.names and v.size == 1)
            raise PiezojaxValueError(
                f"file {str(path)!r}: no struct variable {group!r}; structs in the file: {structs}"
            )
        s = s.reshape(-1)[0]
        return {k: _squeeze_vector(np.asarray(s[k])) for k in s.dtype.names}
    variables = {k: v for k, v in raw.items() if not k.startswith("__")}
    structs = sorted(k for k, v in variables.items() if v.dtype.names and v.size == 1)
    if structs and len(structs) == len(variables):
        raise PiezojaxValueError(f"file {str(path)!r}: holds only struct variables; name the one holding the columns "
                                 f"(`group`, --group): {structs}")
    return {k: _squeeze_vector(np.asarray(v)) for k, v in variables.items()}


def _resolve_path(path: str | os.PathLike) -> Path:
    try:
        p = Path(os.fspath(path)).expanduser()
    except TypeError as e:
        raise PiezojaxValueError(f"`path` must be a file path, got {type(path).__name__}") from e
    if p.suffix.lower() not in SUPPORTED_SUFFIXES:
        raise PiezojaxValueError(
            f"file {str(p)!r}: unsupported suffix {p.suffix!r}; supported formats are {list(SUPPORTED_SUFFIXES)}"
        )
    return p


def load_experiment(
    path: str | os.PathLike,
    name: str | None = None,
    *,
    group: str | None = None,
    ignore_extra: bool = False,
    units: Mapping[str, str] | None = None,
    columns: Mapping[str, str] | None = None,
    sample_rate: float | None = None,
) -> Experiment:
    """Load one experiment from a data file, chosen by suffix.

    Formats: `.csv` (a header row naming the columns, comma-separated numbers — tab or semicolon if the header uses
    them — and `#` comment lines allowed), `.npz`,
    `.h5`/`.hdf5` (one dataset per column at the root, or in the group `group`), `.mat` (MATLAB v5 via
    `scipy.io.loadmat`; v7.3 files are HDF5 and are read with h5py). Columns are named `t` [s], `v_in` [V] and any of
    `CHANNELS`; n×1 and 1×n matrices are squeezed to vectors.

    **Arguments:**

    - `path`: the data file.
    - `name`: the experiment's name; default the file's stem.
    - `group`: HDF5 / v7.3 `.mat` group holding the datasets, or for a v5 `.mat` a struct variable holding the
      columns as fields (default: the root / top-level variables).
    - `ignore_extra`: skip columns that are not `t`, `v_in` or a channel instead of raising.
    - `units`: the units of columns not in SI, `{column: unit}` (e.g. `{"displacement": "um", "v_in": "mV",
      "t": "ms"}`; the SI unit with a prefix k, m, u/µ, n or p); they are converted to SI on loading. Without a
      declared unit, a `t` column of sample indices (0, 1, 2, …) is an error, and implausible magnitudes for SI
      (a displacement spanning centimetres, kilovolt signals, …) give a `UnitWarning`.
    - `columns`: renames file columns, `{file column: column}` (e.g. `{"u": "v_in", "y": "displacement"}`); for a
      CSV file without a header row, the keys are the 1-based positions of the fields to read
      (`{"2": "t", "3": "displacement", "4": "v_in"}`; other fields are skipped). A file that has none of the renamed
      measured channels is read as an input-only file (so one mapping reads both the training files and the files
      to predict from); otherwise a renamed column the file does not have is an error.
    - `sample_rate`: for a file without a `t` column, the sampling rate [Hz]; $t_k = k / f_s$.

    **Returns:**

    The validated `Experiment`. Any problem — missing or unreadable file, unknown suffix, missing `t`/`v_in`,
    unknown column, NaN, non-uniform time, unequal lengths — raises `PiezojaxValueError` naming the file (and the
    column and row where that applies).

    ```python
    exp = load_experiment("data/step_100V.csv")
    ```
    """
    p = _resolve_path(path)
    if not p.exists():
        raise PiezojaxValueError(f"file {str(p)!r} does not exist")
    if p.is_dir():
        raise PiezojaxValueError(f"file {str(p)!r} is a directory, not a data file")
    suffix = p.suffix.lower()
    group = group or None  # "": the root
    if group is not None and suffix in UNGROUPED_SUFFIXES:
        raise PiezojaxValueError(f"file {str(p)!r}: `group` ({group!r}) applies to HDF5 and .mat files, not {suffix}")
    try:
        if suffix == ".csv":
            data = _read_csv(p, parse_columns(columns))
        elif suffix == ".npz":
            data = _read_npz(p)
        elif suffix in (".h5", ".hdf5"):
            data = _read_hdf5(p, group)
        else:
            data = _read_mat(p, group)
    except PiezojaxValueError:
        raise
    except Exception as e:  # parsers raise anything (OSError, ValueError, zipfile.BadZipFile, struct.error, ...)
        raise PiezojaxValueError(f"file {str(p)!r}: cannot read it as {suffix} ({type(e).__name__}: {e})") from e
    exp = _columns_to_experiment(data, p, name, ignore_extra, units, columns, sample_rate)
    for message in plausibility_warnings(exp, units):
        warnings.warn(message, UnitWarning, stacklevel=2)
    return exp


def read_file_marker(path: str | os.PathLike) -> str | None:
    """The piezojax command recorded in a data file written by `save_experiment(..., marker=...)` (e.g.
    `"simulate"`), or None (no marker, or not readable)."""
    p = Path(os.fspath(path))
    suffix = p.suffix.lower()
    try:
        if suffix == ".csv":
            with open(p, encoding="utf-8") as f:
                first = f.readline(4096)
            m = re.match(r"# piezojax (\w+) output:", first)
            return m.group(1) if m else None
        if suffix == ".npz":
            with np.load(p, allow_pickle=False) as z:
                return str(z[FILE_MARKER]) if FILE_MARKER in z.files else None
        if suffix in (".h5", ".hdf5"):
            import h5py

            with h5py.File(p, "r") as f:
                value = f.attrs.get(FILE_MARKER)
            return None if value is None else (value.decode() if isinstance(value, bytes) else str(value))
        if suffix == ".mat":
            import scipy.io

            value = scipy.io.loadmat(p, variable_names=[FILE_MARKER]).get(FILE_MARKER)
            return None if value is None else str(np.asarray(value).reshape(-1)[0])
    except Exception:  # noqa: BLE001 - any unreadable file simply has no marker
        return None
    return None


def save_experiment(
    exp: Experiment, path: str | os.PathLike, *, group: str | None = None, marker: str | None = None,
    units: Mapping[str, str] | None = None,
) -> Path:
    """Write `exp` to a data file (format by suffix, as in `load_experiment`), atomically.

    CSV numbers are written with 17 significant digits, so every format round-trips float64 exactly. `.mat` files
    are MATLAB v5 with column vectors. The experiment's name is not stored (it comes back as the file's stem).

    **Arguments:**

    - `exp`: the experiment.
    - `path`: destination file; its suffix picks the format.
    - `group`: for HDF5, write the datasets into this group instead of the root.
    - `marker`: the piezojax command writing the file (e.g. `"simulate"`), recorded in it (see `FILE_MARKER`) so
      that a later `--overwrite` can tell its own output from a user's data.
    - `units`: labels replacing the SI units of `UNITS` for some columns (CSV header, HDF5 `units` attributes),
      e.g. `{"v_in": "N"}` for a force-driven model's input. The values are written as they are.

    **Returns:**

    The absolute `Path` written.

    ```python
    save_experiment(exp.slice(0, 5), "train.h5")
    ```
    """
    if not isinstance(exp, Experiment):
        raise PiezojaxValueError(f"`exp` must be an Experiment, got {type(exp).__name__}")
    p = _resolve_path(path)
    cols = exp.columns()
    suffix = p.suffix.lower()
    if marker is not None and not re.fullmatch(r"\w+", marker):
        raise PiezojaxValueError(f"`marker` must be a word, got {marker!r}")
    extra = {} if marker is None else {FILE_MARKER: np.array(marker)}
    labels = dict(UNITS)
    if units is not None and not isinstance(units, Mapping):
        raise PiezojaxValueError(f"`units` must be a mapping of column to unit name, got {type(units).__name__}")
    for k, u in dict(units or {}).items():
        if k not in cols or not isinstance(u, str) or not re.fullmatch(r"[\w/.*^ -]+", u):
            raise PiezojaxValueError(f"`units`: {k!r} must be one of the experiment's columns {list(cols)} with a unit "
                                     f"name, got {u!r}")
        labels[k] = u
    if suffix == ".csv":
        units = ", ".join(f"{k} [{labels[k]}]" for k in cols)
        written = "experiment" if marker is None else f"{marker} output: experiment"
        head = f"# piezojax {written} {exp.name!r}; units: {units}\n" + ",".join(cols) + "\n"
        buf = io.StringIO()
        np.savetxt(buf, np.column_stack(list(cols.values())), delimiter=",", fmt="%.17g")
        return atomic_write_bytes(p, (head + buf.getvalue()).encode("utf-8"))
    if suffix == ".npz":
        buf = io.BytesIO()
        np.savez(buf, **cols, **extra)
        return atomic_write_bytes(p, buf.getvalue())
    if suffix == ".mat":
        import scipy.io

        buf = io.BytesIO()
        scipy.io.savemat(buf, {**cols, **extra}, oned_as="column")
        return atomic_write_bytes(p, buf.getvalue())
    import h5py

    with atomic_file(p) as tmp:
        with h5py.File(tmp, "w") as f:
            if marker is not None:
                f.attrs[FILE_MARKER] = marker
            g = f if group is None else f.create_group(group)
            for k, v in cols.items():
                ds = g.create_dataset(k, data=v)
                ds.attrs["units"] = labels[k]
    return p.absolute()


# ----------------------------------------------------------------------------------------------------------- dataset


def _check_channel_names(channels, what: str) -> tuple[str, ...]:
    if isinstance(channels, str):
        channels = (channels,)
    try:
        channels = tuple(channels)
    except TypeError as e:
        raise PiezojaxValueError(f"`{what}` must be a channel name or a sequence of them") from e
    unknown = [c for c in channels if c not in CHANNELS]
    if unknown:
        raise PiezojaxValueError(f"`{what}`: unknown channel(s) {unknown}; allowed channels are {list(CHANNELS)}")
    return tuple(c for c in CHANNELS if c in channels)


class Dataset(Sequence):
    """An immutable, ordered collection of `Experiment`s with unique names.

    Experiments may differ in length, sampling step and measured channels (a `fitting.Problem` pads and groups them
    for `vmap`).

    **Arguments:**

    - `experiments`: the experiments; their names must be unique (`PiezojaxValueError` naming the duplicates
      otherwise — rename with `Experiment(..., name=...)` or `slice(..., name=...)`).

    **Returns:**

    The dataset, indexable by position or by name.

    ```python
    ds = Dataset.from_files(["step_25V.csv", "step_50V.csv"])
    ds.require(["v_out", "displacement"]); ds["step_25V"].v_in
    ```
    """

    __slots__ = ("_experiments", "_index")

    def __init__(self, experiments: Iterable[Experiment]):
        if isinstance(experiments, Experiment):
            experiments = (experiments,)
        exps = tuple(experiments)
        if not exps:
            raise PiezojaxValueError("`experiments` must not be empty")
        for i, e in enumerate(exps):
            if not isinstance(e, Experiment):
                raise PiezojaxValueError(f"`experiments[{i}]` must be an Experiment, got {type(e).__name__}")
        names = [e.name for e in exps]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise PiezojaxValueError(f"`experiments`: duplicate experiment name(s) {dup}; names must be unique")
        object.__setattr__(self, "_experiments", exps)
        object.__setattr__(self, "_index", types.MappingProxyType({n: i for i, n in enumerate(names)}))

    def __setattr__(self, key, value):
        raise AttributeError("Dataset is immutable")

    def __reduce__(self):
        return (Dataset, (self._experiments,))

    @classmethod
    def from_files(
        cls,
        paths: Iterable[str | os.PathLike],
        *,
        group: str | None = None,
        ignore_extra: bool = False,
        units: Mapping[str, str] | None = None,
        columns: Mapping[str, str] | None = None,
        sample_rate: float | None = None,
    ) -> "Dataset":
        """Load every file with `load_experiment`; names are the file stems, made unique by prefixing parent
        directories where stems collide (`run1/data.csv`, `run2/data.csv` → `run1/data`, `run2/data`).

        **Arguments:**

        - `paths`: data files.
        - `ignore_extra`, `units`, `columns`, `sample_rate`: as in `load_experiment`.
        - `group`: as in `load_experiment`, for the HDF5 and `.mat` files among `paths` (CSV and `.npz` files have
          no groups: they are read whole).

        **Returns:**

        The `Dataset`.
        """
        if isinstance(paths, str | os.PathLike):
            paths = (paths,)
        ps = [Path(os.fspath(p)).expanduser() for p in paths]
        if not ps:
            raise PiezojaxValueError("`paths` must name at least one data file")
        seen: dict[Path, Path] = {}
        for p in ps:
            with contextlib.suppress(OSError, RuntimeError):
                real = p.resolve()
                if real in seen and p.exists():
                    also = "" if seen[real] == p else f" (also as {str(p)!r})"
                    raise PiezojaxValueError(f"the data file {str(seen[real])!r} is given twice{also}")
                seen.setdefault(real, p)
        names = _unique_names(ps)
        group = group or None  # "": the root
        grouped = [p.suffix.lower() not in UNGROUPED_SUFFIXES for p in ps]
        if group is not None and not any(grouped):
            raise PiezojaxValueError(f"`group` ({group!r}) applies to HDF5 and .mat files, and none of the data files "
                                     f"is one ({listed_files(ps)})")
        return cls(load_experiment(p, name=n, group=group if g else None, ignore_extra=ignore_extra, units=units,
                                   columns=columns, sample_rate=sample_rate) for p, n, g in zip(ps, names, grouped))

    def __len__(self) -> int:
        return len(self._experiments)

    def __iter__(self) -> Iterator[Experiment]:
        return iter(self._experiments)

    def __getitem__(self, key):
        if isinstance(key, str):
            try:
                return self._experiments[self._index[key]]
            except KeyError:
                raise KeyError(f"no experiment named {key!r}; names are {self.names}") from None
        if isinstance(key, slice):
            return Dataset(self._experiments[key])
        if isinstance(key, int | np.integer):
            return self._experiments[int(key)]
        raise PiezojaxValueError(f"Dataset index must be an int, a slice or a name, got {type(key).__name__}")

    def __contains__(self, item) -> bool:
        if isinstance(item, str):
            return item in self._index
        return any(item is e for e in self._experiments)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self._index)

    @property
    def channels(self) -> tuple[str, ...]:
        """The channels measured in at least one experiment, in `CHANNELS` order."""
        have = {c for e in self._experiments for c in e.channels}
        return tuple(c for c in CHANNELS if c in have)

    def require(self, channels: str | Iterable[str]) -> "Dataset":
        """Check that every experiment measured every channel in `channels`; returns `self` for chaining.

        Raises `PiezojaxValueError` listing, per experiment, the channels it lacks.
        """
        req = _check_channel_names(channels, "channels")
        lacking = {e.name: [c for c in req if c not in e.channels] for e in self._experiments}
        lacking = {k: v for k, v in lacking.items() if v}
        if lacking:
            detail = "; ".join(f"{self[k]._label()} lacks {v}" for k, v in lacking.items())
            raise PiezojaxValueError(f"required channel(s) {list(req)} missing: {detail}")
        return self

    def window(self, start: float | None = None, stop: float | None = None) -> "Dataset":
        """Every experiment scored on $start \\le t < stop$ (seconds; `None`: the record's start or end), as
        `piezojax fit --window START:STOP` fits it: cut at `stop`, and scored from `start`
        (`Experiment.scored_from`), the samples before it run as the model's history. Names are kept.

        ```python
        train = fitting.Dataset.from_files(["record.csv"]).window(None, 7.0)  # the first 7 s
        ```
        """
        out = []
        for e in self._experiments:
            part = e.slice(start, stop, name=e.name)  # the window's own checks (at least 2 samples in it)
            whole = e.slice(None, stop, name=e.name)
            out.append(part if part.t[0] == whole.t[0] else Experiment(
                whole.t, whole.v_in, dict(whole.channels), e.name, e.source, scored_from=float(part.t[0])))
        return Dataset(out)

    def __repr__(self) -> str:
        inner = ", ".join(f"{e.name!r} (n={e.n})" for e in self._experiments[:4])
        more = f", … {len(self) - 4} more" if len(self) > 4 else ""
        return f"Dataset({len(self)} experiments: {inner}{more}; channels: {', '.join(self.channels) or 'none'})"


def _unique_names(paths: Sequence[Path]) -> list[str]:
    """File stems, lengthened only where two different files would share a name: first by the suffix
    (`run.csv`, `run.h5`), then by parent directories (`r1/data`, `r2/data`). Identical paths stay duplicates, which
    `Dataset` reports."""
    full = [p.absolute() for p in paths]

    def name(i: int, level: int) -> str:
        depth, with_suffix = divmod(level, 2)
        parts = full[i].parts[1:-1] + (full[i].name if with_suffix else full[i].stem,)
        return "/".join(parts[max(len(parts) - 1 - depth, 0) :])

    out = []
    for i in range(len(full)):
        others = [j for j in range(len(full)) if full[j] != full[i]]
        level = 0
        while level < 2 * len(full[i].parts) and any(name(j, level) == name(i, level) for j in others):
            level += 1
        out.append(name(i, level))
    return out


def experiments_of(dataset) -> list["Experiment"]:
    """The experiments of `dataset`: an `Experiment`, a `Dataset` or any other iterable of experiments (not a string
    or an array); anything else is one `PiezojaxValueError` naming `dataset`."""
    if isinstance(dataset, Experiment):
        return [dataset]
    if isinstance(dataset, Dataset):
        return list(dataset)
    if isinstance(dataset, str | bytes) or hasattr(dataset, "shape") or not isinstance(dataset, Iterable):
        raise PiezojaxValueError(f"`dataset` must be a fitting.Dataset, an Experiment or a list of Experiments "
                                 f"(e.g. fitting.Experiment.from_arrays(t, v_in)), got {type(dataset).__name__}")
    return list(dataset)
