"""A linear system given by its state-space matrices."""

from jaxtyping import Array, ArrayLike, Float

from .base import AbstractLinearSystem
from .discretise import check_realisation


class StateSpace(AbstractLinearSystem):
    r"""A SISO linear system given by a realisation: $\dot x = A x + B u$, $y = C x + D u$.

    The realisation is used as given (no balancing); for lightly damped or widely spread poles prefer a well-scaled
    (modal) realisation, e.g. `StableTransferFunction`.

    **Arguments:**

    - `A`: state matrix, shape `(n, n)`.
    - `B`: input vector, shape `(n,)`.
    - `C`: output vector, shape `(n,)`.
    - `D`: feedthrough, scalar (default 0).

    ```python
    G = pj.StateSpace([[-1.0]], [1.0], [2.0], 0.0)   # 2 / (s + 1)
    G.dc_gain()  # 2.0
    ```
    """

    A: Float[Array, "n n"]
    B: Float[Array, " n"]
    C: Float[Array, " n"]
    D: Float[Array, ""]

    def __init__(self, A: ArrayLike, B: ArrayLike, C: ArrayLike, D: ArrayLike = 0.0):
        self.A, self.B, self.C, self.D = check_realisation(A, B, C, D)

    @property
    def order(self) -> int:
        return self.A.shape[0]

    def state_space(self):
        return self.A, self.B, self.C, self.D
