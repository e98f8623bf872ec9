"""The `piezojax` command line: fit a model configured in TOML to data files, predict with it, simulate.

Exit status: 0 success; 1 `fit` finished without converging (outputs written, `result.json` says why); 2 bad input
(one line `piezojax: error: ...` on stderr, nothing written); 130 interrupted by Ctrl-C (nothing half-written: an
interrupted `fit` saves the last accepted parameters as a complete folder, or nothing if it was interrupted before
the first step).
"""

import argparse
import sys
import warnings
from pathlib import Path

EXIT_OK, EXIT_NOT_CONVERGED, EXIT_ERROR, EXIT_INTERRUPTED = 0, 1, 2, 130

_CONFIG_HELP = """\
CONFIG is a TOML file naming the model blocks, optional initial values, and the fit options:

  [hysteresis]  kind = "prandtl_ishlinskii" (plays = 10, weights, thresholds, w0)
                     | "bouc_wen" (A, beta, gamma, n, d, method = "closed_form"|"rk4", substeps)
                     | "maxwell_slip" (elements = 8, stiffness, breakaway)
                     | "none";            smoothing = 0.0 (0 = exact operator)
  [creep]       kind = "kelvin_voigt" (order = 1, stiffnesses, time_constants)
                     | "logarithmic" (gamma, t0, gain) | "none"
  [dynamics]    order = 0 | 1 | 2 | 3 | 4 (gain = 1, omega [rad/s], zeta, poles [rad/s] < 0)
  [charge]      capacitance [F], coupling [C/m]   (an actuator that also predicts charge and current)
  [observer]    kind = "current_integration": paper 001 self-sensing, displacement and force from v_in and
                v_out; integrator_capacitance, reference_capacitance, leakage_resistance, force_sensitivity,
                displacement_coefficient, stiffness (required), bias_current = 0, capacitance_p = 0,
                filter_cutoff [Hz]; [hysteresis] and [creep] are then charge operators (C/V)
  [fit]         free = ["hysteresis", "creep.time_constants", ...] (default: every identifiable parameter)
                weights = "range" | "noise" | {displacement = 1e6, force = 1e3}
                smoothing = [0.05, 0.0]   (continuation: relaxed, then exact hysteresis)
                max_steps = 200;  targets = ["displacement", ...] (default: predicted channels in the data)
                method = "levenberg_marquardt" | "trust_region"   (scipy's TRF algorithm; see fitting.solve)

Parameter values not given in CONFIG start from the data (`fit`), see the README ("Command line").
Data files: .csv (header naming t, v_in and any of v_out, displacement, force, charge, current), .npz, .h5/.hdf5,
.mat with the same names; SI units; uniform t.
"""

_FIT_EXAMPLES = """\
examples:
  piezojax fit pi_creep.toml run1.csv run2.npz run3.h5 --out fits/pi_creep
  piezojax fit selfsensing.toml contact.mat --out fits/obs --overwrite --max-steps 50

DIR receives result.json (metrics per experiment and channel, parameters with standard errors, convergence),
model.eqx (the fitted parameters), config.toml (the configuration, to rebuild the model), report.txt and PNG
figures. DIR appears complete or not at all.
exit status: 0 converged, 1 not converged (outputs written), 2 bad input, 130 interrupted.
"""

_PREDICT_EXAMPLES = """\
examples:
  piezojax predict fits/pi_creep held_out.csv --out predictions
  piezojax predict fits/obs day2_*.mat --out predictions --overwrite

OUT is a folder with one CSV per input (t, v_in and the predicted channels on the input's time grid) and
metrics.json; RMSE and NRMSE (% of the measured range) are printed for the channels a file also measures.
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
    from piezojax import __version__

    parser.add_argument("--version", action="version", version=f"piezojax {__version__}")
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
    fit.add_argument("--out", metavar="DIR", required=True, help="result folder to create (must not exist)")
    fit.add_argument("--overwrite", action="store_true", help="replace DIR if it exists (atomically)")
    fit.add_argument("--max-steps", type=int, metavar="N", help="Levenberg–Marquardt steps per smoothing level "
                     "(overrides [fit] max_steps)")
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
    pred.add_argument("--overwrite", action="store_true", help="replace OUT if it exists (atomically)")

    sim = sub.add_parser(
        "simulate", help="forward simulation of the model of CONFIG with its given parameter values",
        description="Simulate the model of CONFIG, with the parameter values CONFIG gives, on the input FILE.\n\n"
        + _CONFIG_HELP,
        epilog=_SIMULATE_EXAMPLES, formatter_class=fmt,
    )
    sim.add_argument("config", metavar="CONFIG", help="TOML model configuration with every parameter value")
    sim.add_argument("--input", metavar="FILE", required=True, help="input file (t, v_in; v_out for an observer)")
    sim.add_argument("--out", metavar="OUT", required=True, help="output file (.csv, .npz, .h5, .mat)")
    sim.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    return parser


# ------------------------------------------------------------------------------------------------------ helpers


def _setup_jax() -> None:
    """x64 and fused CPU scans, before JAX initialises its backends (a no-op for the flag afterwards)."""
    import jax

    import piezojax as pj

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pj.enable_fast_cpu_scans()
    jax.config.update("jax_enable_x64", True)


def _info(msg: str, quiet: bool = False) -> None:
    if not quiet:
        print(f"piezojax: {msg}", file=sys.stderr, flush=True)


def _check_new_output(path: str, overwrite: bool, what: str) -> Path:
    """Fail now, not after the work, if `path` cannot be written."""
    import fitting
    from piezojax._checks import PiezojaxValueError

    p = fitting.check_writable(path)
    if p.exists() and not overwrite:
        raise PiezojaxValueError(f"{what} {str(p)!r} already exists; pass --overwrite to replace it")
    if what == "output folder" and p.exists() and not p.is_dir():
        raise PiezojaxValueError(f"{what} {str(p)!r} is a file")
    if what == "output file" and p.is_dir():
        raise PiezojaxValueError(f"{what} {str(p)!r} is a directory")
    return p


def _experiment_arrays(exp, inputs):
    import jax.numpy as jnp

    from ._predict import ExperimentArrays

    return ExperimentArrays(
        t=jnp.asarray(exp.t), dt=jnp.asarray(exp.dt), v_in=jnp.asarray(exp.v_in),
        channels={c: jnp.asarray(exp[c]) for c in inputs},
    )


def _run_model(config, model, exp) -> dict:
    """The predicted channels (`config.outputs`) of `model` for one experiment, as numpy arrays."""
    import equinox as eqx
    import numpy as np

    from piezojax._checks import PiezojaxValueError

    predictor = config.predictor()
    missing = [c for c in config.inputs if not exp.has(c)]
    if missing:
        raise PiezojaxValueError(
            f"experiment {exp.name!r} (file {exp.source!r}) lacks the column(s) {missing} the model reads as input")
    out = eqx.filter_jit(lambda p, m, d: p(m, d))(predictor, model, _experiment_arrays(exp, config.inputs))
    preds = {c: np.asarray(out[c]) for c in config.outputs}
    bad = [c for c, y in preds.items() if not np.all(np.isfinite(y))]
    if bad:
        raise PiezojaxValueError(f"experiment {exp.name!r}: the model's {bad[0]!r} is not finite")
    return preds


def _safe_name(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in name)


# ------------------------------------------------------------------------------------------------------ commands


def _cmd_fit(args) -> int:
    import fitting
    import piezojax as pj

    from ._config import load_config

    quiet = args.quiet
    out = _check_new_output(args.out, args.overwrite, "output folder")
    config = load_config(args.config)
    if args.max_steps is not None and args.max_steps < 1:
        from piezojax._checks import PiezojaxValueError

        raise PiezojaxValueError(f"--max-steps must be >= 1, got {args.max_steps}")
    dataset = fitting.Dataset.from_files(args.data)
    targets = config.fit_targets(dataset)
    for c in config.inputs:
        dataset.require(c)
    _info(f"{len(dataset)} experiment(s), {sum(e.n for e in dataset)} samples; fitting {', '.join(targets)}", quiet)
    _info("initial values from the data", quiet)
    params = config.build(dataset)
    free = config.fit_free(targets)
    max_steps = args.max_steps if args.max_steps is not None else config.max_steps
    what = "Levenberg–Marquardt" if config.method == "levenberg_marquardt" else "trust region"
    _info(f"{what} on {', '.join(free)} (first step compiles)", quiet)
    result = fitting.fit(
        params, dataset, predictor=config.predictor(), targets=targets, free=free, weights=config.weights,
        smoothing=config.smoothing, max_steps=max_steps, progress=not quiet, method=config.method,
    )
    extra = {
        "cli": {
            "command": "fit",
            "config": "config.toml",
            "config_source": str(Path(args.config).absolute()),
            "data": [str(Path(p).absolute()) for p in args.data],
            "experiments": list(dataset.names),
            "targets": list(targets),
            "free": free,
            "weights": result.problem.weights,
            "outputs": list(config.outputs),
            "piezojax_version": pj.__version__,
        }
    }
    _info(f"writing {out}", quiet)
    with fitting.atomic_directory(out, overwrite=args.overwrite) as tmp:
        result.save(tmp, overwrite=True, figures=not args.no_figures, extra=extra)
        fitting.atomic_write_text(tmp / "config.toml", config.text)
    print(result.report())
    if result.code == "interrupted":
        _info(f"interrupted: the last accepted parameters are saved in {out} (result.json: code 'interrupted')")
        return EXIT_INTERRUPTED
    if not result.success:
        _info(f"the fit did not converge ({result.reason}); results written to {out}")
        return EXIT_NOT_CONVERGED
    return EXIT_OK


def load_fitted(model_dir) -> tuple:
    """`(config, model)` from a folder written by `piezojax fit`: the configuration saved there rebuilds the
    structure, `fitting.load_model` fills in the fitted values."""
    import fitting
    from piezojax._checks import PiezojaxValueError

    from ._config import parse_config

    d = Path(model_dir)
    if not d.is_dir():
        raise PiezojaxValueError(f"model folder {str(d)!r} does not exist or is not a folder")
    cfg_file = d / "config.toml"
    if not cfg_file.exists() or not (d / "model.eqx").exists():
        raise PiezojaxValueError(f"{str(d)!r} is not a folder written by `piezojax fit` (no config.toml/model.eqx)")
    config = parse_config(cfg_file.read_text(encoding="utf-8"), source=str(cfg_file))
    model = fitting.load_model(d, like=config.build(None))
    return config, model


def _cmd_predict(args) -> int:
    import fitting

    out = _check_new_output(args.out, args.overwrite, "output folder")
    config, model = load_fitted(args.model_dir)
    dataset = fitting.Dataset.from_files(args.data)
    results, metrics = [], {}
    for exp in dataset:
        preds = _run_model(config, model, exp)
        results.append((exp, preds))
        measured = [c for c in preds if exp.has(c)]
        if measured:
            metrics[exp.name] = {c: fitting.error_metrics(preds[c], exp[c]) for c in measured}
    names = {}
    for exp, _ in results:
        base = _safe_name(exp.name.replace("/", "__"))
        name, i = base, 1
        while name in names.values():
            i += 1
            name = f"{base}_{i}"
        names[exp.name] = name
    with fitting.atomic_directory(out, overwrite=args.overwrite) as tmp:
        for exp, preds in results:
            pred_exp = fitting.Experiment.from_arrays(t=exp.t, v_in=exp.v_in, name=exp.name, **preds)
            fitting.save_experiment(pred_exp, tmp / f"{names[exp.name]}.csv")
        fitting.save_json(tmp / "metrics.json", {
            "model": str(Path(args.model_dir).absolute()),
            "files": {exp.name: {"input": exp.source, "output": f"{names[exp.name]}.csv"} for exp, _ in results},
            "metrics": metrics,
        })
    for exp, _ in results:
        print(f"{exp.name}: {names[exp.name]}.csv")
        for c, m in metrics.get(exp.name, {}).items():
            print(f"  {c:<13} RMSE {m['rmse']:.6e}  NRMSE {m['nrmse_percent']:.4f} %  "
                  f"max {m['max_error_percent']:.4f} % of range")
    _info(f"wrote {len(results)} prediction file(s) to {out}")
    return EXIT_OK


def _cmd_simulate(args) -> int:
    import fitting
    import piezojax as pj

    from ._config import load_config

    out = _check_new_output(args.out, args.overwrite, "output file")
    config = load_config(args.config)
    model = pj.unwrap(config.build(None, require_values=True))
    exp = fitting.load_experiment(args.input)
    preds = _run_model(config, model, exp)
    fitting.save_experiment(fitting.Experiment.from_arrays(t=exp.t, v_in=exp.v_in, name=exp.name, **preds), out)
    _info(f"wrote {', '.join(preds)} for {exp.n} samples to {out}")
    return EXIT_OK


# ------------------------------------------------------------------------------------------------------ main


def _one_line(e: BaseException) -> str:
    msg = " ".join(str(e).split())
    return msg or type(e).__name__


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `piezojax` console script.

    **Arguments:**

    - `argv`: the arguments (default `sys.argv[1:]`).

    **Returns:** the exit status (0 success, 1 fit not converged, 2 bad input, 130 interrupted).

    ```python
    from fitting.cli import main
    main(["fit", "model.toml", "run1.csv", "--out", "fits/run1"])
    ```
    """
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help, --version, usage errors
        return int(e.code) if isinstance(e.code, int) else EXIT_ERROR
    try:
        _setup_jax()
        import tomllib

        from piezojax._checks import PiezojaxValueError

        commands = {"fit": _cmd_fit, "predict": _cmd_predict, "simulate": _cmd_simulate}
        try:
            return commands[args.command](args)
        except (PiezojaxValueError, OSError, tomllib.TOMLDecodeError) as e:
            print(f"piezojax: error: {_one_line(e)}", file=sys.stderr)
            return EXIT_ERROR
    except KeyboardInterrupt:
        print("\npiezojax: interrupted (nothing was written)", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
