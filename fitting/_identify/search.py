r"""`identify`: find the structure of an actuator's model from its records, then calibrate it.

The search is greedy, by stages, each fitting the current structure's neighbours in one respect and keeping the one
`select` keeps among them and the current one (`validation.py`): the initial state (a fitted prehistory; first, since
a record that starts away from the hysteresis' rest misleads every later comparison), the dynamics (0, 1, 2, 4 poles;
before the creep, since a creep fitted without a resonance the data have bends to mimic it), the creep (none;
Kelvin–Voigt or lag, in series or in parallel; logarithmic), the hysteresis kind (every kind of `HYSTERESIS_KINDS`,
so each is fitted and ranked once), the creep again (for the kind kept), one more creep lag, then twice the plays or
elements, zeros of the dynamics, an output polynomial, a prehistory (where the first stage did not keep one) and an
input delay (`EXTRAS`), one stage each, each adding to the structure kept so far. It starts from `START`. A candidate
is fitted once (a stage that meets it again reuses its fit), without the refinement rounds (`calibrate(...,
refine_rounds=False)`) and with at most `CANDIDATE_MAX_STEPS` steps, from two starts together: its parent's fit (the
stage's current structure) for the blocks it shares with it (`warm_start`, `shared_blocks`), and its own data-driven
start (`_warm_and_own`: the joint cold start only where it changes the parent's hysteresis or creep). Finally the
structure `select` keeps among every candidate is calibrated on every record with the whole pipeline
(`fitting.calibrate`).
"""

import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

import piezojax as pj
from piezojax import PiezojaxValueError

from .. import files
from .._calibrate import Calibration, calibrate
from .._config import ModelConfig, parse_config
from .._data import Dataset, experiments_of
from .._refine import silent
from .._results import LACK_OF_FIT_RATIO
from .structures import (
    EXTRAS,
    Structure,
    creep_neighbours,
    deeper_creep,
    dynamics_neighbours,
    extra_neighbours,
    fixed_tables,
    hysteresis_neighbours,
)
from .validation import Split, Z, scaled_errors, score, select, split

START = Structure("prandtl_ishlinskii", 8, creep="kelvin_voigt", creep_order=1, creep_structure="series")
"""Where the search starts: PI(8) with one Kelvin–Voigt lag in series, no dynamics."""

CANDIDATE_MAX_STEPS = 300
"""Steps of a candidate's fit (the chosen structure's final fit takes the CONFIG's `[fit] max_steps`)."""


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One structure the search fitted: its CONFIG, its fit on the training records, its number of fitted
    parameters, its training and validation scores (RMSE over the noise), its fit's code and time, and what its fit
    repaired (`FitResult.repairs`: a start at which the model was not finite next to it, moved)."""

    structure: Structure
    config: ModelConfig
    parameters: int
    training: float
    validation: float
    code: str
    seconds: float
    errors: np.ndarray = dataclasses.field(repr=False)
    repairs: tuple[str, ...] = ()

    def row(self) -> dict:
        return {"structure": self.structure.label(), "config": self.config.text, "parameters": self.parameters,
                "training_rmse_over_noise": self.training, "validation_rmse_over_noise": self.validation,
                "code": self.code, "seconds": round(self.seconds, 3), "repairs": list(self.repairs)}


@dataclasses.dataclass(frozen=True)
class Identification:
    """What `identify` returns: the chosen structure calibrated on every record (`calibration`), every candidate in
    the order fitted, which one was kept and which were within the best's uncertainty, the split and the time."""

    calibration: Calibration
    candidates: list[Candidate]
    kept: int
    within: list[bool]
    split: str
    seconds: float
    final_seconds: float  # of which the final calibration

    @property
    def chosen(self) -> Candidate:
        return self.candidates[self.kept]

    def table(self) -> str:
        """The ranking: one line per candidate, best validation score first, the one kept marked `*`, those within
        the best's uncertainty `~`."""
        order = sorted(range(len(self.candidates)), key=lambda i: self.candidates[i].validation)
        width = max(len(c.structure.label()) for c in self.candidates)
        lines = [f"structure identification: {len(self.candidates)} candidates fitted in "
                 f"{self.seconds - self.final_seconds:.0f} s, the one kept calibrated on every record in "
                 f"{self.final_seconds:.0f} s (the whole search {self.seconds / max(self.final_seconds, 1e-9):.1f}x "
                 f"that calibration); {self.split}",
                 f"  kept: the fewest parameters within {Z:g} standard errors of the best validation score "
                 "(* kept, ~ within)",
                 f"    {'structure':<{width}}  params  train/noise  valid/noise  seconds  code"]
        for i in order:
            c = self.candidates[i]
            mark = "*" if i == self.kept else "~" if self.within[i] else " "
            lines.append(f"  {mark} {c.structure.label():<{width}}  {c.parameters:>6}  {c.training:>11.3f}  "
                         f"{c.validation:>11.3f}  {c.seconds:>7.1f}  {c.code}{' (repaired)' if c.repairs else ''}")
        lines += [f"  repaired, {c.structure.label()}: {note}" for c in self.candidates for note in c.repairs]
        if not self.reached_noise:
            best = min(self.candidates, key=lambda c: c.validation)
            lines.append(f"  no structure reached the noise in validation: the best, {best.structure.label()}, "
                         f"predicts the validation samples at {best.validation:.2f}x the noise (one that explains "
                         f"the data to their noise scores about 1; {LACK_OF_FIT_RATIO:g} or more is a lack of fit): "
                         "the actuator shows something none of the searched structures has (e.g. a hysteresis that "
                         "depends on the rate of the drive), or the records something the model does not (drift, "
                         "a disturbance)")
        return "\n".join(lines)

    @property
    def reached_noise(self) -> bool:
        """Whether the best candidate predicts the validation samples to within `LACK_OF_FIT_RATIO` (1.2) times
        the noise."""
        return min(c.validation for c in self.candidates) < LACK_OF_FIT_RATIO

    def report(self) -> str:
        return self.table() + "\n\n" + self.calibration.report()

    def summary(self) -> dict:
        """The `identification` entry of `result.json`."""
        return {"candidates": [c.row() for c in self.candidates], "kept": self.kept, "within": self.within,
                "split": self.split, "seconds": round(self.seconds, 3), "final_seconds": round(self.final_seconds, 3),
                "chosen": self.chosen.structure.label(), "reached_noise": self.reached_noise,
                "rule": f"the fewest fitted parameters whose mean squared validation error over the noise exceeds "
                        f"the best's by at most {Z:g} standard errors of the difference (its noise part)"}

    def write_files(self, folder, *, figures: bool = True, **summary) -> None:
        """The calibration's fit folder files (`Calibration.write_files`; its `config.toml` the structure kept),
        with the ranking first in `report.txt` and `identification` in `result.json`."""
        folder = Path(folder)
        self.calibration.write_files(folder, figures=figures, **summary)
        result = json.loads((folder / "result.json").read_text())
        result["identification"] = self.summary()
        files.save_json(folder / "result.json", result)
        files.atomic_write_text(folder / "report.txt", self.report() + "\n")

    def save(self, path, *, overwrite: bool = False, figures: bool = True, **summary) -> Path:
        """Write the fit folder `path/` atomically (see `Calibration.save`)."""
        path = Path(path)
        with files.atomic_directory(path, overwrite=overwrite, kind="fit") as tmp:
            self.write_files(tmp, figures=figures, **summary)
        return path


def identify(dataset, *, base: str | ModelConfig | None = None, max_steps: int | None = None,
             progress: bool = False, log: Callable = silent) -> Identification:
    """Search the structure of an actuator's model (`pj.Actuator`) on `dataset`, then calibrate the one kept.

    **Arguments:**

    - `dataset`: a `Dataset`, an `Experiment` or a list of them, with `displacement` (see `validation.split` for
      how they are divided between fitting and validation).
    - `base`: a CONFIG (its text, or a `ModelConfig`) whose tables are fixed: the search leaves a `[hysteresis]`,
      `[creep]`, `[dynamics]`, `[state]` or `[input]` it gives as it is, and its `[fit]` and `[data]` apply to every
      candidate; it may give no model table (e.g. only `[data]`, how the records are read; see `parse_base`).
    - `max_steps`: the final fit's steps (default: the CONFIG's `[fit] max_steps`).
    - `progress`, `log`: as for `fitting.calibrate` (`log` gets one line per candidate).

    **Returns:** an `Identification`: `.calibration` the calibrated model of the structure kept (`.save(path)` as
    `piezojax fit` writes it; its `config.toml` is that structure's CONFIG), `.table()` the ranking.

    ```python
    ident = fitting.identify(fitting.Dataset.from_files(["run1.csv", "run2.csv"]))
    print(ident.table()); ident.calibration.save("fits/auto")
    ```
    """
    t0 = time.perf_counter()
    base_text = base.text if isinstance(base, ModelConfig) else (base or "")
    fixed = fixed_tables(base_text)
    parse_base(base_text)
    if not isinstance(dataset, Dataset):
        dataset = Dataset(experiments_of(dataset))
    if not all(e.has("displacement") for e in dataset):
        raise PiezojaxValueError("the identification fits displacement: every record needs a 'displacement' column")
    parts = split(dataset)
    log(f"structure identification: {parts.description}")
    search = _Search(parts, base_text, fixed, log)
    current = search.stage([START], None)
    # the initial state first: a record that starts away from the hysteresis' rest (the sensor's reading before the
    # drive, a history of earlier drives) misleads every later comparison while it is not modelled
    current = search.stage(extra_neighbours(current, "prehistory"), current)
    for neighbours in (dynamics_neighbours, creep_neighbours, hysteresis_neighbours, creep_neighbours, deeper_creep):
        current = search.stage(neighbours(current), current)
    for what in EXTRAS:
        current = search.stage(extra_neighbours(current, what), current)
    kept, within = select([c.errors for c in search.candidates], [c.parameters for c in search.candidates])
    chosen = search.candidates[kept]
    log(f"kept {chosen.structure.label()}; calibrating it on every record")
    t_final = time.perf_counter()
    cal = calibrate(chosen.config, dataset, max_steps=max_steps, progress=progress, log=log)
    now = time.perf_counter()
    return Identification(cal, search.candidates, kept, within, parts.description, now - t0, now - t_final)


def warm_start(config, start, fitted, shared: set[str]):
    """`start` (a candidate's data-driven start, reparametrised as `ModelConfig.starts` returns it) with the blocks
    of `shared` (`shared_blocks`) at their values in `fitted` (the parent's fitted model), where their parameter
    shapes agree; an output polynomial the candidate adds keeps its own coefficients around the parent's operator."""
    model = pj.unwrap(start)
    if "dynamics poles" in shared:
        model = _with_poles(model, fitted.dynamics)
    if "hysteresis plays" in shared:
        model = _with_more_plays(model, fitted.hysteresis)
    for name in ("hysteresis", "creep", "dynamics", "offset", "prehistory", "delay"):
        if name not in shared or not hasattr(model, name):
            continue
        where = lambda m, name=name: getattr(m, name)  # noqa: E731
        mine, theirs = where(model), getattr(fitted, name, None)
        if isinstance(mine, pj.OutputPolynomial) and not isinstance(theirs, pj.OutputPolynomial):
            where = lambda m: m.hysteresis.hysteresis  # noqa: E731  (an output polynomial added to the parent's)
            mine = where(model)
        if _alike(mine, theirs):
            model = eqx.tree_at(where, model, theirs)
    return config.constrain(model)


def _warm_and_own(config, dataset, fitted, shared: set[str]) -> list:
    """A candidate's two starts: from its parent's fit (`warm_start`) and its own data-driven start. Where it keeps
    the parent's hysteresis and creep, that is the rule-based start (the parent's fit stands in for the joint cold
    start); where it changes either, the one closest to the data of the rule-based and the joint cold start (the
    parent's other blocks were fitted around another hysteresis or creep: measured on the 150 V record, series
    creeps started from a parallel creep's fit without the cold start fitted 18x the noise in training, against
    3.4-3.7x with it)."""
    own = config.starts(dataset, cold_start=not {"hysteresis", "creep"} <= shared)[0]
    try:
        return [warm_start(config, own, fitted, shared), own]
    except PiezojaxValueError:  # a fitted value the candidate's reparametrisation refuses (at its bound)
        return [own]


def shared_blocks(child: Structure, parent: Structure) -> set[str]:
    """The parts of `child` that are `parent`'s: the hysteresis (its kind and size; an output polynomial may be
    added), the creep (kind, order and structure), the dynamics (poles and zeros; `"dynamics poles"` where the
    child adds zeros to the parent's poles), and the offset, prehistory and delay."""
    out = {"offset", "prehistory", "delay"}
    if (child.hysteresis, child.elements) == (parent.hysteresis, parent.elements) and (
            child.polynomial in (0, parent.polynomial) or not parent.polynomial):
        out.add("hysteresis")
    elif (child.hysteresis == parent.hysteresis in ("prandtl_ishlinskii", "play")
          and child.elements > parent.elements and child.polynomial == parent.polynomial):
        out.add("hysteresis plays")  # more plays than the parent's: its plays kept, new ones between them
    if (child.creep, child.creep_order, child.creep_structure) == (parent.creep, parent.creep_order,
                                                                   parent.creep_structure):
        out.add("creep")
    if (child.dynamics, child.zeros) == (parent.dynamics, parent.zeros):
        out.add("dynamics")
    elif child.dynamics == parent.dynamics and not parent.zeros:
        out.add("dynamics poles")  # zeros added to the parent's poles
    return out


def _with_more_plays(model, fitted):
    """`model` whose PI or play operator has more plays than `fitted`'s (the parent's fitted hysteresis, of the same
    kind, output polynomial and all): the parent's plays at their thresholds and weights (its `w0`, coefficients
    and scale too), the others at thresholds halfway between the parent's (past the last one by half its last
    spacing, once there is no gap left) with 1e-3 of the largest weight (a zero weight is a flat spot of the
    Positive map): the parent's model to within those small weights, so the child starts where its parent ended."""
    mine = model.hysteresis
    inner = lambda h: h.hysteresis if isinstance(h, pj.OutputPolynomial) else h  # noqa: E731
    a, b = inner(mine), inner(fitted)
    if type(a) is not type(b) or type(mine) is not type(fitted) or not hasattr(a, "thresholds"):
        return model
    r, w = np.asarray(b.thresholds, float), np.asarray(b.weights, float)
    n = np.size(a.thresholds)
    if n <= r.size or r.size < 2:
        return model
    extra = list(0.5 * (r[1:] + r[:-1]))
    step = r[-1] - r[-2]
    while len(extra) < n - r.size:
        extra.append(r[-1] + 0.5 * step * (len(extra) - r.size + 2))
    extra = np.asarray(extra[: n - r.size])
    thresholds = np.concatenate([r, extra])
    weights = np.concatenate([w, np.full(extra.size, 1e-3 * float(np.max(w)))])
    order = np.argsort(thresholds, kind="stable")
    new = eqx.tree_at(lambda h: (h.thresholds, h.weights), a, (jnp.asarray(thresholds[order], a.thresholds.dtype),
                                                                jnp.asarray(weights[order], a.weights.dtype)))
    if hasattr(a, "w0"):
        new = eqx.tree_at(lambda h: h.w0, new, b.w0)
    if isinstance(mine, pj.OutputPolynomial):
        new = eqx.tree_at(lambda h: h.hysteresis, fitted, new)
    return eqx.tree_at(lambda m: m.hysteresis, model, new)


def _with_poles(model, fitted):
    """`model` whose dynamics adds zeros to `fitted`'s (the parent's fitted dynamics, the same poles): its gain and
    poles at `fitted`'s, each zero pair at 1.25 times its pole pair's frequency with its damping, each real zero at
    1.25 times its real pole (the CONFIG's start rule, around the fitted poles)."""
    mine = model.dynamics
    fields = ("gain", "omega", "zeta", "poles")
    if not all(np.shape(getattr(mine, f)) == np.shape(getattr(fitted, f)) for f in fields):
        return model
    values = [getattr(fitted, f) for f in fields]
    m2, m1 = np.size(mine.zero_omega), np.size(mine.zeros)
    if m2 <= np.size(fitted.omega):
        fields += ("zero_omega", "zero_zeta")
        values += [1.25 * fitted.omega[:m2], fitted.zeta[:m2]]
    if m1 <= np.size(fitted.poles):
        fields += ("zeros",)
        values += [1.25 * fitted.poles[:m1]]
    return eqx.tree_at(lambda m: tuple(getattr(m.dynamics, f) for f in fields), model,
                       tuple(jnp.asarray(v, getattr(mine, f).dtype) for f, v in zip(fields, values)))


def _alike(a, b) -> bool:
    """Whether `b` can stand for `a`: both present, of one type, tree structure and leaf shapes."""
    if a is None or b is None or type(a) is not type(b) or jtu.tree_structure(a) != jtu.tree_structure(b):
        return False
    return all(np.shape(x) == np.shape(y) for x, y in zip(jtu.tree_leaves(a), jtu.tree_leaves(b)))


def parse_base(text: str, source: str = "the base CONFIG") -> ModelConfig:
    """A base CONFIG (its text) checked as the search will use it: completed with `START`'s tables that it does not
    give (a base may give no model table at all: only `[data]` or `[fit]`). Returns that completed `ModelConfig`
    (its `data` is how the records are read); a bad base raises one `PiezojaxValueError` naming `source`."""
    return parse_config(START.toml(text), source)


class _Search:
    """The candidates fitted so far, by structure (each fitted once)."""

    def __init__(self, parts: Split, base: str, fixed: set[str], log: Callable):
        self.parts, self.base, self.fixed, self.log = parts, base, fixed, log
        self.candidates: list[Candidate] = []
        self.by_structure: dict[Structure, int] = {}
        self.models: dict[Structure, object] = {}  # each fitted candidate's model (unwrapped), its children's start
        v = np.concatenate([e.v_in for e in parts.training])
        self.inputs = (float(np.min(v)), float(np.max(v)))  # the voltages' span: a Preisach grid's range

    def stage(self, structures: list[Structure], current: Structure | None) -> Structure:
        """Fit the structures not fitted yet; the one `select` keeps among them and `current`."""
        indices = [] if current is None else [self.by_structure[current]]
        for s in structures:
            s = self._effective(s)
            if s is None:
                continue
            if s not in self.by_structure:
                self.by_structure[s] = len(self.candidates)
                self.candidates.append(self._fit(s, current))
            indices.append(self.by_structure[s])
        indices = list(dict.fromkeys(indices))
        fitted = [self.candidates[i] for i in indices]
        if not any(np.isfinite(c.validation) for c in fitted):
            return current if current is not None else fitted[0].structure
        kept, _ = select([c.errors for c in fitted], [c.parameters for c in fitted])
        return fitted[kept].structure

    def _effective(self, s: Structure) -> Structure | None:
        """`s` as the base CONFIG leaves it (a fixed table's part is the base's, so it is not varied), or None when
        the CONFIG cannot express it."""
        if not s.valid():
            return None
        reset = {}
        if "hysteresis" in self.fixed:
            reset |= dict(hysteresis=START.hysteresis, elements=START.elements, polynomial=0)
        if "creep" in self.fixed:
            reset |= dict(creep="none", creep_order=1, creep_structure="parallel")
        if "dynamics" in self.fixed:
            reset |= dict(dynamics=0, zeros=0)
        if "state" in self.fixed:
            reset |= dict(prehistory=False)
        if "input" in self.fixed:
            reset |= dict(delay=False)
        return dataclasses.replace(s, **reset).normal()

    def _fit(self, s: Structure, parent: Structure | None) -> Candidate:
        t0 = time.perf_counter()
        text = s.toml(self.base, inputs=self.inputs)
        config = parse_config(text, f"candidate {s.label()}")
        config = dataclasses.replace(config, max_steps=min(config.max_steps, CANDIDATE_MAX_STEPS))
        fitted = None if parent is None else self.models.get(parent)
        try:
            cal = calibrate(config, self.parts.training, progress=False, refine_rounds=False,
                            starts=None if fitted is None else lambda cfg, data: _warm_and_own(
                                cfg, data, fitted, shared_blocks(s, parent)))
        except PiezojaxValueError as e:
            self.log(f"  {s.label()}: not fitted ({e})")
            return Candidate(s, config, 0, np.inf, np.inf, "not_fitted", time.perf_counter() - t0,
                             np.full(1, np.nan))
        result = cal.result
        errors = scaled_errors(result.model, config.predictor(), self.parts.validation, cal.targets)
        training = max((m.get("rmse_over_noise") or np.nan for chans in result.metrics.values()
                        for m in chans.values()), default=np.nan)
        c = Candidate(s, config, len(result.parameter_names), float(training), score(errors), result.code,
                      time.perf_counter() - t0, errors, tuple(result.repairs or ()))
        self.models[s] = result.model
        self.log(f"  {s.label()}: {c.parameters} parameters, RMSE/noise {c.training:.3f} training, "
                 f"{c.validation:.3f} validation ({c.code}, {c.seconds:.1f} s)")
        return c
