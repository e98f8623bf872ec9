"""The `piezojax` command line: fit a model configured in TOML to data files, predict with it, simulate.

Exit status: 0 success; 1 `fit` finished without converging (outputs written, `result.json` says why); 2 bad input
(one line `piezojax: error: ...` on stderr, nothing written); 3 internal error (a bug: one line, nothing written);
130 interrupted by Ctrl-C (SIGINT), 143 terminated (SIGTERM) — nothing half-written: an interrupted `fit` saves the
last accepted parameters as a complete folder, or nothing if it was interrupted before the first step or while its
outputs were being written.

Only argparse and the standard library are imported at module level: the signal handlers are installed before
JAX is loaded, so an interrupt during the imports is handled like any other.
"""

import signal
import sys

if __name__ == "__main__" or sys.argv[0].rsplit("/", 1)[-1] == "piezojax":
    # run as the program: a signal during the imports below (before `main` installs its handlers) ends the process
    # with the status of an interrupt before anything is written, not with a traceback
    def _signal_while_importing(signum, frame):
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGINT, _signal_while_importing)
    signal.signal(signal.SIGTERM, _signal_while_importing)

import argparse
import contextlib
import os
import threading
import warnings
from pathlib import Path

EXIT_OK, EXIT_NOT_CONVERGED, EXIT_ERROR, EXIT_INTERNAL = 0, 1, 2, 3
EXIT_INTERRUPTED, EXIT_TERMINATED = 128 + signal.SIGINT, 128 + signal.SIGTERM

_CONFIG_HELP = """\
CONFIG is a TOML file naming the model blocks, their parameter values (for `fit`: optional initial values; for
`simulate`: every value), and the fit options:

  [hysteresis]  kind = "prandtl_ishlinskii" (plays = 10, weights, thresholds, w0)
                     | "play" (plays = 1, weights, thresholds: backlash, no linear term)
                     | "bouc_wen" (A, beta, gamma, n, d, method = "closed_form"|"rk4", substeps)
                     | "maxwell_slip" (elements = 8, stiffness, breakaway)
                     | "preisach" (levels = 8, range = [v_min, v_max], mu)
                     | "none";            smoothing = 0.0 (0 = exact operator)
                polynomial = 2..6 (coefficients, polynomial_scale): static output polynomial (loop asymmetry)
  [creep]       kind = "kelvin_voigt" (order = 1, stiffnesses, time_constants)
                     | "logarithmic" (gamma, t0, gain) | "lag" (lags = 1, fractions, time_constants) | "none"
                     | "linear" (order = 1 poles [rad/s] < 0, real_zeros, zeros [rad/s] < 0, gain)
                structure = "parallel" (default) | "series" (after the hysteresis; "lag" only in series)
  [dynamics]    order = 0 .. 8 (gain = 1, omega [rad/s], zeta, poles [rad/s] < 0)
                zero_pairs (zero_omega [rad/s], zero_zeta), real_zeros (zeros [rad/s])
  [state]       offset = true | false | value [m];  prehistory = false | true | value [V]
  [charge]      capacitance [F], coupling [C/m]   (an actuator that also predicts charge and current)
  [observer]    kind = "current_integration": paper 001 self-sensing, displacement and force from v_in and
                v_out; integrator_capacitance, reference_capacitance, leakage_resistance, force_sensitivity,
                displacement_coefficient, stiffness (required), bias_current = 0, capacitance_p = 0,
                filter_cutoff [Hz]; [hysteresis] and [creep] are then charge operators (C/V)
              | "dynamic_impedance": paper 000, displacement from v_in, v_out; feedback_resistance, capacitance,
                alpha, beta (required), bias_current, gamma; G(s) from [dynamics]
              | "sensor_layer": paper 002, displacement and force from v_in, v_out; d33, amplifier_capacitance,
                k_p, k_s (required), crosstalk
                (the 000 and 002 observers: [state] offset = true for a displacement offset)
  [model]       kind = "bouc_wen_oscillator": the hysteretic benchmark's oscillator, displacement from the force in
                v_in; m, c, k, alpha, beta, gamma, delta, nu (started from the data when absent),
                hold = "linear" | "zoh" | "periodic", substeps = 4
              | "electromechanical": paper 003, displacement and charge from v_in; m (required), b, k,
                capacitance, t_em or coupling_degree = 0, elements = 4 (element_capacitances,
                breakaway_voltages), hold, substeps = 8
  [fit]         free = ["hysteresis", "creep.time_constants", ...] (default: every identifiable parameter)
                weights = "range" | "noise" | {displacement = 1e6, force = 1e3}
                smoothing = [0.05, 0.0]   (continuation: relaxed, then exact hysteresis)
                max_steps = 500;  targets = ["displacement", ...] (default: predicted channels in the data)
                method = "levenberg_marquardt" | "trust_region"   (scipy's TRF algorithm; see fitting.solve)

  [data]        units = {displacement = "um", v_in = "mV", t = "ms"}   (columns not in SI; also --units)
                columns = {u = "v_in", y = "displacement"}   (rename; {2 = "t", ...} by position without a header)
                group = "multisine" (HDF5);  sample_rate = 750.0 [Hz] (files without t);  ignore_extra = false

Sizes: plays, elements <= 100; Preisach levels <= 30; creep order, lags <= 10; Bouc-Wen substeps <= 64;
max_steps <= 100000.
Data files: .csv (header naming t, v_in and any of v_out, displacement, force, charge, current), .npz, .h5/.hdf5,
.mat with the same names; SI units unless declared; uniform t in seconds.
"""

_FIT_EXAMPLES = """\
Parameter values not given in CONFIG start from the data (the joint cold start and simple rules, both fitted
together, the lower cost kept), see the README ("Command line").

examples:
  piezojax fit pi_creep.toml run1.csv run2.npz run3.h5 --out fits/pi_creep
  piezojax fit selfsensing.toml contact.mat --out fits/obs --overwrite --max-steps 50

DIR receives result.json (metrics per experiment and channel, parameters with standard errors, convergence),
model.eqx (the fitted parameters), config.toml (the configuration, to rebuild the model), report.txt and PNG
figures. DIR appears complete or not at all; an empty DIR is replaced like an absent one.
--overwrite replaces only a folder written by an earlier `piezojax fit` (it holds a .piezojax marker) that holds
nothing else, never the working directory, a folder holding an input or CONFIG, or anything else.
exit status: 0 converged, 1 not converged (outputs written), 2 bad input, 3 internal error, 130 interrupted
(143 terminated).
"""

_PREDICT_EXAMPLES = """\
examples:
  piezojax predict fits/pi_creep held_out.csv --out predictions
  piezojax predict fits/obs day2_*.mat --out predictions --overwrite
  piezojax predict fits/pi_creep test_7to10s.csv --history train_0to7s.csv --out predictions
  piezojax predict fits/pi_creep whole_record.csv --score-from 7.0 --out predictions

OUT is a folder with one CSV per input (t, v_in and the predicted channels on the input's time grid) and
metrics.json; RMSE, NRMSE (% of the measured range) and the RMSE over the file's noise level are printed for the
channels a file also measures.
"""

_SIMULATE_EXAMPLES = """\
examples:
  piezojax simulate pi_known.toml --input drive.csv --out simulated.csv
  piezojax simulate selfsensing.toml --input record.npz --out estimates.h5

CONFIG must give every parameter value (no data are fitted). The input file needs t and v_in (and v_out for an
observer); OUT's suffix picks the format (.csv, .npz, .h5, .mat).
"""


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (`piezojax fit: error: ...`) and exit status 2."""

    def error(self, message):
        self.exit(EXIT_ERROR, f"{self.prog}: error: {' '.join(message.split())} (see {self.prog} --help)\n")


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("piezojax")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree that is not installed
        return "unknown"


def _data_options(parser, source: str) -> None:
    """The options that say how to read the data files (each overrides the `[data]` key of `source`)."""
    parser.add_argument("--units", metavar="COL=UNIT", action="append",
                        help="units of columns not in SI, COLUMN=UNIT[,...] (e.g. displacement=um,v_in=mV,t=ms; "
                        f"prefixes k, m, u, n, p); adds to or overrides [data] units of {source}; '' for every "
                        "column in SI")
    parser.add_argument("--columns", metavar="FILECOL=COL", action="append",
                        help="rename file columns, FILECOL=COL[,...] (e.g. u=v_in,y=displacement); for a CSV file "
                        f"without a header, FILECOL is a 1-based position (2=t,3=displacement,4=v_in); '' for no "
                        f"renaming; replaces [data] columns of {source}")
    parser.add_argument("--group", metavar="NAME", help="HDF5 group (or .mat struct) holding the columns, for the "
                        f"HDF5 and .mat files; '' for the root; overrides [data] group of {source}")
    parser.add_argument("--sample-rate", metavar="HZ", type=float, help="sampling rate of files without a t column")
    parser.add_argument("--ignore-extra", action="store_true", help="skip columns that are not t, v_in or a channel")


def build_parser() -> argparse.ArgumentParser:
    """The `piezojax` argument parser (subcommands `fit`, `predict`, `simulate`)."""
    fmt = argparse.RawDescriptionHelpFormatter
    parser = _Parser(
        prog="piezojax",
        description="Calibrate and run piezojax models of piezoelectric actuators from the command line.\n\n"
        + _CONFIG_HELP,
        epilog="Run `piezojax COMMAND --help` for each command's options and examples.",
        formatter_class=fmt,
    )
    parser.add_argument("--version", action="version", version=f"piezojax {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True

    fit = sub.add_parser(
        "fit", help="fit the model of CONFIG to data files, write a result folder",
        description="Fit the model described by CONFIG to the experiments in DATA (Levenberg–Marquardt over all "
        "files at once) and write the result folder DIR.\n\n" + _CONFIG_HELP,
        epilog=_FIT_EXAMPLES, formatter_class=fmt,
    )
    fit.add_argument("config", metavar="CONFIG", help="TOML model configuration")
    fit.add_argument("data", metavar="DATA", nargs="+", help="experiment files (.csv, .npz, .h5/.hdf5, .mat)")
    fit.add_argument("--out", metavar="DIR", required=True,
                     help="result folder to create (absent or empty; see --overwrite)")
    fit.add_argument("--overwrite", action="store_true",
                     help="replace DIR if it is the output of an earlier `piezojax fit` (atomically)")
    fit.add_argument("--max-steps", type=int, metavar="N", help="Levenberg–Marquardt steps per smoothing level "
                     "(overrides [fit] max_steps)")
    _data_options(fit, "CONFIG")
    fit.add_argument("--window", metavar="START:STOP",
                     help="fit only the samples with START <= t < STOP [s] of every file (either side may be empty, "
                     "e.g. :7 for the first 7 s); the samples before START are run as the model's history, not scored; "
                     "score the rest with `piezojax predict ... --score-from 7`")
    fit.add_argument("--no-figures", action="store_true", help="do not write the PNG figures")
    fit.add_argument("--quiet", action="store_true", help="no progress output")

    pred = sub.add_parser(
        "predict", help="run a fitted model on new inputs, write one CSV per input",
        description="Run the model fitted into DIR (by `piezojax fit`) on the inputs of each DATA file.",
        epilog=_PREDICT_EXAMPLES, formatter_class=fmt,
    )
    pred.add_argument("model_dir", metavar="DIR", help="result folder written by `piezojax fit`")
    pred.add_argument("data", metavar="DATA", nargs="+", help="input files (t, v_in; v_out for an observer)")
    pred.add_argument("--out", metavar="OUT", required=True, help="folder to create for the predictions")
    pred.add_argument("--overwrite", action="store_true",
                      help="replace OUT if it is the output of an earlier `piezojax predict` (atomically)")
    pred.add_argument("--history", metavar="FILE", action="append",
                      help="a record run before each DATA file (repeatable, in order), e.g. the training record that "
                      "a held-out DATA file continues: the model's state carries over; same sampling step")
    pred.add_argument("--score-from", metavar="T", type=float,
                      help="compute the errors only on samples with t >= T [s] (the predictions cover the whole file)")
    _data_options(pred, "the fit (default: the fit's)")

    sim = sub.add_parser(
        "simulate", help="forward simulation of the model of CONFIG with its given parameter values",
        description="Simulate the model of CONFIG, with the parameter values CONFIG gives, on the input FILE.\n\n"
        + _CONFIG_HELP,
        epilog=_SIMULATE_EXAMPLES, formatter_class=fmt,
    )
    sim.add_argument("config", metavar="CONFIG", help="TOML model configuration with every parameter value")
    sim.add_argument("--input", metavar="FILE", required=True, help="input file (t, v_in; v_out for an observer)")
    sim.add_argument("--out", metavar="OUT", required=True, help="output file (.csv, .npz, .h5, .mat)")
    sim.add_argument("--overwrite", action="store_true",
                     help="replace OUT if it was written by an earlier `piezojax simulate`")
    _data_options(sim, "CONFIG")
    return parser


# ------------------------------------------------------------------------------------------------------ signals


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM, raised in the main thread like Ctrl-C's `KeyboardInterrupt`, so that every cleanup path
    (temporary outputs removed, the solver's saving of the last accepted parameters) runs for both."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


_received: list[int] = []
_consumed = 0


def _on_signal(signum, frame):
    _received.append(signum)
    raise Interrupted(signum)


def _check_interrupted() -> None:
    """Raise for a signal whose exception was swallowed on its way (Python drops exceptions raised inside
    garbage-collector callbacks and `__del__`), so that no interrupt is ever lost: called before outputs are made
    visible."""
    if len(_received) > _consumed:
        raise Interrupted(_received[-1])


def _pending_interrupt() -> bool:
    """Whether a signal arrived that no one has handled yet (`_consume_interrupt`)."""
    return len(_received) > _consumed


def _consume_interrupt() -> None:
    """The interrupts so far were handled (the solver stopped and returned its last accepted point)."""
    global _consumed
    _consumed = len(_received)


def _interrupt_status() -> int:
    return 128 + (_received[-1] if _received else signal.SIGINT)


@contextlib.contextmanager
def _signals_handled(restore: bool = True):
    """SIGINT and SIGTERM raise `Interrupted` while the command runs (main thread only); the previous handlers are
    restored after it unless `restore` is False (the console script replaces them itself, see `console_main`)."""
    global _consumed
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _received.clear()
    _consumed = 0
    old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    old_hook = sys.unraisablehook

    def hook(unraisable):
        # An interrupt raised inside a garbage-collector callback or `__del__` cannot propagate; Python would print
        # it with a traceback and go on. It is recorded in `_received`, and `_check_interrupted` raises it again
        # before any output is made visible.
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            return
        old_hook(unraisable)

    sys.unraisablehook = hook
    for s in old:
        signal.signal(s, _on_signal)
    try:
        yield
    finally:
        if restore:
            for s, h in old.items():
                signal.signal(s, h)
            sys.unraisablehook = old_hook


def _record_signal(signum, frame):
    _received.append(signum)


def _hold_signals() -> None:
    """From here on SIGINT and SIGTERM are only recorded, never raised: called once the outputs are about to be made
    visible (the command's outcome is decided), and by the console script before the interpreter's teardown (where a
    raised interrupt would print a traceback from an `atexit` callback). `_signals_handled` restores the previous
    handlers when the command returns in-process."""
    if threading.current_thread() is threading.main_thread():
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, _record_signal)


# ------------------------------------------------------------------------------------------------------ helpers


@contextlib.contextmanager
def _signals_deferred():
    """Hold SIGINT and SIGTERM back (delivered when the block ends) while compiled extensions are imported: an
    interrupt inside an extension's initialisation becomes an `ImportError` with a traceback printed from C."""
    signals = {signal.SIGINT, signal.SIGTERM}
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "pthread_sigmask"):
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, signals)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


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
    from piezojax._checks import PiezojaxValueError

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
    from ._data import parse_columns, parse_units

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

    from ._data import SUPPORTED_SUFFIXES, read_file_marker
    from .files import check_replaceable_directory

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

    from ._data import UNGROUPED_SUFFIXES, UnitWarning, listed_files

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


# ------------------------------------------------------------------------------------------------------ commands


def _cmd_fit(args) -> int:
    import fitting

    from ._calibrate import calibrate
    from ._config import MAX_STEPS, load_config

    quiet = args.quiet
    if args.max_steps is not None and not 1 <= args.max_steps <= MAX_STEPS:
        raise _error(f"--max-steps must be >= 1 and <= {MAX_STEPS} (the documented upper bound), got {args.max_steps}")
    out = _check_output(args.out, args.overwrite, "fit", inputs=[args.config, *args.data])
    config = load_config(args.config)
    settings = _data_settings(args, config.data)
    with fitting.files.atomic_directory(out, overwrite=args.overwrite, kind="fit") as tmp:
        dataset, unit_warnings = _load_data(args.data, settings, args.group)
        if args.window is not None:
            dataset = _windowed(dataset, args.window)
        cal = calibrate(config, dataset, max_steps=args.max_steps, progress=not quiet,
                        log=lambda m, warning=False: _info(m, quiet and not warning), interrupted=_pending_interrupt)
        result = cal.result
        if result.code == "interrupted":
            _consume_interrupt()  # the solver stopped at the interrupt and returned its last accepted point
        _info(f"writing {out}", quiet)
        cal.write_files(tmp, figures=not args.no_figures, config_source=args.config, data=args.data,
                        data_settings=settings, window=args.window, read_warnings=unit_warnings)
        _check_interrupted()
        _hold_signals()  # complete: from here the outcome is this run's, whatever arrives while it is renamed
    _out(cal.report())
    if result.code == "interrupted":
        _info(f"interrupted: the last accepted parameters are saved in {out} (result.json: code 'interrupted')")
        return _interrupt_status()
    if not result.success:
        _info(f"the fit did not converge ({result.reason}); results written to {out}")
        return EXIT_NOT_CONVERGED
    return EXIT_OK


def load_fitted(model_dir) -> tuple:
    """`(config, model)` from a folder written by `piezojax fit`: the configuration saved there rebuilds the
    structure, `fitting.load_model` fills in the fitted values."""
    import fitting

    from ._config import parse_config

    d = Path(model_dir)
    if not d.is_dir():
        raise _error(f"model folder {str(d)!r} does not exist or is not a folder")
    cfg_file = d / "config.toml"
    if not cfg_file.exists() or not (d / "model.eqx").exists():
        raise _error(f"{str(d)!r} is not a folder written by `piezojax fit` (no config.toml/model.eqx)")
    config = parse_config(cfg_file.read_text(encoding="utf-8"), source=str(cfg_file))
    from piezojax._checks import PiezojaxValueError

    try:
        model = fitting.load_model(d, like=config.build(None))
    except PiezojaxValueError as e:
        raise _error(f"{str(d)!r}: model.eqx does not match the model of config.toml there (was one of them edited, "
                     f"or copied from another fit?): {e}") from e
    return config, model


def _fit_data_settings(model_dir, config) -> dict:
    """How the fit in `model_dir` read its files (CONFIG's `[data]` and the command line), for `predict`."""
    import json

    try:
        cli = json.loads((Path(model_dir) / "result.json").read_text(encoding="utf-8")).get("cli", {})
        settings = cli.get("data_settings")
    except (OSError, ValueError, AttributeError):
        settings = None
    return dict(settings) if isinstance(settings, dict) else dict(config.data)


def _cmd_predict(args) -> int:
    import numpy as np

    import fitting

    from ._results import lack_of_fit

    out = _check_output(args.out, args.overwrite, "predict", inputs=[*args.data, *(args.history or [])],
                        fit_folder=args.model_dir)
    config, model = load_fitted(args.model_dir)
    settings = _data_settings(args, _fit_data_settings(args.model_dir, config))
    given = _given_units(args)[1]
    kept = {k: v for k, v in settings.get("units", {}).items() if k not in given}
    if kept:
        shown = ",".join(f"{k}={v}" for k, v in kept.items())
        _info(f"reading the files in the fit's units ({shown}); --units '' reads them in SI")
    with fitting.files.atomic_directory(out, overwrite=args.overwrite, kind="predict") as tmp:
        dataset, unit_warnings = _load_data(args.data, settings, args.group)
        results, metrics = [], {}
        history = _load_data(args.history, settings, args.group)[0] if args.history else ()
        for exp in dataset:
            preds = fitting.predict(model, exp, predictor=config.predictor(), history=history)
            preds = {c: preds[c] for c in config.outputs}
            results.append((exp, preds))
            measured = [c for c in preds if exp.has(c)]
            scored = exp.t >= args.score_from - 1e-6 * exp.dt if args.score_from is not None else slice(None)
            if args.score_from is not None and np.count_nonzero(scored) < 2:
                raise _error(f"{exp._label()}: --score-from {args.score_from:g} s leaves fewer than 2 samples of the "
                             f"record [{exp.t[0]:.6g}, {exp.t[-1]:.6g}] s")
            if measured:
                metrics[exp.name] = {c: fitting.error_metrics(preds[c][scored], exp[c][scored]) for c in measured}
        names = {}
        for exp, _ in results:
            base = _safe_name(exp.name.replace("/", "__"))
            name, i = base, 1
            while name in names.values():
                i += 1
                name = f"{base}_{i}"
            names[exp.name] = name
        for exp, preds in results:
            pred_exp = fitting.Experiment.from_arrays(t=exp.t, v_in=exp.v_in, name=exp.name, **preds)
            fitting.save_experiment(pred_exp, tmp / f"{names[exp.name]}.csv",
                                    units={"v_in": config.model_kind.input_unit})
        fitting.files.save_json(tmp / "metrics.json", {
            "model": str(Path(args.model_dir).absolute()),
            "files": {exp.name: {"input": exp.source, "output": f"{names[exp.name]}.csv"} for exp, _ in results},
            "metrics": metrics,
            "data_settings": settings,
            "history": [str(Path(p).absolute()) for p in args.history or []],
            "score_from": args.score_from,
            "warnings": unit_warnings,
        })
        _check_interrupted()
        _hold_signals()
    for exp, _ in results:
        _out(f"{exp.name}: {names[exp.name]}.csv")
        for c, m in metrics.get(exp.name, {}).items():
            ratio = m.get("rmse_over_noise")
            _out(f"  {c:<13} RMSE {m['rmse']:.6e} {fitting.UNITS.get(c, '')}  NRMSE {m['nrmse_percent']:.4f} %  "
                 f"max {m['max_error_percent']:.4f} % of range"
                 + ("" if ratio is None else f"  {ratio:.2f}x the noise"))
            if lack_of_fit({exp.name: {c: m}}) is not None:
                _out(f"  above the noise: the model misses part of this record's {c}")
    _info(f"wrote {len(results)} prediction file(s) to {out}")
    return EXIT_OK


def _cmd_simulate(args) -> int:
    import fitting
    import piezojax as pj

    from ._config import load_config

    out = _check_output(args.out, args.overwrite, "simulate", inputs=[args.input, args.config])
    config = load_config(args.config)
    settings = _data_settings(args, config.data)
    model = pj.unwrap(config.build(None, require_values=True))
    dataset, _ = _load_data([args.input], settings, args.group)
    exp = dataset[0]
    preds = fitting.predict(model, exp, predictor=config.predictor())
    preds = {c: preds[c] for c in config.outputs}
    result = fitting.Experiment.from_arrays(t=exp.t, v_in=exp.v_in, name=exp.name, **preds)
    _check_interrupted()
    _hold_signals()
    fitting.save_experiment(result, out, marker="simulate", units={"v_in": config.model_kind.input_unit})
    _info(f"wrote {', '.join(preds)} for {exp.n} samples to {out}")
    return EXIT_OK


# ------------------------------------------------------------------------------------------------------ main


def _one_line(e: BaseException) -> str:
    msg = " ".join(str(e).split())
    return msg or type(e).__name__


def main(argv: list[str] | None = None, *, _restore_signals: bool = True) -> int:
    """Entry point of the `piezojax` command (in-process; the console script is `console_main`).

    **Arguments:**

    - `argv`: the arguments (default `sys.argv[1:]`).

    **Returns:** the exit status (0 success, 1 fit not converged, 2 bad input, 3 internal error, 130 interrupted by
    SIGINT, 143 terminated by SIGTERM).

    ```python
    from fitting.cli import main
    main(["fit", "model.toml", "run1.csv", "--out", "run1_fit"])  # --out's parent folder must exist
    ```
    """
    with _signals_handled(restore=_restore_signals):
        try:
            return _main(argv)
        except KeyboardInterrupt as e:  # `Interrupted` (SIGINT, SIGTERM) or a plain KeyboardInterrupt
            status = 128 + getattr(e, "signum", signal.SIGINT)
            what = "terminated" if status == EXIT_TERMINATED else "interrupted"
            with contextlib.suppress(Exception):
                print(f"\npiezojax: {what} (nothing was written)", file=sys.stderr, flush=True)
            return status


def _joined_negative_values(argv: list[str]) -> list[str]:
    """`--window -1:0.2` as `--window=-1:0.2`: argparse takes a value that starts with '-' and is not a plain
    negative number for an option, so a window starting before t = 0 would need the `=` form."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        a = argv[i]
        nxt = argv[i + 1] if i + 1 < len(argv) else ""
        negative = len(nxt) > 1 and nxt[0] == "-" and (nxt[1].isdigit() or nxt[1] in ".:")
        if a in ("--window", "--score-from") and negative:
            out.append(f"{a}={nxt}")
            i += 2
            continue
        out.append(a)
        i += 1
    return out


def _main(argv) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(_joined_negative_values(list(sys.argv[1:] if argv is None else argv)))
    except SystemExit as e:  # --help, --version, usage errors
        return int(e.code) if isinstance(e.code, int) else EXIT_ERROR
    commands = {"fit": _cmd_fit, "predict": _cmd_predict, "simulate": _cmd_simulate}
    try:
        with warnings.catch_warnings():
            # numpy's RuntimeWarnings (an overflow in a trial step, an all-NaN slice) are not messages for the
            # command line: the outcome says what went wrong, in one line
            warnings.simplefilter("ignore", RuntimeWarning)
            default_show = warnings.showwarning

            def show(message, category, *args, **kwargs):  # by name: piezojax need not be imported yet
                if category.__name__ == "OutputWarning":
                    _info(f"warning: {message}")
                else:
                    default_show(message, category, *args, **kwargs)

            warnings.showwarning = show  # restored by catch_warnings
            _setup_jax(figures=args.command == "fit" and not args.no_figures)
            return commands[args.command](args)
    except MemoryError as e:
        _info(f"error: out of memory ({_one_line(e)}); use shorter records or fewer parameters")
        return EXIT_ERROR
    except Exception as e:  # noqa: BLE001 - classified here: the except clause must not need piezojax imported
        _check_interrupted()  # an error caused by an interrupt (e.g. inside an import) is the interrupt
        if _is_bad_input(e):
            _info(f"error: {_one_line(e)}")
            return EXIT_ERROR
        if os.environ.get("PIEZOJAX_TRACEBACK"):
            import traceback

            traceback.print_exc()
        _info(f"internal error (a bug; please report it with this line, PIEZOJAX_TRACEBACK=1 prints the traceback): "
              f"{type(e).__name__}: {_one_line(e)}")
        return EXIT_INTERNAL


def _is_bad_input(e: Exception) -> bool:
    """Errors that mean bad input (one line, exit 2): the project's `PiezojaxValueError`, file-system errors, TOML
    syntax errors."""
    import tomllib

    checks = sys.modules.get("piezojax._checks")
    kinds = (OSError, tomllib.TOMLDecodeError) + ((checks.PiezojaxValueError,) if checks is not None else ())
    return isinstance(e, kinds)


def console_main() -> None:
    """The `piezojax` console script: `main` and then exit with its status.

    Once `main` has returned, SIGINT and SIGTERM are only recorded (`_hold_signals`): the outputs are complete or
    absent, and the exit status is the command's. The process then ends with `os._exit` once the output streams are
    flushed, without the interpreter's teardown: after an interrupt that teardown can crash (SIGSEGV) while JAX/XLA
    threads still run work the interrupt abandoned, and it restores the default dispositions, under which a late
    signal would kill the process instead of leaving the status alone. Nothing is left to clean up by then: every
    output is written, fsynced and renamed, and the standard streams are flushed here."""
    status = None
    try:
        status = main(_restore_signals=False)
        _hold_signals()
    except KeyboardInterrupt:  # a signal between an error message and the return
        _hold_signals()
        if status is None:
            status = _interrupt_status()
    for stream in (sys.stdout, sys.stderr):
        if stream is None:  # closed by the caller (`>&-`)
            continue
        try:
            stream.flush()
        except (OSError, ValueError):
            if stream is sys.stdout:
                _silence_stdout()
    os._exit(status)


if __name__ == "__main__":
    console_main()
