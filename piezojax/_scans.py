r"""Parallel-in-time forms of the library's recurrences, as `jax.lax.associative_scan` (see
`piezojax.set_parallel_scans`, which chooses between them and the sequential `lax.scan`).

- `affine_scan`: $x_k = a_k x_{k-1} + b_k$ (elementwise), by the composition of affine maps
  $(a_1, b_1)$ then $(a_2, b_2)$ = $(a_2 a_1,\ a_2 b_1 + b_2)$.
- `matrix_affine_scan`: $\xi_{k+1} = (I + \Delta)\xi_k + b_k$ for one matrix (a discrete linear system).
- `clamp_scan`: $y_k = \min(\max(y_{k-1}, \ell_k), h_k)$ with $\ell_k \le h_k$ (the exact play operator
  $P_r[v]_k = \max(v_k - r, \min(v_k + r, P_r[v]_{k-1}))$), by the composition of clamps
  $[\ell_1, h_1]$ then $[\ell_2, h_2]$ = $[\mathrm{clip}(\ell_1, \ell_2, h_2),\ \mathrm{clip}(h_1, \ell_2, h_2)]$: exact
  (only comparisons, no rounding).

Each works along axis 0 and under `vmap`; the derivatives are the callers' (hand-derived sensitivities, themselves
affine recurrences).
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array

from ._dtypes import matmul


def affine_scan(a: Array, b: Array, x0: Array | None = None) -> Array:
    """$x_k = a_k x_{k-1} + b_k$ for every $k$ (axis 0), from $x_{-1} = $ `x0` (default 0); `a` broadcasts
    against `b`. **Returns:** $x$, the shape of `b`."""
    a = jnp.broadcast_to(a, b.shape)

    def combine(first, second):
        a1, b1 = first
        a2, b2 = second
        return a2 * a1, a2 * b1 + b2

    prod, x = jax.lax.associative_scan(combine, (a, b))
    return x if x0 is None else x + prod * x0


def matrix_affine_scan(delta: Array, b: Array, x0: Array) -> tuple[Array, Array]:
    r"""$\xi_{k+1} = (I + \Delta)\xi_k + b_k$ from $\xi_0$ = `x0` (`delta`: `(n, n)`, `b`: `(time, n)`).

    The maps are composed in the form $(\Delta, b)$ of $\xi \mapsto \xi + \Delta\xi + b$:
    $(\Delta_1, b_1)$ then $(\Delta_2, b_2)$ = $(\Delta_1 + \Delta_2 + \Delta_2\Delta_1,\ b_1 + b_2 + \Delta_2 b_1)$,
    so a slow mode ($I + \Delta$ within rounding of $I$) keeps its decay to relative rounding, as the sequential
    update $\xi + (\Delta\xi + b)$ does.

    **Returns:** `(states, last)`: $\xi_0 \ldots \xi_{time-1}$ (the state each input meets, shape `(time, n)`)
    and $\xi_{time}$.
    """
    ds = jnp.broadcast_to(delta, (b.shape[0],) + delta.shape)

    def combine(first, second):
        d1, b1 = first
        d2, b2 = second
        return d1 + d2 + matmul(d2, d1), b1 + b2 + matmul(d2, b1[..., None])[..., 0]

    dprod, acc = jax.lax.associative_scan(combine, (ds, b))
    after = x0 + (matmul(dprod, x0) + acc)  # xi_1 ... xi_time
    return jnp.concatenate([x0[None], after[:-1]]), after[-1]


def clamp_scan(lo: Array, hi: Array, y0: Array) -> Array:
    """$y_k = \\min(\\max(y_{k-1}, \\ell_k), h_k)$ from $y_{-1}$ = `y0`, for $\\ell_k \\le h_k$ (axis 0)."""

    def combine(first, second):
        l1, h1 = first
        l2, h2 = second
        return jnp.minimum(jnp.maximum(l1, l2), h2), jnp.minimum(jnp.maximum(h1, l2), h2)

    lo_all, hi_all = jax.lax.associative_scan(combine, (lo, hi))
    return jnp.minimum(jnp.maximum(y0, lo_all), hi_all)
