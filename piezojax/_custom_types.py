"""Shape and type aliases shared across piezojax (jaxtyping)."""

from typing import TypeAlias

from jaxtyping import Array, ArrayLike, Float

Signal: TypeAlias = Float[Array, " time"]
SignalLike: TypeAlias = Float[ArrayLike, " time"]
Scalar: TypeAlias = Float[Array, ""]
ScalarLike: TypeAlias = Float[ArrayLike, ""]
Vector: TypeAlias = Float[Array, " n"]
VectorLike: TypeAlias = Float[ArrayLike, " n"]
