"""Shape and type aliases shared across piezojax (jaxtyping), and the cell interface (`AbstractCell`)."""

import abc
from typing import Any, TypeAlias

import equinox as eqx
from jaxtyping import Array, ArrayLike, Float, PyTree

Signal: TypeAlias = Float[Array, " time"]
SignalLike: TypeAlias = Float[ArrayLike, " time"]
Scalar: TypeAlias = Float[Array, ""]
ScalarLike: TypeAlias = Float[ArrayLike, ""]
Vector: TypeAlias = Float[Array, " n"]
VectorLike: TypeAlias = Float[ArrayLike, " n"]


class AbstractCell(eqx.Module):
    r"""A block run sample by sample: `init() -> state`, then `step(state, x_k) -> (state, y_k)` at each sample.

    The interface of what a loop steps without knowing its type: `pj.closed_loop`'s `observer` (`step` reads the
    plant's measured channels, a mapping of name to sample), `pj.InverseFeedforward`'s `inverse` (`step` reads the
    desired output). Every hysteresis operator (`pj.AbstractHysteresis`) and its inverse is one; so are
    `pj.SensorLayerObserver` and `pj.NarxNetwork`. A cell of one's own subclasses it:

    ```python
    class Gain(pj.AbstractCell):
        g: jax.Array

        def init(self):
            return ()

        def step(self, state, x):
            return state, self.g * x
    ```
    """

    @abc.abstractmethod
    def init(self) -> PyTree[Array]:
        """The state before the first sample."""

    @abc.abstractmethod
    def step(self, state: PyTree[Array], x: Any) -> tuple[PyTree[Array], Any]:
        """Read the sample `x`; return `(state, y)`."""
