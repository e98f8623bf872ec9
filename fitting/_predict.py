"""Predictors: how a model turns one experiment's inputs into predicted channels."""

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

import piezojax as pj
from piezojax import PiezojaxValueError

from ._data import Dataset, Experiment


class ExperimentArrays(eqx.Module):
    """One experiment as JAX arrays, as a predictor sees it (padded experiments carry their padding).

    - `t` [s], `v_in` [V]: shape `(time,)`; `dt` [s]: scalar.
    - `channels`: the measured channels a predictor may read as inputs (e.g. `v_out` for an observer).
    """

    t: Float[Array, " time"]
    dt: Float[Array, ""]
    v_in: Float[Array, " time"]
    channels: dict[str, Float[Array, " time"]]


class Predictor(eqx.Module):
    r"""Maps `(model, ExperimentArrays)` to a dict of predicted channels, each of shape `(time,)`.

    **Arguments:**

    - `fn`: `fn(model, data) -> dict[str, Array]`; must be a pure JAX function of the model's arrays.
    - `outputs`: the channel names `fn` returns (static).
    - `inputs`: measured channels besides `t` and `v_in` that `fn` reads from `data.channels` (e.g. `("v_out",)`
      for an observer); an experiment used for fitting must have them, and they are never fitting targets.

    Built-in predictors: `actuator_predictor()` (an `pj.Actuator`: displacement, charge, current from `v_in`),
    `observer_predictor()` (a `pj.AbstractObserver`: displacement and force from `v_in` and `v_out`),
    `hysteresis_predictor()` (an operator `op(v_in)` read as displacement). `default_predictor(model)` picks one.

    ```python
    pred = fitting.Predictor(lambda m, d: {"displacement": m(d.v_in)}, outputs=("displacement",))
    ```
    """

    fn: Callable[[Any, ExperimentArrays], dict[str, Array]] = eqx.field(static=True)
    outputs: tuple[str, ...] = eqx.field(static=True)
    inputs: tuple[str, ...] = eqx.field(static=True, default=())

    def __call__(self, model, data: ExperimentArrays) -> dict[str, Array]:
        out = self.fn(model, data)
        missing = [c for c in self.outputs if c not in out]
        if missing:
            raise PiezojaxValueError(f"the predictor did not return the channels {missing} it declares")
        return {c: out[c] for c in self.outputs}


def _actuator(model, data):
    out = model.simulate(data.v_in, data.dt)
    return {"displacement": out.displacement, "charge": out.charge, "current": out.current}


def actuator_predictor() -> Predictor:
    """Predictor for a `pj.Actuator`: `displacement` [m], `charge` [C], `current` [A] from `v_in`, from rest."""
    return Predictor(_actuator, ("displacement", "charge", "current"))


def _observer(model, data):
    est = model(data.v_in, data.channels["v_out"], data.dt)
    out = {"displacement": est.displacement}
    if est.force is not None:
        out["force"] = est.force
    return out


def observer_predictor(force: bool = True) -> Predictor:
    """Predictor for a `pj.AbstractObserver`: estimated `displacement` (and `force` when `force=True`) from the
    measured `v_in` and `v_out`; the reference sensors' channels are the targets."""
    return Predictor(_observer, ("displacement", "force") if force else ("displacement",), inputs=("v_out",))


def _hysteresis(model, data):
    return {"displacement": model(data.v_in)}


def hysteresis_predictor() -> Predictor:
    """Predictor for a rate-independent operator (`pj.PrandtlIshlinskii`, ...): `displacement = op(v_in)`."""
    return Predictor(_hysteresis, ("displacement",))


def default_predictor(model) -> Predictor:
    """The built-in predictor for `model`'s type (after unwrapping reparametrisations); error for unknown types."""
    # the type only: traced, not computed (no compilation of the reparametrisations)
    m = eqx.filter_eval_shape(pj.unwrap, model)
    if isinstance(m, pj.Actuator):
        return actuator_predictor()
    if isinstance(m, pj.AbstractObserver):
        return observer_predictor(force="force" in type(m).estimates)
    if isinstance(m, pj.AbstractHysteresis):
        return hysteresis_predictor()
    raise PiezojaxValueError(
        f"no built-in predictor for a {type(m).__name__}: pass `predictor=fitting.Predictor(fn, outputs=...)`"
    )


def as_arrays(experiments, inputs, dtype) -> ExperimentArrays:
    """`experiments` run back to back as one record (their own times are not used: only the common step)."""
    v_in = np.concatenate([e.v_in for e in experiments])
    n = v_in.shape[0]
    return ExperimentArrays(
        t=jnp.asarray(np.arange(n) * experiments[-1].dt, dtype),
        dt=jnp.asarray(experiments[-1].dt, dtype),
        v_in=jnp.asarray(v_in, dtype),
        channels={c: jnp.asarray(np.concatenate([e[c] for e in experiments]), dtype) for c in inputs},
    )


@eqx.filter_jit
def run_predictor(predictor, model, data):
    return predictor(model, data)


def predict(model, experiment, *, predictor: Predictor | None = None, history=(),
            check_finite: bool = True) -> dict[str, np.ndarray]:
    r"""The predicted channels of `model` for one experiment, from rest or after the records of `history`.

    A model starts from rest (demagnetised hysteresis, creep and dynamics settled at its output at 0 V; see
    `pj.Actuator`). A record that continues an earlier
    one (the held-out end of a long record, a test run right after the training runs) is predicted with that earlier
    record as `history`: the records of `history` drive the model first, in order, and then `experiment` continues
    from the state they leave; only `experiment`'s samples are returned. This is the same as predicting the joined
    record and keeping its end, so a record split with `Experiment.slice` is predicted as a whole.

    **Arguments:**

    - `model`: the model (reparametrised or not).
    - `experiment`: a `fitting.Experiment` with the predictor's input channels (e.g. `v_out` for an observer).
    - `predictor`: how the model makes the channels (default `default_predictor(model)`).
    - `history`: an `Experiment` or a sequence of them, run before `experiment`, with its sampling step
      (within 1e-6 relative) and input channels.
    - `check_finite`: raise `PiezojaxValueError` naming the experiment and channel when a prediction is not finite
      (default); `False` returns them as they are (e.g. to plot a failed fit).

    **Returns:** `{channel: array of experiment.n samples}` (NumPy), for every output of the predictor. Any length
    works (no fit is involved).

    ```python
    train, test = record.slice(None, 7.0), record.slice(7.0, None)
    y = fitting.predict(result.model, test, history=train)["displacement"]
    ```
    """

    if not isinstance(experiment, Experiment):
        raise PiezojaxValueError(f"`experiment` must be a fitting.Experiment, got {type(experiment).__name__}")
    if history is None:
        history = ()
    elif isinstance(history, Experiment):
        history = (history,)
    elif isinstance(history, list | tuple | Dataset):
        history = tuple(history)
    else:
        raise PiezojaxValueError(f"`history` must be an Experiment or a list of Experiments (records run before "
                                 f"`experiment`), got {type(history).__name__}")
    for i, h in enumerate(history):
        if not isinstance(h, Experiment):
            raise PiezojaxValueError(f"`history[{i}]` must be a fitting.Experiment, got {type(h).__name__}")
        if abs(h.dt - experiment.dt) > 1e-6 * experiment.dt:
            raise PiezojaxValueError(
                f"history {h.name!r} is sampled every {h.dt:.6g} s but {experiment.name!r} every {experiment.dt:.6g} "
                "s; a warm-up record must have the same sampling step"
            )
    predictor = default_predictor(model) if predictor is None else predictor
    records = (*history, experiment)
    for e in records:
        missing = [c for c in predictor.inputs if not e.has(c)]
        if missing:
            raise PiezojaxValueError(
                f"{e._label()} lacks the column(s) {missing} the model reads as input")
    model = pj.unwrap(model)
    dtype = jnp.result_type(*[x for x in jax.tree_util.tree_leaves(model) if eqx.is_inexact_array(x)] or [0.0])
    out = run_predictor(predictor, model, as_arrays(records, predictor.inputs, dtype))
    start = sum(e.n for e in history)
    preds = {c: np.asarray(out[c])[start:] for c in predictor.outputs}
    bad = [c for c, y in preds.items() if not np.all(np.isfinite(y))]
    if bad and check_finite:
        raise PiezojaxValueError(f"{experiment._label()}: the model's {bad[0]!r} is not finite")
    return preds
