"""The composed piezoelectric actuator: voltage → hysteresis → creep → dynamics → displacement, plus its charge."""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, PyTree

from ._actuator_inverse import ActuatorInverse, actuator_inverse
from ._checks import PiezojaxValueError, check_finite, check_positive, check_scalar, check_signal, check_step
from ._config import use_parallel_scan
from ._creep.base import AbstractCreep, AbstractFusedCreep
from ._creep.linear import LinearCreep
from ._custom_types import Signal, SignalLike
from ._dtypes import cast_module, module_float_dtype
from ._hysteresis.base import AbstractHysteresis
from ._hysteresis.play import exact_cell, exact_flag
from ._linear.base import AbstractLinearSystem
from ._linear.delay import Delay, delay_signal

_STRUCTURES = ("parallel", "series")


class ActuatorOutput(eqx.Module):
    """What an `Actuator` simulation returns: three signals of the input's length (batched under `vmap`).

    **Fields:**

    - `displacement`: $\\delta_k$ [m].
    - `charge`: $q_k$ on the electrodes [C].
    - `current`: $i_k$ drawn from the source [A] (see `Actuator` for its sampled definition).
    """

    displacement: Float[Array, " time"]
    charge: Float[Array, " time"]
    current: Float[Array, " time"]


class Actuator(eqx.Module):
    r"""A piezoelectric actuator as one differentiable model: hysteresis, creep and linear dynamics, and its charge.

    Displacement (the Hammerstein chain of papers 000/001), with $\mathcal{H}$ the hysteresis, $\mathcal{C}$ the
    creep and $G(s)$ the structural dynamics:

    - `structure="parallel"` (default; what papers 000 and 001 use):
      $\delta = G(s)\big[\mathcal{H}[V_{in}] + \mathcal{C}[V_{in}]\big]$. Paper 001 puts the PI operator $F_H$ and
      the creep transfer function $F_C(s)$ (eq. 9) in parallel, both driven by $V_{in}$ (its eq. 4 subtracts
      $F_C(s)V_{in} + F_H(V_{in})$); paper 000 drives $G(s)$ with a term proportional to $V_{in}$ plus a creep term
      ($F_t$, eq. 9). Use a creep-only block here ($h(0^+) = 0$: `KelvinVoigtCreep(..., k0=None)`,
      `LogarithmicCreep(..., instantaneous=False)`, or a `LinearCreep` with $a_0 = 0$), else its instantaneous
      part duplicates the hysteresis' linear term $w_0$.
    - `structure="series"`: $\delta = G(s)\big[\mathcal{C}[\mathcal{H}[V_{in}]]\big]$, the chain
      V_in → hysteresis → creep → dynamics, with a DC-normalised creep ($h(0^+) = 1$ plus slow parts), so the creep
      scales with the hysteretic (polarisation) output.

    A missing block is the identity (`hysteresis=None`: $\mathcal{H}[V] = V$; `dynamics=None`: $G = 1$); a missing
    creep means no creep (both structures then give $\delta = G[\mathcal{H}[V_{in}]]$).

    Initial state and offset. Before the record the voltage has been 0 long enough for everything to settle, with
    the hysteresis in its initial state: demagnetised (default), `hysteresis_state` (the operator's state, as its
    `init()` / `scan` return it), or that state after a *prehistory* excursion $0 \to u_p \to 0$
    (`prehistory` $= u_p$ [V], one fitted scalar for the remanent polarisation a real actuator keeps from its last
    use). Its output at $V = 0$ is the remanent value $h_r$; the creep (series: settled at its input $h_r$; parallel:
    at rest, its input $V$ is 0) and the dynamics (settled at its input $u_r$) start in equilibrium, so the model
    reads $\delta = b + G(0)\,u_r + G[u - u_r]$ with $b$ = `offset`, the displacement sensor's zero (it does not
    enter the charge). With neither a prehistory nor a state, $h_r$ is the demagnetised operator's output at
    $V = 0$: 0 for the operators that `rests_at_zero` (play, stop, PI, Gaussian Preisach, Maxwell slip, Bouc–Wen, and
    the output polynomial or scaled operator of one), where $u_r = 0$ and
    the model starts from rest, not necessarily for others (a Preisach operator's $c + \sum_i \mu_i R_i$), where
    the creep and the dynamics start settled at it as after a prehistory.

    Charge and current (paper 003 after Goldfarb & Celanovic, $q = C V_p + T_{em} x$; paper 000 $Q = C_r V_{in} +
    Q_\delta$ with $Q_\delta \propto \delta$): $q_k = C_p V_k + T\,\delta_k$, so the displacement-coupled charge
    carries the hysteresis, creep and dynamics of $\delta$. The current is the charge increment over the sample,
    $i_k = (q_k - q_{k-1})/dt$ with $q_{-1} = 0$ (at rest before the record): the exact mean current over
    $[t_{k-1}, t_k]$, equal to the derivative of the piecewise-linear interpolant of $q$ on that interval, and
    $dt\sum_{j \le k} i_j = q_k$ exactly (what a charge integrator would read). $i_0 = q_0/dt$ is the charging
    of the electrodes when the record starts at $V_0 \ne 0$.

    Every array leaf (the blocks' parameters, `capacitance`, `coupling`) is a parameter: `jax.jacfwd` with respect
    to the whole module gives the sensitivities of every output. Works under `jit`, `vmap` (batches of equal-length
    experiments), `jax.grad` and `jax.jacfwd`.

    **Arguments:**

    - `hysteresis`: an `AbstractHysteresis` (e.g. `PrandtlIshlinskii`), or `None`.
    - `creep`: an `AbstractCreep` (`LogarithmicCreep`, `KelvinVoigtCreep`, `LinearCreep`), an
      `AbstractLinearSystem` (wrapped as `LinearCreep`), or `None`.
    - `dynamics`: an `AbstractLinearSystem` $G(s)$ from the driving term to displacement, or `None`.
    - `capacitance`: $C_p \ge 0$ [F], finite.
    - `coupling`: $T$ [C/m], the charge per unit displacement, finite (default 0).
    - `structure`: `"parallel"` or `"series"` (static).
    - `offset`: $b$ [m], the displacement sensor's zero, finite (default 0).
    - `prehistory`: $u_p$ [V], finite, or `None` (default) for no excursion before the record. Needs a hysteresis.
    - `hysteresis_state`: the hysteresis state before the prehistory (a PyTree like `hysteresis.init()`), or
      `None` (default) for demagnetised. Needs a hysteresis.
    - `delay`: a `pj.Delay`, the dead time between the recorded voltage and the one the actuator sees (an
      amplifier's latency; the charge follows the delayed voltage too), or `None` (default) for none.

    **Example:**

    ```python
    act = pj.Actuator(pj.PrandtlIshlinskii(w, r, w0=1.0), pj.KelvinVoigtCreep([20.0], [2.0], k0=None),
                      pj.StableTransferFunction(1e-7, omega=[2 * jnp.pi * 800], zeta=[0.05]), capacitance=1.7e-9)
    out = act.simulate(v_in, dt=1e-4)   # out.displacement, out.charge, out.current
    ```
    """

    hysteresis: AbstractHysteresis | None
    creep: AbstractCreep | None
    dynamics: AbstractLinearSystem | None
    capacitance: Float[Array, ""]
    coupling: Float[Array, ""]
    offset: Float[Array, ""]
    prehistory: Float[Array, ""] | None
    hysteresis_state: PyTree[Array] | None
    structure: str = eqx.field(static=True)
    delay: Delay | None = None

    def __init__(
        self,
        hysteresis: AbstractHysteresis | None = None,
        creep: AbstractCreep | AbstractLinearSystem | None = None,
        dynamics: AbstractLinearSystem | None = None,
        capacitance: ArrayLike = 0.0,
        coupling: ArrayLike = 0.0,
        structure: str = "parallel",
        *,
        offset: ArrayLike = 0.0,
        prehistory: ArrayLike | None = None,
        hysteresis_state: PyTree[ArrayLike] | None = None,
        delay: Delay | None = None,
    ):
        if hysteresis is not None and not isinstance(hysteresis, AbstractHysteresis):
            raise PiezojaxValueError(
                f"`hysteresis` must be an AbstractHysteresis or None, got {type(hysteresis).__name__}"
            )
        if isinstance(creep, AbstractLinearSystem):
            creep = LinearCreep(creep)
        if creep is not None and not isinstance(creep, AbstractCreep):
            raise PiezojaxValueError(
                f"`creep` must be an AbstractCreep, an AbstractLinearSystem or None, got {type(creep).__name__}"
            )
        if dynamics is not None and not isinstance(dynamics, AbstractLinearSystem):
            raise PiezojaxValueError(
                f"`dynamics` must be an AbstractLinearSystem or None, got {type(dynamics).__name__}"
            )
        if structure not in _STRUCTURES:
            raise PiezojaxValueError(f"`structure` must be one of {_STRUCTURES}, got {structure!r}")
        # plain numbers follow the blocks' dtype (float32 blocks stay float32)
        typed = [x for x in (capacitance, coupling, offset, prehistory) if hasattr(x, "dtype")]
        dtype = module_float_dtype((hysteresis, creep, dynamics), *typed)
        self.hysteresis = hysteresis
        self.creep = creep
        self.dynamics = dynamics
        capacitance = check_scalar(capacitance, "capacitance", dtype, finite=False)
        self.capacitance = check_positive(capacitance, "capacitance", allow_zero=True)
        self.coupling = check_scalar(coupling, "coupling", dtype)
        self.offset = check_scalar(offset, "offset", dtype)
        if (prehistory is not None or hysteresis_state is not None) and hysteresis is None:
            name = "prehistory" if prehistory is not None else "hysteresis_state"
            raise PiezojaxValueError(f"`{name}` sets the hysteresis' initial state; the actuator has no hysteresis")
        self.prehistory = None if prehistory is None else check_scalar(prehistory, "prehistory", dtype)
        if hysteresis_state is not None:
            hysteresis_state = _check_state(hysteresis, hysteresis_state)
        self.hysteresis_state = hysteresis_state
        self.structure = structure
        if delay is not None and not isinstance(delay, Delay):
            raise PiezojaxValueError(f"`delay` must be a pj.Delay or None, got {type(delay).__name__}")
        self.delay = delay

    def check(self) -> "Actuator":
        """`self` with the value checks of `capacitance` and `coupling` attached (`check_value`); each block checks
        its own parameters when it runs."""
        c = check_positive(self.capacitance, "capacitance", allow_zero=True)
        checked = (c, check_finite(self.coupling, "coupling"), check_finite(self.offset, "offset"))
        out = eqx.tree_at(lambda m: (m.capacitance, m.coupling, m.offset), self, checked)
        if self.prehistory is not None:
            out = eqx.tree_at(lambda m: m.prehistory, out, check_finite(self.prehistory, "prehistory"))
        return out

    def initial_state(self) -> tuple[PyTree[Array] | None, Array]:
        """The hysteresis state at the start of the record and the remanent hysteresis output $h_r$ at $V = 0$.

        **Returns:** `(state, h_r)`; `(None, 0)` when the actuator starts from rest (no prehistory, no state, and
        an operator that `rests_at_zero` or none).
        """
        return self._initial(module_float_dtype(self))

    def drive(self, v_in: SignalLike, dt: ArrayLike, hold: str = "zoh") -> Signal:
        r"""The input of the dynamics: $\mathcal{H}[V] + \mathcal{C}[V]$ (parallel) or $\mathcal{C}[\mathcal{H}[V]]$
        (series), from the initial state; equal to the quasi-static displacement less the offset when $G(0) = 1$.
        Same arguments as `simulate`."""
        m, v, dt = self._prepare(v_in, dt, hold)
        return m._drive(m, v, dt, hold, m._initial(v.dtype))[0]

    def simulate(self, v_in: SignalLike, dt: ArrayLike, hold: str = "zoh") -> ActuatorOutput:
        """Simulate one experiment from the initial state (default: from rest, demagnetised, $V = 0$ before).

        **Arguments:**

        - `v_in`: applied voltage samples [V] (real, finite), shape `(time,)`; `jax.vmap` over a batch of
          equal-length records.
        - `dt`: sample step [s] (scalar > 0).
        - `hold`: how the creep and dynamics see their sampled inputs between samples, `"zoh"` or `"foh"`.

        **Returns:** an `ActuatorOutput` with `displacement`, `charge`, `current`, each of shape `(time,)`.

        An exact play/stop-cell hysteresis whose `smoothing` is a concrete 0 (or none), a finite-state creep (or
        none) and the dynamics run in one loop on the CPU (ZOH), with the derivatives of the block-by-block pass;
        everything else block by block (see the comment above `_blocks` in this module).
        """
        m, v, dt = self._prepare(v_in, dt, hold)
        initial = m._initial(v.dtype)
        if _one_loop(m, v, hold):
            return _one_loop_or_blocks(m, v, dt, initial)
        return _blocks(m, v, dt, hold, initial)

    def __call__(self, v_in: SignalLike, dt: ArrayLike, hold: str = "zoh") -> ActuatorOutput:
        """Same as `simulate`."""
        return self.simulate(v_in, dt, hold)

    def inverse(
        self,
        lower: ArrayLike | None = None,
        upper: ArrayLike | None = None,
        *,
        bandwidth: ArrayLike | None = None,
        relative_degree: int | None = None,
        iterations: int = 20,
        preview: bool = True,
        max_iterations: int = 100,
    ) -> "ActuatorInverse":
        r"""The whole-actuator inverse for open-loop feedforward: `inv(delta_d, dt)` is the voltage whose simulated
        displacement follows `delta_d` (see `ActuatorInverse` for the method and its accuracy).

        **Arguments:**

        - `lower`, `upper`: the admissible voltage range [V]; both or neither. With them the hysteresis is inverted
          by per-sample root finding that saturates there; without, the analytic inverse where the operator has
          one (`PrandtlIshlinskii`, e.g. `MaxwellSlip.as_prandtl_ishlinskii(...)`), else a `PiezojaxValueError`.
        - `bandwidth`: $\omega_f$ [rad/s] of the low-pass that makes the dynamics' inverse proper (default: the
          fastest pole of the dynamics, which needs concrete values: give it to build under `jit`, `vmap` or
          `grad`; see `AbstractLinearSystem.inverse`).
        - `relative_degree`: the dynamics' relative degree (default: computed; give it to build under `jit`, `vmap`
          or `grad`).
        - `iterations`: fixed-point iterations through the creep (default 20).
        - `preview`: read the reference ahead by the low-pass's delay (default True).
        - `max_iterations`: root-finding iterations per sample at most.

        **Returns:** an `ActuatorInverse`.

        ```python
        inv = actuator.inverse(lower=0.0, upper=150.0)
        v = inv(delta_desired, dt)               # actuator.simulate(v, dt).displacement ~ delta_desired
        ```
        """
        return actuator_inverse(self, lower, upper, bandwidth, relative_degree, iterations, preview, max_iterations)

    # -------------------------------------------------------------------------------------------------------------

    def _prepare(self, v_in, dt, hold):
        if hold not in ("zoh", "foh"):
            raise PiezojaxValueError(f'`hold` must be "zoh" or "foh", got {hold!r}')
        dtype = module_float_dtype(self, v_in, dt)
        v = check_signal(v_in, "v_in", dtype)
        dt = check_step(dt, "dt", dtype)
        m = cast_module(self, dtype).check()
        if m.delay is not None:
            v = delay_signal(v, check_positive(m.delay.time, "delay.time", allow_zero=True) / dt)
        return m, v, dt

    def _initial(self, dtype):
        zero = jnp.zeros((), dtype)
        if self.hysteresis is None or (self.prehistory is None and self.hysteresis_state is None
                                       and getattr(self.hysteresis, "rests_at_zero", True)):
            return None, zero
        # settled at the operator's output at V = 0: after a prehistory, from a given state, or demagnetised for
        # an operator whose output is not 0 there (`rests_at_zero`, e.g. a Preisach operator; a component set past
        # the type check with `eqx.tree_at` that has no such attribute starts from rest, as any did before)
        path = jnp.zeros((1,), dtype)
        if self.prehistory is not None:
            path = jnp.stack([self.prehistory.astype(dtype), zero])
        state, h = self.hysteresis.scan(path, self.hysteresis_state)
        return state, h[-1]

    def _rest_drive(self, initial) -> Array:
        """$u_r$, the dynamics' input before the record (at $V = 0$, settled)."""
        state, h_r = initial
        if self.creep is not None and self.structure == "series" and state is not None:
            return self.creep.settled_gain() * h_r
        return h_r

    @staticmethod
    def _drive(m: "Actuator", v: Array, dt: Array, hold: str, initial) -> tuple[Array, Array]:
        """The dynamics' input and its value $u_r$ before the record."""
        state, h_r = initial
        h = v if m.hysteresis is None else m.hysteresis.scan(v, state)[1]
        u_r = m._rest_drive(initial)
        if m.creep is None:
            return h, u_r
        if m.structure == "series":
            return m.creep.simulate(h, dt, hold=hold, u0=None if state is None else h_r), u_r
        return h + m.creep.simulate(v, dt, hold=hold), u_r


# ---------------------------------------------------------------------------------------------------------------------
# The outputs, block by block or in one loop.
#
# Block by block, each block runs its own loop over the record (its fast path: the hand-derived sensitivities of the
# play operators and lags, the parallel-in-time forms on an accelerator). On XLA:CPU every sequential loop costs
# ~15-25 ns per sample whatever little it does, so the forward pass of an exact PI + creep + dynamics chain took
# ~3x a compiled loop's time. The one-loop pass runs the three blocks' per-sample cells in one `lax.scan`
# (`experiments.bench_dynamics` measures both against numba). It is the value of a
# `jax.custom_jvp` whose derivative rule is the block-by-block pass's: derivatives (and the values they come with,
# which differ from the one-loop values by rounding) are exactly those of the blocks.
# ---------------------------------------------------------------------------------------------------------------------


def _blocks(m: Actuator, v: Array, dt: Array, hold: str, initial) -> ActuatorOutput:
    u, u_r = m._drive(m, v, dt, hold, initial)
    if m.dynamics is None:
        delta = u
    elif initial[0] is None:
        delta = m.dynamics.simulate(u, dt, hold=hold)
    else:
        delta = m.dynamics.simulate(u, dt, x0=m.dynamics.equilibrium_state(u_r), hold=hold)
    return _outputs(m, v, dt, initial, delta)


def _outputs(m: Actuator, v: Array, dt: Array, initial, delta: Array) -> ActuatorOutput:
    """The outputs from the displacement before the offset `delta`."""
    charge = m.capacitance * v + m.coupling * delta
    # before the record: V = 0 and the displacement at its remanent value (the charge's zero)
    u_r = m._rest_drive(initial)
    charge0 = m.coupling * (u_r if m.dynamics is None or initial[0] is None else m.dynamics.dc_gain() * u_r)
    current = jnp.diff(charge, prepend=charge0[None]) / dt
    return ActuatorOutput(delta + m.offset, charge, current)


def _one_loop(m: Actuator, v: Array, hold: str) -> bool:
    """Whether `simulate` runs the one-loop pass: zero-order hold, sequential loops (see `pj.set_parallel_scans`: by
    default on the CPU, and for records shorter than `PARALLEL_MIN_LENGTH` on an accelerator), an
    `AbstractFusedHysteresis` whose `smoothing` is a concrete 0 (or none), and an `AbstractFusedCreep` (or none): the
    blocks declare it.

    A traced `smoothing` (a fit's parameters, `eqx.filter_jit` over the model) keeps the block-by-block pass: choosing
    between the two passes at run time would compile both (measured on `experiments.bench_calibration`'s fit: 1.8 s
    more compilation, no faster steps, since a fit's time goes to linearisations, which run the blocks anyway)."""
    if hold != "zoh" or use_parallel_scan(v.shape[0]):
        return False
    if m.hysteresis is not None:
        if exact_cell(m.hysteresis) is None or exact_flag(m.hysteresis.smoothing) is not True:
            return False
    return m.creep is None or isinstance(m.creep, AbstractFusedCreep)


def _one_loop_or_blocks(m: Actuator, v: Array, dt: Array, initial) -> ActuatorOutput:
    # The blocks' parameter checks and the cells (the discretisation checks its matrices) before the values become
    # inputs of the custom_jvp, where they are traced: a model with concrete parameters closed over in `jit` still
    # raises `PiezojaxValueError` at once, as block by block.
    if m.hysteresis is not None:
        m = eqx.tree_at(lambda a: a.hysteresis, m, m.hysteresis.check())
    if m.creep is not None:
        m = eqx.tree_at(lambda a: a.creep, m, m.creep.check())
    cells = (
        None if m.creep is None else m.creep.zoh_cell(dt),
        None if m.dynamics is None else m.dynamics.discretise(dt, "zoh"),
    )
    # Only traced values enter the custom_jvp: concrete ones (a concrete 0 smoothing above all) stay concrete for the
    # blocks' rules, which then compile their exact branch alone.
    dynamic, static = eqx.partition((m, v, dt, initial, cells), lambda x: isinstance(x, jax.core.Tracer))

    def blocks(dynamic):
        m, v, dt, initial, _ = eqx.combine(dynamic, static)
        return _blocks(m, v, dt, "zoh", initial)

    @jax.custom_jvp
    def outputs(dynamic):
        return _one_loop_pass(*eqx.combine(dynamic, static))

    def rule(primals, tangents):
        # Only the leaves with a tangent are differentiated: the others (the signal, dt, fixed parameters) stay
        # "no tangent" for the blocks' own rules, which then skip their input-tangent loops.
        leaves, treedef = jax.tree_util.tree_flatten(primals[0])
        dleaves = treedef.flatten_up_to(tangents[0])
        live = [i for i, d in enumerate(dleaves) if not isinstance(d, jax.custom_derivatives.SymbolicZero)]

        def of_live(*xs):
            full = list(leaves)
            for i, x in zip(live, xs, strict=True):
                full[i] = x
            return blocks(jax.tree_util.tree_unflatten(treedef, full))

        if not live:
            out = of_live()
            return out, jax.tree_util.tree_map(jnp.zeros_like, out)
        return jax.jvp(of_live, [leaves[i] for i in live], [dleaves[i] for i in live])

    outputs.defjvp(rule, symbolic_zeros=True)
    return outputs(dynamic)


def _one_loop_pass(m: Actuator, v: Array, dt: Array, initial, cells) -> ActuatorOutput:
    """The exact chain's outputs, every block's cell in one `lax.scan` (the blocks already checked, `cells` the
    creep's and the dynamics' ZOH cells)."""
    state, h_r = initial
    step_h = None if m.hysteresis is None else exact_cell(m.hysteresis)
    if m.hysteresis is not None and state is None:
        state = m.hysteresis.init()
    zero = jnp.zeros((), v.dtype)
    creep, dynamics = cells
    shift = settled = zero
    if m.creep is not None and m.structure == "series" and initial[0] is not None:
        # settled at the remanent input h_r: settled_gain * h_r + C[h - h_r], as `AbstractCreep.simulate`
        shift, settled = h_r, m.creep.settled_gain() * h_r
    if dynamics is not None:
        x0 = None if initial[0] is None else m.dynamics.equilibrium_state(m._rest_drive(initial))
        xi_d = dynamics.init_state(x0, zero)
    xi_c = None if creep is None else jnp.zeros((creep.order,), v.dtype)

    def body(carry, vk):
        hs, xc, xd = carry
        h = vk
        if step_h is not None:
            hs, h = step_h(hs, vk)
        u = h
        if creep is not None:
            if m.structure == "series":
                xc, c = creep.step(xc, h - shift)
                u = settled + c
            else:
                xc, c = creep.step(xc, vk)
                u = h + c
        d = u
        if dynamics is not None:
            xd, d = dynamics.step(xd, u)
        return (hs, xc, xd), d

    # unroll=1: as fast as 2 or 4 and faster than 8 (XLA:CPU, jax 0.10.2, PI(16) + 2 lags + 2nd order); the charge
    # and current after the loop, elementwise: ~25 % faster than as outputs of the loop (measured there too)
    delta = jax.lax.scan(body, (state, xi_c, None if dynamics is None else xi_d), v)[1]
    return _outputs(m, v, dt, initial, delta)


def _check_state(hysteresis: AbstractHysteresis, state):
    """`state` as arrays of `hysteresis.init()`'s structure, shapes and dtype, or one clear error."""
    ref = hysteresis.init()
    try:
        arrays = jax.tree_util.tree_map(lambda r, x: jnp.asarray(x, r.dtype), ref, state)
    except (ValueError, TypeError) as e:
        raise PiezojaxValueError(
            f"`hysteresis_state` must have the structure of `hysteresis.init()` "
            f"({jax.tree_util.tree_structure(ref)}), got {jax.tree_util.tree_structure(state)}"
        ) from e
    for i, (r, x) in enumerate(zip(jax.tree_util.tree_leaves(ref), jax.tree_util.tree_leaves(arrays), strict=True)):
        if r.shape != x.shape:
            raise PiezojaxValueError(
                f"`hysteresis_state` leaf {i} must have shape {tuple(r.shape)} (as `hysteresis.init()`), "
                f"got {tuple(x.shape)}"
            )
        check_finite(x, "hysteresis_state")
    return arrays
