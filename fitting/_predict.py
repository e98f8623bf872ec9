"""Predictors: how a model turns one experiment's inputs into predicted channels."""

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

import piezojax as pj
from piezojax._checks import PiezojaxValueError


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
        # eval the structure once to see whether the observer estimates force
        return observer_predictor(force=_observer_has_force(model))
    if isinstance(m, pj.AbstractHysteresis):
        return hysteresis_predictor()
    raise PiezojaxValueError(
        f"no built-in predictor for a {type(m).__name__}: pass `predictor=fitting.Predictor(fn, outputs=...)`"
    )


def _observer_has_force(model) -> bool:
    v = jnp.zeros((4,), jnp.zeros(()).dtype)
    est = eqx.filter_eval_shape(lambda: pj.unwrap(model)(v, v, jnp.asarray(1.0, v.dtype)))
    return est.force is not None
