r"""The main command: staged (the paper's way) versus joint calibration of paper 001's self-sensing observer.

Bench: `pj.IvanBench()` (paper 001, Ivan et al. 2009): a PZT/Ni cantilever whose charge has Preisach hysteresis
and two-time-constant creep, read by a charge integrator with bias drift, pushing on a force sensor after a gap;
reference displacement and force sensors with noise and 16-bit converters. The observer (eq. 4–6) assumes a
Prandtl–Ishlinskii charge hysteresis $\mathcal{F}_H$ and a creep $\mathcal{F}_C$ — a model class that does not
contain the truth.

Experiments (1 kHz; seeds fixed):

- identification, force sensor retracted: slow triangles 0 → −20 → 0 V and 0 → −10 → 0 V at 20 V/s, twice each;
  a −10 V step ramped at 20 V/s and held 200 s (`--quick`: 60 s);
- training contact experiments: the paper's drive, steps 0 → −10 V and 0 → −20 V, period 4 s, 3 cycles; steps
  to −2.5, −7.5, −12.5 and −17.5 V, period 4 s, once each;
- held out: the same drive with new noise; steps to −5 and −15 V with period 6 s, 2 cycles; a slow triangle
  0 → −20 → 0 V at 10 V/s in contact.

Calibrations, on the same records:

- staged, the paper's way (`fitting.staged_ivan2009`): circuit constants, $C_P$, α, β, $k_Z$ as identified
  separately (the bench's nominal values); PI (15 plays) from the triangles, then creep (2 lags) from the step,
  alternated twice;
- joint (`fitting.fit`): from the staged observer, every parameter of $\mathcal{F}_H$ and $\mathcal{F}_C$ and
  β, α, $k_Z$, the bias current and the cutoff of the Butterworth on the force term (the staged observer uses a
  hand-chosen 20 Hz; the paper gives no value) by Levenberg–Marquardt on the reference displacement and force of
  all training experiments at once (identification records and the training contact experiments), channels
  weighted by 1/range.

Printed: a table of held-out force error (band and RMSE in % of the maximum measured force, as the paper reports
+8 %/−6 %) and displacement error (RMSE and max in % of range) for the paper's figure, the staged and the joint fit.
Saved to `--out` (default `results/calibrate/`), atomically, replacing only an earlier output of this experiment:
`summary.json`, `report.txt` (the joint fit's report), figures of the held-out force and displacement, and the
joint fit's folder (`joint/`: model, result.json, figures). Ctrl-C stops it with exit status 130, writing nothing.

Run: `python -m experiments.calibrate [--quick] [--out DIR]`.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from experiments._command import output_folder, positive_int, run, stop_if_interrupted, writing

KIND = "experiments.calibrate"  # what the output folder's marker records
OUT = "results/calibrate"
RATE = 1e3


def _progress(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def triangles(amplitudes, rate=20.0, repeats=2) -> np.ndarray:
    """Triangles 0 → −a → 0 V at `rate` V/s for each amplitude, `repeats` times each, at 1 kHz."""
    out = []
    for a in amplitudes:
        ramp = np.arange(int(round(a / rate * RATE)) + 1) / RATE * rate
        out += [-ramp, -ramp[::-1][1:]] * repeats
    return np.concatenate(out)


def ramped_step(level: float, hold: float, rate: float = 20.0) -> np.ndarray:
    """0 → `level` V at `rate` V/s, then held for `hold` seconds."""
    ramp = -np.arange(0, abs(level), rate / RATE) * np.sign(-level)
    return np.concatenate([ramp, np.full(int(round(hold * RATE)), level)])


def make_records(quick: bool):
    """Simulate every record on the bench; returns `(train, held_out, bench)` lists of `fitting.Experiment`."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import fitting
    import piezojax as pj

    bench = pj.IvanBench()
    retracted = eqx.tree_at(lambda b: b.gap, bench, jnp.asarray(1e-3))  # the force sensor moved away
    hold = 60.0 if quick else 200.0
    drives = {
        # name: (drive, bench, seed)
        "triangles": (triangles([20.0, 10.0]), retracted, 1),
        "creep_step": (ramped_step(-10.0, hold), retracted, 2),
        "contact_train": (pj.periodic_steps((-10.0, -20.0), period=4.0, cycles=3), bench, 11),
        "contact_train_levels": (pj.periodic_steps((-2.5, -7.5, -12.5, -17.5), period=4.0, cycles=1), bench, 12),
        "heldout_paper_drive": (pj.periodic_steps((-10.0, -20.0), period=4.0, cycles=3), bench, 21),
        "heldout_5_15V": (pj.periodic_steps((-5.0, -15.0), period=6.0, cycles=2), bench, 22),
        "heldout_triangle": (triangles([20.0], rate=10.0, repeats=1), bench, 23),
    }
    n_max = max(len(d) for d, _, _ in drives.values())
    record = eqx.filter_jit(lambda b, v, k: b.record(v, k))  # one compilation: every drive padded to n_max
    out = {}
    for name, (v, b, seed) in drives.items():
        n = len(v)
        rec = record(b, jnp.asarray(np.concatenate([v, np.zeros(n_max - n)])), jax.random.key(seed))
        cut = lambda x: np.asarray(x)[:n]  # noqa: E731
        out[name] = fitting.Experiment.from_arrays(
            t=cut(rec.t), v_in=cut(rec.v_in), name=name, v_out=cut(rec.v_out), displacement=cut(rec.displacement),
            force=cut(rec.force))
    train = [out[k] for k in out if not k.startswith("heldout")]
    held = [out[k] for k in out if k.startswith("heldout")]
    return train, held, bench


def force_errors(est: np.ndarray, exp) -> dict:
    """Force error in % of the maximum measured force (the paper's measure) and displacement errors in % of range."""
    f = np.asarray(exp.channels["force"])
    fmax = float(f.max())
    e = 100 * (np.asarray(est) - f) / fmax
    return {"min_percent": float(e.min()), "max_percent": float(e.max()),
            "rmse_percent": float(np.sqrt(np.mean(e**2))), "max_force": fmax}


def evaluate(observer, held) -> dict:
    """Held-out errors of `observer`: force (band and RMSE, % of max force) and displacement (% of range)."""
    import equinox as eqx

    import fitting

    run = eqx.filter_jit(lambda o, v, u, dt: o(v, u, dt))
    out = {}
    for exp in held:
        est = run(observer, exp.v_in, exp.channels["v_out"], exp.dt)
        d = fitting.error_metrics(np.asarray(est.displacement), exp.channels["displacement"])
        out[exp.name] = {"force": force_errors(np.asarray(est.force), exp),
                         "displacement": {"rmse_percent": d["nrmse_percent"], "max_percent": d["max_error_percent"],
                                          "rmse_m": d["rmse"]},
                         "estimate": {"force": np.asarray(est.force), "displacement": np.asarray(est.displacement)}}
    return out


def table(staged: dict, joint: dict) -> str:
    """The comparison table (paper's figure, staged, joint) per held-out experiment."""
    rows = [f"{'held-out experiment':<22} {'quantity':<34} {'paper 001':>12} {'staged':>16} {'joint':>16}"]
    rows.append("-" * len(rows[0]))
    for name in staged:
        s, j = staged[name], joint[name]
        band = lambda r: f"{r['force']['min_percent']:+.2f}..{r['force']['max_percent']:+.2f}"  # noqa: E731
        rows.append(f"{name:<22} {'force error band [% of max F]':<34} {'-6..+8':>12} {band(s):>16} {band(j):>16}")
        rows.append(f"{'':<22} {'force RMSE [% of max F]':<34} {'':>12} "
                    f"{s['force']['rmse_percent']:>16.3f} {j['force']['rmse_percent']:>16.3f}")
        rows.append(f"{'':<22} {'displacement RMSE [% of range]':<34} {'':>12} "
                    f"{s['displacement']['rmse_percent']:>16.3f} {j['displacement']['rmse_percent']:>16.3f}")
        rows.append(f"{'':<22} {'displacement max [% of range]':<34} {'':>12} "
                    f"{s['displacement']['max_percent']:>16.3f} {j['displacement']['max_percent']:>16.3f}")
    return "\n".join(rows)


def figures(held, staged: dict, joint: dict, folder: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(held), 2, figsize=(13, 3.3 * len(held)), squeeze=False)
    for i, exp in enumerate(held):
        t = exp.t
        for k, ch in enumerate(("force", "displacement")):
            scale = 1e3 if ch == "force" else 1e6
            ax = axes[i, k]
            ax.plot(t, scale * exp.channels[ch], lw=0.8, color="k", label="reference sensor")
            ax.plot(t, scale * staged[exp.name]["estimate"][ch], lw=0.8, label="staged (paper's way)")
            ax.plot(t, scale * joint[exp.name]["estimate"][ch], lw=0.8, label="joint")
            ax.set_ylabel("force [mN]" if ch == "force" else "displacement [µm]")
            ax.set_title(f"{exp.name}: {ch}", fontsize=9)
        axes[i, 0].legend(fontsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("t [s]")
    fig.tight_layout()
    fig.savefig(folder / "heldout_estimates.png", dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(len(held), 1, figsize=(9, 2.8 * len(held)), squeeze=False)
    for i, exp in enumerate(held):
        f = exp.channels["force"]
        for label, res in (("staged", staged), ("joint", joint)):
            axes[i, 0].plot(exp.t, 100 * (res[exp.name]["estimate"]["force"] - f) / f.max(), lw=0.7, label=label)
        axes[i, 0].axhspan(-6, 8, color="0.9", zorder=0, label="paper's band")
        axes[i, 0].set_ylabel("force error [% of max F]")
        axes[i, 0].set_title(exp.name, fontsize=9)
    axes[0, 0].legend(fontsize=7)
    axes[-1, 0].set_xlabel("t [s]")
    fig.tight_layout()
    fig.savefig(folder / "heldout_force_error.png", dpi=110)
    plt.close(fig)


def joint_start(staged_observer):
    """The staged observer with the fitted blocks reparametrised for the joint fit (thresholds ordered and positive,
    creep stiffnesses and time constants positive)."""
    import piezojax as pj

    m = pj.constrain(staged_observer, lambda o: o.hysteresis.hysteresis.thresholds, pj.OrderedPositive)
    m = pj.constrain(m, lambda o: o.filter_cutoff, pj.Positive)
    m = pj.constrain(m, lambda o: o.creep.stiffnesses, pj.Positive)
    return pj.constrain(m, lambda o: o.creep.time_constants, pj.Positive)


JOINT_FREE = ["hysteresis.hysteresis.weights", "hysteresis.hysteresis.thresholds", "hysteresis.hysteresis.w0",
              "creep.stiffnesses", "creep.time_constants",
              "force_sensitivity", "displacement_coefficient", "stiffness", "bias_current", "filter_cutoff"]
STAGED_CUTOFF = 20.0  # Hz: the hand-chosen cutoff of the Butterworth on F_est/k_Z (the paper gives none)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m experiments.calibrate", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=OUT, help=f"output folder (default {OUT}); an earlier output of this "
                        "experiment is replaced whole, any other folder is refused")
    parser.add_argument("--quick", action="store_true", help="shorter creep record and fewer LM steps (for tests)")
    parser.add_argument("--max-steps", type=positive_int, default=None,
                        help="Levenberg–Marquardt steps (default 80, quick 8)")
    args = parser.parse_args(argv)

    import piezojax as pj

    pj.enable_fast_cpu_scans()
    import jax

    jax.config.update("jax_enable_x64", True)
    pj.enable_compilation_cache()  # compiled programs kept for the next run ($PIEZOJAX_CACHE_DIR)
    import fitting

    out = output_folder(args.out, KIND, default=OUT)  # before any long work
    t_start = time.perf_counter()

    _progress("[1/4] simulating the paper 001 bench records ...")
    train, held, bench = make_records(args.quick)
    t_records = time.perf_counter() - t_start

    _progress("[2/4] staged identification, the paper's way (PI from triangles, creep from a step) ...")
    t0 = time.perf_counter()
    staged = fitting.staged_ivan2009(bench.observer(filter_cutoff=STAGED_CUTOFF), train[0], train[1])
    t_staged = time.perf_counter() - t0

    _progress("[3/4] joint Levenberg–Marquardt fit of the whole observer on all training records ...")
    t0 = time.perf_counter()
    max_steps = args.max_steps or (8 if args.quick else 80)
    result = fitting.fit(joint_start(staged), train, free=JOINT_FREE, weights="range", max_steps=max_steps)
    stop_if_interrupted(result)
    t_joint = time.perf_counter() - t0

    _progress("[4/4] evaluating on held-out experiments ...")
    ev_staged, ev_joint = evaluate(staged, held), evaluate(result.model, held)
    text = table(ev_staged, ev_joint)
    timing = (f"records {t_records:.1f} s, staged {t_staged:.1f} s, joint {t_joint:.1f} s "
              f"({result.steps} steps, {result.reason}), total {time.perf_counter() - t_start:.1f} s")
    print(text)
    print(timing)

    strip = lambda ev: {k: {c: v for c, v in r.items() if c != "estimate"} for k, r in ev.items()}  # noqa: E731
    summary = {"bench": "IvanBench (paper 001)", "paper_force_band_percent": [-6.0, 8.0],
               "staged": strip(ev_staged), "joint": strip(ev_joint), "joint_fit": result.summary(),
               "timing_s": {"records": t_records, "staged": t_staged, "joint": t_joint},
               "quick": bool(args.quick)}
    with writing(out, KIND) as tmp:
        fitting.files.save_json(tmp / "summary.json", summary)
        (tmp / "table.txt").write_text(text + "\n" + timing + "\n")
        (tmp / "report.txt").write_text(result.report() + "\n")
        figures(held, ev_staged, ev_joint, tmp)
        result.save(tmp / "joint", figures=not args.quick)
    _progress(f"written {out}/")
    return 0


if __name__ == "__main__":
    sys.exit(run(main, "python -m experiments.calibrate"))
