"""Benchmark: forward time of a 16-play Prandtl–Ishlinskii operator against a compiled loop, and its Jacobian.

Run: `python -m experiments.bench_hysteresis [--quick]`

Prints, in one run and on the same machine, the time per sample of `piezojax.PrandtlIshlinskii` (exact, n = 16) for
1e5 and 1e6 samples and B = 1 and B = 16 signals (vmap), next to a compiled-loop baseline (numba if installed, else a
numpy loop over samples vectorised over operators), and the time of the forward-mode Jacobian (`jax.jacfwd` with respect
to all 33 parameters, exact operator, and to 34 with the smoothing for the smooth one) per sample: with the
hand-derived sensitivity rule the operator uses (`pi_scan`, a `jax.custom_jvp`) next to plain autodiff through the
scan (`_run_autodiff`), checked to agree, in the same run. Ratios are JAX time / baseline time (lower is better).
Timings are the best of several repeats after a warm-up call that compiles.
"""

import argparse
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

import piezojax as pj

try:
    import numba
except ImportError:  # pragma: no cover - numba is optional
    numba = None


def _pi_loop(v, w0, w, r, out):
    n = r.shape[0]
    for b in range(v.shape[0]):
        y = np.zeros(n)
        for k in range(v.shape[1]):
            vk = v[b, k]
            s = w0 * vk
            for i in range(n):
                hi = vk + r[i]
                lo = vk - r[i]
                yi = y[i]
                if yi > hi:
                    yi = hi
                if yi < lo:
                    yi = lo
                y[i] = yi
                s += w[i] * yi
            out[b, k] = s
    return out


def _pi_numpy(v, w0, w, r, out):
    for b in range(v.shape[0]):
        y = np.zeros(r.shape[0])
        for k in range(v.shape[1]):
            y = np.maximum(v[b, k] - r, np.minimum(v[b, k] + r, y))
            out[b, k] = w0 * v[b, k] + w @ y
    return out


def best_time(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        jax.block_until_ready(out)
        times.append(time.perf_counter() - t0)
    return min(times)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="short signals only (for tests)")
    parser.add_argument(
        "--default-xla-flags",
        action="store_true",
        help="do not raise XLA:CPU's small-loop threshold (see piezojax.enable_fast_cpu_scans)",
    )
    args = parser.parse_args(argv)
    if not args.default_xla_flags:
        pj.enable_fast_cpu_scans()
    jax.config.update("jax_enable_x64", True)

    n = 16
    rng = np.random.default_rng(0)
    r = np.linspace(0.0, 1.5, n + 1)[1:]
    w = rng.uniform(0.1, 1.0, n) / n
    w0 = 0.5
    op = pj.PrandtlIshlinskii(jnp.asarray(w), jnp.asarray(r), w0=w0)

    if numba is not None:
        baseline_name = f"numba {numba.__version__} loop"
        baseline = numba.njit(cache=False)(_pi_loop)
    else:
        baseline_name = "numpy loop (numba not installed)"
        baseline = _pi_numpy

    lengths = [2_000, 20_000] if args.quick else [100_000, 1_000_000]
    batches = [1, 4] if args.quick else [1, 16]
    repeats = 2 if args.quick else 3
    print(f"PI forward, n = {n} plays, float64, {jax.devices()[0].platform}; baseline: {baseline_name}")
    print(f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}")
    print(f"{'samples':>9} {'B':>3} {'jax ns/sample':>14} {'base ns/sample':>15} {'ratio':>7}")
    f_single = jax.jit(lambda v: op(v))
    f_batch = jax.jit(jax.vmap(lambda v: op(v)))
    rows = []
    for length in lengths:
        t = np.linspace(0.0, 1.0, length)
        for batch in batches:
            amps = np.linspace(1.0, 3.0, batch)[:, None]
            v = amps * np.sin(2 * np.pi * 7 * t)[None, :] * np.exp(-t)[None, :]
            vj = jnp.asarray(v)
            fn = (lambda: f_single(vj[0])) if batch == 1 else (lambda: f_batch(vj))
            y_jax = np.asarray(fn()).reshape(batch, length)  # compile
            out = np.empty_like(v)
            if numba is not None:
                baseline(v[:, :10].copy(), w0, w, r, out[:, :10])  # compile
            t_base = best_time(lambda: baseline(v, w0, w, r, out), repeats)
            np.testing.assert_allclose(y_jax, out, atol=1e-12)  # same model, same numbers
            t_jax = best_time(fn, repeats)
            ns = 1e9 / (length * batch)
            rows.append((length, batch, t_jax * ns, t_base * ns))
            print(f"{length:>9} {batch:>3} {t_jax * ns:>14.1f} {t_base * ns:>15.1f} {t_jax / t_base:>7.2f}")

    jac_len = 2_000 if args.quick else 100_000
    t = np.linspace(0.0, 1.0, jac_len)
    v = jnp.asarray(2.0 * np.sin(2 * np.pi * 7 * t) * np.exp(-t))
    t_fwd = best_time(lambda: f_single(v), repeats)
    print(f"jacfwd on {jac_len} samples (forward pass {t_fwd * 1e9 / jac_len:.1f} ns/sample):")
    print(f"{'operator':>22} {'P':>3} {'rule ns/sample':>15} {'autodiff ns/sample':>19} {'autodiff/rule':>14}")
    jac_rows = []
    for smoothing in (0.0, 0.1):
        params = (jnp.asarray(w0), op.weights, op.thresholds)
        if smoothing:
            params = params + (jnp.asarray(smoothing),)

        def model(p, run, s=smoothing):
            # the smoothing is traced (a fitted parameter) for the smooth operator, a concrete 0 for the exact one
            pi = pj.PrandtlIshlinskii(p[1], p[2], w0=p[0], smoothing=p[3] if len(p) > 3 else s)
            pi, signal, state = pi._prepare(v, None)
            return getattr(pi, run)(state, signal)[1]

        times = {}
        jacs = {}
        for run in ("_run", "_run_autodiff"):
            jac = jax.jit(jax.jacfwd(lambda p, run=run: model(p, run)))
            jacs[run] = jax.block_until_ready(jac(params))
            times[run] = best_time(lambda jac=jac: jac(params), repeats)
        for a, b in zip(jax.tree_util.tree_leaves(jacs["_run"]), jax.tree_util.tree_leaves(jacs["_run_autodiff"])):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-9)  # the same Jacobian
        n_par = sum(x.size for x in params)
        ns_rule, ns_ad = (times[k] * 1e9 / jac_len for k in ("_run", "_run_autodiff"))
        label = "exact" if not smoothing else f"smooth (s = {smoothing})"
        print(f"{label:>22} {n_par:>3} {ns_rule:>15.1f} {ns_ad:>19.1f} {ns_ad / ns_rule:>13.1f}x")
        jac_rows.append((smoothing, n_par, ns_rule, ns_ad))
    return rows, jac_rows


if __name__ == "__main__":
    main()
