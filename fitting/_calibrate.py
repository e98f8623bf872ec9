"""The calibration pipeline: everything `piezojax fit` does between reading the data files and writing the result
folder, as one library call (`calibrate`) returning a `Calibration` that the command line only writes."""

import dataclasses
import math
import os
import warnings
from collections.abc import Callable
from pathlib import Path

import jax.tree_util as jtu
import numpy as np

import piezojax as pj
from piezojax import PiezojaxValueError

from . import files
from ._config import ACTUATOR, MAX_STEPS, ModelConfig, StartWarning, load_config
from ._data import Dataset, experiments_of
from ._problem import free_mask, tangent_block
from ._refine import refine, silent
from ._results import FitResult, lack_of_fit
from ._solve import fit
from ._timing import phase

MIN_FIT_SAMPLES = 20
"""Fewest samples per record that `piezojax fit` accepts (the data-driven initial values need a few periods of
the slowest block)."""
# the data-driven starts are fitted together only while they need no more than this: on XLA:CPU the starts are
# linearised one at a time, so their memory does not add up but their time does (a cost gate)
MULTI_START_MEMORY = 3 * 2**29
# the longest record's Jacobian [bytes] above which `fit` returns the freed memory the process retains to the system:
# glibc's threshold for mapping a block apart (`pj.retain_freed_memory`), above which the largest buffers bypass the
# retained heaps anyway
RETAIN_MEMORY_BELOW = 32 * 2**20


@dataclasses.dataclass(frozen=True)
class Calibration:
    """The outcome of `calibrate`: the fit and what the pipeline did around it.

    **Fields:**

    - `result`: the `FitResult` kept (after the refinement rounds, counting the whole run).
    - `config`: the `ModelConfig` calibrated; `targets`, `free`: the channels fitted and the free parameter paths.
    - `start_warnings`: why a data-driven start fell back (`StartWarning` messages).
    - `reseeded`: what the refinement rounds did (`None` when nothing was dead or misplaced), see `refine`.
    - `hints`: the report's lines on a structure that may fit better and on modes the records cannot resolve.
    - `derived`: the values CONFIG does not give, taken from the data (by label).
    - `warnings`: other warnings of the run (a derived value that could not be read).
    """

    result: FitResult
    config: ModelConfig
    targets: tuple[str, ...]
    free: list[str]
    start_warnings: list[str]
    reseeded: dict | None
    hints: list[str]
    derived: dict
    warnings: list[str]

    def report(self) -> str:
        """The fit's report with the pipeline's lines: the values taken from the data, and the hints."""
        fitted = set(self.result.parameter_names)
        lines = [f"  {k} = {v!r}" + ("  (fitted)" if self.config.derived_path(k) in fitted else "  (fixed)")
                 for k, v in self.derived.items()]
        if lines:
            lines.insert(0, "values CONFIG does not give, taken from the data (give them in CONFIG to simulate):")
        return "\n".join([self.result.report(), *lines, *self.hints])

    def summary(self, *, config_source=None, data=None, data_settings=None, window=None,
                read_warnings=()) -> dict:
        """What `result.json` holds beside the fit's own summary: the `"cli"` entry (how the fit was run, read back
        by `piezojax predict`) and `"warnings"`. `config_source`, `data`, `data_settings`, `window` and
        `read_warnings` describe how the data were read (default: the CONFIG's file, the experiments' sources and
        the CONFIG's `[data]` table)."""
        cli = {
            "command": "fit",
            "config": "config.toml",
            "config_source": str(Path(config_source or self.config.source).absolute()),
            "data": [str(Path(p).absolute()) for p in (data if data is not None else self._sources())],
            "experiments": list(self.result.dataset.names),
            "targets": list(self.targets),
            "free": self.free,
            "weights": self.result.weights,
            "outputs": list(self.config.outputs),
            "data_settings": data_settings if data_settings is not None else dict(self.config.data),
            "window": window,
            "piezojax_version": pj.__version__,
        }
        if self.reseeded is not None:
            cli["reseeded"] = self.reseeded
        cli["hints"] = self.hints
        cli["data_derived"] = self.derived
        return {"cli": cli, "warnings": [*read_warnings, *self.start_warnings, *self.warnings]}

    def _sources(self) -> list[str]:
        return list(dict.fromkeys(e.source for e in self.result.dataset if e.source))

    def write_files(self, folder, *, figures: bool = True, **summary) -> None:
        """Write the fit folder's files into the existing folder `folder` (not atomically: for a caller that writes
        into a temporary folder of its own): `model.eqx`, `result.json` (with `summary(**summary)`), `report.txt`
        (`report()`), `config.toml` and, with `figures`, the PNG figures."""
        folder = Path(folder)
        self.result.write_files(folder, figures=figures, extra=self.summary(**summary),
                                input_unit=self.config.model_kind.input_unit)
        if self.hints or self.derived:  # the report with the pipeline's lines
            files.atomic_write_text(folder / "report.txt", self.report() + "\n")
        files.atomic_write_text(folder / "config.toml", self.config.text)

    def save(self, path, *, overwrite: bool = False, figures: bool = True, **summary) -> Path:
        """Write the fit folder `path/` atomically, as `piezojax fit --out path` does (`piezojax predict` reads it);
        `overwrite=True` replaces only an earlier fit folder (see `fitting.files.atomic_directory`)."""
        path = Path(path)
        with files.atomic_directory(path, overwrite=overwrite, kind="fit") as tmp:
            self.write_files(tmp, figures=figures, **summary)
        return path


def calibrate(config, dataset, *, max_steps: int | None = None, progress: bool = True, log: Callable = silent,
              interrupted: Callable[[], bool] = lambda: False, refine_rounds: bool = True,
              starts: Callable[[ModelConfig, Dataset], list] | None = None) -> Calibration:
    """Calibrate the model of `config` on `dataset`: what `piezojax fit` does, without reading or writing files.

    The data are checked (records long enough, every fitted channel present and varying, enough memory), the
    data-driven starts are made (`ModelConfig.starts`: the rule-based start and the joint cold start, fitted together
    when their memory allows, the better kept), the model is fitted by the CONFIG's method, the refinement rounds
    re-seed dead or misplaced hysteresis plays and move creep lags while the cost falls (`refine`), and the report's
    hints and the values taken from the data are collected.

    **Arguments:**

    - `config`: a `ModelConfig` (`fitting.load_config`, `fitting.parse_config`) or the path of a TOML file.
    - `dataset`: a `Dataset`, an `Experiment` or a list of them.
    - `max_steps`: overrides the CONFIG's `[fit] max_steps` (1 to `MAX_STEPS`).
    - `progress`: the solver's progress lines on stderr.
    - `log`: called with each line the command line prints (`log(message, warning=False)`); silent by default.
    - `interrupted`: whether an interrupt arrived that no exception carried (the command line's signal record).
    - `refine_rounds`: run the refinement rounds after the fit (default; `False`: the fit alone, as the structure
      search fits its candidates).
    - `starts`: `starts(config, dataset)` returns the starts to fit together, models of the CONFIG's structure
      reparametrised as `ModelConfig.starts` returns them (e.g. one warm-started from an earlier fit beside
      `config.starts(dataset, cold_start=False)`); default: the data-driven starts, `config.starts(dataset)`.

    **Returns:** a `Calibration`; `.result` is the `FitResult`, `.save(path)` writes the folder `piezojax predict`
    reads. Bad data or options raise one `PiezojaxValueError`.

    ```python
    cal = fitting.calibrate("pi_creep.toml", fitting.Dataset.from_files(["run1.csv", "run2.csv"]))
    print(cal.report()); cal.save("fits/pi_creep")
    ```
    """
    if not isinstance(config, ModelConfig):
        config = load_config(config)
    if max_steps is not None and not 1 <= max_steps <= MAX_STEPS:
        raise PiezojaxValueError(f"`max_steps` must be >= 1 and <= {MAX_STEPS} (the documented upper bound), got "
                                 f"{max_steps}")
    if not isinstance(dataset, Dataset):
        dataset = Dataset(experiments_of(dataset))
    targets = _check_targets(config, dataset)
    free = config.fit_free(targets)
    num_free = _num_free(config.build(None), free)
    check_memory(config, dataset, num_free)
    release_memory_if_long(config, dataset, num_free)
    log(f"{len(dataset)} experiment(s), {sum(e.n for e in dataset)} samples; fitting {', '.join(targets)}")
    log("initial values from the data")
    with warnings.catch_warnings(record=True) as caught, phase("starts"):
        warnings.simplefilter("always", StartWarning)
        made = config.starts(dataset) if starts is None else list(starts(config, dataset))
    if not made:
        raise PiezojaxValueError("`starts` returned no start")
    start_warnings = [str(w.message) for w in caught if issubclass(w.category, StartWarning)]
    for m in start_warnings:
        log(f"warning: {m}", warning=True)
    what = "Levenberg–Marquardt" if config.method == "levenberg_marquardt" else "trust region"
    log(f"{what} on {', '.join(free)} (first step compiles)")
    made = _affordable_starts(config, dataset, num_free, made, log, given=starts is not None)
    fit_args = dict(predictor=config.predictor(), targets=targets, free=free, weights=config.weights,
                    smoothing=config.smoothing, max_steps=max_steps if max_steps is not None else config.max_steps,
                    progress=progress, method=config.method)
    with phase("steps"):
        result = fit(made[0], dataset, starts=made if len(made) > 1 else None, **fit_args)
        reseeded = None
        if result.code != "interrupted" and refine_rounds:
            result, reseeded = refine(config, result, dataset, free, fit_args, log=log, interrupted=interrupted)
    other = []
    try:
        derived = config.derived_values(result.model)
    except (AttributeError, TypeError, ValueError) as e:  # a report's detail must not lose the finished fit
        derived = {}
        other.append(f"the values taken from the data could not be read from the model ({e})")
    return Calibration(result=result, config=config, targets=targets, free=free, start_warnings=start_warnings,
                       reseeded=reseeded, hints=report_hints(config, result), derived=derived, warnings=other)


def _check_targets(config: ModelConfig, dataset: Dataset) -> tuple[str, ...]:
    """The channels to fit, after the checks that name a missing weight, input or unusable record."""
    targets = config.fit_targets(dataset)
    if isinstance(config.weights, dict):
        lacking = [c for c in targets if c not in config.weights]
        if lacking:
            raise PiezojaxValueError(f"{config.source}: [fit] weights: no weight for the target channel "
                                     f"{lacking[0]!r} (the data have it); give one, or set [fit] targets")
    for c in config.inputs:
        dataset.require(c)
    check_fit_data(dataset, targets)
    return targets


def _affordable_starts(config, dataset, num_free: int, starts: list, log: Callable, given: bool = False) -> list:
    """`starts`, or only the first (the one closest to the data) when fitting them together would cost too much."""
    if len(starts) <= 1:
        return starts
    need, have = len(starts) * memory_estimate(config, dataset, num_free), physical_memory()
    if need > MULTI_START_MEMORY or (have is not None and need > 0.5 * have):
        log(f"fitting only the {'first start' if given else 'start closest to the data'}: {len(starts)} starts "
            f"together would need about {need / 2**30:.1f} GiB")
        return starts[:1]
    log(f"{len(starts)} starts {'' if given else '(rule-based and joint cold start) '}fitted together; the best is "
        "kept")
    return starts


def check_fit_data(dataset, targets) -> None:
    """Data problems that would otherwise surface deep inside the initialisation, named by file and column."""
    short = [e for e in dataset if e.n < MIN_FIT_SAMPLES]
    if short:
        e = short[0]
        raise PiezojaxValueError(f"{e._label()} has {e.n} samples; `piezojax fit` needs at least {MIN_FIT_SAMPLES} "
                                 "per record")
    useless = [e for e in dataset if not any(e.has(c) for c in targets)]
    if useless:
        e = useless[0]
        raise PiezojaxValueError(
            f"{e._label()} has none of the fitted channels ({', '.join(targets)}): it would add nothing to the fit; "
            f"its columns are {', '.join(('t', 'v_in') + e.channel_names)} (rename a file's column with --columns "
            "or [data] columns; predict from input-only files with `piezojax predict`)")
    for c in targets:
        having = [e for e in dataset if e.has(c)]
        if having and all(np.ptp(e[c]) == 0 for e in having):
            names = ", ".join(repr(e.source or e.name) for e in having[:3])
            raise PiezojaxValueError(f"column {c!r} is constant in every data file that has it ({names}"
                                     f"{', …' if len(having) > 3 else ''}): there is nothing to fit")
    if all(not np.any(e.v_in) for e in dataset):
        raise PiezojaxValueError("column 'v_in' is zero in every data file: no model can be identified from no "
                                 "excitation")


def memory_estimate(config, dataset, num_free: int) -> int:
    """Bytes the fit is expected to need at its peak: the longest record's forward-mode Jacobian (the solver forms
    it one record at a time on CPU), and the intermediates of the directions formed together (`tangent_block`;
    about twelve floats per sample and direction, times the Bouc–Wen RK4 substeps)."""
    m = max(e.n for e in dataset) * max(1, len(config.outputs))
    together = tangent_block(m, num_free)
    return 8 * m * num_free + 8 * m * (together + 1) * 12 * config.cost() + 200 * 2**20


def _num_free(model, free) -> int:
    """Number of free scalar parameters of `model` for the `free` paths."""
    mask, leaves = jtu.tree_leaves(free_mask(model, free)), jtu.tree_leaves(model)
    return sum(int(np.size(x)) for m, x in zip(mask, leaves) if m is True)


def physical_memory() -> int | None:
    """This machine's memory in bytes (None where it cannot be read)."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, AttributeError):  # pragma: no cover - not POSIX
        return None


def check_memory(config, dataset, num_free: int) -> None:
    """Refuse a fit expected to need more than 80 % of this machine's memory."""
    need, have = memory_estimate(config, dataset, num_free), physical_memory()
    if have is not None and need > 0.8 * have:
        n = max(e.n for e in dataset)
        raise PiezojaxValueError(
            f"the fit would need about {need / 2**30:.1f} GiB ({n} samples in the longest record x {num_free} free "
            f"parameters), more than 80 % of this machine's {have / 2**30:.1f} GiB; resample the records, split long "
            "ones, or fit fewer parameters")


def release_memory_if_long(config, dataset, num_free: int) -> bool:
    """`pj.release_freed_memory()` when the longest record's Jacobian takes more than `RETAIN_MEMORY_BELOW`: a
    process that retains freed memory (`pj.enable_fast_cpu_scans`) gains on short records and holds too much on long
    ones (the benchmark pages give the measurements). Returns whether it released."""
    m = max(e.n for e in dataset) * max(1, len(config.outputs))
    return 8 * m * num_free > RETAIN_MEMORY_BELOW and pj.release_freed_memory()


def report_hints(config, result) -> list[str]:
    """The lines the pipeline adds to the report (`Calibration.hints`): resonances the records cannot resolve
    (`mode_hints`), and after a fit that leaves the residual above the noise (`FitResult.report` says so), where a
    CONFIG left the creep's `structure` to its default (parallel) and the displacement is the worst channel, the
    other one."""
    hints = mode_hints(result)
    worst = lack_of_fit(result.metrics)
    if not result.success or worst is None or worst[2] != "displacement" or config.model_kind is not ACTUATOR:
        return hints
    creep = config.kind("creep")
    given = config.creep_options.structure is not None
    if config.hysteresis_kind.empty or creep.empty or given or len(creep.structures) < 2:
        return hints
    other = next(s for s in creep.structures if s != config.creep_structure)
    return [f"  the creep is in {config.creep_structure} with the hysteresis (the default); `structure = \"{other}\"` "
            f"in [creep] fits the other structure ({'after the hysteresis' if other == 'series' else 'beside it'})",
            *hints]


def mode_hints(result) -> list[str]:
    """Report lines on resonances the records cannot resolve: a fitted `omega` above the Nyquist frequency of the
    finest record (the samples cannot resolve it, whatever its standard error says), and a `zeta` within two
    standard errors of 0 (a nearly undamped mode, where the linearised errors of the mode are not reliable)."""
    steps = [float(e.dt) for e in (result.dataset or [])]
    nyquist = math.pi / min(steps) if steps else math.inf
    out = []
    for name, value, se, status in zip(result.parameter_names, result.values, result.std_errors,
                                       result.std_error_status):
        leaf = name.rsplit(".", 1)[-1]
        if leaf.startswith("omega[") and value > nyquist:
            out.append(f"  {name} = {value:.4g} rad/s is above the Nyquist frequency of the records ({nyquist:.4g} "
                       "rad/s): the samples cannot resolve it, and its value and standard error mean nothing; a lower "
                       "[dynamics] order, or zeros (`zero_pairs`), may describe the records better")
        elif leaf.startswith("zeta[") and status == "finite" and value < 2 * se:
            out.append(f"  {name} = {value:.3g} ± {se:.2g} is within two standard errors of 0 (a nearly undamped "
                       "mode): the records do not determine its damping, and the standard errors of this mode, "
                       "linearised there, are not reliable")
    return out
