"""One measured record on a uniform time grid (`Experiment`) and the channels it may hold."""

import dataclasses
import math
import types
from collections.abc import Mapping

import numpy as np

from piezojax import PiezojaxValueError

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

