r"""Benchmark: calibrating a fleet of actuators at once (`fitting.fit_fleet`) against one at a time (`fitting.fit`).

Run: `python -m experiments.bench_fleet [--sizes 1,16,256] [--samples 20000] [--max-steps 20] [--single 3]
[--devices K] [--out FILE]`, or `python -m experiments.bench_fleet --per-step [--samples N]` for the cost of one
actuator's iteration in a fleet against alone (`step_overhead`).

The fleet: N actuators of one production batch, each its own truth — the calibration benchmark's PI (15 plays) +
two Kelvin–Voigt lags + 400 Hz resonance (`experiments.bench_calibration`) with a per-actuator spread (weights ×
e^{0.1ξ}, thresholds × e^{0.03ξ}, creep stiffnesses × e^{0.1ξ}, ω × (1 + 0.05ξ), ζ × e^{0.2ξ}) — simulated by the
benchmark's numba loop (no piezojax code) on two records per actuator (a decaying sine and a staircase, 10 kHz,
`--samples` samples in all), with white noise of 0.1 % of range. Every actuator starts from the same nominal model
(the benchmark's perturbed start) and fits 37 parameters.

Measured, for each fleet size N (one process; the same machine and backend):

- `fitting.fit_fleet` on the N actuators: the first call with `max_steps=1` (compiles), then the timed call with
  `--max-steps` (compiled: the wall time of the loop, `FleetResult.seconds`, and of the whole call with its set-up);
- one at a time: `fitting.fit` (the same solver, weights and `max_steps`; no kink restarts) on the first `--single`
  actuators after a warm-up fit, the mean per actuator — what a user's loop over the fleet costs;
- the ratio: one-at-a-time seconds per actuator over the fleet's, and the largest relative difference of the final
  costs of the actuators fitted both ways (the fleet runs the same iterations: it should be rounding).

Prints a table (N, devices, steps, fleet seconds, per actuator, one at a time, ratio, converged, median RMSE ÷
noise) and writes the numbers as JSON with `--out`. Pass `--devices K` with
`XLA_FLAGS=--xla_force_host_platform_device_count=K` to split a CPU fleet over K host devices.
"""

import argparse
import json
import os
import sys
import time

import numpy as np

from experiments import bench_calibration as bc

DT = bc.DT


def fleet_truths(n: int, seed: int = 5) -> list[dict]:
    """`n` true parameter sets: the benchmark's truth with a production spread (see the module docstring)."""
    truth = bc.truth_parameters()
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        p = dict(truth)
        p["w"] = truth["w"] * np.exp(0.1 * rng.standard_normal(truth["w"].size))
        p["r"] = truth["r"] * np.exp(0.03 * rng.standard_normal(truth["r"].size))
        p["r"] = np.maximum.accumulate(p["r"])
        p["k"] = truth["k"] * np.exp(0.1 * rng.standard_normal(2))
        p["omega"] = truth["omega"] * (1 + 0.05 * rng.standard_normal())
        p["zeta"] = truth["zeta"] * np.exp(0.2 * rng.standard_normal())
        out.append(p)
    return out


def fleet_data(truths: list[dict], samples: int, seed: int = 9):
    """Per actuator, its records `(v, y)`: two inputs of `samples // 2` samples (a decaying sine and a staircase,
    the same protocol for every actuator) through its numba plant, with white noise of 0.1 % of range; and the
    noise level of each actuator."""
    n = samples // 2
    v = bc.input_signals(3, n, DT)[[0, 2]]  # a decaying sine and a staircase
    rng = np.random.default_rng(seed)
    out, noise = [], []
    for p in truths:
        y = bc.NumbaActuator(v, DT)(p["w0"], p["w"], p["r"], p["k"], p["tau"], p["omega"], p["zeta"])
        sigma = bc.NOISE_FRACTION * float(np.ptp(y))
        out.append((v, y + sigma * rng.standard_normal(y.shape)))
        noise.append(sigma)
    return out, np.asarray(noise)


def datasets_of(records):
    import fitting

    t = np.arange(records[0][0].shape[1]) * DT
    return [fitting.Dataset([fitting.Experiment.from_arrays(t=t, v_in=v[j], displacement=y[j], name=f"record{j}")
                             for j in range(v.shape[0])]) for v, y in records]


def run(sizes=(1, 16, 256), samples: int = 20_000, max_steps: int = 20, single: int = 3, devices: int | None = None,
        progress: bool = False, batch: int | None = None, out: str | None = None, scans: str = "auto") -> list[dict]:
    import jax

    import piezojax as pj

    pj.set_parallel_scans(scans)
    model = bc.constrained(bc.jax_model(bc.start_parameters(bc.truth_parameters())))
    largest = max(sizes)
    truths = fleet_truths(largest)
    t0 = time.perf_counter()
    records, noise = fleet_data(truths, samples)
    print(f"data: {largest} actuators x {samples} samples simulated in {time.perf_counter() - t0:.1f} s "
          f"(numba); backend {jax.default_backend()}, devices {jax.devices()}", file=sys.stderr)
    all_sets = datasets_of(records)
    # one weight for every fleet size and the one-at-a-time fits: 1 / the displacement range over the largest fleet
    weights = {"displacement": 1.0 / float(max(np.ptp(y) for _, y in records))}
    use = None if devices is None else jax.devices()[:devices]
    rows = []
    for n in sizes:
        try:
            rows.append(_measure(n, all_sets[:n], model, weights, noise, batch, max_steps, single, use, progress,
                                 scans))
        except Exception as e:  # noqa: BLE001 - e.g. out of device memory: reported, and the next size runs
            print(f"N={n}: failed: {type(e).__name__}: {str(e).splitlines()[0][:300]}", file=sys.stderr)
            continue
        if out:
            from fitting.files import atomic_write_bytes

            atomic_write_bytes(os.fspath(out), json.dumps(rows, indent=1).encode())
    _table(rows, samples, max_steps, scans)
    return rows


_COMPILED: set = set()  # the batch shapes compiled in this process


def _measure(n, sets, model, weights, noise, batch, max_steps, single, use, progress, scans) -> dict:
    """One fleet size: the fleet fit (after a compiling call, unless this batch shape is compiled already) and
    `single` actuators fitted one at a time."""
    import jax

    import fitting

    b = None if batch is None or batch >= n else batch
    t0 = time.perf_counter()
    if b is None or b not in _COMPILED:
        fitting.fit_fleet(model, sets[: b or n], free=bc.FREE, weights=weights, max_steps=1, devices=use,
                          progress=False, batch_size=b)
        if b is not None:
            _COMPILED.add(b)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = fitting.fit_fleet(model, sets, free=bc.FREE, weights=weights, max_steps=max_steps, devices=use,
                            progress=progress, batch_size=b)
    whole = time.perf_counter() - t0
    print(f"N={n}: {res.report()}", file=sys.stderr)
    k = min(n, single)
    single_per, diff = float("nan"), float("nan")
    if k > 0:
        fitting.fit(model, sets[0], free=bc.FREE, weights=weights, max_steps=1, progress=False,
                    kink_restarts=0)  # compiles
        t0 = time.perf_counter()
        costs = [fitting.fit(model, sets[i], free=bc.FREE, weights=weights, max_steps=max_steps, progress=False,
                             kink_restarts=0).cost for i in range(k)]
        single_per = (time.perf_counter() - t0) / k
        diff = float(np.max(np.abs(np.array(costs) - res.cost[:k]) / np.array(costs)))
    return dict(n=n, batch=b, devices=res.devices, backend=jax.default_backend(), device=str(jax.devices()[0]),
                scans=scans, samples=int(sum(e.n for e in sets[0])),
                steps_median=float(np.median(res.steps)), steps_max=int(np.max(res.steps)),
                fleet_loop_s=res.seconds, fleet_call_s=whole, first_call_s=first,
                per_actuator_s=res.seconds / n, single_per_actuator_s=single_per,
                ratio=single_per / (res.seconds / n), cost_rel_diff=diff, converged=int(np.sum(res.success)),
                rmse_over_noise_median=float(np.median(res.rmse["displacement"] / noise[:n])))


def step_overhead(samples: int = 20_000, reps: int = 3) -> dict:
    """Seconds per iteration (trial step, linearisation, acceptance) of one actuator: alone (`fitting.fit`) and per
    actuator in a fleet of two (`fitting.fit_fleet`, the actuator twice), each the difference of whole calls with
    `max_steps` 6 and 1 over the difference of their steps (the set-up cancels), best of `reps`, after compiling.
    The fleet's should cost about what the actuator alone does. (Before the operators kept their choice of loop
    unmapped, a stacked `smoothing` ran their sequential smooth loop too: on an H200 at 2e4 samples one
    linearisation took 77 ms in a fleet of one against 2.2 ms alone.) Prints and returns the seconds."""
    import jax

    import fitting

    model = bc.constrained(bc.jax_model(bc.start_parameters(bc.truth_parameters())))
    records, _ = fleet_data(fleet_truths(1), samples)
    data = datasets_of(records)[0]
    weights = {"displacement": 1.0 / float(np.ptp(records[0][1]))}

    def alone(k):
        r = fitting.fit(model, data, free=bc.FREE, weights=weights, max_steps=k, progress=False, kink_restarts=0)
        return r.steps

    def fleet(k):
        return int(np.max(fitting.fit_fleet(model, [data, data], free=bc.FREE, weights=weights, max_steps=k,
                                            progress=False).steps))

    def per_step(run, per):
        run(1)  # compiles
        best = float("inf")
        for _ in range(reps):
            t0 = time.perf_counter()
            s1 = run(1)
            t1 = time.perf_counter()
            s6 = run(6)
            t6 = time.perf_counter()
            best = min(best, ((t6 - t1) - (t1 - t0)) / max(1, s6 - s1) / per)
        return best

    out = {"alone": per_step(alone, 1), "in a fleet of two": per_step(fleet, 2)}
    print(f"one actuator's iteration, {samples} samples, 37 parameters, backend {jax.default_backend()}:")
    for k, v in out.items():
        print(f"  {k:20s} {1e3 * v:9.2f} ms  ({v / out['alone']:.2f}x alone)")
    return out


def _table(rows, samples, max_steps, scans):
    import jax

    print(f"\nfleet calibration, {samples} samples per actuator, 37 parameters, max_steps {max_steps}, "
          f"backend {jax.default_backend()}, scans {scans}")
    head = ("N", "batch", "dev", "steps", "first call", "fleet loop", "per act.", "one at a time", "ratio",
            "cost diff", "conv.", "RMSE/noise")
    print("  ".join(f"{h:>12s}" for h in head))
    for r in rows:
        vals = (r["n"], r["batch"] or r["n"], r["devices"], f"{r['steps_median']:.0f}/{r['steps_max']}",
                f"{r['first_call_s']:.1f} s", f"{r['fleet_loop_s']:.2f} s", f"{r['per_actuator_s']:.4f} s",
                f"{r['single_per_actuator_s']:.3f} s", f"{r['ratio']:.1f}x" if r["ratio"] == r["ratio"] else "-",
                f"{r['cost_rel_diff']:.1e}", f"{r['converged']}/{r['n']}", f"{r['rmse_over_noise_median']:.3f}")
        print("  ".join(f"{str(v):>12s}" for v in vals))


def main(argv=None):
    import piezojax as pj

    pj.enable_fast_cpu_scans()  # XLA:CPU only (before the backends start); no effect on an accelerator
    import jax

    jax.config.update("jax_enable_x64", True)
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="1,16,256", help="fleet sizes, comma-separated (default 1,16,256)")
    parser.add_argument("--samples", type=int, default=20_000, help="samples per actuator (two records)")
    parser.add_argument("--max-steps", type=int, default=20)
    parser.add_argument("--single", type=int, default=3, help="actuators fitted one at a time for the baseline")
    parser.add_argument("--devices", type=int, default=None, help="split the fleet over this many devices")
    parser.add_argument("--batch", type=int, default=None, help="actuators stepped together (default: all)")
    parser.add_argument("--scans", choices=("auto", "always", "never"), default="auto",
                        help="parallel-in-time recurrences (pj.set_parallel_scans; auto: on an accelerator)")
    parser.add_argument("--progress", action="store_true")
    parser.add_argument("--per-step", action="store_true",
                        help="only time one actuator's iteration alone and in a fleet of two")
    parser.add_argument("--out", default=None, help="write the rows as JSON to this file")
    args = parser.parse_args(argv)
    if args.per_step:
        return step_overhead(args.samples)
    sizes = tuple(int(s) for s in args.sizes.split(","))
    return run(sizes, args.samples, args.max_steps, args.single, args.devices, args.progress, args.batch, args.out,
               args.scans)


if __name__ == "__main__":
    main()
