"""The closed loop plant → observer → controller as one `lax.scan`."""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, PyTree

from .._checks import PiezojaxValueError, check_signal, check_value, checked
from .._custom_types import AbstractCell, SignalLike
from .._dtypes import cast_module, module_float_dtype
from .adaptive_inverse import AdaptiveInverseController
from .base import AbstractController, AbstractPlant, as_time_major


class LoopRecord(eqx.Module):
    """What a closed loop did at each instant $k$ (all arrays of shape `(time,)`).

    - `reference`: $r_k$; `control`: the command $u_k$ the controller returned;
    - `feedback`: $\\hat y_k$, the value the controller read (the observer's estimate, or the measured channel);
    - `channels`: the plant's output channels at instant $k$ (`AbstractPlant.output`), e.g. the true
      `displacement` of a virtual bench next to the measured `v_out`.
    """

    reference: Float[Array, " time"]
    control: Float[Array, " time"]
    feedback: Float[Array, " time"]
    channels: dict[str, Float[Array, " time"]]


def closed_loop(
    controller: AbstractController,
    plant: AbstractPlant,
    reference: SignalLike,
    *,
    observer: AbstractCell | None = None,
    feedback: str = "displacement",
    noise: PyTree[ArrayLike] | None = None,
    preview: int = 0,
) -> LoopRecord:
    r"""Simulate the sampled loop plant → observer → controller, one `jax.lax.scan` over the reference.

    At each instant $k$: the plant's channels $y_k = h(x_k, w_k)$ are read; the observer turns them into the
    feedback $\hat y_k$; the controller returns $u_k$ from $(r_k, \hat y_k)$; the plant advances with $u_k$ held,
    $x_{k+1} = f(x_k, u_k)$. The command acts from the next instant on (one sample of delay, as with a DAC and
    an ADC clocked together). Everything is a pure function of the three cells' arrays: it works under `jit`,
    `vmap` (over references, noise, or stacked controllers) and `grad` (e.g. of a tracking cost with respect to
    PID gains).

    **Arguments:**

    - `controller`: an `AbstractController`.
    - `plant`: an `AbstractPlant`.
    - `reference`: $r_k$, shape `(time,)`.
    - `observer`: a `pj.AbstractCell` whose `step(state, channels) -> (state, estimate)` turns the plant's
      channels into the feedback (e.g. `pj.SensorLayerObserver`: displacement from the sensor voltage); `None`:
      the feedback is the channel named `feedback`.
    - `feedback`: the channel fed back when `observer` is None (default `"displacement"`).
    - `noise`: the exogenous samples $w_k$ the plant's `output` reads (leaves with a leading time axis of the
      reference's length), or None.
    - `preview`: $p \ge 0$; the controller reads $r_{k+p}$ instead of $r_k$ (the last sample held past the
      end), for references known in advance. The command $u_k$ first shows in the feedback at $k+1$, so a
      feedforward that reads $r_k$ aims one sample late (on a ramp of slope $s$, a lag of $s\,\Delta t$);
      `preview=1` aims it at the instant it acts. The record's `reference` and the tracking error stay aligned
      with $r_k$. A `pj.AdaptiveInverseController` must be built with the same `preview` (refused otherwise).

    **Returns:** a `LoopRecord`.

    ```python
    plant = pj.ChenBench().plant()                  # a plant from paper 002's bench
    pid = pj.PID(kp=2e5, ki=4e7, kd=0.0, dt=1e-3, offset=100.0, u_min=-20.0, u_max=200.0)
    rec = pj.closed_loop(pid, plant, reference)
    error = rec.reference - rec.channels["displacement"]
    ```
    """
    if not isinstance(controller, AbstractController):
        raise PiezojaxValueError(f"`controller` must be a pj.AbstractController, got {type(controller).__name__}")
    if not isinstance(plant, AbstractPlant):
        raise PiezojaxValueError(f"`plant` must be a pj.AbstractPlant, got {type(plant).__name__}")
    if observer is not None and not isinstance(observer, AbstractCell):
        raise PiezojaxValueError(f"`observer` must be a pj.AbstractCell (init() and step(state, channels)) or None, "
                                 f"got {type(observer).__name__}")
    if not isinstance(preview, int) or isinstance(preview, bool) or preview < 0:
        raise PiezojaxValueError(f"`preview` must be an int >= 0, got {preview!r}")
    for aic in jax.tree.leaves(controller, is_leaf=lambda x: isinstance(x, AdaptiveInverseController)):
        # its targets are the references read `preview` samples before: another loop preview misaligns them (also
        # inside a composite controller, e.g. `FeedforwardFeedback`)
        if isinstance(aic, AdaptiveInverseController) and aic.preview != preview:
            raise PiezojaxValueError(f"`preview` = {preview} differs from the controller's own `preview` = "
                                     f"{aic.preview} (the preview of the loop it was built for)")
    dtype = module_float_dtype((controller, plant, observer), reference)
    r = check_signal(reference, "reference", dtype)
    held = jnp.broadcast_to(r[-1], (min(preview, r.shape[0]),))
    r_read = r if preview == 0 else jnp.concatenate([r[preview:], held])
    w = as_time_major(noise, r.shape[0], "noise", dtype)
    ctrl, plant = cast_module(controller, dtype).check(), cast_module(plant, dtype)
    obs = None if observer is None else checked(cast_module(observer, dtype))
    read: Callable = _reader(obs, feedback)

    def body(carry, rw):
        p_state, o_state, c_state = carry
        r_k, w_k = rw
        channels = plant.output(p_state, w_k)
        o_state, y_hat = read(o_state, channels)
        c_state, u = ctrl.step(c_state, r_k, y_hat)
        u = jnp.asarray(u, dtype)
        return (plant.step(p_state, u), o_state, c_state), (u, y_hat, channels)

    init = (plant.init(), None if obs is None else obs.init(), ctrl.init())
    _, (u, y_hat, channels) = jax.lax.scan(body, init, (r_read, w))
    return LoopRecord(reference=r, control=u, feedback=y_hat, channels=channels)


def _reader(observer, feedback: str):
    if observer is None:
        def read(state, channels):
            if feedback not in channels:
                raise PiezojaxValueError(
                    f"`feedback` {feedback!r} is not a channel of the plant's output {sorted(channels)}"
                )
            return state, channels[feedback]
        return read
    return lambda state, channels: observer.step(state, channels)


def tracking_error_percent(reference: SignalLike, output: SignalLike) -> Float[Array, ""]:
    r"""Paper 002's eq. (20): the RMS tracking error as a percentage of the reference's range,

    $e_{rms} = \dfrac{\sqrt{\frac{1}{N}\sum_k (r_k - y_k)^2}}{\max_k r_k - \min_k r_k} \times 100\,\%$

    (a constant reference, without a range, is refused).
    """
    dtype = module_float_dtype(None, reference, output)
    r = check_signal(reference, "reference", dtype)
    y = check_signal(output, "output", dtype)
    if r.shape != y.shape:
        raise PiezojaxValueError(f"`reference` and `output` must have the same length, got {r.shape} and {y.shape}")
    span = check_value(jnp.max(r) - jnp.min(r), lambda a: a > 0,
                       "`reference` is constant: eq. (20) divides by its range, which is 0")
    return 100 * jnp.sqrt(jnp.mean((r - y) ** 2)) / span
