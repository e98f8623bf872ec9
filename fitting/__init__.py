"""fitting: end-to-end calibration of piezojax models by nonlinear least squares.

- The pipeline: `calibrate` does everything `piezojax fit` does (checks, data-driven starts, multi-start, the
  refinement rounds, hints) and returns a `Calibration` (`.result`, `.report()`, `.save(folder)`).
- Structure identification: `identify` searches the structure of an actuator's model (hysteresis kind, creep,
  dynamics, initial state, input delay), judged on data each candidate's fit did not see, and calibrates the one
  kept (`Identification`, `Structure`).
- Data: `Experiment`, `Dataset`, `load_experiment`, `save_experiment` (CSV, NPZ, HDF5, MATLAB .mat).
- Model configurations: `load_config`, `parse_config`, `ModelConfig`; the registry of block kinds a CONFIG can
  name (`BlockKind`, its typed options `KindOptions`, `HysteresisOptions`, `CreepOptions`, `register_kind`,
  `ConfigTable`, `StartData`) and of whole-model kinds (`ModelKind`).
- Problem: `Problem` (model, data, free parameters, channel weights, weighted residuals), `Predictor` and the
  built-in predictors.
- Solver: `fit` / `solve` (optimistix's Levenberg–Marquardt, or `method="trust_region"`: scipy's TRF algorithm, in
  normal-equation form: $J^\top J$ and $J^\top r$ by forward mode at each accepted point, a chunk of experiments at
  a time), multi-start in lockstep, smoothing continuation, failure reasons instead of NaN. The solvers as
  components (`AbstractNormalSolver` with `init`/`step`/`terminate`; `LevenbergMarquardt`, `TrustRegion`), the
  outcomes `RESULTS`, progress meters (`AbstractProgressMeter`, `TextProgressMeter`, `NoProgressMeter`),
  `FitError` (`throw=True`) and `PrecisionWarning` (a fit in single precision).
- Fleets: `fit_fleet` calibrates many actuators of one structure, each on its own records, in one compiled loop
  (`vmap` over the fleet, sharded over devices), returning a `FleetResult`.
- A record from another occasion: `warm_up` estimates its sensors' zeros and the model's initial state from a
  window at its start (`WarmUp`), as `piezojax predict --warm-up` does.
- Results: `FitResult` (metrics, standard errors, correlations, report, figures, atomic save), `load_model`.
- Figures (engineering units, no pyplot state): `plot_timeseries`, `plot_loops`, `plot_parameters`,
  `plot_convergence` (also `FitResult.plot(kind)`), `save_figures`.
- Files: the submodule `fitting.files` writes files and folders completely or not at all (used by the command line
  and the experiments; not part of the calibration API above).

Importing `fitting` is cheap: each name is imported from its module on first use (PEP 562), so the command line
(`fitting.cli`) can install its signal handlers before JAX is loaded.
"""

import importlib
from typing import TYPE_CHECKING

_EXPORTS = {
    "._calibrate": ("Calibration", "calibrate"),
    "._config": (
        "BlockKind", "ConfigTable", "CreepOptions", "HysteresisOptions", "KindOptions", "ModelConfig", "ModelKind",
        "StartData", "StartWarning", "load_config", "parse_config", "register_kind", "register_model_kind",
        "registered_kinds", "unregister_kind",
    ),
    "._data": (
        "CHANNELS", "SUPPORTED_SUFFIXES", "UNITS", "Dataset", "Experiment", "load_experiment",
        "save_experiment",
    ),
    "._fit_folder": ("FitFolder", "load_fit"),
    "._fleet": ("FleetResult", "fit_fleet"),
    "._identify": ("Identification", "Structure", "identify"),
    "._initialise": ("cold_start_actuator", "cold_start_free"),
    "._plots": (
        "plot_convergence", "plot_loops", "plot_parameters", "plot_timeseries", "save_figures",
    ),
    "._predict": (
        "ExperimentArrays", "Predictor", "actuator_predictor", "default_predictor", "hysteresis_predictor",
        "observer_predictor", "predict",
    ),
    "._problem": ("Problem", "estimate_noise_std", "free_mask", "parameter_paths"),
    "._results": ("FitResult", "error_metrics", "load_model", "load_summary"),
    "._solve": ("PrecisionWarning", "fit", "set_smoothing", "solve"),
    "._solver": (
        "RESULTS", "AbstractNormalSolver", "AbstractProgressMeter", "FitError", "LevenbergMarquardt", "Linearisation",
        "NoProgressMeter", "Progress", "TextProgressMeter", "Trial", "TrustRegion", "Verdict",
    ),
    "._staged": ("staged_ivan2009",),
    "._warm_up": ("WarmUp", "warm_up"),
}
_LAZY = {name: module for module, names in _EXPORTS.items() for name in names}
# The public names, every one `_EXPORTS` gives (`fitting.files`, also loaded on first use, is a helper submodule for
# the command line and the experiments, not part of the calibration API)
__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name == "files":  # the submodule, loaded on first use like the names above
        value = importlib.import_module(".files", __name__)
        globals()[name] = value
        return value
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'fitting' has no attribute {name!r}")
    value = getattr(importlib.import_module(module, __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY) | {"files"})


if TYPE_CHECKING:  # the same names for static analysis
    from ._calibrate import Calibration as Calibration, calibrate as calibrate
    from ._config import (
        BlockKind as BlockKind,
        ConfigTable as ConfigTable,
        CreepOptions as CreepOptions,
        HysteresisOptions as HysteresisOptions,
        KindOptions as KindOptions,
        ModelConfig as ModelConfig,
        ModelKind as ModelKind,
        StartData as StartData,
        StartWarning as StartWarning,
        load_config as load_config,
        parse_config as parse_config,
        register_kind as register_kind,
        register_model_kind as register_model_kind,
        registered_kinds as registered_kinds,
        unregister_kind as unregister_kind,
    )
    from ._data import (
        CHANNELS as CHANNELS,
        SUPPORTED_SUFFIXES as SUPPORTED_SUFFIXES,
        UNITS as UNITS,
        Dataset as Dataset,
        Experiment as Experiment,
        load_experiment as load_experiment,
        save_experiment as save_experiment,
    )
    from ._fit_folder import FitFolder as FitFolder, load_fit as load_fit
    from ._fleet import FleetResult as FleetResult, fit_fleet as fit_fleet
    from ._identify import Identification as Identification, Structure as Structure, identify as identify
    from ._initialise import cold_start_actuator as cold_start_actuator, cold_start_free as cold_start_free
    from ._plots import (
        plot_convergence as plot_convergence,
        plot_loops as plot_loops,
        plot_parameters as plot_parameters,
        plot_timeseries as plot_timeseries,
        save_figures as save_figures,
    )
    from ._predict import (
        ExperimentArrays as ExperimentArrays,
        Predictor as Predictor,
        actuator_predictor as actuator_predictor,
        default_predictor as default_predictor,
        hysteresis_predictor as hysteresis_predictor,
        observer_predictor as observer_predictor,
        predict as predict,
    )
    from ._problem import (
        Problem as Problem,
        estimate_noise_std as estimate_noise_std,
        free_mask as free_mask,
        parameter_paths as parameter_paths,
    )
    from ._results import (
        FitResult as FitResult,
        error_metrics as error_metrics,
        load_model as load_model,
        load_summary as load_summary,
    )
    from ._solve import (
        PrecisionWarning as PrecisionWarning,
        fit as fit,
        set_smoothing as set_smoothing,
        solve as solve,
    )
    from ._solver import (
        RESULTS as RESULTS,
        AbstractNormalSolver as AbstractNormalSolver,
        AbstractProgressMeter as AbstractProgressMeter,
        FitError as FitError,
        LevenbergMarquardt as LevenbergMarquardt,
        Linearisation as Linearisation,
        NoProgressMeter as NoProgressMeter,
        Progress as Progress,
        TextProgressMeter as TextProgressMeter,
        Trial as Trial,
        TrustRegion as TrustRegion,
        Verdict as Verdict,
    )
    from ._staged import staged_ivan2009 as staged_ivan2009
    from ._warm_up import WarmUp as WarmUp, warm_up as warm_up
