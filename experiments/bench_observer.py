r"""Benchmark: the Jacobian of paper 001's observer through each block's fast path, against generic scans.

Run: `python -m experiments.bench_observer [--quick]`

The observer is the main command's (`experiments.calibrate`): `pj.ForceDisplacementObserver` on the `pj.IvanBench`
constants with the charge hysteresis $C_P\,\mathrm{PI}[V]$ (`pj.ScaledHysteresis` of a 15-play
`pj.PrandtlIshlinskii`), a two-lag creep (`pj.KelvinVoigtCreep(k0=None)`) and the third-order Butterworth on the
force term. Timed: the forward-mode Jacobian (`jax.jacfwd`) of the stacked force and displacement estimates with
respect to the joint fit's 40 free parameters (15 weights, 15 thresholds, $w_0$, 2 creep stiffnesses and 2 time
constants, β, α, $k_Z$, the bias current, the filter cutoff), on one record of the contact drive.

- "blocks' own paths" — the library: the PI through its own loop and hand-derived sensitivities (`pi_scan`), the
  creep through `lags.lag_sum` (sensitivities in one scan), the Butterworth filter in modal form
  (`butterworth_zoh`: decoupled first-order modes);
- "generic scans" — the same observer with the same values, the hysteresis scanned through its cell's `step`, the
  creep as a plain scan of the lag recurrence per time constant and the filter as the dense state update of its
  `pj.TransferFunction`, all differentiated by autodiff (what circuits and observers did before each block's path
  was used). The filter enters eq. (6) only: the generic displacement is the unfiltered observer's (`filter_cutoff
  = None`) with $F/k_Z$ replaced by $B(s)[F]/k_Z$.

Both forms of the Jacobian are timed: `jax.jacfwd` ($J$, time by direction) and the engine's $J^\top$ (direction by
time, `jax.vmap` of `jax.jvp` over the identity, what `fitting` forms before $J^\top J$). The Jacobians are checked
to agree. Timings are the best of 30 rounds (quick: 2), the two paths called in turn, after a warm-up call that
compiles; the ratios are generic / library (higher is better). On 2 CPU cores timings drift by ±20 % between
runs, so compare ratios within a run.
"""

import argparse
import os
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import piezojax as pj


class _StepScan(eqx.Module):
    """A hysteresis cell run by a plain `lax.scan` of its `step` (autodiff through the scan body)."""

    op: pj.AbstractHysteresis

    def __call__(self, v):
        op = self.op
        return jax.lax.scan(lambda s, x: op.step(s, x), op.init(), v)[1]


class _PlainLags(eqx.Module):
    """$\\sum_i \\frac{1/k_i}{1 + \\tau_i s}$ (ZOH, from rest) by a plain scan per lag (autodiff through it)."""

    stiffnesses: jax.Array
    time_constants: jax.Array

    def __call__(self, u, dt):
        def one(tau):
            a = jnp.exp(-dt / tau)

            def step(x, uk):
                return a * x + (1 - a) * uk, x

            return jax.lax.scan(step, jnp.zeros((), u.dtype), u)[1]

        return (1 / self.stiffnesses) @ jax.vmap(one)(self.time_constants)


class _Scaled(eqx.Module):
    """`gain * op(v)`."""

    gain: jax.Array
    op: eqx.Module

    def __call__(self, v):
        return self.gain * self.op(v)


def _best(fns, repeats):
    """The best time of each of `fns` over `repeats` rounds, the functions called in turn within a round (so a
    slow spell of a shared machine falls on all of them), after one warm-up call each."""
    for f in fns:
        f().block_until_ready()
    times = [[] for _ in fns]
    for _ in range(repeats):
        for f, t in zip(fns, times):
            t0 = time.perf_counter()
            f().block_until_ready()
            t.append(time.perf_counter() - t0)
    return tuple(min(t) for t in times)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="a 4000-sample record and 2 repeats")
    args = parser.parse_args(argv)
    pj.enable_fast_cpu_scans()
    jax.config.update("jax_enable_x64", True)

    bench = pj.IvanBench()
    v = pj.periodic_steps((-10.0, -20.0), period=4.0, cycles=1 if args.quick else 3)
    rec = eqx.filter_jit(bench.record)(jnp.asarray(v), jax.random.key(0))
    dt = 1.0 / bench.sample_rate
    cp = bench.capacitance_p
    pi = pj.PrandtlIshlinskii(jnp.full(15, 0.02), jnp.linspace(0.5, 18.0, 15), w0=0.9)
    k, tau = 1 / (cp * jnp.array([0.02, 0.03])), jnp.array([10.0, 100.0])
    library = bench.observer(pj.ScaledHysteresis(pi, cp), pj.KelvinVoigtCreep(k, tau, k0=None), filter_cutoff=20.0)
    # the generic components are plain scans, not library blocks: set past the constructor's type check
    generic = (eqx.tree_at(lambda o: (o.hysteresis, o.creep), bench.observer(), (_Scaled(cp, _StepScan(pi)),
                           _PlainLags(k, tau)), is_leaf=lambda x: x is None), jnp.asarray(20.0))

    def paths(model):  # the joint fit's free parameters
        if isinstance(model, tuple):
            o, cutoff = model
            inner = o.hysteresis.op.op
        else:
            o, cutoff = model, model.filter_cutoff
            inner = o.hysteresis.hysteresis
        return (inner.weights, inner.thresholds, inner.w0, o.creep.stiffnesses, o.creep.time_constants,
                o.force_sensitivity, o.displacement_coefficient, o.stiffness, o.bias_current, cutoff)

    def observe(model):
        if not isinstance(model, tuple):
            return model(rec.v_in, rec.v_out, dt)
        o, cutoff = model  # eq. (6) with the filter as a dense state update (the TransferFunction's scan)
        e = o(rec.v_in, rec.v_out, dt)
        w = 2 * jnp.pi * cutoff
        butterworth = pj.TransferFunction(jnp.stack([w**3]), jnp.stack([jnp.ones_like(w), 2 * w, 2 * w**2, w**3]))
        filtered = butterworth.simulate(e.force, dt)
        return pj.Estimate(displacement=e.displacement + (e.force - filtered) / o.stiffness, force=e.force)

    def jacobian_fn(observer):
        leaves = paths(observer)
        sizes = [int(np.size(x)) for x in leaves]
        theta = jnp.concatenate([jnp.ravel(x) for x in leaves])

        def estimates(th):
            parts, i = [], 0
            for x, n in zip(leaves, sizes):
                parts.append(jnp.reshape(th[i:i + n], jnp.shape(x)))
                i += n
            e = observe(eqx.tree_at(paths, observer, tuple(parts)))
            return jnp.concatenate([e.force, e.displacement])

        jac = eqx.filter_jit(jax.jacfwd(estimates))
        eye = jnp.eye(theta.size, dtype=theta.dtype)
        jac_t = eqx.filter_jit(lambda th: jax.vmap(lambda e: jax.jvp(estimates, (th,), (e,))[1])(eye))
        return (lambda: jac(theta)), (lambda: jac_t(theta)), theta.size

    repeats = 2 if args.quick else 30
    f_lib, ft_lib, p = jacobian_fn(library)
    f_gen, ft_gen, _ = jacobian_fn(generic)
    j_lib, j_gen = np.asarray(f_lib()), np.asarray(f_gen())
    scale = np.abs(j_gen).max(axis=0)
    agree = float(np.max(np.abs(j_lib - j_gen) / np.where(scale > 0, scale, 1.0)))
    agree_t = float(np.max(np.abs(np.asarray(ft_lib()).T - j_gen) / np.where(scale > 0, scale, 1.0)))
    times = {}
    for form, fl, fg in (("jacfwd", f_lib, f_gen), ("engine", ft_lib, ft_gen)):
        times[form] = _best((fg, fl), repeats)
    n = len(v)
    print(f"paper 001 observer: Jacobian of force and displacement, {n} samples, P = {p} free parameters, float64, "
          f"{jax.devices()[0].platform}")
    print(f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}")
    print(f"max |J_library - J_generic| / max|column| = {agree:.1e} (jacfwd), {agree_t:.1e} (engine J^T)")
    print(f"{'form':>22} {'generic scans ms':>17} {'blocks own paths ms':>20} {'ratio':>7}")
    for form, label in (("jacfwd", "jacfwd J"), ("engine", "engine J^T (vmap jvp)")):
        t_gen, t_lib = times[form]
        print(f"{label:>22} {t_gen * 1e3:>17.1f} {t_lib * 1e3:>20.1f} {t_gen / t_lib:>6.2f}x")
    if not max(agree, agree_t) < 1e-8:
        raise SystemExit("the Jacobians differ")
    return {form: t_gen / t_lib for form, (t_gen, t_lib) in times.items()} | {"agreement": max(agree, agree_t)}


if __name__ == "__main__":
    main()
