"""Staged identification the papers' way (block by block, in their order), for comparison with joint fitting."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy  # submodules (signal, optimize, linalg) load on first use: importing them costs about a second

import piezojax as pj
from piezojax import PiezojaxValueError
from piezojax.internal import lag_columns

from ._data import Experiment


@eqx.filter_jit
def _charge(obs, v_in, v_out, dt):
    return obs.compensated_charge(v_in, v_out, dt)


@eqx.filter_jit
def _apply(op, v):
    return op(v)


def staged_ivan2009(
    observer: pj.ForceDisplacementObserver,
    triangles: Experiment,
    creep_step: Experiment,
    *,
    n_plays: int = 15,
    creep_lags: int = 2,
    rounds: int = 2,
) -> pj.ForceDisplacementObserver:
    r"""Identify the charge hysteresis $\mathcal{F}_H$ and creep $\mathcal{F}_C$ of paper 001 block by block, as the
    paper does, and return the observer with them.

    The paper (Ivan et al. 2009, §III) takes the circuit constants, $C_P$, $\alpha$, $\beta$ and $k_Z$ from separate
    experiments (ref. 1 and a force step at $V_{in} = 0$) — here from `observer` — and then, with the force sensor
    retracted:

    1. $\mathcal{F}_H$: Prandtl–Ishlinskii weights and thresholds from slow triangles (20 V/s) covering the range
       used, fitted to the compensated charge $Q$ (eq. 4 with $F = 0$) in volts of $C_P$ — here by
       `pj.pi_cold_start` (dense-grid non-negative least squares, then `n_plays` clustered thresholds);
    2. $\mathcal{F}_C$: the creep from a long voltage step (the paper fits a 4th-order ARMAX model; here
       `creep_lags` first-order lags $\sum_i g_i/(1 + \tau_i s)$, $g_i > 0$, by nonlinear least squares on
       $Q - \mathcal{F}_H$ in $\log g_i, \log\tau_i$).

    Steps 1 and 2 alternate `rounds` times (the triangles' creep part is removed with the current creep estimate).

    **Arguments:**

    - `observer`: a `pj.ForceDisplacementObserver` with the circuit constants, $C_P$, $\beta$, $\alpha$ and $k_Z$
      (its own hysteresis/creep are ignored).
    - `triangles`, `creep_step`: experiments with `v_in` and `v_out`, recorded with the sensor retracted.

    **Returns:** the observer with `hysteresis = pj.ScaledHysteresis(PI, C_P)` and
    `creep = pj.KelvinVoigtCreep(1 / (C_P g), τ, k0=None)` (the lags of held drive samples).

    Not differentiable (NNLS and scipy least squares): it is a reference procedure, not a model.
    """
    for name, exp in (("triangles", triangles), ("creep_step", creep_step)):
        if not exp.has("v_out"):
            raise PiezojaxValueError(f"`{name}` ({exp.name!r}) has no v_out channel: the charge cannot be measured")
    cp = float(observer.capacitance_p)
    if not cp > 0:
        raise PiezojaxValueError("`observer.capacitance_p` must be > 0 (the charge is identified in volts of C_P)")
    plain = eqx.tree_at(lambda o: (o.hysteresis, o.creep), observer, (None, None), is_leaf=lambda x: x is None)

    def charge(exp):
        q = _charge(plain, jnp.asarray(exp.v_in), jnp.asarray(exp.channels["v_out"]), exp.dt)
        return np.asarray(q) / cp, np.asarray(exp.v_in)

    q_tri, v_tri = charge(triangles)
    q_step, v_step = charge(creep_step)
    dt_tri, dt_step = triangles.dt, creep_step.dt
    duration = creep_step.duration
    gains = np.full(creep_lags, 0.01)
    taus = np.geomspace(duration / 40, duration / 4, creep_lags)
    pi = None
    for _ in range(rounds):
        pi = pj.pi_cold_start(v_tri, q_tri - lag_columns(v_tri, dt_tri, taus) @ gains, n_plays)
        rest = q_step - np.asarray(_apply(pi, jnp.asarray(v_step)))

        def residual(p):
            return lag_columns(v_step, dt_step, np.exp(p[creep_lags:])) @ np.exp(p[:creep_lags]) - rest

        sol = scipy.optimize.least_squares(residual, np.log(np.concatenate([gains, taus])))
        gains, taus = np.exp(sol.x[:creep_lags]), np.exp(sol.x[creep_lags:])
    dtype = jnp.asarray(observer.capacitance_p).dtype
    pi = jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype) if eqx.is_array(x) else x, pi)
    hysteresis = pj.ScaledHysteresis(pi, jnp.asarray(cp, dtype))
    creep = pj.KelvinVoigtCreep(jnp.asarray(1 / (cp * gains), dtype), jnp.asarray(taus, dtype), k0=None)
    return eqx.tree_at(lambda o: (o.hysteresis, o.creep), observer, (hysteresis, creep), is_leaf=lambda x: x is None)
