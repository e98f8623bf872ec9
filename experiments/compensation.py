r"""Open-loop compensation of the measured ±150 V actuator: a plain gain, the hysteresis inverse, the whole-actuator
inverse.

Data: `experiments/data/piezo_150V_1Hz/hysteresis_v_150_1hz.csv` (see `experiments/data/README.md`).

1. Two models are fitted by the command line, as a user would (`piezojax fit CONFIG DATA --window :7`):
   - **truth**: `experiments/configs/piezo_150v_pi.toml` — PI(10) → cubic output polynomial → lag creep in series →
     resonance, offset and prehistory (held out on the record's last 3 s: about 0.06 µm, the sensor's noise);
   - **compensator**: `experiments/configs/piezo_150v_pi_creep.toml` — PI(10) and two Kelvin–Voigt lags in
     parallel, then the resonance, offset and prehistory: a simpler model of the same record (held out: about
     0.07 µm), so the compensation is scored against a plant it does not match exactly (the real actuator is not
     available in closed form).
2. Feedforward voltages for ±15 µm sines about the middle of the measured stroke, at 1 and 10 Hz, ramped in from the
   rest position over 0.5 s and scored after the first second, within ±150 V, from each model's
   - **plain gain**: the least-squares line $x = k v + b$ of the measured record, $V = (r - b)/k$;
   - **hysteresis inverse**: the model's hysteresis inverted with the dynamics replaced by their static gain and
     the creep by its instantaneous part (`rate_independent`), as a hysteresis-only compensator does;
   - **whole-actuator inverse**: `Actuator.inverse(-150, 150)` (hysteresis, creep and dynamics, with preview).
3. Each voltage drives the truth; the table gives the RMS and maximum tracking error in µm. The compensator's
   voltages show what a model error costs; the truth's own show the inversion itself (exact up to its low-pass).

Run: `python -m experiments.compensation [--fits DIR] [--out results/compensation]` (about 3 min on 2
cores: the two fits 60 s and 107 s, the study 21 s; `--fits DIR` reuses `DIR/truth` and `DIR/compensator` written
earlier by this script, refitting one whose fit was interrupted).
"""

import argparse
import json
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import fitting
import piezojax as pj

ROOT = Path(__file__).resolve().parent
DATA = ROOT / "data" / "piezo_150V_1Hz" / "hysteresis_v_150_1hz.csv"
CONFIGS = {"truth": ROOT / "configs" / "piezo_150v_pi.toml", "compensator": ROOT / "configs" / "piezo_150v_pi_creep.toml"}
DT = 2e-4  # the record's 5 kHz
V_MIN, V_MAX = -150.0, 150.0
AMPLITUDE = 15e-6  # m
METHODS = ("plain gain", "hysteresis inverse", "whole-actuator inverse")


def _fit(config: Path, out: Path, overwrite: bool) -> None:
    """`piezojax fit CONFIG DATA --window :7 --out OUT` through the library; an interrupted fit ends the run (exit
    status 130), its partial fit saved and refitted next time."""
    from .plant_study import calibrate_files

    cal = calibrate_files(config, [str(DATA)], out, window=(None, 7.0), overwrite=overwrite)
    if cal.result.code == "interrupted":
        print(f"interrupted while fitting; the partial fit in {out} is refitted next time")
        raise SystemExit(130)


def reusable(out: Path) -> bool:
    """Whether `out` holds a complete fit written earlier: `model.eqx`, and a `result.json` whose code is not
    'interrupted' (the command line saves the last accepted parameters of an interrupted fit)."""
    try:
        return (out / "model.eqx").exists() and json.loads((out / "result.json").read_text())["code"] != "interrupted"
    except (OSError, ValueError, KeyError, TypeError):
        return False


def fitted_models(folder: Path) -> dict[str, pj.Actuator]:
    """Fit (or reuse) both models in `folder/truth` and `folder/compensator`; return them in SI units."""

    models = {}
    for name, config in CONFIGS.items():
        out = folder / name
        if not reusable(out):
            t0 = time.perf_counter()
            folder.mkdir(parents=True, exist_ok=True)
            _fit(config, out, overwrite=out.exists())  # an interrupted fit of this script: refit in place
            print(f"fitted {name} ({config.name}) in {time.perf_counter() - t0:.0f} s")
        models[name] = pj.unwrap(fitting.load_fit(out).model)
    return models


def measured_sine() -> tuple[np.ndarray, np.ndarray]:
    """Voltage [V] and displacement [m] of the measured record's sine (t > 3.3 s)."""
    exp = fitting.load_experiment(DATA, columns={"2": "t", "3": "displacement", "4": "v_in"},
                                  units={"displacement": "um"})
    keep = np.asarray(exp.t) > 3.3
    return np.asarray(exp.v_in)[keep], np.asarray(exp.channels["displacement"])[keep]


def plain_gain(v: np.ndarray, x: np.ndarray) -> tuple[float, float]:
    """The least-squares line x = k v + b [m/V, m]."""
    k, b = np.polyfit(v, x, 1)
    return float(k), float(b)


def rate_independent(model: pj.Actuator) -> pj.Actuator:
    """`model` with the dynamics replaced by their static gain and the creep by its instantaneous gain $h(0^+)$
    (none for a creep-only parallel block): the rate-independent part a hysteresis-only inverse compensates.

    (Not the creep's settled gain: on this record the fitted creeps settle over seconds to minutes, beyond what the
    record determines — the parallel model's settled creep gain is 15x its hysteresis slope.)"""
    c0 = None if model.creep is None else float(model.creep.instantaneous_gain())
    creep = None if not c0 else pj.LinearCreep(pj.StableTransferFunction(c0))
    dynamics = None if model.dynamics is None else pj.StableTransferFunction(model.dynamics.dc_gain())
    return pj.Actuator(model.hysteresis, creep, dynamics, structure=model.structure, offset=model.offset,
                       prehistory=model.prehistory)


def reference(truth: pj.Actuator, frequency: float, seconds: float, middle: float) -> jnp.ndarray:
    """A ±15 µm sine about `middle`, ramped in from the truth's rest position over 0.5 s (smooth step)."""
    t = DT * np.arange(int(round(seconds / DT)))
    rest = float(truth.simulate(jnp.zeros(2), DT).displacement[0])
    s = np.clip(t / 0.5, 0.0, 1.0)
    ramp = s * s * (3 - 2 * s)
    return jnp.asarray(rest + ramp * (middle - rest + AMPLITUDE * np.sin(2 * np.pi * frequency * t)))


# Module-level jits: every compensator and frequency of a study reuses the programs of its structure and length.
@eqx.filter_jit
def _run_inverse(inv, ref):
    return inv(ref, DT)


@eqx.filter_jit
def _displacement(model, v):
    return model.simulate(v, DT).displacement


def voltages(model: pj.Actuator, ref: jnp.ndarray, gain: tuple[float, float], iterations: int) -> dict:
    """The three feedforward voltages for `ref` from `model` (and the plain gain)."""
    k, b = gain

    def inverse(m):  # the inverse is built outside jit: its relative degree needs values
        return _run_inverse(m.inverse(V_MIN, V_MAX, iterations=iterations), ref)

    return {
        "plain gain": jnp.clip((ref - b) / k, V_MIN, V_MAX),
        "hysteresis inverse": inverse(rate_independent(model)),
        "whole-actuator inverse": inverse(model),
    }


def study(truth: pj.Actuator, compensators: dict[str, pj.Actuator], gain: tuple[float, float], middle: float,
          frequencies=(1.0, 10.0), seconds: float = 3.0, score_from: float = 1.0, iterations: int = 20) -> list:
    """Tracking errors of every method and compensator on `truth`: rows of dicts (µm)."""
    rows = []
    for f in frequencies:
        ref = reference(truth, f, seconds, middle)
        scored = slice(int(round(score_from / DT)), None)
        for name, model in compensators.items():
            for method, v in voltages(model, ref, gain, iterations).items():
                e = np.asarray(_displacement(truth, v) - ref)[scored]
                rows.append({"frequency_hz": f, "model": name, "method": method,
                             "rms_um": float(np.sqrt(np.mean(e**2)) * 1e6), "max_um": float(np.max(np.abs(e)) * 1e6),
                             "v_min": float(jnp.min(v)), "v_max": float(jnp.max(v))})
    return rows


def print_table(rows: list) -> None:
    models = list(dict.fromkeys(r["model"] for r in rows))
    print(f"\nTracking error on the truth (RMS / max, µm; ±{AMPLITUDE * 1e6:.0f} µm sine, within ±150 V)")
    for model in models:
        print(f"\nvoltages from the {model} model")
        freqs = sorted({r["frequency_hz"] for r in rows})
        print(f"  {'method':<24}" + "".join(f"{f:>8.0f} Hz RMS / max" for f in freqs))
        for method in METHODS:
            cells = [next(r for r in rows if r["model"] == model and r["method"] == method and r["frequency_hz"] == f)
                     for f in freqs]
            print(f"  {method:<24}" + "".join(f"{c['rms_um']:>12.4f} / {c['max_um']:<7.4f}" for c in cells))


def main(argv: list[str] | None = None) -> list:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--fits", type=Path, help="folder with (or for) the fitted models: reused when present")
    parser.add_argument("--out", type=Path, default=Path("results/compensation"), help="result folder")
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    pj.enable_compilation_cache()  # compiled programs kept for the next run ($PIEZOJAX_CACHE_DIR)
    fits = args.fits or args.out / "fits"
    models = fitted_models(fits)
    v, x = measured_sine()
    gain = plain_gain(v, x)
    middle = 0.5 * (x.min() + x.max())
    t0 = time.perf_counter()
    rows = study(models["truth"], {"compensator": models["compensator"], "truth": models["truth"]}, gain, middle)
    print(f"plain gain: {gain[0] * 1e6:.4f} µm/V, intercept {gain[1] * 1e6:.3f} µm; study in "
          f"{time.perf_counter() - t0:.0f} s")
    print_table(rows)
    args.out.mkdir(parents=True, exist_ok=True)
    fitting.files.save_json(args.out / "compensation.json", {"plain_gain": gain, "rows": rows})
    print(f"\nwritten {args.out / 'compensation.json'}")
    return rows


if __name__ == "__main__":
    main()
