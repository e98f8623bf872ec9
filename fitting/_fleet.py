r"""Calibrating a fleet: many actuators of one structure, each with its own parameters and records, in one call.

Each actuator is its own least-squares problem (`Problem`: its records, its start, its free parameters in its own
scaling). `fit_fleet` stacks the problems on a leading *fleet* axis and runs the solver's loop for all of them at
once: one iteration — trial step, linearisation at the trial point, acceptance, termination tests — is the
compiled step that `fitting.solve` takes too (`fitting._solver.step`), here with one problem per row of the fleet;
its arrays are sharded over the devices along the fleet axis (`NamedSharding`) and XLA partitions the step. A
finished actuator is frozen while the others go on. The steps are dispatched from Python, `steps_per_call` at a
time before the verdicts are read, so progress is reported and Ctrl-C keeps the last accepted parameters.

The model's runtime checks must be `piezojax`'s value checks (`check_value`, which a fleet traces as per-actuator NaN
refusals; `simulate_ode`'s failed integration, in the `BoucWenOscillator`, refuses the same way). An `eqx.error_if`
written directly in a user's model raises for the whole fleet.

Differences from `fitting.solve` (one problem, stepped from Python): every iteration linearises at the trial point,
accepted or not (under `vmap` both branches of a choice run anyway; a rejected trial of one actuator costs what an
accepted one does), and there is no smoothing continuation, multi-start or probing past kinks: an actuator whose
steps end at a kink of an exact hysteresis operator ends `"successful"` by the window test or `"stalled"`; refit it
with `fitting.solve` (starting from `result[i].params`) for those. As in `fitting.solve`, an actuator stopped by
`max_steps` while its cost no longer falls by what its data resolve is converged in practice (`settled`).
"""

import dataclasses
import time
import warnings
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from piezojax import PiezojaxValueError
from piezojax.internal import refusals_as_nan

from ._data import Dataset
from ._problem import (
    Problem,
    ProblemCore,
    channel_weights,
    jacobian_scales,
    model_error,
    over_starts,
    residual_counts,
)
from ._results import FitResult, summarise
from ._solve import SETTLED_WINDOW, PrecisionWarning, caller_level, make_solver, settled
from ._solver import (
    RESULTS,
    Progress,
    Verdict,
    as_progress_meter,
    linearise_one,
    result_names,
    start,
    step,
    verdict_of,
)


def _fleet_map(fn):
    """`fn` mapped over the fleet axis (every argument's leading axis) by `over_starts`: a batch of one is a plain
    call with the axis added back (a unit batch axis made the linearisation 1.5x as long on 2 cores, 2e4 samples)."""

    def mapped(*args):
        return over_starts(fn, (0,) * len(args), jtu.tree_leaves(args)[0].shape[0])(*args)

    return mapped


@eqx.filter_jit
def _fleet_init(solver, window, statics, arrays, u, padding):
    def one(arrays, u, padding):
        lin, finite = linearise_one(eqx.combine(arrays, statics), u)
        return start(solver, u, lin, finite, window=window, keep=SETTLED_WINDOW, padding=padding)

    return _fleet_map(one)(arrays, u, padding)


def _fleet_step(solver, window, max_rejections, statics, arrays, carry):
    """One iteration of every actuator of a batch: the compiled `step` that `iterate` takes too, here with one
    problem per row and the model linearised at each trial point; `fit_fleet` dispatches it `steps_per_call` times
    without waiting for the device, then reads the verdicts."""
    carry, _ = step(solver, statics, carry, None, rows=arrays, linearise=True, window=window,
                    max_rejections=max_rejections)
    return carry


@eqx.filter_jit
def _fleet_linearise(statics, arrays, u):
    def one(arrays, u):
        return linearise_one(eqx.combine(arrays, statics), u)[0]

    return _fleet_map(one)(arrays, u)


def _shard(tree, mesh: Mesh | None, device=None):
    """Place every array of `tree` split along its leading (fleet) axis over the mesh's devices (XLA then partitions
    the compiled loop: each device steps its share of the fleet), or on `device` without a mesh."""
    if mesh is None:
        if device is None:
            return tree
        return jtu.tree_map(lambda x: jax.device_put(x, device) if eqx.is_array(x) else x, tree)
    sharding = NamedSharding(mesh, PartitionSpec("fleet"))
    return jtu.tree_map(lambda x: jax.device_put(x, sharding) if eqx.is_array(x) else x, tree)


@dataclasses.dataclass
class FleetResult:
    """What `fit_fleet` returns: per actuator (arrays with a leading fleet axis of length `len(result)`), and a full
    `FitResult` of actuator `i` as `result[i]` (standard errors, correlations, metrics, report; built on demand from
    the fleet's last linearisation, no further simulation).

    - `params`, `model`: the fitted models stacked on a leading fleet axis (with and without their
      reparametrisation wrappers); `model_at(i)` is actuator `i`'s model alone. Simulate the whole fleet with
      `eqx.filter_vmap` (settings such as the operators' `smoothing` are stacked too; the operators still run one
      loop, see `piezojax._hysteresis.play.exact_everywhere`).
    - `success`, `codes`, `reasons`: verdicts (`fitting.RESULTS` names); `steps`, `accepted_steps`,
      `initial_cost`, `cost`: per actuator.
    - `rmse`: per target channel, each actuator's RMSE over all its records [channel units].
    - `seconds`: the wall time of the loop (not the set-up); `devices`: the devices the fleet was split over.
    """

    params: Any
    model: Any
    success: np.ndarray
    codes: list[str]
    reasons: list[str]
    steps: np.ndarray
    accepted_steps: np.ndarray
    initial_cost: np.ndarray
    cost: np.ndarray
    rmse: dict[str, np.ndarray]
    seconds: float
    devices: int
    _problem: Any = dataclasses.field(repr=False, default=None)
    _u: Any = dataclasses.field(repr=False, default=None)
    _lin: Any = dataclasses.field(repr=False, default=None)

    def __len__(self) -> int:
        return len(self.codes)

    def model_at(self, i: int):
        """Actuator `i`'s fitted model (reparametrisations unwrapped)."""
        return jtu.tree_map(lambda x: x[i] if eqx.is_array(x) else x, self.model)

    def __getitem__(self, i: int) -> FitResult:
        """Actuator `i`'s `FitResult`, as `fitting.fit` reports one fit (from the fleet's last linearisation)."""
        n = len(self)
        if isinstance(i, bool) or not isinstance(i, int | np.integer) or not -n <= i < n:
            raise PiezojaxValueError(f"actuator index must be an integer in [-{n}, {n}), got {i!r}")
        i = int(i) % n
        lin = jtu.tree_map(lambda x: x[i], self._lin)
        verdict = Verdict(self.codes[i], self.reasons[i])
        return summarise(self._problem(i), self._u[i], lin, verdict, steps=int(self.steps[i]),
                         accepted=int(self.accepted_steps[i]),
                         history=[float(self.initial_cost[i]), float(self.cost[i])], history_steps=None,
                         seconds=self.seconds / n, levels=[])

    def report(self) -> str:
        """A short text summary: verdicts by code, steps, and RMSE quantiles over the fleet."""
        lines = [f"fleet of {len(self)} actuators on {self.devices} device(s), {self.seconds:.1f} s: "
                 f"{int(np.sum(self.success))} converged"]
        codes, counts = np.unique(np.asarray(self.codes), return_counts=True)
        lines.append("  verdicts: " + ", ".join(f"{c} {k}" for c, k in zip(codes, counts)))
        lines.append(f"  steps: median {np.median(self.steps):.0f}, max {np.max(self.steps)}")
        for c, v in self.rmse.items():
            q = np.quantile(v, [0.0, 0.5, 1.0])
            lines.append(f"  {c} RMSE: min {q[0]:.4g}, median {q[1]:.4g}, max {q[2]:.4g}")
        return "\n".join(lines)


def _stack(items, what):
    """Stack equinox pytrees of one structure on a new leading axis: `(statics, arrays)`, the non-array part once
    (it must be equal across items) and the arrays stacked."""
    parts = [eqx.partition(x, eqx.is_array) for x in items]
    statics0 = parts[0][1]
    def0 = jtu.tree_structure(parts[0][0])
    for i, (arrays, statics) in enumerate(parts[1:], start=1):
        if jtu.tree_structure(arrays) != def0 or jtu.tree_structure(statics) != jtu.tree_structure(statics0):
            raise PiezojaxValueError(what(i))
        shapes = [jnp.shape(a) for a in jtu.tree_leaves(arrays)]
        if shapes != [jnp.shape(a) for a in jtu.tree_leaves(parts[0][0])]:
            raise PiezojaxValueError(what(i))
        if not all(_same(a, b) for a, b in zip(jtu.tree_leaves(statics), jtu.tree_leaves(statics0))):
            raise PiezojaxValueError(what(i))
    arrays = jtu.tree_map(lambda *xs: jnp.stack(xs), *[a for a, _ in parts])
    return statics0, arrays


def _share_frozen(statics, arrays):
    """Move the frozen model leaves that are equal for every actuator out of the stacked `arrays` into `statics`
    (one copy, mapped over by no actuator): `(statics, arrays, shared)`, `shared` the moved leaves (one copy each, in
    the layout of `arrays.frozen`).

    Why: a value the fleet stacks is mapped under `vmap`, and so is everything computed from it, one copy per
    actuator of work that is the same for all (and a mapped `smoothing` would make the operators' choice of loop,
    `exact_everywhere`, depend on every actuator's value)."""

    def equal_rows(x):  # bit for bit (-0.0 is not 0.0); a leaf numpy cannot read (PRNG keys) stays stacked
        if not eqx.is_array(x) or x.shape[0] < 1:
            return False
        try:
            a = np.ascontiguousarray(np.asarray(x))
        except TypeError:
            return False
        bits = a.view(np.uint8).reshape(a.shape[0], -1)
        return bool(np.all(bits == bits[:1]))

    mask = jtu.tree_map(equal_rows, arrays.frozen)
    shared, per_actuator = eqx.partition(arrays.frozen, mask)
    shared = jtu.tree_map(lambda x: x[0], shared)
    statics = eqx.tree_at(lambda c: c.frozen, statics, eqx.combine(shared, statics.frozen),
                          is_leaf=lambda x: x is None)
    arrays = eqx.tree_at(lambda c: c.frozen, arrays, per_actuator, is_leaf=lambda x: x is None)
    return statics, arrays, shared


def _same(a, b) -> bool:
    try:
        return bool(np.all(a == b))
    except Exception:  # noqa: BLE001 - not comparable: not the same
        return a is b


def fit_fleet(
    model,
    datasets: Sequence,
    *,
    starts: Sequence | None = None,
    predictor=None,
    targets: Sequence[str] | None = None,
    free=None,
    weights="range",
    scales="jacobian",
    jacobian_chunk: int | None = None,
    method="levenberg_marquardt",
    max_steps: int = 200,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    ftol: float = 1e-8,
    linear_solver=None,
    devices: Sequence | None = None,
    batch_size: int | None = None,
    steps_per_call: int = 10,
    max_rejections: int = 40,
    progress=True,
) -> FleetResult:
    r"""Calibrate a fleet of actuators of one structure at once: actuator $i$'s parameters fitted to its own records
    `datasets[i]`, all of them in one compiled loop (`vmap` over the fleet, split over `devices`).

    **Arguments:**

    - `model`: the model structure and, unless `starts` is given, every actuator's start (e.g. a nominal model from
      the data sheet, or one actuator's calibration); reparametrised leaves (`pj.constrain`) are kept as in `fit`.
    - `datasets`: one `fitting.Dataset` (or sequence of `Experiment`s) per actuator. Every actuator needs the same
      test protocol: the same number of records, of the same lengths (in samples), with the same channels; the
      sampling steps and values may differ.
    - `starts`: optional, one model per actuator (the structure of `model`), e.g. data-driven starts.
    - `predictor`, `targets`, `free`, `scales`, `jacobian_chunk`: as for `fitting.Problem`, per actuator (the
      Jacobian scaling of each actuator from its own start).
    - `weights`: `"range"`, `"noise"` or a mapping, as for `fitting.Problem`, computed for each actuator from its
      own records, as `fitting.fit` would (the costs of two actuators are then in their own weights; the RMSEs are
      comparable). An actuator whose records make its weight undefined (a channel constant in all of them, with
      `"range"`) is an error naming it, as `fitting.fit` would refuse it: leave it out of the fleet.
    - `method`, `max_steps`, `rtol`, `atol`, `ftol`, `linear_solver`: the solver, as for `fitting.solve`; each
      actuator also ends converged when its cost decreased by less than `ftol` relative per accepted step over the
      last five, `"stalled"` after `max_rejections` consecutive rejected trials; one stopped by `max_steps` whose
      cost fell over its last 50 accepted steps by less than cost/(m - p) (what moving one parameter by one standard
      error changes) has converged in practice, `"successful"`, as in `fitting.solve` (`fitting._solve.settled`). A
      solver instance must evaluate the residuals once per step, at its trial point (the built-in ones do).
    - `devices`: the devices the fleet is split over (its arrays sharded along the fleet axis; XLA partitions the
      compiled loop, each device stepping its share); default every device of JAX's default backend.
    - `batch_size`: actuators stepped together (over all devices; a multiple of their number); the fleet runs
      batch after batch, each until its actuators finish. Default: the whole fleet at once. Memory grows with it:
      about 4–5 times one actuator's Jacobian (records × samples × free parameters × 8 bytes) per actuator
      (measured on CPU: 131 MB per actuator for 1e5 samples and 37 parameters). The fleet is padded to a multiple
      of it with copies of the first actuator that do not run.
    - `steps_per_call`: the compiled steps dispatched before the verdicts are read (progress, Ctrl-C, the stop when
      every actuator has finished).
    - `progress`: as for `fitting.solve` (the meter's "accepted" count is the fleet's median).

    **Returns:** a `FleetResult` (per-actuator verdicts, costs and RMSEs; `result[i]` is actuator $i$'s
    `FitResult`). A failed actuator keeps its last accepted parameters, never NaN. A trial point at which one
    actuator's model refuses its parameters (a runtime check) is a rejected trial of that actuator alone
    (`piezojax._checks.refusals_as_nan`).

    ```python
    result = fitting.fit_fleet(nominal, [fitting.Dataset.from_files(f) for f in files_by_actuator],
                               free=["hysteresis", "creep", "dynamics.omega", "dynamics.zeta", "offset"])
    print(result.report()); print(result[3].report())
    ```
    """
    for name, value, low in (("max_steps", max_steps, 1), ("steps_per_call", steps_per_call, 1),
                             ("max_rejections", max_rejections, 1)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < low:
            raise PiezojaxValueError(f"`{name}` must be an integer >= {low}, got {value!r}")
    datasets, starts = _fleet_inputs(model, datasets, starts)
    n = len(datasets)
    devices_given = devices is not None
    devices = list(jax.devices()) if devices is None else list(devices)
    if not devices:
        raise PiezojaxValueError("`devices` must list at least one device")
    if batch_size is None:
        batch_size = n + (-n) % len(devices)
    elif isinstance(batch_size, bool) or not isinstance(batch_size, int | np.integer) or batch_size < 1 or (
            batch_size % len(devices)):
        raise PiezojaxValueError(f"`batch_size` must be a positive multiple of the number of devices "
                                 f"({len(devices)}), got {batch_size!r}")
    solver = make_solver(method, rtol, atol, ftol, linear_solver)
    meter = as_progress_meter(progress)
    explicit = not isinstance(scales, str)
    if not explicit and scales not in ("jacobian", "value"):
        raise PiezojaxValueError(f'`scales` must be "jacobian", "value" or an array, got {scales!r}')
    actuators = _Actuators.build(starts, datasets, predictor=predictor, targets=targets, free=free, weights=weights,
                                 jacobian_chunk=jacobian_chunk)
    fleet = _Stacked.build(actuators, scales if explicit else "value", devices, devices_given, int(batch_size),
                           jacobian_scaling=not explicit and scales == "jacobian")
    batches, interrupted, seconds = _run_batches(fleet, solver, max_rejections=max_rejections, max_steps=max_steps,
                                                 steps_per_call=steps_per_call, meter=meter)
    return _fleet_result(fleet, actuators, batches, solver, max_steps=max_steps, interrupted=interrupted,
                         seconds=seconds, devices=len(devices))


_WINDOW = 5  # accepted steps over which the loop's flat-cost test averages, as `iterate`'s default


def _fleet_inputs(model, datasets, starts) -> tuple[list, list]:
    """`fit_fleet`'s datasets (one `Dataset` per actuator) and starts (one model per actuator, `model`'s structure)."""
    if isinstance(datasets, Dataset) or not isinstance(datasets, Sequence) or len(datasets) == 0:
        raise PiezojaxValueError("`datasets` must be a non-empty sequence with one dataset per actuator")
    datasets = [d if isinstance(d, Dataset) else Dataset(list(d)) for d in datasets]
    n = len(datasets)
    if starts is None:
        return datasets, [model] * n
    starts = list(starts)
    if len(starts) != n:
        raise PiezojaxValueError(f"`starts` must list one model per actuator ({n}), got {len(starts)}")
    for i, s in enumerate(starts):
        if jtu.tree_structure(s) != jtu.tree_structure(model):
            raise PiezojaxValueError(f"`starts[{i}]` does not have the structure of `model` (same blocks, "
                                     "parameter shapes and reparametrisations)")
    return datasets, starts


@dataclasses.dataclass(frozen=True)
class _Actuators:
    """The fleet's actuators: each one's start and records, the options they share, and each one's channel weights
    (from its own records, so that its fit is the one `fitting.fit` makes: a solver's path depends on the weights'
    scale through the step size)."""

    starts: list
    datasets: list
    predictor: Any
    targets: tuple
    free: Any
    weights: list
    jacobian_chunk: int | None

    @classmethod
    def build(cls, starts, datasets, *, predictor, targets, free, weights, jacobian_chunk) -> "_Actuators":
        first = Problem(starts[0], datasets[0], predictor=predictor, targets=targets, free=free, weights=weights,
                        scales="value", jacobian_chunk=jacobian_chunk)
        targets = first.targets

        def weights_of(i):
            try:
                return channel_weights(list(datasets[i]), targets, weights)
            except PiezojaxValueError as e:
                raise PiezojaxValueError(f"actuator {i}: {e}") from e

        per_actuator = [dict(first.weights)] + [weights_of(i) for i in range(1, len(datasets))]
        return cls(starts, datasets, first.predictor, targets, free, per_actuator, jacobian_chunk)

    def problem(self, i: int, scales) -> Problem:
        """Actuator `i`'s problem with the parameter scaling `scales`."""
        try:
            return Problem(self.starts[i], self.datasets[i], predictor=self.predictor, targets=self.targets,
                           free=self.free, weights=self.weights[i], scales=scales, jacobian_chunk=self.jacobian_chunk)
        except PiezojaxValueError as e:
            raise PiezojaxValueError(f"actuator {i}: {e}") from e


@dataclasses.dataclass(frozen=True)
class _Stacked:
    """The actuators' problems stacked along a leading fleet axis (padded to whole batches with copies of the first,
    which do not run), their frozen leaves shared by all where equal, placed on the devices."""

    statics: Any
    arrays: Any
    shared: Any
    u0: jax.Array
    theta0: jax.Array
    padding: jax.Array
    mesh: Mesh | None
    device: Any
    batch_size: int
    n: int
    jacobian_scaling: bool

    @classmethod
    def build(cls, actuators: _Actuators, scales, devices, devices_given: bool, batch_size: int, *,
              jacobian_scaling: bool) -> "_Stacked":
        # value scaling, or the given scales (the Jacobian scaling is computed batch by batch for the whole fleet)
        n = len(actuators.datasets)

        def mismatch(i):
            return (f"`datasets[{i}]` does not have the layout of `datasets[0]`: every actuator needs the same number "
                    "of records, of the same lengths in samples and with the same channels (the same test protocol)")

        problems = [actuators.problem(i, scales) for i in range(n)]
        statics, arrays = _stack([p.core for p in problems], mismatch)
        u0 = jnp.stack([p.u0 for p in problems])
        theta0 = jnp.stack([p.theta0 for p in problems])  # to rescale the starts exactly (powers of two)
        del problems  # their data live on in `arrays`; a `FitResult` rebuilds one on demand
        if u0.dtype != jnp.float64:
            warnings.warn(f"fitting in {u0.dtype}: JAX's 64-bit mode is off (see fitting.solve)", PrecisionWarning,
                          stacklevel=caller_level())
        mesh = Mesh(np.array(devices), ("fleet",)) if len(devices) > 1 else None
        total = n + (-n) % batch_size
        padding = jnp.arange(total) >= n
        if total > n:  # padded with copies of the first actuator, which do not run
            arrays, u0, theta0 = jtu.tree_map(lambda x: jnp.concatenate([x, jnp.repeat(x[:1], total - n, axis=0)]),
                                              (arrays, u0, theta0))
        device = devices[0] if devices_given and len(devices) == 1 else None
        statics, arrays, shared = _share_frozen(statics, arrays)
        if mesh is not None or device is not None:  # the shared leaves: one copy on each device
            where = device if mesh is None else NamedSharding(mesh, PartitionSpec())
            statics = jtu.tree_map(lambda x: jax.device_put(x, where) if eqx.is_array(x) else x, statics)
        return cls(statics, arrays, shared, u0, theta0, padding, mesh, device, batch_size, n, jacobian_scaling)

    @property
    def total(self) -> int:
        return self.padding.shape[0]

    def begin_batch(self, solver, b0: int) -> dict:
        """The batch from actuator `b0` on, placed and initialised (with the fleet's Jacobian scaling)."""
        part = slice(b0, b0 + self.batch_size)
        arr_b, u_b, th_b, pad_b = _shard(jtu.tree_map(lambda x: x[part], (self.arrays, self.u0, self.theta0,
                                                                          self.padding)), self.mesh, self.device)
        if self.jacobian_scaling:
            lin = _fleet_linearise(self.statics, arr_b, u_b)
            old = np.asarray(arr_b.scales)
            new = jacobian_scales(old, lin.h).astype(old.dtype)
            u_b = _shard(jnp.asarray(np.asarray(th_b) / new), self.mesh, self.device)  # the same starts, exactly
            arr_b = _shard(eqx.tree_at(lambda a: a.scales, arr_b, jnp.asarray(new)), self.mesh, self.device)
        carry = _fleet_init(solver, _WINDOW, self.statics, arr_b, u_b, pad_b)
        return {"carry": carry, "arrays": arr_b, "initial": np.asarray(carry.lin.cost), "finished": False}

    def not_begun(self, solver, b0: int) -> dict:
        """A batch that Ctrl-C kept from starting: its starts, every other number NaN."""
        part = slice(b0, b0 + self.batch_size)
        arr_b, u_b, pad_b = jtu.tree_map(lambda x: x[part], (self.arrays, self.u0, self.padding))
        shapes = eqx.filter_eval_shape(_fleet_init, solver, _WINDOW, self.statics, arr_b, u_b, pad_b)
        carry = jtu.tree_map(lambda x: jnp.full(x.shape, np.nan if jnp.issubdtype(x.dtype, jnp.inexact) else 0,
                                                x.dtype), shapes)
        result = jax.vmap(lambda p: RESULTS.where(p, RESULTS.padding, RESULTS.running))(pad_b)
        carry = eqx.tree_at(lambda c: (c.y, c.book.result), carry, (u_b, result))
        return {"carry": carry, "arrays": arr_b, "initial": np.full(u_b.shape[0], np.nan), "finished": False}


def _run_batches(fleet: _Stacked, solver, *, max_rejections: int, max_steps: int, steps_per_call: int,
                 meter) -> tuple[list[dict], bool, float]:
    """Each batch stepped `steps_per_call` compiled steps at a time until its actuators stop or `max_steps`:
    `(batches, interrupted, seconds)`; after Ctrl-C the batches not begun are filled in."""
    n, batch_size = fleet.n, fleet.batch_size
    batches, t0, interrupted = [], time.perf_counter(), False
    meter_state = meter.init("[fleet] ", n)
    with refusals_as_nan():
        try:
            for b0 in range(0, fleet.total, batch_size):
                batches.append(fleet.begin_batch(solver, b0))
                batch = batches[-1]
                done = 0
                while done < max_steps:
                    for _ in range(min(steps_per_call, max_steps - done)):  # dispatched without waiting
                        batch["carry"] = _fleet_step(solver, _WINDOW, max_rejections, fleet.statics, batch["arrays"],
                                                     batch["carry"])
                    done = min(done + steps_per_call, max_steps)
                    running_b = np.asarray(batch["carry"].running)
                    running = int(np.sum(running_b)) + max(0, n - b0 - batch_size)
                    best = float(np.nanmin(np.concatenate([np.asarray(b["carry"].lin.cost) for b in batches])[:n]))
                    accepted = np.concatenate([np.asarray(b["carry"].book.accepted) for b in batches])[:n]
                    meter_state = meter.step(meter_state, Progress(
                        "[fleet] ", done, best, int(np.median(accepted)), running, n, time.perf_counter() - t0))
                    if not np.any(running_b):
                        break
                batch["finished"] = True
        except KeyboardInterrupt:
            interrupted = True
        finally:
            meter.close(meter_state)
    for b0 in range(len(batches) * batch_size, fleet.total, batch_size):  # after Ctrl-C: the batches not begun
        batches.append(fleet.not_begun(solver, b0))
    jax.block_until_ready([b["carry"] for b in batches])
    return batches, interrupted, time.perf_counter() - t0


def _fleet_result(fleet: _Stacked, actuators: _Actuators, batches: list[dict], solver, *, max_steps: int,
                  interrupted: bool, seconds: float, devices: int) -> "FleetResult":
    """The batches joined into one `FleetResult`, with each actuator's verdict."""
    n = fleet.n
    # an actuator still running when the loop ended: interrupted, unless its batch ran to max_steps
    cut = np.concatenate([np.full(b["carry"].y.shape[0], not b["finished"]) for b in batches])[:n]

    def joined(get):
        return jtu.tree_map(lambda *xs: jnp.concatenate(xs)[:n], *[get(b) for b in batches])

    carry = joined(lambda b: b["carry"])
    core_arrays = joined(lambda b: b["arrays"])
    # the result's problems hold every array per actuator: the shared frozen leaves repeated along the fleet axis
    stacked = jtu.tree_map(lambda x: jnp.broadcast_to(x, (n, *x.shape)), fleet.shared)
    core_arrays = eqx.tree_at(lambda c: c.frozen, core_arrays, eqx.combine(stacked, core_arrays.frozen),
                              is_leaf=lambda x: x is None)
    statics = eqx.tree_at(lambda c: c.frozen, fleet.statics, eqx.filter(fleet.statics.frozen, eqx.is_array,
                                                                         inverse=True),
                          is_leaf=lambda x: x is None)
    core = eqx.combine(core_arrays, statics)
    initial_cost = np.concatenate([b["initial"] for b in batches])[:n]
    scales_np = np.asarray(core.scales)
    names = result_names(carry.book.result)
    since = np.asarray(carry.book.since)
    stalled_note = ", or a kink of an exact operator: refit with fitting.solve"
    verdicts = [verdict_of(name, solver=solver, window=_WINDOW, since=int(k), max_steps=max_steps,
                           interrupted=interrupted and bool(cut[i]), stalled_note=stalled_note)
                for i, (name, k) in enumerate(zip(names, since))]
    # as `fitting.solve`: an actuator stopped by max_steps whose cost no longer falls by what its data resolve
    accepted = np.asarray(carry.book.accepted)
    tails = np.asarray(carry.book.recent)
    targets = actuators.targets
    rmse = _rmse(core, np.asarray(carry.lin.r), {c: np.array([w[c] for w in actuators.weights]) for c in targets})
    m = np.asarray(residual_counts(core.groups))
    verdicts = [settled(v, list(tails[i][-1 - min(int(accepted[i]), SETTLED_WINDOW):]), int(carry.steps[i]),
                        int(m[i]), int(carry.y.shape[1])) for i, v in enumerate(verdicts)]
    for i, v in enumerate(verdicts):
        if v.code == "nonfinite_initial":  # the model's own message, from a trace that raises
            why = model_error(actuators.problem(i, scales_np[i]).core, carry.y[i])
            verdicts[i] = Verdict(v.code, v.reason + (f" ({why})" if why else ""))
    params = jax.vmap(lambda c, u: c.params(u))(core, carry.y)
    model_out = jax.vmap(lambda c, u: c.model_at(u))(core, carry.y)
    return FleetResult(
        params=params,
        model=model_out,
        success=np.array([v.success for v in verdicts]),
        codes=[v.code for v in verdicts],
        reasons=[v.reason for v in verdicts],
        steps=np.asarray(carry.steps),
        accepted_steps=np.asarray(carry.book.accepted),
        initial_cost=initial_cost,
        cost=np.asarray(carry.lin.cost),
        rmse=rmse,
        seconds=seconds,
        devices=devices,
        _problem=lambda i: actuators.problem(i, scales_np[i]),  # actuator i's problem in the fleet's scaling
        _u=carry.y,
        _lin=carry.lin,
    )


def _rmse(core: ProblemCore, r: np.ndarray, weights: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per target channel, each actuator's RMSE over its records, from the stacked residuals (layout of
    `ProblemCore.residuals`: group by group, channel by channel, experiments stacked) and each actuator's channel
    weights (`weights[c]`, shape `(fleet,)`)."""
    sums: dict[str, np.ndarray] = {}
    counts: dict[str, np.ndarray] = {}
    k = 0
    for g in core.groups:
        for c in g.targets:
            mask = np.asarray(g.masks[c])  # (fleet, experiments, time)
            size = mask[0].size
            block = r[:, k: k + size] / weights[c][:, None]
            k += size
            sums[c] = sums.get(c, 0.0) + np.sum(block**2, axis=1)
            counts[c] = counts.get(c, 0) + mask.reshape(mask.shape[0], -1).sum(axis=1)
    return {c: np.sqrt(sums[c] / np.maximum(counts[c], 1)) for c in sums}
