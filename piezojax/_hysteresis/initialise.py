"""Cold-start initialisation of Prandtl–Ishlinskii operators from data, without knowing the answer.

These run once before a nonlinear fit, on concrete numpy data of data-dependent size, so they are plain
numpy/scipy functions (not jit-able and not differentiable, on purpose).
"""

from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np
import scipy.optimize
from jaxtyping import ArrayLike

from .._checks import PiezojaxValueError
from .play import PlayOperator
from .prandtl_ishlinskii import PrandtlIshlinskii


def _as_records(signals, outputs) -> list[tuple[np.ndarray, np.ndarray]]:
    if isinstance(signals, np.ndarray | jnp.ndarray) and np.ndim(signals) == 1:
        signals, outputs = [signals], [outputs]
    if len(signals) != len(outputs):
        raise PiezojaxValueError(
            f"`signals` and `outputs` must hold the same number of records, got {len(signals)} and {len(outputs)}"
        )
    records = []
    for i, (v, y) in enumerate(zip(signals, outputs)):
        v, y = np.asarray(v, dtype=float), np.asarray(y, dtype=float)
        if v.ndim != 1 or v.shape != y.shape or v.size == 0:
            raise PiezojaxValueError(
                f"record {i}: `signals` and `outputs` must be non-empty 1-D arrays of equal length, "
                f"got shapes {v.shape} and {y.shape}"
            )
        if not (np.all(np.isfinite(v)) and np.all(np.isfinite(y))):
            raise PiezojaxValueError(f"record {i}: `signals` or `outputs` contains NaN or infinite values")
        records.append((v, y))
    return records


def _design(records, thresholds):
    """Rows [v, P_r1[v], ..., P_rn[v]] for every sample of every record (demagnetised start)."""
    play = PlayOperator(jnp.asarray(thresholds))
    blocks = [np.column_stack([v, np.asarray(play(jnp.asarray(v)))]) for v, _ in records]
    return np.concatenate(blocks), np.concatenate([y for _, y in records])


def pi_weights_least_squares(
    signals: ArrayLike | Sequence[ArrayLike],
    outputs: ArrayLike | Sequence[ArrayLike],
    thresholds: ArrayLike,
    nonnegative: bool = True,
) -> PrandtlIshlinskii:
    r"""Linear least squares for the weights of a Prandtl–Ishlinskii operator with given thresholds.

    The output $w_0 v + \sum_i w_i P_{r_i}[v]$ is linear in the weights, so for fixed thresholds they follow from one
    (non-negative, by default) least-squares solve over all records.

    **Arguments:**

    - `signals`, `outputs`: one 1-D input/output pair, or sequences of them (records of any lengths).
    - `thresholds`: the thresholds $r_i$, ascending.
    - `nonnegative`: solve with `scipy.optimize.nnls` (default) or plain least squares.

    **Returns:** the fitted `PrandtlIshlinskii` (exact, `smoothing = 0`).
    """
    records = _as_records(signals, outputs)
    thresholds = np.asarray(thresholds, dtype=float)
    a, b = _design(records, thresholds)
    if nonnegative:
        coef, _ = scipy.optimize.nnls(a, b)
    else:
        coef = np.linalg.lstsq(a, b, rcond=None)[0]
    return PrandtlIshlinskii(jnp.asarray(coef[1:]), jnp.asarray(thresholds), w0=float(coef[0]))


def contiguous_runs(active: np.ndarray) -> list[list[int]]:
    """Indices of the `True` entries of the 1-D mask `active`, grouped into runs of consecutive indices."""
    runs: list[list[int]] = []
    for i in np.flatnonzero(active):
        if runs and runs[-1][-1] == i - 1:
            runs[-1].append(int(i))
        else:
            runs.append([int(i)])
    return runs


def pi_cold_start(
    signals: ArrayLike | Sequence[ArrayLike],
    outputs: ArrayLike | Sequence[ArrayLike],
    n: int,
    grid_size: int | None = None,
    min_weight_fraction: float = 1e-3,
) -> PrandtlIshlinskii:
    r"""Initial Prandtl–Ishlinskii operator with `n` plays from input/output data, needing no prior guess.

    1. Non-negative least squares for the weights on a dense threshold grid over $(0, \max|v|)$ (`grid_size`
       thresholds, default $8n$). A play of threshold $r$ between two grid points is well represented by its two
       neighbours, so the dense weights form separated clusters around the thresholds that the data support.
    2. Clusters are the runs of grid weights above `min_weight_fraction` of the largest; neighbouring clusters are
       merged (smallest gap first) while there are more than `n`, and the heaviest is split while there are fewer.
    3. Each cluster gives one threshold (its weight-averaged position); the weights are then re-solved by non-negative
       least squares for those `n` thresholds.

    The result is a starting point for Levenberg–Marquardt on weights and thresholds together (exact or smoothed).

    **Arguments:**

    - `signals`, `outputs`: one 1-D input/output pair, or sequences of them.
    - `n`: the number of plays.
    - `grid_size`: size of the dense grid (default `8 * n`).
    - `min_weight_fraction`: dense weights below this fraction of the largest are treated as zero.

    **Returns:** a `PrandtlIshlinskii` with `n` strictly ascending positive thresholds.
    """
    if not isinstance(n, int) or n < 1:
        raise PiezojaxValueError(f"`n` must be a positive integer, got {n!r}")
    records = _as_records(signals, outputs)
    vmax = max(np.max(np.abs(v)) for v, _ in records)
    if not vmax > 0:
        raise PiezojaxValueError("`signals` are identically zero: no threshold can be identified")
    grid_size = 8 * n if grid_size is None else int(grid_size)
    if grid_size < n:
        raise PiezojaxValueError(f"`grid_size` must be at least `n` = {n}, got {grid_size}")
    grid = vmax * np.arange(1, grid_size + 1) / (grid_size + 1)
    a, b = _design(records, grid)
    coef, _ = scipy.optimize.nnls(a, b)
    dense = coef[1:]

    clusters = contiguous_runs(dense > min_weight_fraction * max(dense.max(), np.finfo(float).tiny))

    def centre(c):
        w = dense[c]
        return float(np.sum(w * grid[c]) / np.sum(w)) if np.sum(w) > 0 else float(np.mean(grid[c]))

    while len(clusters) > n:
        gaps = [centre(c1) - centre(c0) for c0, c1 in zip(clusters[:-1], clusters[1:])]
        j = int(np.argmin(gaps))
        clusters[j : j + 2] = [clusters[j] + clusters[j + 1]]
    thresholds = [centre(c) for c in clusters]
    spacing = grid[0]
    while len(thresholds) < n:
        # Split the point with the widest free interval around it (or seed an empty grid uniformly).
        edges = [0.0] + thresholds + [vmax]
        widths = [edges[i + 2] - edges[i] for i in range(len(thresholds))] if thresholds else []
        if not widths:
            thresholds = list(grid[:: max(1, grid_size // n)][:n])
            continue
        j = int(np.argmax(widths))
        r = thresholds[j]
        lo, hi = max(r - spacing, 0.5 * (edges[j] + r)), min(r + spacing, 0.5 * (r + edges[j + 2]))
        thresholds[j : j + 1] = [lo, hi]
    thresholds = np.sort(np.asarray(thresholds))
    thresholds = np.maximum.accumulate(np.maximum(thresholds, 0.25 * spacing))
    thresholds = thresholds + 1e-9 * vmax * np.arange(n)  # strictly ascending
    op = pi_weights_least_squares(signals, outputs, thresholds)
    # Keep every weight strictly positive so a log/softplus reparametrisation can start from it.
    floor = 1e-3 * max(float(jnp.max(op.weights)), 1e-12)
    return PrandtlIshlinskii(jnp.maximum(op.weights, floor), op.thresholds, w0=jnp.maximum(op.w0, floor))
