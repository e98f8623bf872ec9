"""The `piezojax` argument parser: subcommands, options and their help."""

import argparse

from .status import EXIT_ERROR

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
  [input]       delay = false | true | value [s]   (the voltage's dead time, fractional samples)
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
  piezojax fit --auto run1.csv run2.csv --out fits/auto          (search the structure: no CONFIG)
  piezojax fit --auto run1.csv --config units.toml --out fits/auto   (CONFIG's tables fixed, the rest searched)

With --auto the model's structure is searched (hysteresis kind, creep, dynamics, prehistory, input delay), each
candidate fitted on the first 70 % of every file and judged on the rest (predicted after the beginning); the
simplest within the best's uncertainty is fitted on every file and written to DIR, its config.toml
the structure chosen, the ranking in report.txt and result.json ("identification").

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
  piezojax predict fits/pi_creep day2.csv --warm-up 1.0 --out predictions

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
    fit.add_argument("config", metavar="CONFIG", help="TOML model configuration (with --auto: the first DATA file)")
    fit.add_argument("data", metavar="DATA", nargs="*", help="experiment files (.csv, .npz, .h5/.hdf5, .mat)")
    fit.add_argument("--auto", action="store_true", help="search the model's structure (no CONFIG: every "
                     "positional argument is a DATA file; see --config)")
    fit.add_argument("--config", dest="base", metavar="CONFIG", help="with --auto: a CONFIG whose tables are fixed "
                     "(units, [fit] options, a block you know); the rest is searched")
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
    pred.add_argument("--warm-up", metavar="SECONDS", type=float,
                      help="a record from another occasion: estimate its sensors' zeros (an offset per measured "
                      "channel) and the actuator's initial state (the creep's free response, a prehistory excursion) "
                      "from its first SECONDS, and score only after them (off by default; the estimates go to "
                      "metrics.json); with --history, the hysteresis memory is the history's (no prehistory estimated)")
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


