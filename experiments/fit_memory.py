r"""Peak memory of a large joint fit: 8 experiments x 1e5 samples, 49 free parameters, a few LM steps.

Run: `python -m experiments.fit_memory [--steps 3] [--samples 100000] [--chunks none,8]`

Model: `pj.Actuator(PrandtlIshlinskii(20 plays), KelvinVoigtCreep(2 lags, k0=None), StableTransferFunction(1, omega,
zeta), capacitance, coupling)` fitted to `displacement` and `charge` (two channels): free parameters $w_0$, 20 weights,
20 thresholds, 2 stiffnesses, 2 time constants, $\omega$, $\zeta$, $C_p$, $T$ = 49; residuals
$m = 8 \times 10^5 \times 2 = 1.6\cdot10^6$; the whole Jacobian would be $m \times p$ float64
($1.6\cdot10^6 \cdot 49 \cdot 8$ B = 627 MB), but the solver only forms $J^\top J$ and $J^\top r$, `jacobian_chunk`
experiments at a time (default on CPU: one; `--chunks none,8` compares it with all eight at once).

Each `jacobian_chunk` setting runs in a fresh Python process (`--child`), which builds the data, runs
`fitting.solve(Problem(..., jacobian_chunk=c), max_steps=steps)` and prints its peak resident set size
(`resource.getrusage(RUSAGE_SELF).ru_maxrss`), also measured after building the data and the problem (Python, JAX,
the data, and the one linearisation that the problem's Jacobian scaling makes).
"""

import argparse
import json
import resource
import subprocess
import sys
import time

import numpy as np

N_PLAYS = 20
DT = 1e-4


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kilobytes


def child(samples: int, steps: int, chunk: int | None, n_exp: int = 8) -> dict:
    """Build the data and problem, run `steps` LM steps (0: only form residuals and Jacobian once), measure RSS."""
    import piezojax as pj

    pj.enable_fast_cpu_scans()
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    import fitting

    from .bench_calibration import input_signals

    i = np.arange(N_PLAYS)

    def model(w0, w, r, k, tau, omega, zeta, cp, T):
        return pj.Actuator(
            pj.PrandtlIshlinskii(w, r, w0=w0),
            pj.KelvinVoigtCreep(k, tau, k0=None),
            pj.StableTransferFunction(1.0, omega=[omega], zeta=[zeta]),
            capacitance=cp,
            coupling=T,
        )

    truth = model(0.05e-6, 0.02e-6 * np.exp(-i / 8.0), np.linspace(2.0, 70.0, N_PLAYS), np.array([2.5e8, 1.5e8]),
                  np.array([0.05, 0.6]), 2 * np.pi * 400.0, 0.08, 1.5e-6, 0.2)
    v = input_signals(n_exp, samples, DT)
    out = jax.jit(jax.vmap(lambda m, x: m.simulate(x, DT), in_axes=(None, 0)))(truth, jnp.asarray(v))
    rng = np.random.default_rng(5)
    disp = np.asarray(out.displacement)
    charge = np.asarray(out.charge)
    disp = disp + 1e-3 * np.ptp(disp) * rng.standard_normal(disp.shape)
    charge = charge + 1e-3 * np.ptp(charge) * rng.standard_normal(charge.shape)
    t = np.arange(samples) * DT
    ds = fitting.Dataset([
        fitting.Experiment.from_arrays(t=t, v_in=v[e], name=f"e{e}", displacement=disp[e], charge=charge[e])
        for e in range(n_exp)
    ])
    del out
    start = model(0.04e-6, 0.025e-6 * np.exp(-i / 7.0), np.linspace(2.5, 65.0, N_PLAYS), np.array([3e8, 1.2e8]),
                  np.array([0.07, 0.5]), 2 * np.pi * 420.0, 0.1, 1.3e-6, 0.25)
    params = pj.constrain(start, lambda m: m.hysteresis.thresholds, pj.OrderedPositive)
    free = ["hysteresis.w0", "hysteresis.weights", "hysteresis.thresholds", "creep", "dynamics.omega",
            "dynamics.zeta", "capacitance", "coupling"]
    problem = fitting.Problem(params, ds, free=free, targets=("displacement", "charge"), jacobian_chunk=chunk)
    baseline = _rss_mb()
    m_res = int(problem.residuals(problem.u0).shape[0])
    p = int(problem.u0.shape[0])
    t0 = time.perf_counter()
    if steps == 0:
        import jax

        jax.block_until_ready(problem.residuals_and_jacobian(problem.u0))
        cost0 = float(0.5 * jnp.sum(problem.residuals(problem.u0) ** 2))
        result = type("R", (), {"steps": 0, "initial_cost": cost0, "cost": cost0})
    else:
        result = fitting.solve(problem, max_steps=steps, progress=False)
    wall = time.perf_counter() - t0
    return {
        "chunk": chunk,
        "samples": samples,
        "experiments": n_exp,
        "residuals": m_res,
        "params": p,
        "jacobian_mb": m_res * p * 8 / 2**20,
        "baseline_rss_mb": baseline,
        "peak_rss_mb": _rss_mb(),
        "steps": result.steps,
        "initial_cost": result.initial_cost,
        "cost": result.cost,
        "wall_s": wall,
    }


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=2, help="LM steps (0: form the Jacobian once, no solve)")
    parser.add_argument("--samples", type=int, default=100_000)
    parser.add_argument("--experiments", type=int, default=8)
    parser.add_argument("--chunks", default="none,8", help="comma-separated jacobian_chunk values ('none' = all)")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--chunk", default="none", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        chunk = None if args.chunk == "none" else int(args.chunk)
        print(json.dumps(child(args.samples, args.steps, chunk, args.experiments)))
        return []
    rows = []
    for c in args.chunks.split(","):
        cmd = [sys.executable, "-m", "experiments.fit_memory", "--child", "--chunk", c, "--steps", str(args.steps),
               "--samples", str(args.samples), "--experiments", str(args.experiments)]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            print(proc.stdout, proc.stderr, file=sys.stderr)
            raise RuntimeError(f"child with jacobian_chunk={c} failed")
        row = json.loads(proc.stdout.strip().splitlines()[-1])
        rows.append(row)
        print(
            f"jacobian_chunk={str(row['chunk']):>4s}: {row['experiments']} exp x {row['samples']} samples, "
            f"m = {row['residuals']}, p = {row['params']}, J (m x p float64) = {row['jacobian_mb']:.0f} MiB; "
            f"peak RSS {row['peak_rss_mb']:.0f} MiB (after data set-up {row['baseline_rss_mb']:.0f} MiB); "
            f"{row['steps']} LM steps in {row['wall_s']:.1f} s, cost {row['initial_cost']:.4e} -> {row['cost']:.4e}",
            flush=True,
        )
    return rows


if __name__ == "__main__":
    main()
