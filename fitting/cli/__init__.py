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

# run as the program (the console script, or `python -m fitting.cli`)
if sys.argv[0].rsplit("/", 1)[-1] == "piezojax" or (
        "-m" in sys.orig_argv and sys.orig_argv[sys.orig_argv.index("-m") + 1 :][:1] == ["fitting.cli"]):
    # a signal during the imports below (before `main` installs its handlers) ends the process with the status of an
    # interrupt before anything is written, not with a traceback
    def _signal_while_importing(signum, frame):
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGINT, _signal_while_importing)
    signal.signal(signal.SIGTERM, _signal_while_importing)

from .commands import load_fitted as load_fitted
from .parser import build_parser as build_parser
from .program import console_main as console_main, main as main
from .signals import Interrupted as Interrupted
from .status import (
    EXIT_ERROR as EXIT_ERROR,
    EXIT_INTERNAL as EXIT_INTERNAL,
    EXIT_INTERRUPTED as EXIT_INTERRUPTED,
    EXIT_NOT_CONVERGED as EXIT_NOT_CONVERGED,
    EXIT_OK as EXIT_OK,
    EXIT_TERMINATED as EXIT_TERMINATED,
)
