"""An ordered collection of experiments (`Dataset`), as the calibration engine takes them."""

import contextlib
import os
import types
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path

import numpy as np

from piezojax import PiezojaxValueError

from .experiment import CHANNELS, Experiment
from .formats import UNGROUPED_SUFFIXES, listed_files, load_experiment


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
