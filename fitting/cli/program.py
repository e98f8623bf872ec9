"""`main` (in-process) and `console_main` (the console script): run a command, classify its errors, exit."""

import contextlib
import os
import signal
import sys
import time
import warnings

from . import common
from .commands import _cmd_fit, _cmd_predict, _cmd_simulate
from .common import _info, _setup_jax, _silence_stdout
from .parser import build_parser
from .signals import _check_interrupted, _hold_signals, _interrupt_status, _signals_handled
from .status import EXIT_ERROR, EXIT_INTERNAL, EXIT_TERMINATED

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
    common.CALLED_AT = time.time()  # a command run in-process counts its time from here (`fitting._timing`)
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

    checks = sys.modules.get("piezojax._checks")  # loaded with piezojax (or partly, by an interrupted import)
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
    common.AS_PROGRAM = True  # the command's time counts from the process' start
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


