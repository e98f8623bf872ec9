"""The commands: `fit`, `predict`, `simulate`; each parses nothing and writes its outputs atomically."""

import json
from pathlib import Path

from .._timing import phase
from . import common
from .common import _check_output, _data_settings, _error, _given_units, _info, _load_data, _out, _safe_name, _windowed
from .signals import _check_interrupted, _consume_interrupt, _hold_signals, _interrupt_status, _pending_interrupt
from .status import EXIT_NOT_CONVERGED, EXIT_OK

# ------------------------------------------------------------------------------------------------------ commands


def _cmd_fit(args) -> int:
    from .._timing import Timings, process_start

    timings = Timings(start=(process_start() if common.AS_PROGRAM else None) or common.CALLED_AT)
    with timings:
        timings.add("imports", timings.start, max(common.IMPORTED_AT or timings.start, timings.start))
        with phase("imports"):
            import fitting  # noqa: F401  (the command's own imports count in `imports`)

            from .._calibrate import calibrate  # noqa: F401
            from .._identify import identify  # noqa: F401
        status = _fit(args, timings)
    return status


def _timings_out(timings, folder, quiet: bool) -> None:
    """`timings` into the `result.json` of the fit folder being written (`folder`) and on stderr."""
    import fitting

    path = Path(folder) / "result.json"
    result = json.loads(path.read_text())
    result["timings"] = timings.summary()
    fitting.files.save_json(path, result)
    _info(f"time {timings.line()} (seconds; compile: tracing and compiling, out of the others)", quiet)


def _fit(args, timings) -> int:
    import fitting

    from .._calibrate import calibrate
    from .._config import MAX_STEPS, load_config

    quiet = args.quiet
    if args.max_steps is not None and not 1 <= args.max_steps <= MAX_STEPS:
        raise _error(f"--max-steps must be >= 1 and <= {MAX_STEPS} (the documented upper bound), got {args.max_steps}")
    if args.auto:
        return _cmd_fit_auto(args, timings)
    if args.base is not None:
        raise _error("--config gives the fixed tables of a structure search: use it with --auto (without --auto, "
                     "CONFIG is the first argument)")
    if not args.data:
        raise _error("the following arguments are required: DATA (the files to fit, after CONFIG; or --auto to "
                     "search the structure without a CONFIG)")
    out = _check_output(args.out, args.overwrite, "fit", inputs=[args.config, *args.data])
    config = load_config(args.config)
    settings = _data_settings(args, config.data)
    with fitting.files.atomic_directory(out, overwrite=args.overwrite, kind="fit") as tmp:
        with phase("read"):
            dataset, unit_warnings = _load_data(args.data, settings, args.group)
            if args.window is not None:
                dataset = _windowed(dataset, args.window)
        cal = calibrate(config, dataset, max_steps=args.max_steps, progress=not quiet,
                        log=lambda m, warning=False: _info(m, quiet and not warning), interrupted=_pending_interrupt)
        result = cal.result
        if result.code == "interrupted":
            _consume_interrupt()  # the solver stopped at the interrupt and returned its last accepted point
        _info(f"writing {out}", quiet)
        with phase("write"):
            cal.write_files(tmp, figures=not args.no_figures, config_source=args.config, data=args.data,
                            data_settings=settings, window=args.window, read_warnings=unit_warnings)
        _timings_out(timings, tmp, quiet)
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


def _cmd_fit_auto(args, timings) -> int:
    """`piezojax fit --auto DATA... [--config CONFIG]`: the structure search (`fitting.identify`), then the folder
    of the structure kept."""
    import fitting

    from .._config import read_config_text
    from .._identify import parse_base

    quiet = args.quiet
    data = [args.config, *args.data]
    out = _check_output(args.out, args.overwrite, "fit", inputs=[*data, *([args.base] if args.base else [])])
    base = read_config_text(args.base) if args.base else None
    settings = _data_settings(args, parse_base(base, args.base).data if base is not None else {})
    with fitting.files.atomic_directory(out, overwrite=args.overwrite, kind="fit") as tmp:
        with phase("read"):
            dataset, unit_warnings = _load_data(data, settings, args.group)
            if args.window is not None:
                dataset = _windowed(dataset, args.window)
        ident = fitting.identify(dataset, base=base, max_steps=args.max_steps, progress=not quiet,
                                 log=lambda m, warning=False: _info(m, quiet and not warning))
        _info(ident.table(), quiet)
        result = ident.calibration.result
        if result.code == "interrupted":
            _consume_interrupt()
        _info(f"writing {out}", quiet)
        source = args.base or str(Path(out) / "config.toml")  # without a base: the structure kept, written there
        with phase("write"):
            ident.write_files(tmp, figures=not args.no_figures, config_source=source, data=data,
                              data_settings=settings, window=args.window, read_warnings=unit_warnings)
        _timings_out(timings, tmp, quiet)
        _check_interrupted()
        _hold_signals()
    _out(ident.report())
    if result.code == "interrupted":
        _info(f"interrupted: the last accepted parameters are saved in {out} (result.json: code 'interrupted')")
        return _interrupt_status()
    if not result.success:
        _info(f"the fit did not converge ({result.reason}); results written to {out}")
        return EXIT_NOT_CONVERGED
    return EXIT_OK


def load_fitted(model_dir) -> tuple:
    """`(config, model)` from a folder written by `piezojax fit`. Deprecated: `fitting.load_fit(model_dir)` returns
    them, validated, with the fit's summary and data settings."""
    import warnings

    import fitting

    warnings.warn("fitting.cli.load_fitted is deprecated; use fitting.load_fit (config, model = "
                  "fitting.load_fit(folder))", DeprecationWarning, stacklevel=2)
    fit = fitting.load_fit(model_dir)
    return fit.config, fit.model


def _cmd_predict(args) -> int:
    import numpy as np

    import fitting

    from .._results import lack_of_fit

    out = _check_output(args.out, args.overwrite, "predict", inputs=[*args.data, *(args.history or [])],
                        fit_folder=args.model_dir)
    fit = fitting.load_fit(args.model_dir)
    config, model = fit.config, fit.model
    settings = _data_settings(args, fit.data_settings)
    given = _given_units(args)[1]
    kept = {k: v for k, v in settings.get("units", {}).items() if k not in given}
    if kept:
        shown = ",".join(f"{k}={v}" for k, v in kept.items())
        _info(f"reading the files in the fit's units ({shown}); --units '' reads them in SI")
    with fitting.files.atomic_directory(out, overwrite=args.overwrite, kind="predict") as tmp:
        dataset, unit_warnings = _load_data(args.data, settings, args.group)
        results, metrics = [], {}
        history = _load_data(args.history, settings, args.group)[0] if args.history else ()
        warmed = {}
        for exp in dataset:
            scored = np.ones(exp.n, bool)
            if args.warm_up is not None:
                w = fitting.warm_up(model, exp, args.warm_up, predictor=config.predictor(), history=history)
                preds, scored, warmed[exp.name] = w.predictions, w.scored, w.summary()
                if not all(np.all(np.isfinite(y)) for y in preds.values()):
                    raise _error(f"{exp._label()}: the model's prediction is not finite")
            else:
                preds = fitting.predict(model, exp, predictor=config.predictor(), history=history)
            preds = {c: preds[c] for c in config.outputs}
            results.append((exp, preds))
            measured = [c for c in preds if exp.has(c)]
            if args.score_from is not None:
                scored = scored & (exp.t >= args.score_from - 1e-6 * exp.dt)
            if np.count_nonzero(scored) < 2:
                what = (f"--score-from {args.score_from:g} s leaves" if args.warm_up is None else
                        f"--score-from {args.score_from:g} s after --warm-up {args.warm_up:g} s leave")
                raise _error(f"{exp._label()}: {what} fewer than 2 samples of the record "
                             f"[{exp.t[0]:.6g}, {exp.t[-1]:.6g}] s to score")
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
            "warm_up": {"seconds": args.warm_up, "records": warmed} if args.warm_up is not None else None,
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

    from .._config import load_config

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


