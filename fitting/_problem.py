"""A calibration problem: model, data, free parameters, channel weights, and the weighted residuals."""

import math
from collections.abc import Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array, Float

import piezojax as pj
from piezojax import PiezojaxValueError
from piezojax.internal import common_float_dtype, matmul, parallel_scans, refusal_mode, scan_mode

from ._data import CHANNELS, Dataset, experiments_of
from ._predict import ExperimentArrays, Predictor, default_predictor, predict


def is_reparam(x) -> bool:
    return isinstance(x, pj.AbstractReparam)


def _key_name(k) -> str:
    if isinstance(k, jtu.GetAttrKey):
        return "." + k.name
    if isinstance(k, jtu.SequenceKey):
        return f"[{k.idx}]"
    if isinstance(k, jtu.DictKey):
        return f"[{k.key!r}]"
    return "." + str(getattr(k, "name", getattr(k, "key", k)))


def path_string(path) -> str:
    """`(GetAttrKey('hysteresis'), GetAttrKey('weights'))` → `"hysteresis.weights"` (reparam `.raw` dropped)."""
    s = "".join(_key_name(k) for k in path)
    return s[1:] if s.startswith(".") else s


def parameter_paths(model) -> dict[str, Any]:
    """The model's parameters by path (`"hysteresis.weights"`, `"dynamics.omega"`): every inexact array leaf, a
    reparametrised one (`pj.Positive`, ...) listed once under the path of its wrapper, with its constrained value."""
    out = {}
    for path, leaf in jtu.tree_flatten_with_path(model, is_leaf=is_reparam)[0]:
        if is_reparam(leaf):
            out[path_string(path)] = leaf.unwrap()
        elif eqx.is_inexact_array(leaf):
            out[path_string(path)] = leaf
    return out


def matches(path: str, selector: str) -> bool:
    return path == selector or path.startswith(selector + ".") or path.startswith(selector + "[")


def free_mask(model, free=None):
    """Boolean pytree (same structure as `model`) marking the free array leaves.

    `free`: `None` — every inexact array leaf except the fields its blocks declare as settings with `pj.setting()`
    (the hysteresis operators' `smoothing`: a continuation setting, not a parameter); a callable `where(model)`
    returning the sub-trees to free (as for `eqx.tree_at`); or a sequence of path strings (see `parameter_paths`),
    each naming a parameter or a whole block (`"hysteresis"`). A whole block frees its parameters, not its settings:
    a setting is freed only when named itself (`"hysteresis.smoothing"`, `lambda m: m.hysteresis.smoothing`).
    """
    available = list(parameter_paths(model))
    settings = [path_string(path) for path in pj.setting_key_paths(model)]

    def is_setting(p):
        return any(matches(p, s) for s in settings)

    if free is None:
        chosen = {p for p in available if not is_setting(p)}
    elif callable(free):
        marker = jtu.tree_map(lambda x: 0, model)

        def select(sub):  # 1: a parameter selected itself, 2: part of a selected block (whose settings stay fixed)
            alone = is_reparam(sub) or not isinstance(sub, eqx.Module | list | tuple | dict)
            return jtu.tree_map(lambda _: 1 if alone else 2, sub)

        try:
            marked = eqx.tree_at(free, marker, replace_fn=select)
        except Exception as e:  # noqa: BLE001 - re-raised with the argument named
            raise PiezojaxValueError(f"`free`: the selector could not be applied to the model ({e})") from e
        mask = jtu.tree_map_with_path(
            lambda path, m, x: (m == 1 or (m == 2 and not is_setting(path_string(path)))) and eqx.is_inexact_array(x),
            marked, model,
        )
        if not any(jtu.tree_leaves(mask)):
            raise PiezojaxValueError("`free` selects no inexact array parameter: nothing to fit")
        return mask
    else:
        if isinstance(free, str):
            free = [free]
        chosen = set()
        for sel in free:
            if not isinstance(sel, str):
                raise PiezojaxValueError(f"`free` entries must be parameter paths (str), got {sel!r}")
            hits = [p for p in available if matches(p, sel) and (p == sel or not is_setting(p))]
            if not hits:
                raise PiezojaxValueError(
                    f"`free`: no parameter {sel!r} in the model; available: {', '.join(available)}"
                )
            chosen.update(hits)
    if not chosen:
        raise PiezojaxValueError("`free` selects no parameter: nothing to fit")

    def mark(path, leaf):
        p = path_string(path)
        if is_reparam(leaf):
            return jtu.tree_map(lambda x: p in chosen and eqx.is_inexact_array(x), leaf)
        return p in chosen and eqx.is_inexact_array(leaf)

    return jtu.tree_map_with_path(mark, model, is_leaf=is_reparam)


class _Group(eqx.Module):
    """Experiments padded to a common length, with one dt and one set of channels."""

    data: ExperimentArrays  # stacked (E, N)
    targets: dict[str, Array]  # channel -> (E, N) measured
    masks: dict[str, Array]  # channel -> (E, N) bool
    index: tuple[int, ...] = eqx.field(static=True)  # experiment indices in the dataset
    lengths: tuple[int, ...] = eqx.field(static=True)


class _Unflatten(eqx.Module):
    """Inverse of flattening the free leaves (hashable, so that compiled steps are reused across problems)."""

    treedef: Any = eqx.field(static=True)
    shapes: tuple[tuple[int, ...], ...] = eqx.field(static=True)

    def __call__(self, theta):
        leaves, i = [], 0
        for shape in self.shapes:
            size = int(np.prod(shape, dtype=int))
            leaves.append(theta[i : i + size].reshape(shape))
            i += size
        return jtu.tree_unflatten(self.treedef, leaves)


class ProblemCore(eqx.Module):
    """Everything the residuals depend on, as one equinox Module: arrays are leaves (data, frozen parameters,
    scales), the structure is static. Two problems with the same structure and shapes share compiled code."""

    groups: tuple[_Group, ...]
    frozen: Any
    scales: Array
    unflatten: _Unflatten
    predictor: Predictor
    # the channel weights, array leaves: problems that differ only in their data's ranges share compiled code (also
    # across processes, through the persistent compilation cache)
    weights: dict[str, Array]
    chunk: int | None = eqx.field(static=True)
    # `pj.set_parallel_scans`'s mode when the problem was built: the model's recurrences are traced in it (and, being
    # static, a problem built in another mode compiles anew instead of reusing the other form)
    scan_mode: str = eqx.field(static=True, default="auto")
    # how the model's runtime checks act when traced here: "nan" (a refused point has non-finite residuals: a
    # rejected trial; no host callbacks, so the compiled steps can be cached on disk) or "raise" (`model_error`)
    refusals: str = eqx.field(static=True, default="nan")

    def params(self, u):
        return eqx.combine(self.unflatten(u * self.scales), self.frozen)

    def model_at(self, u):
        return pj.unwrap(self.params(u))

    def group_predictions(self, model, g: _Group) -> dict[str, Array]:
        d = g.data
        axes = ExperimentArrays(t=0, dt=None, v_in=0, channels={c: 0 for c in d.channels})
        return jax.vmap(lambda x: self.predictor(model, x), in_axes=(axes,))(d)

    def predictions(self, u) -> list[dict[str, Array]]:
        model = self.model_at(u)
        with parallel_scans(self.scan_mode), refusal_mode(self.refusals):
            return [self.group_predictions(model, g) for g in self.groups]

    def residuals(self, u):
        weights = dict(self.weights)
        parts = []
        for g, pred in zip(self.groups, self.predictions(u)):
            for c in g.targets:
                r = jnp.where(g.masks[c], (pred[c] - g.targets[c]) * weights[c], 0.0)
                parts.append(jnp.ravel(r))
        return jnp.concatenate(parts)

    def jacobian_t(self, u):
        """$J^\\top$, shape `(p, m)`, by forward mode (all directions at once). Holds the whole Jacobian: for long
        records prefer `normal_equations`."""
        eye = jnp.eye(u.size, dtype=u.dtype)
        return jax.vmap(lambda e: jax.jvp(self.residuals, (u,), (e,))[1])(eye)

    def chunk_size(self, g: _Group, p: int) -> int:
        """Experiments of group `g` whose Jacobian is formed at once (`chunk`, or by the memory budget)."""
        b = len(g.index)
        if self.chunk is not None:
            return max(1, min(b, self.chunk))
        if jax.default_backend() == "cpu":
            # one experiment at a time: measured faster on XLA:CPU than vmapping several (8 x 2e4 samples x 37
            # parameters: 178 vs 315 ms per linearisation; 4 x 2500: 12.9 vs 15.3 ms), and the least memory
            return 1
        m_e = sum(int(g.masks[c].shape[1]) for c in g.targets)
        itemsize = jnp.dtype(g.data.v_in.dtype).itemsize
        return max(1, min(b, _JACOBIAN_BUDGET // max(1, m_e * p * itemsize)))

    def normal_equations(self, u):
        r"""`(r, g, H)`: the weighted residuals (as `residuals`), $g = J^\top r$ and $H = J^\top J$.

        $J$ is formed by forward mode (one JVP per parameter direction, batched), one chunk of experiments at a
        time, and reduced to $g$ and $H$ at once: no $m \times p$ matrix is kept, so the memory is one chunk's
        Jacobian (`chunk_size`) plus $p^2$, whatever the number of experiments. Within a long experiment the
        directions themselves go `tangent_block` at a time (each block's JVPs hold the simulation's intermediates
        once per direction: measured 57 MB per direction on a 1e6-sample PI + creep + resonance record), into one
        $J^\top$ of the experiment; short records take every direction at once."""
        with parallel_scans(self.scan_mode), refusal_mode(self.refusals):
            return self._normal_equations(u)

    def _normal_equations(self, u):
        p = u.size
        eye = jnp.eye(p, dtype=u.dtype)
        weights = dict(self.weights)
        r_parts, g_sum, h_sum = [], jnp.zeros((p,), u.dtype), jnp.zeros((p, p), u.dtype)
        for grp in self.groups:
            d = grp.data

            def one(x, grp=grp, dt=d.dt):
                t, v_in, channels, targets, masks = x
                data = ExperimentArrays(t=t, dt=dt, v_in=v_in, channels=channels)

                def res(v):
                    pred = self.predictor(self.model_at(v), data)
                    return jnp.concatenate(
                        [jnp.where(masks[c], (pred[c] - targets[c]) * weights[c], 0.0) for c in grp.targets]
                    )

                def directions(e):
                    return jax.vmap(lambda d: jax.jvp(res, (u,), (d,)), out_axes=(None, 0))(e)

                m_e = sum(int(masks[c].shape[-1]) for c in grp.targets)
                q = tangent_block(m_e, p, u.dtype.itemsize)
                if q >= p:
                    r, jt = directions(eye)
                    return r, matmul(jt, r), matmul(jt, jt.T)
                # blocks of q directions (zero directions pad the last: zero rows of J^T, cut from g and H); the
                # residuals, the same in every block, are carried rather than stacked (stacked: one residual vector
                # per block, 13 x 16 MB of a 2e6-residual, 26-parameter linearisation's 1056 MB of temporaries)
                nb = -(-p // q)
                blocks = jnp.concatenate([eye, jnp.zeros((nb * q - p, p), u.dtype)]).reshape(nb, q, p)
                shape = jax.eval_shape(res, u)
                r, jt = jax.lax.scan(lambda _, e: directions(e), jnp.zeros(shape.shape, shape.dtype), blocks)
                jt = jt.reshape(nb * q, -1)
                return r, matmul(jt, r)[:p], matmul(jt, jt.T)[:p, :p]

            xs = (d.t, d.v_in, d.channels, grp.targets, grp.masks)
            b, bs = len(grp.index), self.chunk_size(grp, p)
            if bs >= b:
                r, gs, hs = jax.vmap(one)(xs)
            elif bs == 1:  # a plain scan: no unit batch axis (XLA:CPU copies arrays to move unit axes)
                r, gs, hs = jax.lax.map(one, xs)
            else:
                r, gs, hs = jax.lax.map(one, xs, batch_size=bs)
            g_sum, h_sum = g_sum + jnp.sum(gs, axis=0), h_sum + jnp.sum(hs, axis=0)
            n = d.v_in.shape[1]
            # back to the layout of `residuals`: channel by channel, experiments stacked
            r_parts += [jnp.ravel(r[:, i * n : (i + 1) * n]) for i in range(len(grp.targets))]
        return jnp.concatenate(r_parts), g_sum, h_sum


def free_physical_tree(params, mask) -> dict[str, Array]:
    """The free leaves of `params` (a model with reparametrisation wrappers) in physical units, by path."""
    flat = jtu.tree_flatten_with_path(params, is_leaf=is_reparam)[0]
    masks = jtu.tree_leaves(mask, is_leaf=is_reparam)
    out = {}
    for (path, leaf), m in zip(flat, masks):
        if is_reparam(leaf):
            if jtu.tree_leaves(m.raw) == [True]:
                out[path_string(path)] = leaf.unwrap()
        elif m is True:
            out[path_string(path)] = leaf
    return out


def _physical(core: ProblemCore, mask, u):
    tree = free_physical_tree(core.params(u), mask)
    return jnp.concatenate([jnp.ravel(v) for v in tree.values()])


@eqx.filter_jit
def _physical_jacobian(core: ProblemCore, mask, u):
    return jax.jacfwd(lambda v: _physical(core, mask, v))(u)


# the forward-mode Jacobian of one chunk of experiments is kept under this many bytes when `chunk` is None
_JACOBIAN_BUDGET = 256 * 2**20
# the forward-mode directions of one experiment formed together: at most this many bytes of Jacobian per block
_TANGENT_BUDGET = 32 * 2**20


def tangent_block(m: int, p: int, itemsize: int = 8) -> int:
    """Parameter directions whose JVPs `ProblemCore.normal_equations` forms together for an experiment of `m`
    residuals and `p` parameters: all of them (`p`) while that Jacobian takes at most 32 MiB, else as many as fit
    in it (at least one): a 1e6-sample record with 20 parameters goes 4 directions at a time (measured there: 603
    MB of temporaries instead of 1144, and no slower)."""
    return max(1, min(p, _TANGENT_BUDGET // max(1, m * itemsize)))


def over_starts(fn, in_axes, n_starts):
    """`fn` mapped over the starts (the arguments with `in_axes` 0): `eqx.filter_vmap`, or for a single start a plain
    call with the axis added back (a unit batch axis makes XLA:CPU copy arrays to move it: measured ~20 % of a
    linearisation)."""
    if n_starts > 1:
        return eqx.filter_vmap(fn, in_axes=in_axes)

    def call(*args):
        args = [jtu.tree_map(lambda x: x[0], a) if ax == 0 else a for a, ax in zip(args, in_axes)]
        return jtu.tree_map(lambda x: x[None], fn(*args))

    return call


@eqx.filter_jit
def linearise(core: ProblemCore, u):
    r"""`core.normal_equations` for each row of `u` (shape `(starts, p)`), under `vmap`: `(r, cost, g, H, finite)`
    with the cost $\tfrac12\|r\|^2$ and whether $g$ and $H$ are finite, per start. One compiled function for the
    solver, the problem's set-up and the results (the checks inside it, not as separate small computations)."""
    r, g, h = over_starts(core.normal_equations, (0,), u.shape[0])(u)
    finite = jnp.all(jnp.isfinite(g), axis=1) & jnp.all(jnp.isfinite(h), axis=(1, 2))
    return r, 0.5 * jnp.sum(r**2, axis=1), g, h, finite


def _normal_equations(core: ProblemCore, u):
    # through the batched function with one start: the same compiled code as a single-start fit
    r, _, g, h, _ = linearise(core, u[None])
    return r[0], g[0], h[0]


@eqx.filter_jit
def _residuals_and_jacobian(core: ProblemCore, u):
    return core.residuals(u), core.jacobian_t(u)


@eqx.filter_jit
def _residuals(core: ProblemCore, u):
    return core.residuals(u)


LOST_COLUMN = 1e-30
"""A Jacobian column whose squared norm is at most this fraction of the largest finite one counts as zero: its
digits are rounding noise or lost to underflow (`lost_columns`)."""


def lost_columns(diag) -> np.ndarray:
    r"""Per column of a Jacobian (`diag` the diagonal of $J^\top J$, any leading batch axes): a finite column whose
    squared norm is at most `LOST_COLUMN` of the largest finite one (of its row of the batch). Such a column is zero
    in exact arithmetic or has lost its digits: measured, a prehistory started at an excursion of 0 V, where the
    output's derivative in it vanishes, had a column of norm 5e-23 (rounding noise) among columns of order 1;
    scaled to a unit norm, every trial step overflowed and the fit stalled at its start. A resonance's damping
    driven to 3e-199 on a record that never excites it gave a column that underflowed."""
    diag = np.clip(np.asarray(diag, dtype=float), 0.0, None)
    finite = np.isfinite(diag)
    top = np.max(np.where(finite, diag, 0.0), axis=-1, keepdims=True, initial=0.0)
    return finite & (diag <= LOST_COLUMN * top)


def residual_counts(groups):
    """The residuals that count (the masks' true entries, over every group and target channel): a number, or one per
    entry of the masks' axes before (experiments, time), e.g. a fleet's actuators."""
    return sum(np.asarray(m).reshape(*np.shape(m)[:-2], -1).sum(axis=-1) for g in groups for m in g.masks.values())


def jacobian_scales(scales, jtj) -> np.ndarray:
    r"""The Jacobian-column scaling $s_j / \|\partial r/\partial u_j\|$ from $J^\top J$ at $u = \theta/s$ (any leading
    batch axes), rounded to powers of two (so that $\theta/s \cdot s = \theta$ exactly: the start is the user's model,
    bit for bit); a column without effect (zero, or lost: `lost_columns`) keeps its scale `s`."""
    scales, jtj = np.asarray(scales), np.asarray(jtj)
    diag = np.diagonal(jtj, axis1=-2, axis2=-1)
    norms = np.sqrt(np.clip(diag, 0.0, None))
    ok = np.isfinite(norms) & (norms > 0) & ~lost_columns(diag)
    new = np.where(ok, scales / np.where(ok, norms, 1.0), scales)
    return np.exp2(np.round(np.log2(new)))


def model_error(core: ProblemCore, u) -> str:
    """The message of the runtime check the model fails at scaled parameters `u` (first line), or "" if none does:
    the residuals traced once more with raising checks (the fit's own trace NaNs a refused point instead)."""
    import dataclasses

    try:
        jax.block_until_ready(_residuals(dataclasses.replace(core, refusals="raise"), u))
    except eqx.EquinoxRuntimeError as e:
        return str(e).strip().splitlines()[0]
    return ""


def estimate_noise_std(y: np.ndarray, order: int = 4) -> float:
    r"""Robust white-noise standard deviation of a sampled signal: the median absolute deviation of its differences
    of `order` $k$ (default 4), $\hat\sigma = \mathrm{MAD}(\Delta^k y)/(0.6745\sqrt{\binom{2k}{k}})$ — white noise of
    variance $\sigma^2$ gives $\Delta^k$ of variance $\binom{2k}{k}\sigma^2$ (6 for $k = 2$, 70 for $k = 4$), while a
    component of angular frequency $\omega$ shrinks by $(\omega\,dt)^k$, and steps make a few outliers the median
    ignores. The fourth differences keep slow, large signals out of the estimate where the second do not: on four
    records of a PI + creep + 40 Hz mode at 1 kHz with noise 1e-4 of the range, $k = 2$ overestimated the noise by
    10–100 %, $k = 4$ by at most 5 %; on the plant study's records (noise 0.1–0.5 % of the range) both were within
    5 %. It measures the sample-to-sample (white) part of the noise: noise correlated over samples comes out lower,
    and a signal's own content near the Nyquist frequency, which differences do not shrink ($\omega\,dt \approx 1$),
    counts as noise (a noise-free multisine up to 150 Hz sampled at 750 Hz reads as noisy). 0 for a signal of at most
    `order` samples."""
    if not isinstance(order, int | np.integer) or isinstance(order, bool) or order < 1:
        raise PiezojaxValueError(f"`order` must be an integer >= 1, got {order!r}")
    k = int(order)
    d = np.diff(np.asarray(y, float), k)
    if d.size == 0:
        return 0.0
    return float(np.median(np.abs(d - np.median(d))) / (0.6745 * np.sqrt(math.comb(2 * k, k))))


def channel_weights(experiments, targets: Sequence[str], weights) -> dict[str, float]:
    r"""The weight $w_c$ of each target channel over `experiments` (see `Problem`'s `weights`): `"range"` — one over
    the channel's range over all the experiments that have it; `"noise"` — one over its estimated noise level
    (`estimate_noise_std`, root mean square over the experiments); or a mapping with an entry for every target."""
    out = {}
    if isinstance(weights, Mapping):

        stray = [k for k in weights if k not in CHANNELS]  # a misspelt channel (another channel's is not used)
        if stray:
            raise PiezojaxValueError(f"`weights` has an entry for {stray[0]!r}, which is no channel (the channels: "
                                     f"{', '.join(CHANNELS)}; the targets: {', '.join(targets)})")
    for c in targets:
        ys = [np.asarray(exp.channels[c]) for exp in experiments if exp.has(c)]
        if isinstance(weights, Mapping):
            if c not in weights:
                raise PiezojaxValueError(f"`weights` has no entry for the target channel {c!r}")
            w = float(weights[c])
        elif weights == "range":
            rng = max(float(y.max()) for y in ys) - min(float(y.min()) for y in ys)
            if not rng > 0:
                raise PiezojaxValueError(f"channel {c!r} is constant in every experiment: use explicit `weights`")
            w = 1.0 / rng
        elif weights == "noise":
            sigma = float(np.sqrt(np.mean([estimate_noise_std(y) ** 2 for y in ys])))
            rng = max(float(y.max()) for y in ys) - min(float(y.min()) for y in ys)
            w = 1.0 / max(sigma, 1e-9 * rng, np.finfo(float).tiny)
        else:
            raise PiezojaxValueError(f'`weights` must be "range", "noise" or a dict, got {weights!r}')
        if not (np.isfinite(w) and w > 0):
            raise PiezojaxValueError(f"`weights[{c!r}]` must be finite and > 0, got {w}")
        out[c] = w
    return out


class Problem:
    r"""A least-squares calibration problem: weighted residuals of a model's predictions over a dataset.

    The residual vector stacks, for every experiment $e$, target channel $c$ and sample $k$,
    $r_{eck} = w_c\,(\hat y_{ec}[k] - y_{ec}[k])$. Experiments with the same sample step and channels, and lengths in
    the same power-of-2 bracket, are padded to a common length (inputs held at their last value; padded samples
    masked out — valid because every model is causal) and simulated together under `jax.vmap`.

    **Arguments:**

    - `model`: any piezojax model (an equinox Module), possibly with reparametrised leaves (`pj.Positive`, ...).
    - `dataset`: a `fitting.Dataset` (or one `fitting.Experiment`, or a sequence of them).
    - `predictor`: a `fitting.Predictor` (default: `default_predictor(model)`).
    - `targets`: channels to fit (default: every predicted channel the data contain, except the predictor's inputs).
      Every experiment must measure at least one of them (`PiezojaxValueError` naming it otherwise: it would add
      nothing to the fit).
    - `free`: which parameters are fitted (see `free_mask`); the others stay frozen.
    - `weights`: `"range"` (default: $w_c = 1/\mathrm{range}_c$ over all experiments, so each channel counts by
      its relative error), `"noise"` ($w_c = 1/\hat\sigma_c$, the robust noise estimate of `estimate_noise_std`,
      pooled over experiments — the statistically efficient choice for white noise), or a dict channel → $w_c$.
      The standard errors use the residual variance, so they do not depend on the overall scale of the weights.
    - `scales`: the scaling of the free parameters the solver works with, $\theta = s\,u$; the Levenberg–Marquardt
      damping is isotropic in $u$. `"jacobian"` (default): unit Jacobian columns at the start,
      $s_j = 1/\|\partial r/\partial\theta_j\|$ (scipy's `x_scale="jac"` frozen at the start; measured ≈ 3× fewer
      steps than value scaling on a PI + creep + dynamics fit); `"value"`: $s = |\theta_0|$ (1 where $\theta_0 = 0$);
      or an array. A parameter without effect at the start (zero column) falls back to value scaling.
    - `jacobian_chunk`: experiments whose Jacobian is formed at once when the solver builds $J^\top J$ and
      $J^\top r$ (`normal_equations`); `None` (default): one at a time on CPU (measured fastest there), on other
      backends as many as keep that chunk's Jacobian under 256 MiB. The whole $m \times p$ Jacobian is never
      kept, so the memory of a fit does not grow with the number of experiments.
    """

    def __init__(
        self,
        model,
        dataset,
        *,
        predictor: Predictor | None = None,
        targets: Sequence[str] | None = None,
        free=None,
        weights: str | Mapping[str, float] = "range",
        scales: Array | str = "jacobian",
        jacobian_chunk: int | None = None,
    ):

        if not isinstance(dataset, Dataset):
            dataset = Dataset(experiments_of(dataset))
        if len(dataset) == 0:
            raise PiezojaxValueError("`dataset` is empty")
        predictor = default_predictor(model) if predictor is None else predictor
        self._set(dataset=dataset, predictor=predictor, model=model)
        outputs, inputs = predictor.outputs, predictor.inputs
        for exp in dataset:
            missing = [c for c in inputs if not exp.has(c)]
            if missing:
                raise PiezojaxValueError(
                    f"experiment {exp.name!r} lacks the channel(s) {missing} the model reads as input"
                )
        available = {c for exp in dataset for c in exp.channels}
        if targets is None:
            targets = [c for c in outputs if c in available and c not in inputs]
            if not targets:
                raise PiezojaxValueError(
                    f"the dataset has none of the channels the model predicts ({', '.join(outputs)}); "
                    f"it has: {', '.join(sorted(available)) or 'only t and v_in'}"
                )
        else:
            if isinstance(targets, str):  # one channel, not its letters
                targets = [targets]
            targets = list(targets)
            for c in targets:
                if c not in outputs:
                    raise PiezojaxValueError(f"`targets`: the model does not predict {c!r} (it predicts {outputs})")
                if c in inputs:
                    raise PiezojaxValueError(f"`targets`: {c!r} is an input of the predictor, not a target")
                if c not in available:
                    raise PiezojaxValueError(f"`targets`: no experiment in the dataset has the channel {c!r}")
        useless = [exp.name for exp in dataset if not any(exp.has(c) for c in targets)]
        if useless:
            raise PiezojaxValueError(
                f"experiment {useless[0]!r} has none of the target channels ({', '.join(targets)}): it would add "
                "nothing to the fit; leave it out (predict it with `fitting.predict`)"
            )
        self._set(targets=tuple(targets))
        self._set(_channel_weights=self._weights(weights))

        if jacobian_chunk is not None and not (isinstance(jacobian_chunk, int) and jacobian_chunk >= 1):
            raise PiezojaxValueError(f"`jacobian_chunk` must be a positive int or None, got {jacobian_chunk!r}")
        mask = free_mask(model, free)
        free_part, frozen = eqx.partition(model, mask)
        leaves, treedef = jtu.tree_flatten(free_part)
        if not leaves:
            raise PiezojaxValueError("`free` selects no array parameter: nothing to fit")
        dtype = common_float_dtype(*leaves)
        theta0 = jnp.concatenate([jnp.ravel(jnp.asarray(x, dtype)) for x in leaves])
        unflatten = _Unflatten(treedef, tuple(tuple(x.shape) for x in leaves))
        value_scales = jnp.where(jnp.abs(theta0) > 0, jnp.abs(theta0), 1.0)
        by_jacobian = isinstance(scales, str) and scales == "jacobian"
        if scales is None or by_jacobian or (isinstance(scales, str) and scales == "value"):
            scales = value_scales
        elif isinstance(scales, str):
            raise PiezojaxValueError(f'`scales` must be "jacobian", "value" or an array, got {scales!r}')
        scales = jnp.asarray(scales, theta0.dtype)
        if scales.shape != theta0.shape or not bool(jnp.all(jnp.isfinite(scales) & (scales > 0))):
            raise PiezojaxValueError(f"`scales` must be {theta0.shape[0]} finite values > 0")
        groups = self._make_groups(dtype)
        channel_w = {c: jnp.asarray(w, dtype) for c, w in self.weights.items()}
        core = ProblemCore(tuple(groups), frozen, scales, unflatten, predictor, channel_w, jacobian_chunk,
                           scan_mode())
        if by_jacobian:
            # unit columns at the start (one Jacobian, compiled once and reused by the results' covariance)
            _, _, jtj = _normal_equations(core, theta0 / scales)
            scales = jnp.asarray(jacobian_scales(scales, jtj), theta0.dtype)
            core = eqx.tree_at(lambda c: c.scales, core, scales)
        num_residuals = int(residual_counts(groups))
        if num_residuals <= theta0.size:
            raise PiezojaxValueError(
                f"{num_residuals} data points for {theta0.size} free parameters: the fit is underdetermined"
            )
        self._set(mask=mask, core=core, theta0=theta0, u0=theta0 / scales, num_residuals=num_residuals,
                  num_params=int(theta0.size), value_scales=value_scales)

    def _set(self, **attributes):
        for k, v in attributes.items():
            object.__setattr__(self, k, v)

    def __setattr__(self, name, value):
        raise AttributeError(f"a fitting.Problem is immutable (cannot set {name!r}); build a new one, or use "
                             "`with_frozen` for another frozen part")

    def __delattr__(self, name):
        raise AttributeError(f"a fitting.Problem is immutable (cannot delete {name!r})")

    # ------------------------------------------------------------------ setup

    def _weights(self, weights) -> dict[str, float]:
        return channel_weights(self.dataset, self.targets, weights)

    def _make_groups(self, dtype) -> list[_Group]:
        keys: dict[tuple, list[int]] = {}
        for i, exp in enumerate(self.dataset):
            chans = tuple(c for c in self.targets if exp.has(c))
            if not chans:
                continue
            # pad only experiments of similar length together (within a factor 2), to bound the padding overhead
            key = (float(np.float32(exp.dt)), chans, int(np.ceil(np.log2(exp.n))))
            keys.setdefault(key, []).append(i)
        if not keys:
            raise PiezojaxValueError("no experiment has any of the target channels")
        groups = []
        inputs = self.predictor.inputs
        for (_, chans, _), idx in keys.items():
            exps = [self.dataset[i] for i in idx]
            n = max(e.n for e in exps)
            dt = float(np.mean([e.dt for e in exps]))

            def pad(x, n=n):
                x = np.asarray(x, float)
                return np.concatenate([x, np.full(n - x.size, x[-1])])

            data = ExperimentArrays(
                t=jnp.asarray(np.stack([np.arange(n) * dt + e.t[0] for e in exps]), dtype),
                dt=jnp.asarray(dt, dtype),
                v_in=jnp.asarray(np.stack([pad(e.v_in) for e in exps]), dtype),
                channels={c: jnp.asarray(np.stack([pad(e.channels[c]) for e in exps]), dtype) for c in inputs},
            )
            targets = {c: jnp.asarray(np.stack([pad(e.channels[c]) for e in exps]), dtype) for c in chans}
            # the padding, and the history before `scored_from`, are run but not scored
            masks = {c: jnp.asarray(np.stack([(np.arange(n) < e.n) & (np.arange(n) >= e.first_scored) for e in exps]))
                     for c in chans}
            groups.append(_Group(data, targets, masks, tuple(idx), tuple(e.n for e in exps)))
        return groups

    # ------------------------------------------------------------------ parameters

    @property
    def frozen(self):
        """The frozen part of the model (free leaves replaced by `None`)."""
        return self.core.frozen

    def with_frozen(self, frozen) -> "Problem":
        """A shallow copy with another frozen part of the same structure (e.g. another hysteresis `smoothing`)."""
        import copy

        new = copy.copy(self)
        new._set(core=eqx.tree_at(lambda c: c.frozen, self.core, frozen))
        return new

    @property
    def weights(self) -> dict[str, float]:
        """The weight $w_c$ of each target channel (a new dict: the problem itself does not change)."""
        return dict(self._channel_weights)

    @property
    def scales(self) -> Array:
        return self.core.scales

    def params(self, u: Float[Array, " p"]):
        """The (still reparametrised) model at scaled free parameters `u`."""
        return self.core.params(u)

    def model_at(self, u: Float[Array, " p"]):
        """The usable (unwrapped) model at scaled free parameters `u`."""
        return self.core.model_at(u)

    def parameter_names(self) -> list[str]:
        """Names of the free physical parameters, one per scalar (`"hysteresis.weights[3]"`), in `physical` order."""
        names = []
        for path, value in free_physical_tree(self.model, self.mask).items():
            a = np.asarray(value)
            names += [path] if a.ndim == 0 else [f"{path}[{j}]" for j in range(a.size)]
        return names

    def u_of(self, model, name: str = "model") -> Float[Array, " p"]:
        """The scaled free parameters `u` of `model`, a model of the same structure as the problem's (same blocks,
        shapes and reparametrisation wrappers: e.g. the initial model with other values)."""
        if jtu.tree_structure(model) != jtu.tree_structure(self.model):
            raise PiezojaxValueError(
                f"`{name}` does not have the structure of the problem's model (same blocks, parameter shapes and "
                "reparametrisations, e.g. `pj.constrain` applied the same way)"
            )
        leaves = jtu.tree_leaves(eqx.filter(model, self.mask))
        shapes = tuple(tuple(jnp.shape(x)) for x in leaves)
        if shapes != self.core.unflatten.shapes:
            raise PiezojaxValueError(f"`{name}`: free parameter shapes {shapes}, expected {self.core.unflatten.shapes}")
        theta = jnp.concatenate([jnp.ravel(jnp.asarray(x, self.theta0.dtype)) for x in leaves])
        return theta / self.scales

    def physical(self, u: Float[Array, " p"]) -> Float[Array, " q"]:
        """The free parameters in physical (constrained) units, flattened in `parameter_names` order."""
        return _physical(self.core, self.mask, u)

    def physical_jacobian(self, u: Float[Array, " p"]) -> Float[Array, "q p"]:
        """The Jacobian of `physical` at `u` (the reparametrisation's, in scaled parameters), compiled."""
        return _physical_jacobian(self.core, self.mask, u)

    # ------------------------------------------------------------------ residuals

    def residuals(self, u: Float[Array, " p"]) -> Float[Array, " m"]:
        """The weighted residual vector at scaled parameters `u` (padded entries are exactly 0); compiled, and
        differentiable in `u`."""
        return _residuals(self.core, u)

    def jacobian_t(self, u: Float[Array, " p"]) -> Float[Array, "p m"]:
        """$J^\\top$ (shape `(p, m)`) by forward mode: the whole Jacobian, `m × p` floats (the solver itself only
        forms `normal_equations`)."""
        return self.core.jacobian_t(u)

    def residuals_and_jacobian(self, u: Float[Array, " p"]) -> tuple[Array, Array]:
        """`(residuals(u), jacobian_t(u))`, compiled (cached across problems of the same structure)."""
        return _residuals_and_jacobian(self.core, u)

    def normal_equations(self, u: Float[Array, " p"]) -> tuple[Array, Array, Array]:
        """`(r, J^T r, J^T J)` at `u`, compiled, formed `jacobian_chunk` experiments at a time without keeping $J$
        (what each Levenberg–Marquardt linearisation computes)."""
        return _normal_equations(self.core, u)

    def experiment_errors(self, r) -> list[dict[str, np.ndarray]]:
        """Per experiment (dataset order), the prediction errors (predicted − measured, in channel units, unpadded
        NumPy arrays, from the experiment's `first_scored` sample on) of each target channel, from a weighted
        residual vector `r` in the layout of `residuals`."""
        r = np.asarray(r)
        if r.shape != (sum(int(np.prod(m.shape)) for g in self.core.groups for m in g.masks.values()),):
            raise PiezojaxValueError(f"`r` must be a residual vector of this problem, got shape {r.shape}")
        weights = dict(self.weights)
        out: list[dict[str, np.ndarray]] = [{} for _ in self.dataset]
        k = 0
        for g in self.core.groups:
            for c in g.targets:
                e, n = g.masks[c].shape
                block = r[k : k + e * n].reshape(e, n) / weights[c]
                k += e * n
                for j, (i, length) in enumerate(zip(g.index, g.lengths)):
                    out[i][c] = block[j, self.dataset[i].first_scored:length]
        return out

    def experiment_predictions(self, u: Float[Array, " p"]) -> list[dict[str, np.ndarray]]:
        """Per experiment (dataset order), the predicted target channels it has at `u`, NumPy arrays of its length:
        `fitting.predict` of the model at `u` (the one prediction path; the residuals compute the same, padded)."""
        model = self.model_at(u)
        out = []
        for exp in self.dataset:
            preds = predict(model, exp, predictor=self.predictor, check_finite=False)
            out.append({c: preds[c] for c in self.targets if exp.has(c)})
        return out
