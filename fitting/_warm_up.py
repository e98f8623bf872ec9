r"""`warm_up`: a record's own sensor zeros and initial state, estimated from a window at its start.

A record made on another occasion than the training records starts from a state the model does not know: the
displacement sensor's zero has moved (a capacitive or interferometric sensor is zeroed at each session), the
actuator keeps a remanent polarisation from whatever drove it last, and its creep has not settled. The nonlinear
system-identification benchmarks score a model after a warm-up window at the start of each test record, which may
be used to estimate its state; `warm_up` does that for a fitted model. On the window it fits, by least squares:

- **each sensor's zero**: a constant added to each predicted channel the record measures;
- **the creep's state** (a `pj.Actuator` whose creep has `time_constants`: Kelvin–Voigt, lag): the free response
  of the creep from an unknown state, $\sum_i c_i\,e^{-(t - t_0)/\tau_i}$ added to the displacement, one amplitude
  per time constant (a linear block's response to its initial state; the dynamics' modes die out within the window),
  kept only where, fitted on the window's first half, it predicts the second half better than the offset alone
  (a time constant much longer than the window would otherwise turn any drift into a large extrapolated creep); a
  time constant many times the window is estimated from the window's slope only: the longer the window, the better;
- **the hysteresis' memory** (a `pj.Actuator` with a hysteresis, and no `history` given): the prehistory
  excursion $u_p$ (`pj.Actuator`'s `prehistory`), the model as fitted and a grid of `GRID` excursions over
  $\pm\max|v_{in}|$ tried, the best refined by a bounded scalar search, each judged by the window's residual after
  the least-squares terms above.

The terms are then extrapolated over the record (a zero stays, a creep's free response decays) and the prediction
is scored after the window only. Not a JAX transformation: the search runs on the host (each trial is one compiled
prediction of the window, compiled once per shape).
"""

import dataclasses
import numbers
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import scipy.optimize

import piezojax as pj
from piezojax import PiezojaxValueError

from ._data import Experiment
from ._predict import Predictor, default_predictor, predict

GRID = 17
"""Prehistory excursions tried over $\\pm\\max|v_{in}|$ before the bounded refinement."""


@dataclasses.dataclass(frozen=True)
class WarmUp:
    """What `warm_up` estimated for one record.

    - `model`: the model with the prehistory estimated (the model given where none was estimated or better).
    - `offsets`: per measured channel, the constant added to its prediction (the sensor's zero, SI units).
    - `creep`: the free response's amplitude per creep time constant [m], `{tau: c}` (empty without one).
    - `prehistory`: the excursion $u_p$ [V] chosen, or `None` (the model's own start kept).
    - `seconds`, `samples`: the window's length and its number of samples.
    - `predictions`: every predicted channel over the whole record, the fitted terms included.
    - `scored`: a boolean mask of the record's samples after the window.
    """

    model: Any
    offsets: dict[str, float]
    creep: dict[float, float]
    prehistory: float | None
    seconds: float
    samples: int
    predictions: dict[str, np.ndarray] = dataclasses.field(repr=False)
    scored: np.ndarray = dataclasses.field(repr=False)

    def summary(self) -> dict:
        """The estimates as JSON values (`metrics.json` of `piezojax predict --warm-up`)."""
        return {"seconds": self.seconds, "samples": self.samples, "offsets": dict(self.offsets),
                "creep_free_response": [{"time_constant": tau, "amplitude": c} for tau, c in self.creep.items()],
                "prehistory": self.prehistory}


def _time_constants(model) -> list[float]:
    """The creep's time constants of a `pj.Actuator` (none for another model or a creep without them)."""
    creep = getattr(model, "creep", None) if isinstance(model, pj.Actuator) else None
    taus = getattr(creep, "time_constants", None)
    return [] if taus is None else [float(x) for x in np.ravel(np.asarray(taus)) if np.isfinite(x) and x > 0]


def warm_up(model, experiment: Experiment, seconds: float, *, predictor: Predictor | None = None,
            history=()) -> WarmUp:
    r"""Estimate `experiment`'s sensor zeros and the model's initial state from its first `seconds` (see the module
    docstring), and predict the record with them.

    **Arguments:**

    - `model`: a fitted model (`FitResult.model`, `load_fit(folder).model`).
    - `experiment`: the record, with the channels to score (at least one channel the predictor outputs).
    - `seconds`: the window's length [s] from the record's first sample; it must hold 2 samples and leave 2.
    - `predictor`: as for `fitting.predict`.
    - `history`: records run before `experiment` (as for `fitting.predict`): the hysteresis' memory is then theirs
      (no prehistory is estimated).

    **Returns:** a `WarmUp`; score `predictions[c][scored]` against `experiment[c][scored]`. Not for `jit`, `vmap`
    or differentiation: a search on the host over compiled predictions.

    ```python
    w = fitting.warm_up(fit.model, day2, 1.0)
    err = w.predictions["displacement"][w.scored] - day2["displacement"][w.scored]
    ```
    """
    if not isinstance(experiment, Experiment):
        raise PiezojaxValueError(f"`experiment` must be a fitting.Experiment, got {type(experiment).__name__}")
    if isinstance(seconds, bool) or not isinstance(seconds, numbers.Real) or not np.isfinite(seconds) or seconds <= 0:
        raise PiezojaxValueError(f"the warm-up must be a number of seconds > 0, got {seconds!r}")
    predictor = default_predictor(model) if predictor is None else predictor
    channels = [c for c in predictor.outputs if experiment.has(c)]
    if not channels:
        raise PiezojaxValueError(f"{experiment._label()}: a warm-up estimates the sensors' zeros from a measured "
                                 f"channel; it has none of {list(predictor.outputs)}")
    end = float(experiment.t[0]) + float(seconds)
    inside = experiment.t < end - 1e-6 * experiment.dt
    samples = int(np.count_nonzero(inside))
    if samples < 2 or experiment.n - samples < 2:
        raise PiezojaxValueError(
            f"{experiment._label()}: a warm-up of {seconds:g} s holds {samples} sample(s) of the record "
            f"[{experiment.t[0]:.6g}, {experiment.t[-1]:.6g}] s and leaves {experiment.n - samples}; each needs 2")
    history = (history,) if isinstance(history, Experiment) else tuple(history or ())
    model = pj.unwrap(model)
    taus = _time_constants(model)
    elapsed = experiment.t - experiment.t[0]
    terms = {c: np.stack([np.ones(experiment.n)] + [np.exp(-elapsed / tau) for tau in taus] * (c == "displacement"),
                         axis=1) for c in channels}
    window = experiment.slice(None, end)
    measured = {c: np.asarray(window[c], float) for c in channels}
    whole = {c: np.asarray(experiment[c], float) for c in channels}
    scale = {c: max(float(np.ptp(y)), float(np.max(np.abs(y))), np.finfo(float).tiny) for c, y in whole.items()}

    def least_squares(pred: dict) -> tuple[dict, float]:
        """The terms' coefficients per channel over the window, and the sum of the squared residuals after them
        (each channel over its range; inf where not finite)."""
        coefs, total = {}, 0.0
        for c in channels:
            r = measured[c] - np.asarray(pred[c][:samples], float)
            if not np.all(np.isfinite(r)):
                return {}, np.inf
            coefs[c] = np.linalg.lstsq(terms[c][inside], r, rcond=None)[0]
            with np.errstate(over="ignore", invalid="ignore"):  # a wild trial: inf, not a warning
                total += float(np.sum(((r - terms[c][inside] @ coefs[c]) / scale[c]) ** 2))
        return coefs, total

    def misfit(m) -> float:
        return least_squares(predict(m, window, predictor=predictor, history=history, check_finite=False))[1]

    prehistory = None
    if not history and isinstance(model, pj.Actuator) and model.hysteresis is not None \
            and model.hysteresis_state is None:
        dtype = model.offset.dtype

        def with_prehistory(u: float):
            return eqx.tree_at(lambda a: a.prehistory, model, jnp.asarray(u, dtype), is_leaf=lambda x: x is None)

        vmax = float(np.max(np.abs(experiment.v_in))) or 1.0
        grid = vmax * np.linspace(-1.0, 1.0, GRID)
        costs = np.array([misfit(with_prehistory(u)) for u in grid])
        if np.any(np.isfinite(costs)):
            i = int(np.argmin(costs))
            best = scipy.optimize.minimize_scalar(
                lambda u: misfit(with_prehistory(float(u))), bounds=(grid[max(i - 1, 0)], grid[min(i + 1, GRID - 1)]),
                method="bounded", options={"xatol": 1e-4 * vmax, "maxiter": 30})
            u, cost = (float(best.x), float(best.fun)) if best.fun <= costs[i] else (float(grid[i]), costs[i])
            if cost < misfit(model):  # never worse over the window than the model's own start
                model, prehistory = with_prehistory(u), u
    pred = predict(model, experiment, predictor=predictor, history=history, check_finite=False)
    if "displacement" in channels and taus and not _creep_extrapolates(
            measured["displacement"] - pred["displacement"][:samples], terms["displacement"][:samples]):
        terms["displacement"] = terms["displacement"][:, :1]  # the offset alone
        taus = []
    coefs, _ = least_squares(pred)
    offsets, creep = {}, {}
    for c in channels:
        k = coefs.get(c)
        if k is None:
            raise PiezojaxValueError(f"{experiment._label()}: the model's {c!r} is not finite over the warm-up")
        pred[c] = pred[c] + terms[c] @ k
        offsets[c] = float(k[0])
        if c == "displacement":
            creep = {tau: float(x) for tau, x in zip(taus, k[1:])}
    return WarmUp(model, offsets, creep, prehistory, float(seconds), samples, pred, ~inside)


def _creep_extrapolates(residual: np.ndarray, terms: np.ndarray) -> bool:
    """Whether the creep's free response (the columns of `terms` after the offset's) predicts the window's second
    half better than the offset alone, each fitted on its first half: a time constant much longer than the window
    makes its column nearly a constant plus a slope, which the least squares would fit to any drift of the
    residual, noise or misfit, and extrapolate; kept only when it extrapolates within the window."""
    half = residual.size // 2
    if half < 2 * terms.shape[1]:
        return False
    errors = []
    for cols in (terms[:, :1], terms):
        k = np.linalg.lstsq(cols[:half], residual[:half], rcond=None)[0]
        errors.append(float(np.sum((residual[half:] - cols[half:] @ k) ** 2)))
    return errors[1] < errors[0]
