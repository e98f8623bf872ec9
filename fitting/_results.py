"""Fit results: metrics, Gauss–Newton uncertainty, text report, figures, and atomic save/load."""

import dataclasses
import json
from pathlib import Path
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import piezojax as pj
from piezojax._checks import PiezojaxValueError


def error_metrics(predicted: np.ndarray, measured: np.ndarray) -> dict[str, float]:
    """RMSE (channel units), NRMSE and max |error| in % of the measured range."""
    return _metrics(np.asarray(predicted, float) - np.asarray(measured, float), measured)


def _metrics(e: np.ndarray, measured: np.ndarray) -> dict[str, float]:
    """`error_metrics` from the errors `e` = predicted − measured."""
    rng = float(np.ptp(measured))
    rmse = float(np.sqrt(np.mean(e**2)))
    scale = rng if rng > 0 else float("nan")
    return {
        "rmse": rmse,
        "nrmse_percent": 100 * rmse / scale,
        "max_error_percent": 100 * float(np.max(np.abs(e))) / scale,
        "range": rng,
        "samples": int(e.size),
    }


@dataclasses.dataclass
class FitResult:
    """What `fitting.solve`/`fitting.fit` return.

    - `model`: the fitted model, ready to use (reparametrisations unwrapped); `params`: the same with its
      reparametrisation wrappers (start a further fit from it).
    - `success`, `reason`, `code`: convergence verdict and why (`"successful"`, `"max_steps_reached"`, `"stalled"`,
      `"interrupted"`, `"nonfinite_initial"`, ...); `steps`, `accepted_steps`, `initial_cost`, `cost`
      ($\\tfrac12\\|r\\|^2$ of the weighted residuals), `history` (the start's and every accepted cost),
      `history_steps` (the step at which each was reached, counted over all levels), `seconds`, `levels` (per
      smoothing level).
    - `parameter_names`, `values`, `std_errors`, `correlation`: the free parameters in physical units with their
      Gauss–Newton standard errors $\\sqrt{\\mathrm{diag}(D\\,s^2(J^\\top J)^{+}D^\\top)}$, $s^2 = \\|r\\|^2/(m - p)$,
      $D$ the Jacobian of the reparametrisation; `condition`: the condition number of $J^\\top J$ (scaled);
      `gradient_cosine`: $\\max_i |\\cos(r, J_{:,i})|$, ≈ 0 at a stationary point (a fit that stops with it above
      `gtol` is reported as failed, code `"not_stationary"`).
    - `metrics`: per experiment, per target channel: RMSE [channel units], NRMSE and max error in % of range.
    - `starts`: with a multi-start fit (`solve(..., starts=...)`), per start: final `cost`, `success`, `code`,
      `reason`, `steps`, and `best` (the one reported); `None` otherwise.
    - `problem`: the `Problem` (not saved).
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
    correlation: np.ndarray
    condition: float
    gradient_cosine: float
    num_residuals: int
    num_params: int
    metrics: dict[str, dict[str, dict[str, float]]]
    starts: list[dict] | None = None
    problem: Any = dataclasses.field(repr=False, default=None)
    u: Any = dataclasses.field(repr=False, default=None)

    def summary(self) -> dict:
        """A JSON-ready summary (everything but the models and the problem)."""
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
                n: {"value": float(v), "std_error": float(s), "std_error_status": _std_error_status(s)}
                for n, v, s in zip(self.parameter_names, self.values, self.std_errors)
            },
            "correlation": np.asarray(self.correlation).tolist(),
            "metrics": self.metrics,
            "history": self.history,
            "history_steps": self.history_steps,
            "starts": self.starts,
        }

    def report(self) -> str:
        """A plain-text report: verdict, cost, parameters ± standard errors, strong correlations, errors."""
        lines = [
            f"fit {'converged' if self.success else 'FAILED'}: {self.reason}",
            f"  steps {self.steps} ({self.accepted_steps} accepted), cost {self.initial_cost:.6e} -> "
            f"{self.cost:.6e}, {self.seconds:.1f} s, {self.num_residuals} residuals, {self.num_params} parameters",
        ]
        if self.starts:
            ok = sum(st["success"] for st in self.starts)
            lines.append(f"  multi-start: {len(self.starts)} starts, {ok} converged; final costs "
                         + ", ".join(f"{st['cost']:.4e}{'*' if st['best'] else ''}" for st in self.starts)
                         + " (* reported)")
        lines.append("parameters (value ± standard error):")
        w = max(len(n) for n in self.parameter_names)
        for n, v, s in zip(self.parameter_names, self.values, self.std_errors):
            rel = f"({100 * s / abs(v):.2g} %)" if v != 0 and np.isfinite(s) else ""
            lines.append(f"  {n:<{w}}  {v: .6e} ± {s:.2e} {rel}")
        c = np.asarray(self.correlation)
        strong = [(abs(c[i, j]), i, j) for i in range(len(c)) for j in range(i) if abs(c[i, j]) > 0.99]
        if strong:
            lines.append("strongly correlated pairs (|corr| > 0.99):")
            for a, i, j in sorted(strong, reverse=True)[:10]:
                lines.append(f"  {self.parameter_names[i]} ~ {self.parameter_names[j]}: {c[i, j]:+.4f}")
        lines.append("errors per experiment and channel (RMSE, NRMSE % of range, max % of range):")
        for name, chans in self.metrics.items():
            for ch, m in chans.items():
                lines.append(
                    f"  {name:<20} {ch:<13} {m['rmse']:.4e}  {m['nrmse_percent']:7.3f} %  "
                    f"{m['max_error_percent']:7.3f} %"
                )
        return "\n".join(lines)

    def predict(self, dataset, history=()) -> list[dict[str, np.ndarray]]:
        """The fitted model's predicted target channels for each experiment of `dataset` (a `Dataset`, a list of
        experiments or one `Experiment`), each after the records of `history` (see `fitting.predict`: e.g. the
        training record before a held-out record that continues it). Any record length works."""
        from ._data import Experiment
        from ._predict import predict

        exps = [dataset] if isinstance(dataset, Experiment) else list(dataset)
        out = []
        for e in exps:
            preds = predict(self.model, e, predictor=self.problem.predictor, history=history)
            out.append({c: y for c, y in preds.items() if c in self.problem.targets})
        return out

    def save(self, path, overwrite: bool = False, figures: bool = True, extra: dict | None = None) -> Path:
        """Write `path/` atomically: `model.eqx` (equinox serialisation of `params`), `result.json` (summary plus
        `extra`), `report.txt` and, with `figures=True`, PNG figures. Nothing appears at `path` unless all succeed.

        `overwrite=True` replaces only a folder written by an earlier `save` (or `piezojax fit`), recognised by its
        marker file; never the working directory or a folder containing it."""
        from ._io import atomic_directory

        path = Path(path)
        with atomic_directory(path, overwrite=overwrite, kind="fit") as tmp:
            self.write_files(tmp, figures=figures, extra=extra)
        return path

    def write_files(self, folder, figures: bool = True, extra: dict | None = None) -> None:
        """Write the files of `save` into the existing folder `folder` (not atomically: for a caller that writes
        into a temporary folder of its own)."""
        from ._io import save_json

        folder = Path(folder)
        eqx.tree_serialise_leaves(folder / "model.eqx", self.params)
        summary = self.summary()
        if extra:
            summary.update(extra)
        save_json(folder / "result.json", summary)
        (folder / "report.txt").write_text(self.report() + "\n")
        if figures:
            from ._plots import plot_result

            plot_result(self, folder)


def _std_error_status(s) -> str:
    """How to read a standard error in `result.json`, where JSON can hold neither inf nor NaN (both are `null`):
    `"finite"`, `"infinite"` (the data do not determine the parameter) or `"not computed"` (no finite Jacobian)."""
    s = float(s)
    if np.isfinite(s):
        return "finite"
    return "infinite" if np.isinf(s) else "not computed"


def load_model(path, like):
    """Load the fitted (reparametrised) parameters saved by `FitResult.save` into a model of the structure of
    `like` (e.g. the initial model), and return the unwrapped model."""
    path = Path(path)
    f = path / "model.eqx" if path.is_dir() else path
    if not f.exists():
        raise PiezojaxValueError(f"no saved model at {f}")
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


def summarise(
    problem, u, *, success, reason, code, steps, accepted, history, seconds, levels, gtol=1e-2, history_steps=None
) -> FitResult:
    """Build a `FitResult` at the scaled parameters `u`: metrics, covariance and standard errors."""
    r, jtr, jtj = (np.asarray(x) for x in problem.normal_equations(u))
    m, p = problem.num_residuals, problem.num_params
    cost = 0.5 * float(np.sum(r**2))
    s2 = 2 * cost / max(m - p, 1)
    finite = bool(np.all(np.isfinite(r)) and np.all(np.isfinite(jtj)) and np.all(np.isfinite(jtr)))
    if not finite:  # e.g. a fit that failed at a non-finite start: no uncertainty can be computed
        jtr, jtj = np.zeros_like(jtr), np.zeros_like(jtj)
    evals, evecs = np.linalg.eigh(jtj)
    top = evals.max() if evals.size else 0.0
    keep = evals > top * 1e-14 * p
    inv = (evecs[:, keep] / evals[keep]) @ evecs[:, keep].T
    cov_u = s2 * inv
    d = np.asarray(problem.physical_jacobian(u))
    cov = d @ cov_u @ d.T
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    if not np.all(keep):
        # directions the data do not determine: their standard error is infinite, not zero
        null = evecs[:, ~keep]
        undetermined = np.abs(d @ null).max(axis=1) > 1e-12 * np.maximum(np.abs(d).max(axis=1), 1e-300)
        se = np.where(undetermined, np.inf, se)
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(se, se)
    condition = float(top / evals.min()) if evals.size and evals.min() > 0 else float("inf")
    if not finite:
        se, corr = np.full_like(se, np.nan), np.full_like(corr, np.nan)
    # first-order optimality (MINPACK's gtol test): the largest cosine between the residual and a Jacobian column
    col_norms = np.sqrt(np.clip(np.diag(jtj), 0.0, None))
    rnorm = np.sqrt(np.sum(r**2))
    with np.errstate(invalid="ignore", divide="ignore"):
        cosines = np.abs(jtr) / (col_norms * rnorm)
    gradient_cosine = float(np.nanmax(cosines)) if cosines.size and rnorm > 0 else 0.0
    if success and gradient_cosine > gtol:
        success, code = False, "not_stationary"
        reason = (f"stopped where the cost is not stationary (max |cos(r, J_i)| = {gradient_cosine:.2e} > gtol = "
                  f"{gtol:g}): the trust region shrank without a decrease (non-finite or non-smooth model?)")

    # the errors are the residuals unweighted: no further simulation
    metrics = {}
    for exp, errors in zip(problem.dataset, problem.experiment_errors(r)):
        metrics[exp.name] = {c: _metrics(e, exp.channels[c]) for c, e in errors.items()}
    params = problem.params(u)
    return FitResult(
        model=pj.unwrap(params),
        params=params,
        success=bool(success),
        reason=reason,
        code=code,
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
        correlation=corr,
        condition=condition,
        gradient_cosine=gradient_cosine,
        num_residuals=m,
        num_params=p,
        metrics=metrics,
        problem=problem,
        u=jnp.asarray(u),
    )
