"""Fit results: metrics, Gauss–Newton uncertainty, text report, figures, and atomic save/load."""

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

import piezojax as pj
from piezojax import PiezojaxValueError

from . import _plots
from ._config.table import Negative
from ._data import UNITS, experiments_of
from ._predict import predict
from ._problem import estimate_noise_std, free_physical_tree, is_reparam, lost_columns, path_string
from ._stationarity import max_gradient_cosine
from .files import atomic_directory, save_json

# A fit whose residual is this many times the records' white-noise level or more is reported as missing part of
# what the data show. At the noise, the ratio is 1 within a few per cent: `estimate_noise_std` was within 5 % of the
# true noise on the independent plant's records (`experiments.plant_study`), and the RMSE of n white samples within
# about 1/sqrt(2n). Shorter records scatter more (the estimate by about 11 % at 200 samples, 5 % at 1000), so only
# records of LACK_OF_FIT_MIN_SAMPLES or more are judged.
LACK_OF_FIT_RATIO = 1.2
LACK_OF_FIT_MIN_SAMPLES = 1000


def error_metrics(predicted: np.ndarray, measured: np.ndarray) -> dict[str, float | None]:
    """RMSE (channel units), NRMSE and max |error| in % of the measured range, the measurement's white-noise level
    `noise` (`estimate_noise_std`, channel units: the sample-to-sample, white part of the noise; noise correlated
    over samples is underestimated) and `rmse_over_noise` (None for a record without noise above rounding: a noise
    estimate at most 1e-9 of the largest |value|, e.g. noiseless simulated data of a signal slow against the
    sampling)."""
    return _metrics(np.asarray(predicted, float) - np.asarray(measured, float), measured)


def _metrics(e: np.ndarray, measured: np.ndarray) -> dict[str, float | None]:
    """`error_metrics` from the errors `e` = predicted − measured."""

    rng = float(np.ptp(measured))
    rmse = float(np.sqrt(np.mean(e**2)))
    scale = rng if rng > 0 else float("nan")
    noise = estimate_noise_std(measured)
    measured_noise = noise > 1e-9 * float(np.max(np.abs(measured), initial=0.0))
    return {
        "rmse": rmse,
        "nrmse_percent": 100 * rmse / scale,
        "max_error_percent": 100 * float(np.max(np.abs(e))) / scale,
        "range": rng,
        "samples": int(e.size),
        "noise": noise,
        "rmse_over_noise": rmse / noise if measured_noise else None,
    }


def _lack_of_fit_summary(metrics) -> dict | None:
    worst = lack_of_fit(metrics)
    return None if worst is None else {"rmse_over_noise": worst[0], "experiment": worst[1], "channel": worst[2]}


def lack_of_fit(metrics: dict[str, dict[str, dict]]) -> tuple[float, str, str] | None:
    """The largest `rmse_over_noise` of `metrics` (per experiment, per channel, as `FitResult.metrics`) over the
    records of `LACK_OF_FIT_MIN_SAMPLES` samples or more, with its experiment and channel, when it is
    `LACK_OF_FIT_RATIO` or more; else None."""
    worst = max(((m["rmse_over_noise"], name, c) for name, chans in metrics.items() for c, m in chans.items()
                 if m.get("samples", 0) >= LACK_OF_FIT_MIN_SAMPLES and m.get("rmse_over_noise") is not None
                 and math.isfinite(m["rmse_over_noise"])), default=None)
    return worst if worst is not None and worst[0] >= LACK_OF_FIT_RATIO else None


# how a start that did not converge ended, in the report's multi-start line
_START_CODES = {"max_steps_reached": "max_steps"}


@dataclasses.dataclass
class FitResult:
    """What `fitting.solve`/`fitting.fit` return.

    - `model`: the fitted model, ready to use (reparametrisations unwrapped); `params`: the same with its
      reparametrisation wrappers (start a further fit from it).
    - `success`, `reason`, `code`: convergence verdict and why (`"successful"`, `"max_steps_reached"`, `"stalled"`,
      `"interrupted"`, `"nonfinite_initial"`, ...); `steps`, `accepted_steps` (counted over every smoothing level
      and every restart past a kink, so they can exceed `max_steps`, which bounds each), `initial_cost`, `cost`
      ($\\tfrac12\\|r\\|^2$ of the weighted residuals), `history` (the start's and every accepted cost),
      `history_steps` (the step at which each was reached, counted over all levels), `seconds`, `levels` (per
      smoothing level).
    - `parameter_names`, `values`, `std_errors`, `correlation` (and `covariance`, from the two): the free
      parameters in physical units with their
      Gauss–Newton standard errors $\\sqrt{\\mathrm{diag}(D\\,s^2(J^\\top J)^{+}D^\\top)}$, $s^2 = \\|r\\|^2/(m - p)$,
      $D$ the Jacobian of the reparametrisation; `condition`: the condition number of $J^\\top J$ with its
      columns scaled to unit norm at the fitted point, the scaling in which the errors and the undetermined
      directions are computed (so they do not depend on the solver's own scaling, fixed at the start);
      `gradient_cosine`: $\\max_i |\\cos(r, J_{:,i})|$, ≈ 0 at a stationary point. A fit that stops with it above
      `gtol` is probed along ± each parameter, the gradient and the Gauss–Newton step: if the cost rises along all
      of them (one-sided slopes above $-$`gtol` in the same units) it is a minimum at a kink of the piecewise smooth
      model, code `"converged_at_kink"`; else it failed, code `"not_stationary"`. A fit to rounding-level residuals
      is `"converged_zero_residual"`.
    - `std_error_status`: per parameter, `"finite"`, `"infinite"` (a tenth or more of its scaled change lies along a
      direction the data do not determine, or along such a direction it changes by a tenth or more of the largest
      relative change there, e.g. every parameter of a whole-scale redundancy), `"at a bound"` (a constrained entry
      within 1e-9 of its leaf's largest magnitude from zero) or `"not computed"` (no finite Jacobian); the standard
      error of all but the first is reported as infinite for all statuses but `"finite"` (NaN when not computed) and
      their correlations as NaN.
    - `metrics`: per experiment, per target channel: RMSE [channel units], NRMSE and max error in % of range, the
      record's white-noise level `noise` and `rmse_over_noise` (see `error_metrics`); 1 within a few per cent for a
      model that explains the data to their noise, and the report of a converged fit names a lack of fit from
      `LACK_OF_FIT_RATIO` (1.2; records of 1000 samples or more); `summary()`'s `lack_of_fit` gives the worst ratio
      there, converged or not.
    - `starts`: with a multi-start fit (`solve(..., starts=...)`), per start: final `cost`, `success`, `code`,
      `reason`, `steps`, and `best` (the one reported); `None` otherwise. After the command line's re-seeding
      rounds, the first fit's, each with `first_of`, the number of fits run (`best`: the one the second fit
      started from).
    - `repairs`: where `fitting.fit` moved a point at which the model was not finite next to it and fitted again
      (`fitting._stationarity.repair_point`), one line each saying what it moved; `None` otherwise.
    - `u`: the scaled parameters the solver worked with (`Problem.u_of` of `params`), to compare with another
      solver run on `Problem.residuals`.
    - `predictor`, `targets`, `weights`, `dataset`: how the model was fitted (the predictor, the target channels,
      their weights $w_c$) and to which records; `predict` uses the first two, the figures the last. (Not saved.)
    """

    model: Any
    params: Any
    success: bool
    reason: str
    code: str
    steps: int
    accepted_steps: int
    initial_cost: float
    cost: float
    history: list[float]
    history_steps: list[int]
    seconds: float
    levels: list[dict]
    parameter_names: list[str]
    values: np.ndarray
    std_errors: np.ndarray
    std_error_status: list[str]
    correlation: np.ndarray
    condition: float
    gradient_cosine: float
    num_residuals: int
    num_params: int
    metrics: dict[str, dict[str, dict[str, float | None]]]
    starts: list[dict] | None = None
    repairs: list[str] | None = None
    u: Any = dataclasses.field(repr=False, default=None)
    predictor: Any = dataclasses.field(repr=False, default=None)
    targets: tuple[str, ...] = ()
    weights: dict[str, float] = dataclasses.field(default_factory=dict)
    dataset: Any = dataclasses.field(repr=False, default=None)

    @property
    def covariance(self) -> np.ndarray:
        """The covariance matrix of the free parameters in physical units (rows and columns as `parameter_names`),
        `std_errors[i] * std_errors[j] * correlation[i, j]`: the Gauss–Newton covariance of the determined
        parameters, NaN in the rows and columns of those whose `std_error_status` is not `"finite"`."""
        se = np.asarray(self.std_errors, dtype=float)
        finite = np.asarray(self.std_error_status) == "finite"
        with np.errstate(invalid="ignore"):
            cov = np.outer(se, se) * np.asarray(self.correlation, dtype=float)
        cov[~finite, :] = np.nan
        cov[:, ~finite] = np.nan
        return cov

    def summary(self) -> dict:
        """A JSON-ready summary (everything but the models, the predictor and the data)."""
        return {
            "success": self.success,
            "reason": self.reason,
            "code": self.code,
            "steps": self.steps,
            "accepted_steps": self.accepted_steps,
            "initial_cost": self.initial_cost,
            "cost": self.cost,
            "seconds": self.seconds,
            "levels": self.levels,
            "num_residuals": self.num_residuals,
            "num_params": self.num_params,
            "condition": self.condition,
            "gradient_cosine": self.gradient_cosine,
            "parameters": {
                n: {"value": float(v), "std_error": float(s) if st == "finite" else None, "std_error_status": st}
                for n, v, s, st in zip(self.parameter_names, self.values, self.std_errors, self.std_error_status)
            },
            "correlation": np.asarray(self.correlation).tolist(),
            "correlation_names": list(self.parameter_names),  # its rows and columns, as in `parameters`
            "precision": str(np.asarray(self.u).dtype),  # float32: JAX's 64-bit mode was off (7 digits)
            "metrics": self.metrics,
            "lack_of_fit": _lack_of_fit_summary(self.metrics),
            "history": self.history,
            "history_steps": self.history_steps,
            "starts": self.starts,
            "repairs": self.repairs,
        }

    def report(self) -> str:
        """A plain-text report: verdict, cost, parameters ± standard errors, strong correlations, errors."""
        lines = [
            f"fit {'converged' if self.success else 'FAILED'}: {self.reason}",
            f"  steps {self.steps} ({self.accepted_steps} accepted), cost {self.initial_cost:.6e} -> "
            f"{self.cost:.6e}, {self.seconds:.1f} s, {self.num_residuals} residuals, {self.num_params} parameters",
        ]
        if np.asarray(self.u).dtype != np.float64:
            lines.append(f"  computed in {np.asarray(self.u).dtype} (JAX's 64-bit mode off): costs and standard errors "
                         "are good to about 7 digits at best")
        if self.starts:
            ok = sum(st["success"] for st in self.starts)
            fits = self.starts[0].get("first_of", 1)
            # the starts of the first of several fits (the command line's re-seeding rounds, `first_of`): the
            # verdict above is that of the fit kept, and the second fit started from the start marked *
            head = (f"multi-start of the first fit (of {fits}; the second started from *)" if fits > 1
                    else "multi-start")
            lines.append(f"  {head}: {len(self.starts)} starts, {ok} converged; final costs "
                         + ", ".join(f"{st['cost']:.4e}{'*' if st['best'] else ''}"
                                     + ("" if st["success"] else f" ({_START_CODES.get(st['code'], st['code'])})")
                                     for st in self.starts)
                         + ("" if fits > 1 else " (* reported)"))
        for note in self.repairs or ():
            lines.append(f"  start repaired: {note}")
        lines.append("parameters (value ± standard error):")
        w = max(len(n) for n in self.parameter_names)
        for n, v, s, st in zip(self.parameter_names, self.values, self.std_errors, self.std_error_status):
            if st == "finite":
                rel = f"({100 * s / abs(v):.2g} %)" if v != 0 else ""
                lines.append(f"  {n:<{w}}  {v: .6e} ± {s:.2e} {rel}")
            else:
                what = {"infinite": "± inf (not determined by the data)", "at a bound": "(at its constraint's bound)"}
                lines.append(f"  {n:<{w}}  {v: .6e} {what.get(st, '(standard error not computed)')}")
        c = np.asarray(self.correlation)
        strong = [(abs(c[i, j]), i, j) for i in range(len(c)) for j in range(i) if abs(c[i, j]) > 0.99]
        if strong:
            lines.append("strongly correlated pairs (|corr| > 0.99):")
            for a, i, j in sorted(strong, reverse=True)[:10]:
                lines.append(f"  {self.parameter_names[i]} ~ {self.parameter_names[j]}: {c[i, j]:+.4f}")
        lines.append("errors per experiment and channel (RMSE, NRMSE % of range, max % of range, RMSE / noise):")
        for name, chans in self.metrics.items():
            for ch, m in chans.items():
                ratio = m.get("rmse_over_noise")
                lines.append(
                    f"  {name:<20} {ch:<13} {m['rmse']:.4e} {UNITS.get(ch, ''):<2} {m['nrmse_percent']:7.3f} %  "
                    f"{m['max_error_percent']:7.3f} %  " + ("     -" if ratio is None else f"{ratio:6.2f}")
                )
        worst = lack_of_fit(self.metrics)
        if worst is not None and self.success:  # (a fit stopped early may only be short of its minimum)
            lines.append(
                f"lack of fit: the RMSE is {worst[0]:.2f}x the measurement noise in {worst[1]} ({worst[2]}; the worst "
                "record, its noise estimated from its fourth differences): the model misses part of what the data "
                "show, and the standard errors, which take the residual for white noise, understate the uncertainty"
            )
        return "\n".join(lines)

    def predict(self, dataset, history=(), check_finite: bool = True) -> list[dict[str, np.ndarray]]:
        """The fitted model's predicted target channels for each experiment of `dataset` (a `Dataset`, a list of
        experiments or one `Experiment`), each after the records of `history`, by `fitting.predict` (e.g. the
        training record before a held-out record that continues it; `check_finite` as there). Any record length
        works. `result.predict(result.dataset)` are the fitted records' predictions."""

        out = []
        for e in experiments_of(dataset):
            preds = predict(self.model, e, predictor=self.predictor, history=history, check_finite=check_finite)
            out.append({c: y for c, y in preds.items() if c in self.targets})
        return out

    def save(self, path, overwrite: bool = False, figures: bool = True, extra: dict | None = None) -> Path:
        """Write `path/` atomically: `model.eqx` (equinox serialisation of `params`), `result.json` (summary plus
        `extra`), `report.txt` and, with `figures=True`, PNG figures. Nothing appears at `path` unless all succeed.

        `overwrite=True` replaces only a folder written by an earlier `save` (or `piezojax fit`), recognised by its
        marker file, and holding nothing but what was written then (see `fitting.files.atomic_directory`); never the
        working directory or a folder containing it."""

        path = Path(path)
        with atomic_directory(path, overwrite=overwrite, kind="fit") as tmp:
            self.write_files(tmp, figures=figures, extra=extra)
        return path

    def write_files(self, folder, figures: bool = True, extra: dict | None = None, input_unit: str = "V") -> None:
        """Write the files of `save` into the existing folder `folder` (not atomically: for a caller that writes
        into a temporary folder of its own); `input_unit` as in `fitting.save_figures`."""

        folder = Path(folder)
        eqx.tree_serialise_leaves(folder / "model.eqx", self.params)
        summary = self.summary()
        if extra:
            summary.update(extra)
        summary["model_structure"] = model_structure(self.params)
        save_json(folder / "result.json", summary)
        (folder / "report.txt").write_text(self.report() + "\n")
        if figures:

            _plots.save_figures(self, folder, input_unit=input_unit)

    def plot(self, kind: str = "timeseries", experiment=0):
        """One figure of the fit (a `matplotlib.figure.Figure`, in engineering units): `kind` is `"timeseries"`
        (measured, model and residual against time), `"loops"` (against `v_in`), `"parameters"` (relative standard
        errors and correlations) or `"convergence"` (cost per step); `experiment` (index or name in the fit's
        dataset) for the first two. See `fitting.plot_timeseries` and its siblings.

        ```python
        result.plot("loops", experiment="run3").savefig("loops.png")
        ```
        """

        if kind == "timeseries":
            return _plots.plot_timeseries(self, experiment)
        if kind == "loops":
            return _plots.plot_loops(self, experiment)
        if kind == "parameters":
            return _plots.plot_parameters(self)
        if kind == "convergence":
            return _plots.plot_convergence(self)
        raise PiezojaxValueError(f"`kind` must be 'timeseries', 'loops', 'parameters' or 'convergence', got {kind!r}")


def _at_bound(problem, u) -> np.ndarray:
    """Per free parameter: an entry of a leaf constrained away from zero (`pj.Positive`, `pj.OrderedPositive`,
    `pj.Fractions`, negative poles) pressed against that bound, i.e. within 1e-9 of the largest magnitude in its
    leaf of zero (a dead play weight, a vanished lag fraction)."""

    flags = []
    params = problem.params(u)
    flat = jtu.tree_flatten_with_path(params, is_leaf=is_reparam)[0]
    zero_bounded = (pj.Positive, pj.OrderedPositive, pj.Fractions, Negative)
    reparam = {path_string(p) for p, leaf in flat if isinstance(leaf, zero_bounded)}
    for path, value in free_physical_tree(params, problem.mask).items():
        a = np.abs(np.ravel(np.asarray(value, dtype=float)))
        top = a.max() if a.size else 0.0
        flags += list((a <= 1e-9 * top) & (path in reparam) & (a.size > 1)) if top > 0 else [False] * a.size
    return np.asarray(flags, dtype=bool)


def _std_error_status(s) -> str:
    """How to read a standard error in `result.json`, where JSON can hold neither inf nor NaN (both are `null`):
    `"finite"`, `"infinite"` (the data do not determine the parameter) or `"not computed"` (no finite Jacobian)."""
    s = float(s)
    if np.isfinite(s):
        return "finite"
    return "infinite" if np.isinf(s) else "not computed"


def model_structure(params) -> list[str]:
    """`"path: kind"` for every parameter leaf of `params`, the kind a reparametrisation's class name (e.g.
    `"hysteresis.thresholds: OrderedPositive"`) or `"array"`: what `load_model` checks `like` against, since the
    saved leaves alone cannot tell a constrained model's internal values from physical ones."""

    out = []
    for path, leaf in jtu.tree_flatten_with_path(params, is_leaf=is_reparam)[0]:
        if is_reparam(leaf):
            out.append(f"{path_string(path)}: {type(leaf).__name__}")
        elif eqx.is_array(leaf):
            out.append(f"{path_string(path)}: array")
    return out


def load_model(path, like):
    """Load the fitted (reparametrised) parameters saved by `FitResult.save` into a model of the structure of
    `like` (the model the fit started from, with the same reparametrisations: `pj.OrderedPositive`, ...), and
    return the unwrapped model. The folder's `result.json` must be beside the model file: it records the saved
    reparametrisations, and a `like` whose parameters are reparametrised differently is an error, not a silent
    reading of internal values as physical (a missing `result.json` is an error naming it)."""
    path = Path(path)
    f = path / "model.eqx" if path.is_dir() else path
    if not f.exists():
        raise PiezojaxValueError(f"no saved model at {f}")
    summary = f.parent / "result.json"
    if not summary.is_file():
        raise PiezojaxValueError(f"{str(summary)!r} is missing: it records how {f.name} stores the parameters (their "
                                 "reparametrisations), without which its values cannot be read; keep the folder "
                                 "`FitResult.save` wrote whole")
    try:
        saved = json.loads(summary.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise PiezojaxValueError(f"cannot read {str(summary)!r} ({e})") from e
    saved = saved.get("model_structure") if isinstance(saved, dict) else None  # None: saved before it was recorded
    if isinstance(saved, list):
        given = model_structure(like)
        if saved != given:
            diff = next((f"saved {a!r}, `like` has {b!r}" for a, b in zip(saved, given) if a != b),
                        f"{len(saved)} saved parameter leaves, {len(given)} in `like`")
            raise PiezojaxValueError(f"{f}: `like` does not have the structure of the saved model ({diff}); pass "
                                     "the model the fit started from, with the same reparametrisations")
    try:
        params = eqx.tree_deserialise_leaves(f, like)
    except Exception as e:  # noqa: BLE001
        raise PiezojaxValueError(f"{f}: cannot load the model into the given structure ({e})") from e
    return pj.unwrap(params)


def load_summary(path) -> dict:
    """The `result.json` summary saved by `FitResult.save`."""
    f = Path(path) / "result.json"
    if not f.exists():
        raise PiezojaxValueError(f"no result summary at {f}")
    return json.loads(f.read_text())


def summarise(problem, u, lin, verdict, *, steps, accepted, history, seconds, levels, history_steps=None,
              starts=None) -> FitResult:
    r"""The `FitResult` of `problem` at the scaled parameters `u` with the solver's `verdict` (`fitting.Verdict`):
    metrics, covariance and standard errors, all from `lin`, the linearisation at `u` (`fitting.Linearisation`, as
    the solver formed it): no further simulation or Jacobian."""
    r, jtr, jtj = (np.asarray(x) for x in (lin.r, lin.g, lin.h))
    m, p = problem.num_residuals, problem.num_params
    cost = 0.5 * float(np.sum(r**2))
    s2 = 2 * cost / max(m - p, 1)
    finite = bool(np.all(np.isfinite(r)) and np.all(np.isfinite(jtj)) and np.all(np.isfinite(jtr)))
    if not finite:  # e.g. a fit that failed at a non-finite start: no uncertainty can be computed
        jtr, jtj = np.zeros_like(jtr), np.zeros_like(jtj)
    # In the Jacobi scaling of the fitted point, z_j = c_j u_j with c_j the norm of J's column j (a lost column,
    # `lost_columns`, zeroed): which directions the data determine, and the errors, then do not depend on the
    # solver's scaling of u, frozen at the start (measured before: the same Bouc–Wen optimum, started from n = 1 and
    # from n = 2, had A, beta and gamma determined to 0.2-6 % in one report and "infinite" in the other).

    diag = np.clip(np.diag(jtj), 0.0, None)
    # a lost column is judged in the start values' relative changes (value scaling), whatever the solver's scaling
    to_value = (np.asarray(problem.value_scales, float) / np.asarray(problem.scales, float)) ** 2
    lost = lost_columns(diag * to_value)  # zero columns too
    c = np.where(lost, 1.0, np.sqrt(diag))
    scaled_jtj = jtj / np.outer(c, c)
    scaled_jtj[lost, :] = 0.0
    scaled_jtj[:, lost] = 0.0
    evals, evecs = np.linalg.eigh(scaled_jtj)
    top = evals.max() if evals.size else 0.0
    keep = evals > top * 1e-14 * p
    inv = (evecs[:, keep] / evals[keep]) @ evecs[:, keep].T
    cov_z = s2 * inv
    d = np.asarray(problem.physical_jacobian(u)) / c[None, :]  # physical parameters per z
    cov = d @ cov_z @ d.T
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    status = np.full(se.shape, "finite", dtype=object)
    if not np.all(keep):
        # Directions the data do not determine. A parameter is undetermined (infinite standard error) when it
        # moves along them by either measure:
        # - scaled: a tenth or more of its change (in z) lies along one of them (a sum a + b of two parameters,
        #   whatever their values);
        # - relative: along them each parameter changes by a relative amount a_i (a row vector over a basis of
        #   those directions; per |value| + standard error), and along the direction that moves parameter i most
        #   (a_i / |a_i|) it changes by a tenth or more of the largest relative change there,
        #   |a_i|^2 >= 0.1 max_j |a_j . a_i| (a small parameter of a whole-scale redundancy — every play weight
        #   times c, the gain divided by c — counts as fully as a large one; unrelated undetermined directions do
        #   not mask each other).
        # The others keep the finite errors of the pseudo-inverse, i.e. with the undetermined combination held
        # fixed (touching it by 1e-3 does not make a parameter unknown).
        move = d @ evecs[:, ~keep]  # each parameter's change along an orthonormal basis of those directions (in z)
        reach = np.abs(d).max(axis=1)
        scaled = np.abs(move).max(axis=1) / np.maximum(reach, 1e-300)
        size = np.maximum(np.abs(np.asarray(problem.physical(u))) + se, 1e-9 * reach)
        a = move / np.maximum(size, 1e-300)[:, None]
        overlap = np.abs(a @ a.T)
        own = np.diag(overlap)
        relative = np.where(own > 0, own / np.maximum(overlap.max(axis=0), 1e-300), 0.0)
        status[(scaled >= 0.1) | (relative >= 0.1)] = "infinite"
    status[_at_bound(problem, u)] = "at a bound"
    # the correlations of the determined parameters, from the covariance before the others are marked
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(se, se)
    corr[status != "finite", :] = np.nan
    corr[:, status != "finite"] = np.nan
    np.fill_diagonal(corr, np.where(status == "finite", 1.0, np.nan))
    se = np.where(status == "finite", se, np.inf)
    condition = float(top / evals.min()) if evals.size and evals.min() > 0 else float("inf")
    if not finite:
        se, corr = np.full_like(se, np.nan), np.full_like(corr, np.nan)
        status[:] = "not computed"

    # the errors are the residuals unweighted: no further simulation
    metrics = {}
    for exp, errors in zip(problem.dataset, problem.experiment_errors(r)):
        metrics[exp.name] = {c: _metrics(e, exp.channels[c][exp.first_scored:]) for c, e in errors.items()}
    params = problem.params(u)
    return FitResult(
        model=pj.unwrap(params),
        params=params,
        success=verdict.success,
        reason=verdict.reason,
        code=verdict.code,
        steps=int(steps),
        accepted_steps=int(accepted),
        initial_cost=float(history[0]) if history else cost,
        cost=cost,
        history=[float(h) for h in history],
        history_steps=list(range(len(history))) if history_steps is None else [int(k) for k in history_steps],
        seconds=float(seconds),
        levels=levels,
        parameter_names=problem.parameter_names(),
        values=np.asarray(problem.physical(u)),
        std_errors=se,
        std_error_status=[str(x) for x in status],
        correlation=corr,
        condition=condition,
        gradient_cosine=max_gradient_cosine(r, jtr, jtj),
        num_residuals=m,
        num_params=p,
        metrics=metrics,
        starts=starts,
        u=jnp.asarray(u),
        predictor=problem.predictor,
        targets=tuple(problem.targets),
        weights=dict(problem.weights),
        dataset=problem.dataset,
    )
