"""What the commands share: JAX set up, messages, data settings from options, output paths checked, data read."""

import contextlib
import os
import sys
import time
import warnings
from pathlib import Path

from .signals import _signals_deferred


def _setup_jax(figures: bool = False) -> None:
    """Import JAX, piezojax (and matplotlib for `figures`) with interrupts deferred; x64 and fused CPU scans, set
    before JAX initialises its backends."""
    with _signals_deferred():
        import jax

        import piezojax as pj

        if figures:
            import matplotlib

            matplotlib.use("Agg")
            import matplotlib.pyplot  # noqa: F401

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            pj.enable_fast_cpu_scans()  # also retains freed memory: `fit` releases it for long records
        jax.config.update("jax_enable_x64", True)
        pj.enable_compilation_cache()  # a second run of the same shapes loads its programs ($PIEZOJAX_CACHE_DIR)
    global IMPORTED_AT
    IMPORTED_AT = time.time()


IMPORTED_AT: float | None = None
"""When `_setup_jax` finished (`time.time()`): the end of the command's imports (`fitting._timing`)."""
CALLED_AT: float | None = None
"""When `main` was last called (`time.time()`): where an in-process command's time starts."""
AS_PROGRAM = False
"""Whether this process is the `piezojax` program (`console_main`): its commands' time starts with the process."""


def _info(msg: str, quiet: bool = False) -> None:
    if not quiet:
        with contextlib.suppress(BrokenPipeError):
            print(f"piezojax: {msg}", file=sys.stderr, flush=True)


def _out(text: str) -> None:
    """Print to stdout; a closed pipe (`piezojax fit ... | head -1`) silences stdout instead of failing: the
    outputs are written and the exit status stays that of the command."""
    try:
        print(text, flush=True)
    except BrokenPipeError:
        _silence_stdout()
    except OSError as e:  # e.g. a full disk behind a redirection: the outputs are written, say so on stderr
        _silence_stdout()
        _info(f"warning: could not write to standard output ({e.strerror or e}); the outputs are complete")


def _silence_stdout() -> None:
    with contextlib.suppress(OSError, ValueError):
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)


def _error(msg: str):
    from piezojax import PiezojaxValueError

    return PiezojaxValueError(msg)


def _pairs(items: list[str] | None, option: str, example: str) -> dict[str, str]:
    """`--units displacement=um,t=ms` (repeatable) as a mapping."""
    out: dict[str, str] = {}
    for item in items or []:
        for part in item.split(","):
            key, sep, value = part.partition("=")
            if not sep or not key.strip() or not value.strip():
                raise _error(f"{option}: expected {example}, got {part.strip()!r}")
            if key.strip() in out:
                raise _error(f"{option}: {key.strip()!r} is given twice")
            out[key.strip()] = value.strip()
    return out


def _given_units(args) -> tuple[bool, dict[str, str]]:
    """`--units` as given: whether an empty value asks to drop the base's units (every column in SI but those the
    other values declare), and the declared `{column: unit}`."""
    items = args.units or []
    return any(not u.strip() for u in items), _pairs([u for u in items if u.strip()], "--units",
                                                    "COLUMN=UNIT (e.g. displacement=um), or '' for SI")


def _data_settings(args, base: dict) -> dict:
    """How to read the data files: `base` (CONFIG's `[data]`, or the fit's for `predict`) with the command line's
    options on top; checked here, so that a bad option is named before any file is read."""
    from .._data import parse_columns, parse_units

    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in base.items()}
    si, units = _given_units(args)  # `--units ''`: no unit of the base kept; other --units add to or replace them
    # `--columns ''`: no renaming; any other --columns replaces the whole mapping (its keys are the file's names)
    clear = args.columns is not None and not any(c.strip() for c in args.columns)
    columns = {} if clear else _pairs(args.columns, "--columns", "FILECOLUMN=COLUMN (e.g. u=v_in)")
    parse_units(units, "--units")
    parse_columns(columns, "--columns")
    if si:
        out["units"] = units
    elif units:
        out["units"] = {**out.get("units", {}), **units}
    if columns or clear:
        out["columns"] = columns
    if args.group is not None:
        out["group"] = args.group.strip() or None  # `--group ''`: the root
    if args.sample_rate is not None:
        if not (args.sample_rate > 0 and args.sample_rate < float("inf")):
            raise _error(f"--sample-rate must be a positive number of Hz, got {args.sample_rate}")
        out["sample_rate"] = args.sample_rate
    if args.ignore_extra:
        out["ignore_extra"] = True
    return out


def _check_output(path: str, overwrite: bool, command: str, *, inputs=(), fit_folder=None) -> Path:
    """Refuse now, before any work, an output that must not be written: an empty path, the working directory or
    an ancestor of it, a folder holding an input (data, CONFIG, the fit folder of `predict`), the input file
    itself, an existing output without `--overwrite`, and with `--overwrite` anything but an earlier output of the
    same command (recognised by its marker)."""
    import fitting

    from .._data import SUPPORTED_SUFFIXES, read_file_marker
    from ..files import check_replaceable_directory

    is_file = command == "simulate"
    what = "output file" if is_file else "output folder"
    if not path.strip():
        raise _error(f"--out is empty; name the {what}")
    if is_file and path.endswith(("/", os.sep)):
        raise _error(f"{what} {path!r} ends with a slash (a folder); name the file")
    if is_file and Path(path).suffix.lower() not in SUPPORTED_SUFFIXES:
        raise _error(f"{what} {path!r}: unsupported suffix {Path(path).suffix!r}; its suffix picks the format, one "
                     f"of {', '.join(SUPPORTED_SUFFIXES)}")
    p = fitting.files.check_writable(path)
    try:
        rp = p.resolve()
        resolved_inputs = [(f, Path(f).expanduser().resolve()) for f in inputs]
    except (OSError, RuntimeError) as e:  # a symlink loop in a parent folder
        raise _error(f"cannot resolve the paths of {what} {str(p)!r} and the inputs ({e})") from e
    for f, rf in resolved_inputs:
        if rp == rf:
            raise _error(f"refusing to write the {what} {str(p)!r}: it is the input {str(f)!r}")
        if not is_file and rp in rf.parents:
            raise _error(f"refusing to write the {what} {str(p)!r}: it holds the input {str(f)!r}")
    if fit_folder is not None:
        rd = Path(fit_folder).expanduser().resolve()
        if rp == rd or rp in rd.parents:
            raise _error(f"refusing to write the {what} {str(p)!r}: it {'is' if rp == rd else 'holds'} the fitted "
                         f"model folder {str(fit_folder)!r}")
    if not is_file:
        check_replaceable_directory(p, overwrite, command, option="--overwrite")
        return p
    if not p.exists():
        return p
    if p.is_dir():
        raise _error(f"{what} {str(p)!r} is a directory")
    if not overwrite:
        raise _error(f"{what} {str(p)!r} already exists; pass --overwrite to replace it")
    if read_file_marker(p) != command:
        raise _error(f"refusing to replace {str(p)!r}: it was not written by `piezojax {command}`, and --overwrite "
                     "replaces only such a file; remove it yourself or choose another --out")
    return p


def _load_data(paths, settings: dict, group_option: str | None):
    """The `Dataset` of `paths` read with `settings` (`fitting.load_experiment`'s keywords); unit-plausibility
    warnings on stderr, and returned for the result files. `group_option`: `--group` as given (None: not given); a
    group from CONFIG or the fit concerns the HDF5 and .mat files only, and is not used when `paths` has none."""
    import fitting

    from .._data import UNGROUPED_SUFFIXES, UnitWarning, listed_files

    if settings.get("group") is not None and all(Path(p).suffix.lower() in UNGROUPED_SUFFIXES for p in paths):
        if group_option is not None:
            raise _error(f"--group {group_option}: a group applies to HDF5 and .mat files, and none of the data "
                         f"files is one ({listed_files(paths)})")
        settings = {k: v for k, v in settings.items() if k != "group"}

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", UnitWarning)
        dataset = fitting.Dataset.from_files(paths, **settings)
    messages = [str(w.message) for w in caught if issubclass(w.category, UnitWarning)]
    for m in messages:
        _info(f"warning: {m}")  # also with --quiet: it may mean the fit is meaningless
    return dataset, messages


def _windowed(dataset, window: str):
    """Every experiment of `dataset` scored on `START <= t < STOP` (`--window START:STOP`, seconds): cut at STOP,
    and scored from START (`Experiment.scored_from`), the samples before it run as the model's history."""
    start, sep, stop = window.partition(":")
    try:
        bounds = [None if not b.strip() else float(b) for b in (start, stop)]
    except ValueError:
        bounds = None
    if not sep or bounds is None or any(b is not None and b != b for b in bounds):
        raise _error(f"--window: expected START:STOP in seconds (either may be empty, e.g. :7), got {window!r}")
    from piezojax import PiezojaxValueError

    try:
        return dataset.window(*bounds)
    except PiezojaxValueError as e:
        raise _error(f"--window {window}: {e}") from e


def _safe_name(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in name)


