"""Data files: reading CSV, NPZ, HDF5 and MATLAB files into an `Experiment` (`load_experiment`) and writing one
(`save_experiment`), with the marker of the piezojax command that wrote it."""

import io
import math
import os
import re
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from piezojax import PiezojaxValueError

from ..files import atomic_file, atomic_write_bytes
from .experiment import CHANNELS, COLUMNS, UNITS, Experiment, _column
from .units import UnitWarning, parse_units, plausibility_warnings

SUPPORTED_SUFFIXES: tuple[str, ...] = (".csv", ".npz", ".h5", ".hdf5", ".mat")

UNGROUPED_SUFFIXES = (".csv", ".npz")
"""The data formats without groups (read whole): a `group` concerns the others, HDF5 and `.mat`."""


def listed_files(paths: Sequence) -> str:
    """The first three of `paths` for a message: `'a.csv', 'b.csv', 'c.csv', …`."""
    return ", ".join(repr(str(p)) for p in paths[:3]) + (", …" if len(paths) > 3 else "")

FILE_MARKER = "piezojax_output"
"""Name under which `save_experiment(..., marker=...)` records the piezojax command that wrote a file (a variable in
NPZ and .mat files, a root attribute in HDF5, the first comment line in CSV); readers skip it."""




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

