"""Feedforward from a model's inverse, and feedforward plus feedback."""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, PyTree

from .._checks import PiezojaxValueError, check_nonzero, check_scalar_param, checked, error_if_not_finite
from .._custom_types import AbstractCell
from .._dtypes import param_dtype
from .base import AbstractController


class InverseFeedforward(AbstractController):
    r"""Open-loop compensation by an inverse model: $u_k = u_0 + H^{-1}[(r - r_0)/g]_k$, ignoring the feedback.

    **Arguments:**

    - `inverse`: a `pj.AbstractCell` whose `step(state, y) -> (state, v)` maps a desired output to the input that
      produces it, e.g. `pi.inverse()` of a fitted `pj.PrandtlIshlinskii` $H$ (its inverse is exact and
      rate-independent), or any operator that maps displacement to voltage.
    - `offset`: $u_0$, added to the inverse's output (e.g. a bias voltage the model was fitted around).
    - `reference_offset`: $r_0$, and `reference_scale`: $g \ne 0$ — the reference in the inverse's input units
      (e.g. `reference_scale=1e-6` for a model fitted in µm and a reference in m). All finite scalars.

    ```python
    ff = pj.InverseFeedforward(pi.inverse(), offset=100.0, reference_scale=1e-6)
    ```
    """

    inverse: AbstractCell
    offset: Float[Array, ""]
    reference_offset: Float[Array, ""]
    reference_scale: Float[Array, ""]

    def __init__(self, inverse: AbstractCell, *, offset: ArrayLike = 0.0, reference_offset: ArrayLike = 0.0,
                 reference_scale: ArrayLike = 1.0):
        if not isinstance(inverse, AbstractCell):
            raise PiezojaxValueError(f"`inverse` must be a pj.AbstractCell (init() and step(state, y)), got "
                                     f"{type(inverse).__name__}")
        self.inverse = inverse
        dtype = param_dtype(*jax.tree.leaves(inverse), offset, reference_offset, reference_scale)
        self.offset = check_scalar_param(offset, "offset", dtype)
        self.reference_offset = check_scalar_param(reference_offset, "reference_offset", dtype)
        self.reference_scale = check_nonzero(check_scalar_param(reference_scale, "reference_scale", dtype),
                                        "reference_scale")

    def check(self) -> "InverseFeedforward":
        m = error_if_not_finite(self, ("offset", "reference_offset"))
        return eqx.tree_at(lambda f: (f.inverse, f.reference_scale), m,
                           (checked(m.inverse), check_nonzero(m.reference_scale, "reference_scale")))

    def init(self) -> PyTree[Array]:
        return self.inverse.init()

    def step(self, state, reference, measurement):
        state, v = self.inverse.step(state, (reference - self.reference_offset) / self.reference_scale)
        return state, self.offset + v


class FeedforwardFeedback(AbstractController):
    r"""Two degrees of freedom: $u_k = u^{ff}_k + u^{fb}_k$ — e.g. an `InverseFeedforward` that linearises the
    plant plus a `PID` (with `offset` 0) that removes what the inverse model missed.

    **Arguments:** `feedforward`, `feedback`: two `AbstractController`s, both given $(r_k, y_k)$.
    """

    feedforward: AbstractController
    feedback: AbstractController

    def __init__(self, feedforward: AbstractController, feedback: AbstractController):
        for name, c in (("feedforward", feedforward), ("feedback", feedback)):
            if not isinstance(c, AbstractController):
                raise PiezojaxValueError(f"`{name}` must be a pj.AbstractController, got {type(c).__name__}")
        self.feedforward, self.feedback = feedforward, feedback

    def check(self) -> "FeedforwardFeedback":
        return FeedforwardFeedback(self.feedforward.check(), self.feedback.check())

    def init(self):
        return self.feedforward.init(), self.feedback.init()

    def step(self, state, reference, measurement):
        s_ff, u_ff = self.feedforward.step(state[0], reference, measurement)
        s_fb, u_fb = self.feedback.step(state[1], reference, measurement)
        return (s_ff, s_fb), jnp.asarray(u_ff) + u_fb
