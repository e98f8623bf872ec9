"""Cold-start initialisation of Prandtl–Ishlinskii operators from data, without knowing the answer.

These run once before a nonlinear fit, on concrete numpy data of data-dependent size, so they are plain
numpy/scipy functions (not jit-able and not differentiable, on purpose).
"""

import functools
from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import scipy  # submodules (signal, optimize, linalg) load on first use: importing them costs about a second
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


MAX_ROWS = 200_000


def check_max_rows(max_rows) -> None:
    """Raise unless `max_rows` (the row budget of a start's least squares) is a positive integer or `None`."""
    if max_rows is not None and not (isinstance(max_rows, int) and max_rows >= 1):
        raise PiezojaxValueError(f"`max_rows` must be a positive integer or None, got {max_rows!r}")


def row_subset(sizes: Sequence[int], max_rows: int | None, seed: int = 0) -> list:
    """Rows of a least squares over records of the given `sizes` to keep within `max_rows` in all: every row
    (`slice(None)` per record) when they fit, else the same fraction of each record's rows, drawn at random (a
    fixed `seed`: the same rows on every call) and in order. Initial values are heuristics whose accuracy is set by
    a few hundred thousand rows, not millions; the signals themselves (play outputs, filters) are still computed
    on whole records, since they carry the history."""
    return list(_row_subset(tuple(int(n) for n in sizes), max_rows, seed))


@functools.lru_cache(maxsize=8)
def _row_subset(sizes: tuple[int, ...], max_rows: int | None, seed: int) -> tuple:
    # cached: the alternating least squares of a start ask for the same rows many times (read-only index arrays)
    if max_rows is None or sum(sizes) <= max_rows:
        return (slice(None),) * len(sizes)
    rng = np.random.default_rng(seed)
    frac = max_rows / sum(sizes)
    out = []
    for n in sizes:
        k = np.sort(rng.choice(n, size=max(1, int(round(frac * n))), replace=False)) if n else np.zeros(0, int)
        k.flags.writeable = False
        out.append(k)
    return tuple(out)


def nnls_gram(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    r"""Non-negative least squares $\min_{x \ge 0}\|Ax - b\|$ through the small Gram system.

    Columns are equilibrated (they span many decades), $A^\top A = R^\top R$ (Cholesky, with a $10^{-12}$ ridge on
    the unit diagonal for nearly collinear neighbouring plays, raised up to $10^{-6}$ for identical ones), and
    `scipy.optimize.nnls` runs on $\|Rx - R^{-\top}A^\top b\|$, which differs from $\|Ax - b\|^2$ by a
    constant. The products use `einsum` (no multithreaded BLAS: on a loaded machine its spinning threads made a
    32000 × 66 QR take seconds)."""
    norms = np.sqrt(np.einsum("ij,ij->j", a, a))
    norms = np.where(norms > 0, norms, 1.0)
    an = a / norms
    gram = np.einsum("ij,ik->jk", an, an)
    for ridge in (1e-12, 1e-10, 1e-8, 1e-6):  # identical columns (plays between the levels of held steps)
        try:
            r = np.linalg.cholesky(gram + ridge * np.eye(a.shape[1])).T
            break
        except np.linalg.LinAlgError:
            continue
    else:
        raise np.linalg.LinAlgError("the design's Gram matrix is not positive definite even with a 1e-6 ridge")
    rhs = scipy.linalg.solve_triangular(r, np.einsum("ij,i->j", an, b), trans="T")
    coef, _ = scipy.optimize.nnls(r, rhs, maxiter=50 * a.shape[1])
    return coef / norms


@eqx.filter_jit
def _plays(play: PlayOperator, v):
    """The play outputs of one record, jitted once per record length and number of plays (an eager call would trace
    its scan again every time)."""
    return play(v)


# the columns of one record a start forms at once, at most (before they are cut to the least-squares rows)
COLUMNS_BUDGET = 128 * 2**20


def columns_at_rows(make, count: int, samples: int, rows) -> np.ndarray:
    """`(rows, count)` columns of one record of `samples` samples, `make(j, k)` giving columns `j:k` over the whole
    record as `(samples, k - j)`: as many at a time as fit in `COLUMNS_BUDGET`, each group cut to `rows` at once, so
    that the whole record's columns are never held (a 1e6-sample record's 64 plays at once took 512 MB)."""
    step = max(1, COLUMNS_BUDGET // (8 * max(1, samples)))
    return np.concatenate([np.asarray(make(j, min(j + step, count)))[rows] for j in range(0, count, step)], axis=1)


def _design(records, thresholds, max_rows: int | None = None):
    """Rows [v, P_r1[v], ..., P_rn[v]] of every record (demagnetised start), and the outputs: every sample, or the
    `row_subset` of at most `max_rows` (the plays run over each whole record, `columns_at_rows`)."""
    thresholds = jnp.asarray(thresholds)
    keep = row_subset([v.size for v, _ in records], max_rows)
    blocks = []
    for (v, _), k in zip(records, keep):
        vj = jnp.asarray(v)
        plays = columns_at_rows(lambda j, e, vj=vj: _plays(PlayOperator(thresholds[j:e]), vj), thresholds.shape[0],
                                v.size, k)
        blocks.append(np.column_stack([v[k], plays]))
    return np.concatenate(blocks), np.concatenate([y[k] for (_, y), k in zip(records, keep)])


def pi_weights_least_squares(
    signals: ArrayLike | Sequence[ArrayLike],
    outputs: ArrayLike | Sequence[ArrayLike],
    thresholds: ArrayLike,
    nonnegative: bool = True,
    max_rows: int | None = None,
) -> PrandtlIshlinskii:
    r"""Linear least squares for the weights of a Prandtl–Ishlinskii operator with given thresholds.

    The output $w_0 v + \sum_i w_i P_{r_i}[v]$ is linear in the weights, so for fixed thresholds they follow from one
    (non-negative, by default) least-squares solve over all records.

    **Arguments:**

    - `signals`, `outputs`: one 1-D input/output pair, or sequences of them (records of any lengths).
    - `thresholds`: the thresholds $r_i$, ascending.
    - `nonnegative`: solve with `scipy.optimize.nnls` (default) or plain least squares.
    - `max_rows`: solve on at most this many samples, a fixed random subset of every record's (the plays still run
      over whole records); `None` (default): every sample.

    **Returns:** the fitted `PrandtlIshlinskii` (exact, `smoothing = 0`).
    """
    check_max_rows(max_rows)
    return _weights(_as_records(signals, outputs), np.asarray(thresholds, dtype=float), nonnegative, max_rows)


def _weights(records, thresholds: np.ndarray, nonnegative: bool, max_rows: int | None) -> PrandtlIshlinskii:
    """`pi_weights_least_squares` on checked records."""
    a, b = _design(records, thresholds, max_rows)
    if nonnegative:
        coef = nnls_gram(a, b)
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
    max_rows: int | None = MAX_ROWS,
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
    - `max_rows`: both least squares use at most this many samples (default 200000), a fixed random subset of
      every record's when the records are longer (the plays still run over whole records): a 1e6-sample record
      starts in a fraction of the time and memory; `None`: every sample.

    **Returns:** a `PrandtlIshlinskii` with `n` strictly ascending positive thresholds.
    """
    if not isinstance(n, int) or n < 1:
        raise PiezojaxValueError(f"`n` must be a positive integer, got {n!r}")
    check_max_rows(max_rows)
    records = _as_records(signals, outputs)
    vmax = max(np.max(np.abs(v)) for v, _ in records)
    if not vmax > 0:
        raise PiezojaxValueError("`signals` are identically zero: no threshold can be identified")
    grid_size = 8 * n if grid_size is None else int(grid_size)
    if grid_size < n:
        raise PiezojaxValueError(f"`grid_size` must be at least `n` = {n}, got {grid_size}")
    grid = vmax * np.arange(1, grid_size + 1) / (grid_size + 1)
    a, b = _design(records, grid, max_rows)
    coef = nnls_gram(a, b)
    del a
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
    op = _weights(records, thresholds, True, max_rows)
    # Keep every weight strictly positive so a log/softplus reparametrisation can start from it.
    floor = 1e-3 * max(float(jnp.max(op.weights)), 1e-12)
    return PrandtlIshlinskii(jnp.maximum(op.weights, floor), op.thresholds, w0=jnp.maximum(op.w0, floor))
