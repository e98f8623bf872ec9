"""Benchmark: a 4th-order linear block and the composed actuator against scipy / a compiled loop, with Jacobians.

Run: `python -m experiments.bench_dynamics [--quick]`

Prints, in one run and on the same machine (float64, XLA:CPU unless JAX is told otherwise):

1. a 4th-order `StableTransferFunction` (two lightly damped pole pairs, exact ZOH) on 1e6 samples: JAX `simulate`
   next to `scipy.signal.lfilter` on the ZOH-discretised polynomials and a numba loop over the same state-space
   recursion;
2. the composed `Actuator` (Prandtl–Ishlinskii with 16 plays + a 2-lag Kelvin–Voigt creep in parallel + a 2nd-order
   dynamics, with charge and current) on 1e5 and 1e6 samples, next to a numba loop of the same model: `simulate`
   (its one-loop pass) and the block-by-block pass (each block its own loop, which its derivatives run), timed in
   turn;
3. the forward-mode Jacobian (`jax.jacfwd` with respect to every parameter: 5 for the linear block, 42 for the
   actuator — the PI smoothing is held at 0, the exact operator) on 1e5 samples (1e6 × 42 × 3 outputs in float64
   would be 1 GB), next to the baseline users run today: a forward-difference Jacobian of the numba loop (P + 1
   runs, re-discretising the dynamics with scipy for each). The actuator's Jacobian is timed twice in the same run:
   with the hand-derived forward-sensitivity rule of the Prandtl–Ishlinskii scan (what `PrandtlIshlinskii` uses) and
   with plain autodiff through that scan (`_run_autodiff`, the previous behaviour); both are checked to agree.

4. the Jacobian cost of each block alone, and the same 2-state linear scan written with a matrix product or with
   elementwise products in its body (the difference is the cost of a batched `dot_general` inside a scan on XLA:CPU).

Ratios are JAX time / baseline time (lower is better for JAX). Every timing is the best of several repeats after a
warm-up call that compiles; the JAX and numba outputs are checked to agree before timing.
"""

import argparse
import contextlib
import os
import time
import warnings

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import scipy.linalg
import scipy.signal

try:
    import numba
except ImportError:  # pragma: no cover - numba is optional
    numba = None


def _njit(fn):
    return numba.njit(cache=False, fastmath=False)(fn) if numba is not None else fn


# ---------------------------------------------------------------------------------------------------------------------
# Baselines: the same recursions as piezojax, as plain loops.


def _ss_loop(u, delta, B, C, D, out):
    n = B.shape[0]
    x = np.zeros(n)
    dx = np.zeros(n)
    for k in range(u.shape[0]):
        uk = u[k]
        y = D * uk
        for i in range(n):
            y += C[i] * x[i]
        out[k] = y
        for i in range(n):
            s = B[i] * uk
            for j in range(n):
                s += delta[i, j] * x[j]
            dx[i] = s
        for i in range(n):
            x[i] += dx[i]
    return out


def _actuator_loop(v, w0, w, r, kv_a, kv_b, kv_c, delta, B, C, D, cp, coupling, dt, out_d, out_q, out_i):
    n = r.shape[0]
    m = kv_a.shape[0]
    p = np.zeros(n)  # play outputs
    z = np.zeros(m)  # Kelvin–Voigt lag states
    x0 = 0.0
    x1 = 0.0  # 2nd-order dynamics state
    q_prev = 0.0
    for k in range(v.shape[0]):
        vk = v[k]
        h = w0 * vk
        for i in range(n):
            hi = vk + r[i]
            lo = vk - r[i]
            pi = p[i]
            if pi > hi:
                pi = hi
            if pi < lo:
                pi = lo
            p[i] = pi
            h += w[i] * pi
        c = 0.0
        for j in range(m):
            c += kv_c[j] * z[j]
            z[j] = kv_a[j] * z[j] + kv_b[j] * vk
        u = h + c
        d = C[0] * x0 + C[1] * x1 + D * u
        dx0 = delta[0, 0] * x0 + delta[0, 1] * x1 + B[0] * u
        dx1 = delta[1, 0] * x0 + delta[1, 1] * x1 + B[1] * u
        x0 += dx0
        x1 += dx1
        q = cp * vk + coupling * d
        out_d[k] = d
        out_q[k] = q
        out_i[k] = (q - q_prev) / dt
        q_prev = q
    return out_d


def zoh_delta(A, B, dt):
    """`(Ad - I, Bd)` by the block matrix exponential (as piezojax does)."""
    n = A.shape[0]
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = A * dt
    M[:n, n:] = np.eye(n) * dt
    F12 = scipy.linalg.expm(M)[:n, n:]
    return A @ F12, F12 @ B


def pair_realisation(gain, omega, zeta):
    """The scaled section piezojax's `StableTransferFunction` uses for one pole pair, DC gain `gain`."""
    A = np.array([[0.0, omega], [-omega, -2 * zeta * omega]])
    return A, np.array([0.0, omega]), np.array([gain, 0.0]), 0.0


def numba_actuator_inputs(p, dt):
    """Discretised loop inputs from the flat physical parameter vector (ordering of `ACTUATOR_PARAMS`)."""
    w, r, w0 = p[0:16], p[16:32], p[32]
    k, tau = p[33:35], p[35:37]
    gain, omega, zeta, cp, coupling = p[37:42]
    A, B, C, D = pair_realisation(gain, omega, zeta)
    delta, Bd = zoh_delta(A, B, dt)
    x = dt / tau
    return (w0, w, r, np.exp(-x), -np.expm1(-x), 1 / k, delta, Bd, C, D, cp, coupling, dt)


ACTUATOR_PARAMS = "weights (16), thresholds (16), w0, KV stiffnesses (2), time constants (2), gain, omega, zeta, C_p, T"


@contextlib.contextmanager
def plain_autodiff_pi():
    """Within this block (tracing included), `PrandtlIshlinskii` is differentiated by plain autodiff through its scan
    instead of its hand-derived sensitivity rule: the reference timing."""
    from piezojax._hysteresis.prandtl_ishlinskii import PrandtlIshlinskii

    fast = PrandtlIshlinskii._run
    PrandtlIshlinskii._run = PrandtlIshlinskii._run_autodiff
    try:
        yield
    finally:
        PrandtlIshlinskii._run = fast


def _blocks_pass(act, v, dt):
    """`act.simulate` block by block (each block's own loop): the pass `simulate` differentiates."""
    from piezojax._actuator import _blocks

    m, v, dt = act._prepare(v, dt, "zoh")
    return _blocks(m, v, dt, "zoh", m._initial(v.dtype))


def interleaved_best(fns, repeats):
    """The best time of each of `fns` over `repeats` rounds, the functions called in turn within each round (so that
    a slow spell of a shared machine hits all of them)."""
    times = [[] for _ in fns]
    for _ in range(repeats):
        for fn, ts in zip(fns, times):
            t0 = time.perf_counter()
            jax.block_until_ready(fn())
            ts.append(time.perf_counter() - t0)
    return [min(ts) for ts in times]


def best_time(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return min(times)


def _row(name, t, n, t_ref=None, ref=""):
    s = f"  {name:<44} {t * 1e9 / n:>10.1f} ns/sample"
    if t_ref is not None:
        s += f"   ratio {t / t_ref:>6.2f}x vs {ref}"
    print(s, flush=True)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="short signals (smoke test)")
    parser.add_argument(
        "--default-xla-flags",
        action="store_true",
        help="do not raise XLA:CPU's small-loop threshold (see piezojax.enable_fast_cpu_scans)",
    )
    args = parser.parse_args(argv)
    import piezojax as pj

    if not args.default_xla_flags:
        pj.enable_fast_cpu_scans()
    jax.config.update("jax_enable_x64", True)
    from piezojax import PrandtlIshlinskii

    # cont2discrete warns about the numerator's leading zeros (an all-pole G): harmless here
    warnings.filterwarnings("ignore", category=scipy.signal.BadCoefficients)

    n_fwd = 20_000 if args.quick else 1_000_000
    n_jac = 2_000 if args.quick else 100_000
    repeats = 2 if args.quick else 5
    dt = 1e-4
    rng = np.random.default_rng(0)
    base_name = f"numba {numba.__version__} loop" if numba is not None else "python loop (numba missing)"
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(
        f"piezojax dynamics benchmark: jax {jax.__version__} on {jax.devices()[0].platform} "
        f"({jax.devices()[0].device_kind}, {os.cpu_count()} cores, load average {load:.1f}), float64, "
        f"dt = {dt}, best of {repeats}"
    )
    print(f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}")

    # -- 1. 4th-order linear block --------------------------------------------------------------------------------
    G = pj.StableTransferFunction(1.0, omega=[2 * np.pi * 50, 2 * np.pi * 500], zeta=[0.3, 0.02])
    u = rng.standard_normal(n_fwd)
    uj = jnp.asarray(u)
    g_params, g_static = eqx.partition(G, eqx.is_inexact_array)
    sim_g = jax.jit(lambda p, x: eqx.combine(p, g_static).simulate(x, dt))
    y_jax = np.asarray(sim_g(g_params, uj))
    t_jax = best_time(lambda: sim_g(g_params, uj), repeats)

    num, den = (np.asarray(c) for c in G.transfer_function())
    bd, ad, _ = scipy.signal.cont2discrete((num, den), dt, method="zoh")
    bd = np.ravel(bd)
    y_lf = scipy.signal.lfilter(bd, ad, u)
    t_lf = best_time(lambda: scipy.signal.lfilter(bd, ad, u), repeats)

    A, B, C, D = (np.asarray(x) for x in G.state_space())
    disc = G.discretise(dt)
    delta, Bd = np.asarray(disc.delta), np.asarray(disc.Bd)
    ss_loop = _njit(_ss_loop)
    out = np.empty(n_fwd)
    ss_loop(u[:10], delta, Bd, C, float(D), out[:10])  # compile
    t_nb = best_time(lambda: ss_loop(u, delta, Bd, C, float(D), out), repeats)
    scale = np.abs(y_jax).max()
    print(f"\n1. 4th-order linear block (StableTransferFunction, ZOH), {n_fwd:.0e} samples")
    print(
        f"   agreement: max|jax - numba| = {np.abs(y_jax - out).max() / scale:.1e}, "
        f"max|jax - lfilter| = {np.abs(y_jax - y_lf).max() / scale:.1e} (relative to max|y|)"
    )
    _row("jax simulate (jit)", t_jax, n_fwd)
    _row("scipy.signal.lfilter (direct form II)", t_lf, n_fwd)
    _row(base_name + " (same state-space recursion)", t_nb, n_fwd)
    print(f"   ratios: jax/lfilter {t_jax / t_lf:.2f}x, jax/numba {t_jax / t_nb:.2f}x")

    # -- 2. composed actuator -------------------------------------------------------------------------------------
    n_play = 16
    w = rng.uniform(0.02, 0.08, n_play)
    r = np.linspace(0.0, 15.0, n_play + 1)[1:]
    act = pj.Actuator(
        PrandtlIshlinskii(jnp.asarray(w), jnp.asarray(r), w0=1.0),
        pj.KelvinVoigtCreep(jnp.asarray([8.0, 25.0]), jnp.asarray([0.05, 2.0]), k0=None),
        pj.StableTransferFunction(jnp.asarray(1e-7), omega=jnp.asarray([2 * np.pi * 200]), zeta=jnp.asarray([0.1])),
        capacitance=jnp.asarray(1.7e-9),
        coupling=jnp.asarray(2e-3),
    )
    t = np.arange(n_fwd) * dt
    v = 40 * np.abs(2 * ((3 * t) % 1.0) - 1) * (1 + 0.5 * np.sin(2 * np.pi * 0.7 * t)) + rng.normal(0, 0.1, n_fwd)
    vj = jnp.asarray(v)
    # every parameter traced (as in fitting) except the PI smoothing, held at the exact operator, and the offset (the
    # numba loop has none)
    spec = jax.tree_util.tree_map(eqx.is_inexact_array, act)
    spec = eqx.tree_at(lambda a: (a.hysteresis.smoothing, a.offset), spec, (False, False))
    a_params, a_static = eqx.partition(act, spec)
    sim_a = jax.jit(lambda p, x: eqx.combine(p, a_static).simulate(x, dt))
    # the block-by-block pass (each block its own loop; what `simulate` ran before the one-loop pass, and what its
    # derivatives still run), for the same-run comparison
    sim_blocks = jax.jit(lambda p, x: _blocks_pass(eqx.combine(p, a_static), x, dt))
    flat0 = np.concatenate([w, r, [1.0], [8.0, 25.0], [0.05, 2.0], [1e-7, 2 * np.pi * 200, 0.1, 1.7e-9, 2e-3]])
    act_loop = _njit(_actuator_loop)
    nd, nq, ni = np.empty(n_fwd), np.empty(n_fwd), np.empty(n_fwd)
    act_loop(v[:10], *numba_actuator_inputs(flat0, dt), nd[:10], nq[:10], ni[:10])  # compile
    print(
        f"\n2. Actuator: PI ({n_play} plays) + Kelvin–Voigt creep (2 lags, parallel) + 2nd-order dynamics, "
        "with charge and current (one-loop pass; the block-by-block pass; numba), runs interleaved"
    )
    t_jax_a = t_nb_a = None
    actuator_agreement = 0.0
    for n in sorted({min(n_fwd, 100_000), n_fwd}):
        x, xj = v[:n], vj[:n]
        o, ob = sim_a(a_params, xj), sim_blocks(a_params, xj)
        act_loop(x, *numba_actuator_inputs(flat0, dt), nd[:n], nq[:n], ni[:n])
        diffs = [
            max(np.abs(np.asarray(getattr(a, f)) - ref).max() / np.abs(ref).max() for a in (o, ob))
            for f, ref in (("displacement", nd[:n]), ("charge", nq[:n]), ("current", ni[:n]))
        ]
        t_one, t_blk, t_nb = interleaved_best(
            [
                lambda xj=xj: sim_a(a_params, xj),
                lambda xj=xj: sim_blocks(a_params, xj),
                lambda x=x, n=n: act_loop(x, *numba_actuator_inputs(flat0, dt), nd[:n], nq[:n], ni[:n]),
            ],
            3 * repeats,
        )
        print(
            f"   {n:.0e} samples: agreement with numba (max abs diff / max abs value) displacement {diffs[0]:.1e}, "
            f"charge {diffs[1]:.1e}, current {diffs[2]:.1e}"
        )
        _row("jax Actuator.simulate (jit, params traced)", t_one, n)
        _row("jax block by block", t_blk, n)
        _row(base_name + " (same model)", t_nb, n)
        print(f"   ratio jax/numba {t_one / t_nb:.2f}x (block by block {t_blk / t_nb:.2f}x)")
        t_jax_a, t_nb_a = t_one, t_nb
        actuator_agreement = max(actuator_agreement, *diffs)

    # -- 3. Jacobians ---------------------------------------------------------------------------------------------
    print(f"\n3. Forward-mode Jacobians on {n_jac:.0e} samples (1e6 would need ~1 GB for the actuator's)")
    uj_s = uj[:n_jac]
    g_flat, g_unravel = jax.flatten_util.ravel_pytree(g_params)
    jac_g = jax.jit(jax.jacfwd(lambda p: eqx.combine(g_unravel(p), g_static).simulate(uj_s, dt)))
    jax.block_until_ready(jac_g(g_flat))
    t_jac_g = best_time(lambda: jac_g(g_flat), repeats)
    t_fwd_g = best_time(lambda: sim_g(g_params, uj_s), repeats)
    _row(f"linear block: jacfwd wrt {g_flat.shape[0]} params", t_jac_g, n_jac, t_fwd_g, "its forward pass")

    vj_s, v_s = vj[:n_jac], v[:n_jac]
    a_flat, a_unravel = jax.flatten_util.ravel_pytree(a_params)

    def outputs(p):
        o = eqx.combine(a_unravel(p), a_static).simulate(vj_s, dt)
        return o.displacement, o.charge, o.current

    jac_a = jax.jit(jax.jacfwd(outputs))
    jac = jac_a(a_flat)
    jax.block_until_ready(jac)
    t_jac_a = best_time(lambda: jac_a(a_flat), repeats)
    with plain_autodiff_pi():
        jac_ad = jax.jit(jax.jacfwd(outputs))
        jac_ref = jax.block_until_ready(jac_ad(a_flat))
        t_jac_ad = best_time(lambda: jac_ad(a_flat), repeats)
    rule_err = max(
        float(np.max(np.abs(np.asarray(a) - np.asarray(b)) / np.maximum(np.abs(np.asarray(b)).max(axis=0), 1e-300)))
        for a, b in zip(jac, jac_ref, strict=True)
    )
    t_fwd_a = best_time(lambda: sim_a(a_params, vj_s), repeats)
    n_par = a_flat.shape[0]

    # baseline: forward differences of the numba loop, P + 1 runs (re-discretising the dynamics each time)
    sd, sq, si = np.empty(n_jac), np.empty(n_jac), np.empty(n_jac)

    def fd_jacobian():
        jd = np.empty((n_jac, n_par))
        act_loop(v_s, *numba_actuator_inputs(flat0, dt), sd, sq, si)
        base = sd.copy()
        for k in range(n_par):
            p = flat0.copy()
            h = 1e-7 * max(abs(p[k]), 1e-12)
            p[k] += h
            act_loop(v_s, *numba_actuator_inputs(p, dt), sd, sq, si)
            jd[:, k] = (sd - base) / h
        return jd

    jd = fd_jacobian()
    t_fd = best_time(fd_jacobian, max(2, repeats // 2))
    # the JAX parameter order (weights, thresholds, w0, k, tau, gain, omega, zeta, C_p, T) is the loop's order
    col = np.abs(jd).max(axis=0)
    agree = np.max(np.abs(np.asarray(jac[0]) - jd).max(axis=0) / np.where(col > 0, col, 1.0))
    _row(f"actuator: jacfwd wrt {n_par} params (3 outputs)", t_jac_a, n_jac, t_fwd_a, "its forward pass")
    _row("  same, PI by plain autodiff (no rule)", t_jac_ad, n_jac, t_jac_a, "with the rule")
    _row(f"{base_name}: forward differences ({n_par + 1} runs)", t_fd, n_jac)
    print(
        f"   ratio jax jacfwd / numba finite differences {t_jac_a / t_fd:.2f}x "
        f"(plain autodiff {t_jac_ad / t_fd:.2f}x); "
        f"per parameter and sample: jax {t_jac_a * 1e9 / (n_jac * n_par):.1f} ns, "
        f"numba FD {t_fd * 1e9 / (n_jac * (n_par + 1)):.1f} ns"
    )
    print(f"   rule vs plain autodiff: max column-relative difference {rule_err:.1e}")
    print(f"   displacement Jacobian, jax vs numba FD: max column-relative difference {agree:.1e} (FD error ~1e-6)")
    print(f"   parameters: {ACTUATOR_PARAMS}")

    # -- 4. where the Jacobian time goes --------------------------------------------------------------------------
    print(f"\n4. Jacobian cost per block alone ({n_jac:.0e} samples, each wrt its own parameters)")
    blocks = (
        ("PI, 16 plays (exact)", act.hysteresis, lambda m: m(vj_s), ("smoothing",)),
        ("Kelvin–Voigt creep, 2 lags", act.creep, lambda m: m.simulate(vj_s, dt), ()),
        ("2nd-order StableTransferFunction", act.dynamics, lambda m: m.simulate(vj_s, dt), ()),
    )
    for name, block, fn, frozen in blocks:
        spec = jax.tree_util.tree_map(eqx.is_inexact_array, block)
        for field in frozen:
            spec = eqx.tree_at(lambda b, field=field: getattr(b, field), spec, False)
        p, s = eqx.partition(block, spec)
        flat, unravel = jax.flatten_util.ravel_pytree(p)
        g = lambda q, s=s, unravel=unravel, fn=fn: fn(eqx.combine(unravel(q), s))  # noqa: E731
        f, jf = jax.jit(g), jax.jit(jax.jacfwd(g))
        jax.block_until_ready((f(flat), jf(flat)))
        t_f, t_j = best_time(lambda: f(flat), repeats), best_time(lambda: jf(flat), repeats)
        print(
            f"  {name:<36} P = {flat.shape[0]:>2}: forward {t_f * 1e9 / n_jac:7.1f} ns/sample, "
            f"jacfwd {t_j * 1e9 / n_jac:8.1f} ns/sample ({t_j / t_f:5.1f}x)"
        )
        if block is act.hysteresis:
            with plain_autodiff_pi():
                jf_ad = jax.jit(jax.jacfwd(g))
                jax.block_until_ready(jf_ad(flat))
                t_ad = best_time(lambda jf_ad=jf_ad: jf_ad(flat), repeats)
            print(
                f"  {'  same, plain autodiff (no rule)':<36} P = {flat.shape[0]:>2}: "
                f"jacfwd {t_ad * 1e9 / n_jac:8.1f} ns/sample ({t_ad / t_j:5.1f}x the rule)"
            )

    # The same 2-state linear recursion written with a matrix product or with elementwise products in the scan body.
    def two_state(p, elementwise):
        w, z, g = p[0], p[1], p[2]
        delta = jnp.stack([jnp.stack([-1e-3 * w, 1e-2 * w]), jnp.stack([-1e-2 * w, -2e-2 * z * w])])
        b = jnp.stack([0.0 * w, 1e-2 * w])
        c = jnp.stack([g, 0.0 * g])

        def step(x, uk):
            if elementwise:
                return x + jnp.sum(delta * x[None, :], axis=1) + b * uk, jnp.sum(c * x)
            return x + delta @ x + b * uk, jnp.dot(c, x)

        return jax.lax.scan(step, jnp.zeros(2), uj_s)[1]

    p3 = jnp.asarray([1.0, 0.1, 1.0])
    print("  2-state linear scan, 3 parameters — scan body with:")
    for label, elementwise in (("matrix product (delta @ x, dot)", False), ("elementwise products + sum", True)):
        f = jax.jit(lambda p, e=elementwise: two_state(p, e))
        jf = jax.jit(jax.jacfwd(lambda p, e=elementwise: two_state(p, e)))
        jax.block_until_ready((f(p3), jf(p3)))
        t_f, t_j = best_time(lambda: f(p3), repeats), best_time(lambda: jf(p3), repeats)
        print(f"    {label:<34} forward {t_f * 1e9 / n_jac:7.1f} ns/sample, jacfwd {t_j * 1e9 / n_jac:8.1f} ns/sample")
    return {
        "linear": (t_jax, t_lf, t_nb),
        "actuator": (t_jax_a, t_nb_a),
        "jacobian": (t_jac_g, t_jac_a, t_fd),
        "jacobian_plain_autodiff": t_jac_ad,
        # max relative differences: the linear block and the actuator's passes against numba, the PI rule against
        # autodiff, the actuator's displacement Jacobian against numba finite differences
        "agreement": {
            "linear": float(np.abs(y_jax - out).max() / scale),
            "actuator": actuator_agreement,
            "rule": float(rule_err),
            "finite_differences": float(agree),
        },
    }


if __name__ == "__main__":
    main()
