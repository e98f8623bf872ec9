"""The electromechanical piezo actuator model of Goldfarb & Celanovic with Maxwell-slip voltage hysteresis."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._checks import PiezojaxValueError, as_float_array, check_positive, check_scalar, check_value, check_vector
from .._dtypes import common_float_dtype
from .._linear.transfer_function import TransferFunction
from ._input import check_samples, check_step

_SCALARS = ("m", "b", "k", "capacitance")


def _clip(x: Array, lo: Array, hi: Array) -> Array:
    # `jnp.clip` splits the derivative 0.5/0.5 at exact ties (e.g. a saturated element with no charge change);
    # here a tie takes the bound, whose derivative is the right one for a saturated element.
    return jnp.where(x >= hi, hi, jnp.where(x <= lo, lo, x))


def maxwell_voltages(s0: Array, q0: Array, q: Array, caps: Array, limits: Array) -> Array:
    r"""Element voltages of a Maxwell-slip hysteresis after the charge moves straight from `q0` to `q`.

    $V_i = \mathrm{clip}(s_{0,i} + (q - q_0)/C_i,\ -v_i,\ v_i)$: each element is a capacitor $C_i$ in series with
    a breakaway (slip) voltage $v_i$; it sticks (linear in $q$) until $|V_i| = v_i$, then slips at $\pm v_i$.
    """
    return _clip(s0 + (q - q0) / caps, -limits, limits)


def solve_charge(s0: Array, q0: Array, rhs: Array, capacitance: Array, caps: Array, limits: Array):
    r"""Exact solution of the implicit charge equation $q + C\,V_H(q) = \text{rhs}$ for the Maxwell-slip $V_H$.

    $V_H(q) = \sum_i V_i(q)$ (`maxwell_voltages`) is piecewise linear and non-decreasing in $q$, so
    $g(q) = q + C V_H(q) - \text{rhs}$ is piecewise linear with slope $\ge 1$. Element $i$ is saturated high at the
    root iff $g$ is $\le 0$ at its upper breakpoint $q_0 + C_i(v_i - s_{0,i})$, low iff $g \ge 0$ at its lower one;
    the others stick, and on that set the equation is linear:
    $q - q_0 = \dfrac{\text{rhs} - q_0 - C(\sum_{hi} v_i - \sum_{lo} v_i + \sum_{stick} s_{0,i})}
    {1 + C\sum_{stick} 1/C_i}$. Differentiable (almost everywhere) through this formula.

    **Returns:** `(q, V_H, element voltages)`.
    """
    up = caps * (limits - s0)
    down = -caps * (limits + s0)
    breaks = jnp.concatenate([up, down])

    def g(delta):
        return delta + capacitance * jnp.sum(_clip(s0 + delta / caps, -limits, limits)) - (rhs - q0)

    gb = jax.vmap(g)(jax.lax.stop_gradient(breaks))
    n = caps.shape[0]
    hi = gb[:n] <= 0
    lo = (gb[n:] >= 0) & ~hi
    stick = ~(hi | lo)
    zero = jnp.zeros_like(s0)
    fixed = jnp.sum(jnp.where(hi, limits, zero)) - jnp.sum(jnp.where(lo, limits, zero))
    fixed = fixed + jnp.sum(jnp.where(stick, s0, zero))
    slope = 1.0 + capacitance * jnp.sum(jnp.where(stick, 1.0 / caps, zero))
    delta = (rhs - q0 - capacitance * fixed) / slope
    volts = jnp.where(hi, limits, jnp.where(lo, -limits, s0 + delta / caps))
    return q0 + delta, jnp.sum(volts), volts


class ElectromechanicalActuator(eqx.Module):
    r"""Lumped electromechanical piezo actuator (Goldfarb & Celanovic; Quant 2009 thesis §3.3) with Maxwell-slip
    hysteresis between voltage and charge.

    $$V_{in} = V_H + V_p,\quad q = C\,V_p + T_{em}(V_{in})\,x,\quad
      m\ddot x + b\dot x + k x = T_{em}(V_{in})\,V_p - F_{ext},\quad V_H = \sum_i V_i(q)$$

    with Maxwell-slip elements (capacitance $C_i$, breakaway voltage $v_i$), each sticking
    ($\dot V_i = \dot q / C_i$) while $|V_i| < v_i$ and slipping at $V_i = \pm v_i$ otherwise. The voltage-dependent
    electromechanical coefficient (the thesis fits $d_{31}$ as a function of the input voltage, Fig. 33) is a
    polynomial in $V_{in}$: $T_{em}(V) = \sum_j t_j V^j$ (`t_em`, ascending powers; one entry = constant).

    **Our reading with a voltage-dependent $T_{em}$.** The thesis' equations of §3.3.2 are missing from our copy; its
    nomenclature names a transformer current $\dot q_T$ and force $F_T$, as in Goldfarb & Celanovic, where
    $q = C V_p + q_T$ with $\dot q_T = T\dot x$. For a constant $T$ that is $q = C V_p + T x$, the form used here. With
    $T_{em}(V_{in})$ the two differ by $\int T'(V_{in})\dot V_{in} x\,dt$: we keep the algebraic form
    $q = C V_p + T_{em}(V_{in}) x$, the quasi-static charge of a coefficient measured as a function of the voltage
    (the thesis' $d_{31}(V)$, Fig. 33), which is not power-conserving as a two-port ($V_p \dot q_T \ne F_T \dot x$).
    Measured with $T = 0.5 + 2\cdot10^{-3}V - 10^{-5}V^2$ on a 0–100 V, 10 Hz triangle: the displacement of the two
    forms differs by up to 0.5 % of its range and the charge by up to 5 % (an independent RK4 reference of the
    transformer form); with a constant $T$ they agree within that reference's integration error, 1e-5.

    **Implicit loop.** $V_H$ depends on $q$, which depends on $V_p = V_{in} - V_H$: at every evaluation of the
    vector field the equation $q + C V_H(q) = C V_{in} + T_{em} x$ is solved exactly (`solve_charge`), never lagged.

    **Element states.** The elements are path dependent. They are advanced exactly along the charge path at every
    integration step: within a step the vector field uses $V_i(q)$ from the step's initial element state
    (`maxwell_voltages`), and at the step's end the state is updated to that value. This is exact whenever $q$ is
    monotone within each step (true except within one step of a charge reversal, where the error is bounded by
    the reversal's overshoot within that step and vanishes as the step shrinks), rate-independent, and
    differentiable (clamped elements have derivative 1 with respect to their breakaway voltage).

    **Integration.** The mechanics $(x, \dot x)$ are integrated with diffrax `Tsit5` (explicit; `solver.step`),
    `substeps` fixed steps per sample, in a `lax.scan`; forward and reverse mode, `jit` and `vmap` all work. Explicit
    steps need $h(\sqrt{k/m} + b/m) \le 3$ with $h = dt/\text{substeps}$: checked (`eqx.error_if`).

    **Inputs.** $V_{in}$ and $F_{ext}$ from samples with `hold="linear"` (default) or `"zoh"`; the element state starts
    relaxed ($V_i = 0$ at $q = 0$) and $x = \dot x = 0$ at $t = 0$.

    **Arguments:**

    - `m` (> 0), `b` (≥ 0), `k` (≥ 0): mass, damping, stiffness.
    - `capacitance` (> 0): the linear capacitance $C$.
    - `t_em`: polynomial coefficients of $T_{em}(V_{in})$ (N/V), shape `(p,)`.
    - `element_capacitances` (> 0), `breakaway_voltages` (≥ 0): Maxwell-slip elements, shape `(n,)`, n ≥ 0
      (n = 0 or zero breakaway voltages: no hysteresis).

    All real and finite: otherwise a `PiezojaxValueError` naming the argument (`eqx.error_if` under `jit`).

    ```python
    act = ElectromechanicalActuator(m=0.01, b=5.0, k=1e5, capacitance=1e-6, t_em=[0.5],
                                    element_capacitances=jnp.full(5, 2e-6), breakaway_voltages=jnp.arange(1., 6.))
    out = act.simulate(v_in, dt=1e-4)  # dict: x, q, v_h, v_p at the sample times
    ```
    """

    m: Float[Array, ""]
    b: Float[Array, ""]
    k: Float[Array, ""]
    capacitance: Float[Array, ""]
    t_em: Float[Array, " p"]
    element_capacitances: Float[Array, " n"]
    breakaway_voltages: Float[Array, " n"]

    def __init__(self, m, b, k, capacitance, t_em, element_capacitances=(), breakaway_voltages=()):
        self.m = check_scalar(m, "m")
        self.b = check_scalar(b, "b")
        self.k = check_scalar(k, "k")
        self.capacitance = check_scalar(capacitance, "capacitance")
        self.t_em = check_vector(jnp.atleast_1d(as_float_array(t_em, "t_em")), "t_em")
        self.element_capacitances = check_vector(element_capacitances, "element_capacitances", allow_empty=True)
        self.breakaway_voltages = check_vector(breakaway_voltages, "breakaway_voltages", allow_empty=True)
        if self.element_capacitances.shape != self.breakaway_voltages.shape:
            raise PiezojaxValueError(
                "`element_capacitances` and `breakaway_voltages` must have the same shape, got "
                f"{tuple(self.element_capacitances.shape)} and {tuple(self.breakaway_voltages.shape)}"
            )
        for name, positive in (("m", True), ("b", False), ("k", False), ("capacitance", True),
                               ("element_capacitances", True), ("breakaway_voltages", False)):
            setattr(self, name, check_positive(getattr(self, name), name, allow_zero=not positive))

    def check(self) -> "ElectromechanicalActuator":
        """Return `self` with one value check of every parameter attached (raised now if concrete, one
        `eqx.branched_error_if` if traced)."""
        names = ("m", "capacitance", "element_capacitances", "b", "k", "breakaway_voltages", "t_em")

        def ok(p):
            pos = [jnp.all(jnp.isfinite(x) & (x > 0)) for x in p[:3]]
            nonneg = [jnp.all(jnp.isfinite(x) & (x >= 0)) for x in p[3:6]]
            return jnp.stack(pos + nonneg + [jnp.all(jnp.isfinite(p[6]))])

        messages = [f"ElectromechanicalActuator: `{n}` must be finite and > 0" for n in names[:3]]
        messages += [f"ElectromechanicalActuator: `{n}` must be finite and >= 0" for n in names[3:6]]
        messages += ["ElectromechanicalActuator: `t_em` contains NaN or infinite values"]
        params = check_value(tuple(getattr(self, n) for n in names), ok, messages)
        return eqx.tree_at(lambda s: tuple(getattr(s, n) for n in names), self, params)

    def coupling(self, v_in: Array) -> Array:
        r"""$T_{em}(V_{in}) = \sum_j t_j V_{in}^j$."""
        return jnp.polyval(self.t_em[::-1], v_in)

    def _accel(self, y, v_in, f_ext, s0, q0):
        x, xd = y[0], y[1]
        t_em = self.coupling(v_in)
        q, v_h, _ = solve_charge(s0, q0, self.capacitance * v_in + t_em * x, self.capacitance,
                                 self.element_capacitances, self.breakaway_voltages)
        v_p = v_in - v_h
        acc = (t_em * v_p - f_ext - self.b * xd - self.k * x) / self.m
        return jnp.stack([xd, acc]), q, v_h

    def simulate(
        self,
        v_in: ArrayLike,
        dt: ArrayLike,
        f_ext: ArrayLike | None = None,
        *,
        hold: str = "linear",
        substeps: int = 8,
    ) -> dict[str, Float[Array, " time"]]:
        r"""Simulate from rest under the voltage samples `v_in` (and external force samples `f_ext`).

        **Arguments:**

        - `v_in`: applied voltage (V) at $t_k = k\,dt$, shape `(time,)`.
        - `dt`: sample period (s, > 0).
        - `f_ext`: external force (N), same shape as `v_in` (default 0).
        - `hold`: `"linear"` or `"zoh"` between samples (both inputs).
        - `substeps`: fixed Tsit5 steps per sample.

        **Returns:** dict of signals at the sample times: `x` (m), `v` (velocity, m/s), `q` (C), `v_h` (V),
        `v_p` (V).
        """
        if hold not in ("linear", "zoh"):
            raise PiezojaxValueError(f"`hold` must be 'linear' or 'zoh', got {hold!r}")
        if not isinstance(substeps, int) or substeps < 1:
            raise PiezojaxValueError(f"`substeps` must be a positive int, got {substeps!r}")
        v_in = check_samples(v_in, "v_in")
        if v_in.ndim != 1:
            raise PiezojaxValueError(f"`v_in` must be 1-D of shape (time,), got shape {tuple(v_in.shape)}")
        if f_ext is None:
            f_ext = jnp.zeros_like(v_in)
        f_ext = check_samples(f_ext, "f_ext")
        if f_ext.shape != v_in.shape:
            raise PiezojaxValueError(
                f"`f_ext` must have the same shape as `v_in` {tuple(v_in.shape)}, got {tuple(f_ext.shape)}"
            )
        leaves = [x for x in jax.tree_util.tree_leaves(self) if eqx.is_array(x)]
        dtype = common_float_dtype(v_in, f_ext, dt, *leaves)
        v_in, f_ext = v_in.astype(dtype), f_ext.astype(dtype)
        dt = check_step(dt, "dt", dtype)
        model = jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype) if eqx.is_array(x) else x, self).check()
        h = dt / substeps
        # Bound on the mechanical eigenvalues |lambda| <= sqrt(k/m) + b/m; explicit Tsit5 is stable for |h lambda| < 3.
        h = check_value(h, lambda x: x * (jnp.sqrt(model.k / model.m) + model.b / model.m) <= 3.0,
                        "`dt / substeps` too large for the mechanics (explicit Tsit5 needs h*(sqrt(k/m) + b/m) <= 3): "
                        "increase `substeps` or decrease `dt`")

        # Per-sample input pieces u(t_k + tau) = a + b tau on [t_k, t_k+1]; after the last sample the input is held.
        inputs = jnp.stack([v_in, f_ext], axis=1)
        nxt = jnp.concatenate([inputs[1:], inputs[-1:]], axis=0)
        slopes = (nxt - inputs) / dt if hold == "linear" else jnp.zeros_like(inputs)

        # "bounded": a stage loop that forward mode (jacfwd) and reverse mode (grad) can both differentiate.
        solver = diffrax.Tsit5(scan_kind="bounded")
        n_el = model.element_capacitances.shape[0]

        def substep(carry, j, a, slope):
            y, s0, q0 = carry
            t_start = j * h

            def vf(tau, yy, args):
                u = a + slope * (t_start + tau)
                return model._accel(yy, u[0], u[1], s0, q0)[0]

            term = diffrax.ODETerm(vf)
            tau0 = jnp.zeros((), dtype)
            state = solver.init(term, tau0, h, y, None)
            y1, _, _, _, _ = solver.step(term, tau0, h, y, None, state, made_jump=True)
            u1 = a + slope * (t_start + h)
            q1, _, _ = solve_charge(s0, q0, model.capacitance * u1[0] + model.coupling(u1[0]) * y1[0],
                                    model.capacitance, model.element_capacitances, model.breakaway_voltages)
            s1 = maxwell_voltages(s0, q0, q1, model.element_capacitances, model.breakaway_voltages)
            return (y1, s1, q1), None

        def sample(carry, ab):
            a, slope = ab
            y, s0, q0 = carry
            _, q, v_h = model._accel(y, a[0], a[1], s0, q0)
            out = jnp.stack([y[0], y[1], q, v_h, a[0] - v_h])
            # the elements move with the charge's jump at the sample (a zero-order hold's step of the input): the
            # substeps start from the state after it, not on a straight path from before it (first order in h)
            carry = (y, maxwell_voltages(s0, q0, q, model.element_capacitances, model.breakaway_voltages), q)
            carry, _ = jax.lax.scan(lambda c, j: substep(c, j, a, slope), carry,
                                    jnp.arange(substeps, dtype=dtype))
            return carry, out

        carry0 = (jnp.zeros(2, dtype), jnp.zeros(n_el, dtype), jnp.zeros((), dtype))
        _, outs = jax.lax.scan(sample, carry0, (inputs, slopes))
        return dict(x=outs[:, 0], v=outs[:, 1], q=outs[:, 2], v_h=outs[:, 3], v_p=outs[:, 4])

    def inverse(
        self,
        *,
        dynamics: bool = True,
        bandwidth: ArrayLike | None = None,
        preview: bool = True,
        iterations: int = 8,
    ) -> "ElectromechanicalInverse":
        r"""The inverse model for open-loop feedforward (paper 003 Fig. 49–50): `inv(x_d, dt)` is the voltage whose
        simulated displacement follows `x_d` (see `ElectromechanicalInverse` for the method and its accuracy).

        **Arguments:**

        - `dynamics`: invert the mechanics (default); `False` for the quasi-static inverse (force $k x_d$: the
          electrical part, hysteresis and $T_{em}(V)$, only).
        - `bandwidth`: $\omega_f$ [rad/s] of the low-pass that makes the mechanics' inverse proper (default
          $\sqrt{k/m} + b/m$, above the resonance; see `AbstractLinearSystem.inverse`).
        - `preview`: read the reference ahead by the low-pass's delay $2/\omega_f$ (default True).
        - `iterations`: Newton iterations per sample on the voltage (default 8; one suffices for a constant
          $T_{em}$).

        **Returns:** an `ElectromechanicalInverse`.

        ```python
        v = act.inverse()(x_desired, dt)        # act.simulate(v, dt)["x"] ~ x_desired
        ```
        """
        if not isinstance(dynamics, bool) or not isinstance(preview, bool):
            raise PiezojaxValueError(f"`dynamics` and `preview` must be True or False, got {dynamics!r}, {preview!r}")
        if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
            raise PiezojaxValueError(f"`iterations` must be an int >= 1, got {iterations!r}")
        model = self.check()
        dtype = model.m.dtype
        if not dynamics:
            return ElectromechanicalInverse(model, None, None, jnp.zeros((), dtype), iterations, preview)
        if bandwidth is None:
            bandwidth = jnp.sqrt(model.k / model.m) + model.b / model.m
        bandwidth = check_positive(check_scalar(bandwidth, "bandwidth"), "bandwidth").astype(dtype)
        # G(s) = 1 / (m s^2 + b s + k): force -> displacement; its inverse with a 2nd-order low-pass is the force
        plant = TransferFunction(jnp.ones((1,), dtype), jnp.stack([model.m, model.b, model.k]))
        one = jnp.ones((), dtype)
        lowpass = TransferFunction(jnp.stack([bandwidth**2]), jnp.stack([one, 2 * bandwidth, bandwidth**2]))
        return ElectromechanicalInverse(model, plant.inverse(bandwidth, 2), lowpass, 2.0 / bandwidth, iterations,
                                        preview)


def _voltage_residual(model: ElectromechanicalActuator, v, force, x, s0, q0):
    # r(V) = V - V_H(q) - V_p with V_p = F / T(V), q = C V_p + T(V) x, V_H the elements moved from (s0, q0) to q
    t_em = model.coupling(v)
    v_p = force / t_em
    q = model.capacitance * v_p + t_em * x
    v_h = jnp.sum(maxwell_voltages(s0, q0, q, model.element_capacitances, model.breakaway_voltages))
    return v - v_h - v_p, q


def electrical_inverse(model: ElectromechanicalActuator, force: Array, x: Array, iterations: int = 8):
    r"""The voltages $V_k$ that give the transducer force $T_{em}(V_k)\,V_{p,k}$ = `force[k]` at displacement
    `x[k]`, sample by sample from the relaxed state: Newton's iteration on $r(V) = V - V_H(q(V)) - F/T_{em}(V)$,
    $q(V) = C F/T_{em}(V) + T_{em}(V)\,x$, from the previous sample's voltage, safeguarded by bisection inside the
    bracket of sign changes seen so far (the Maxwell-slip kinks), then the elements are moved to the new charge
    (`maxwell_voltages`). $r$ is usually increasing in $V$; where it is not (a sticking element of small $C_i$ with
    $T_{em}'(V)\,x < 0$) the bisection still finds a root, and any root is a valid inverse. The first derivatives
    are those of the implicit function $r(V) = 0$ (not of the iterations); higher derivatives are not.
    **Returns:** `(voltage, charge, |residual|)`, each `(time,)`."""

    frozen = jax.lax.stop_gradient(model)

    def sample(carry, fx):
        s0, q0, v = carry
        f, xk = fx

        def residual(mdl, u, f, xk, s0, q0):
            return _voltage_residual(mdl, u, f, xk, s0, q0)[0]

        def newton(state, _):
            # Newton's step while it stays inside the bracket [lo, hi] of the sign changes seen so far, bisection
            # otherwise: r(V) is increasing but only piecewise smooth (each element's stick-slip kink; an element
            # of tiny capacitance is a near-jump), where plain Newton can cycle across a kink.
            u, lo, hi = state
            r, dr = jax.jvp(lambda w: residual(frozen, w, *args), (u,), (jnp.ones_like(u),))
            lo = jnp.where(r <= 0, u, lo)
            hi = jnp.where(r >= 0, u, hi)
            step = u - r / jnp.where(dr > 0, dr, 1.0)
            inside = jnp.isfinite(step) & (step >= lo) & (step <= hi) & (dr > 0)
            bracketed = jnp.isfinite(lo) & jnp.isfinite(hi)
            u = jnp.where(inside, step, jnp.where(bracketed, 0.5 * (lo + hi), u - r))
            return (u, lo, hi), None

        args = jax.lax.stop_gradient((f, xk, s0, q0))
        inf = jnp.full_like(v, jnp.inf)
        (v, _, _), _ = jax.lax.scan(newton, (jax.lax.stop_gradient(v), -inf, inf), None, length=iterations)
        # the value found, with the implicit function's derivative: dv = -(dr/dtheta) / (dr/dv)
        r, dr = jax.jvp(lambda w: residual(frozen, w, *args), (v,), (jnp.ones_like(v),))
        r_live = residual(model, v, f, xk, s0, q0)
        v = v - (r_live - jax.lax.stop_gradient(r_live)) / jnp.where(dr != 0, dr, 1.0)
        r, q = _voltage_residual(model, v, f, xk, s0, q0)
        s1 = maxwell_voltages(s0, q0, q, model.element_capacitances, model.breakaway_voltages)
        return (s1, q, v), jnp.stack([v, q, jnp.abs(r)])

    dtype = force.dtype
    n_el = model.element_capacitances.shape[0]
    carry0 = (jnp.zeros(n_el, dtype), jnp.zeros((), dtype), jnp.zeros((), dtype))
    _, out = jax.lax.scan(sample, carry0, (force, x))
    return out[:, 0], out[:, 1], out[:, 2]


class ElectromechanicalInverse(eqx.Module):
    r"""The voltage that makes an `ElectromechanicalActuator` follow a desired displacement (paper 003 §6.2,
    Fig. 49–50, the inverse model for open-loop linearisation). Built by `ElectromechanicalActuator.inverse()`.

    The model is inverted from its output back:

    1. **Mechanics.** The transducer force $F = T_{em}(V)V_p$ that moves $x$ along $x_d$ is
       $F = (m s^2 + b s + k)\,x_d$; it is made proper with the unit-DC-gain low-pass $(\omega_f/(s+\omega_f))^2$
       (`AbstractLinearSystem.inverse` of $1/(ms^2+bs+k)$), so the displacement the force produces is
       $x_f = x_d$ low-passed, and with `preview` the reference is read $2/\omega_f$ ahead (the low-pass's delay
       to first order; plus $dt/2$ for `hold="zoh"`). Quasi-static (`dynamics=False`): $F = k x_d$, $x_f = x_d$.
    2. **Electrical part** (`electrical_inverse`): per sample, the voltage $V$ with
       $V = V_H(q) + F/T_{em}(V)$, $q = C\,F/T_{em}(V) + T_{em}(V)\,x_f$, by Newton's iteration (safeguarded by
       bisection at the elements' kinks) from the previous sample's voltage, the Maxwell-slip elements advanced
       exactly along the charge (as `simulate` does). With
       a constant $T_{em}$ the equation is explicit ($V_p = F/T$, $q$ and $V_H(q)$ follow) and one iteration is exact.

    So `act.simulate(inv(x_d, dt), dt)["x"]` follows $x_d$ with the low-pass's error $O((\omega/\omega_f)^2)$ at
    frequency $\omega$ and the sampling error of the held drive. The electrical part inverts the forward model's own
    samples to round-off wherever the charge is monotone over each sample; within a sample of a charge reversal it
    differs by the forward model's own path error there (see `ElectromechanicalActuator`: the elements move along the
    straight path between samples here, along the sub-steps there). The reference must start at rest ($x_d = 0$:
    the model starts relaxed). If a Newton iteration ends with a residual above $10^{-6}$ of the voltage scale, the
    call fails (`eqx.error_if`) rather than return it: raise `iterations`. $T_{em}(V)$ must not vanish on the voltages
    used.
    Works under `jit`, `vmap` and differentiation with respect to the reference and the model's parameters.

    **Fields:** `actuator`, `dynamics_inverse` (a `StateSpace`, or `None` when quasi-static), `lowpass` (the
    low-pass as a `TransferFunction`, or `None`), `delay` [s],
    `iterations`, `preview`.
    """

    actuator: ElectromechanicalActuator
    dynamics_inverse: eqx.Module | None
    lowpass: eqx.Module | None
    delay: Array
    iterations: int = eqx.field(static=True)
    preview: bool = eqx.field(static=True)

    def __call__(self, displacement: ArrayLike, dt: ArrayLike, hold: str = "linear") -> Array:
        """The voltage samples for the desired `displacement` (1-D, real, finite, starting at 0), sample step `dt`
        [s] and the `hold` the actuator will be simulated with (`"linear"` or `"zoh"`). **Returns:** voltage [V],
        the shape of `displacement`."""
        if hold not in ("linear", "zoh"):
            raise PiezojaxValueError(f"`hold` must be 'linear' or 'zoh', got {hold!r}")
        target = check_samples(displacement, "displacement")
        if target.ndim != 1:
            raise PiezojaxValueError(f"`displacement` must be 1-D of shape (time,), got shape {tuple(target.shape)}")
        leaves = [x for x in jax.tree_util.tree_leaves(self) if eqx.is_array(x)]
        dtype = common_float_dtype(target, dt, *leaves)
        target = target.astype(dtype)
        dt = check_step(dt, "dt", dtype)
        m = jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype) if eqx.is_array(x) else x, self)
        act = m.actuator.check()
        if m.dynamics_inverse is None:
            force, x = act.k * target, target
        else:
            if m.preview:
                lead = m.delay + (0.5 * dt if hold == "zoh" else 0.0)
                t = dt * jnp.arange(target.shape[0], dtype=dtype)
                target = jnp.interp(t + lead, t, target)
            force = m.dynamics_inverse.simulate(target, dt, hold="foh")
            # the displacement this force produces: the reference through the low-pass (a critically damped pair)
            x = m.lowpass.simulate(target, dt, hold="foh")
        v, _, res = electrical_inverse(act, force, x, m.iterations)
        scale = jnp.maximum(jnp.max(jnp.abs(v)), 1.0)
        return eqx.error_if(v, ~(jnp.max(res) <= 1e-6 * scale),  # NaN fails too
                            "ElectromechanicalInverse: Newton's iteration did not converge; raise `iterations`")

