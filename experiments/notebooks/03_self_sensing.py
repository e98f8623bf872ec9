# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Self-sensing: papers 000 and 001 observers on their virtual benches, staged vs joint
#
# A self-sensing actuator is its own sensor: the charge that flows into the piezo element carries the
# displacement (and, in contact, the force), and an *observer* turns the drive voltage $V_{in}$ and the output of a
# sensing circuit $V_{out}$ into estimates of them. Both papers calibrate their observer **block by block**: each
# parameter from its own dedicated experiment, in a fixed order. Here we do exactly that on each paper's virtual
# bench, and then calibrate the same observer **jointly** — every free parameter at once by Levenberg–Marquardt
# (`fitting.fit`) on the same training records — and compare both on records neither calibration has seen.
#
# The benches (`pj.BafumbaBench`, `pj.IvanBench`) are deliberately richer than the observers: their truth holds
# effects the observer's model class does not contain (a capacitance drop over a few volts, field-dependent creep,
# drifting bias currents, Preisach instead of Prandtl–Ishlinskii hysteresis), plus sensor noise and 16-bit
# converters. So neither calibration can be exact; the question is which one uses the data better.
#
# * **Part 1 — paper 000** (Bafumba Liseli et al. 2018): a unimorph read by a transimpedance amplifier; the
#   dynamic-impedance observer $\hat\delta = G(s)[\alpha V_{in} + \beta(Q_\delta + \gamma V_{in})]$ estimates the
#   displacement over minutes-long steps (ultra-low frequency), where creep matters.
# * **Part 2 — paper 001** (Ivan et al. 2009): a cantilever read by a charge integrator, pushing on a force sensor
#   after a gap; the observer estimates force (eq. 4) and displacement (eq. 6) through a Prandtl–Ishlinskii charge
#   hysteresis $\mathcal{F}_H$ and a creep $\mathcal{F}_C$. This is the project's main command,
#   `python -m experiments.calibrate`.
#
# The procedures themselves live in `experiments/bafumba2018.py` and `experiments/calibrate.py` (with
# `fitting.staged_ivan2009`); this notebook calls their public functions with shorter records.
# `PIEZOJAX_NOTEBOOK_SMALL=1` shortens everything further (the automated test); the numbers below then move, and the
# prose describes them qualitatively.

# %%
import os
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import piezojax as pj

SMALL = os.environ.get("PIEZOJAX_NOTEBOOK_SMALL") == "1"
jax.config.update("jax_enable_x64", True)
pj.enable_fast_cpu_scans()
pj.enable_compilation_cache()  # reuses compiled programs across runs ($PIEZOJAX_CACHE_DIR=off disables it)

ROOT = next(p for p in (Path.cwd(), *Path.cwd().parents) if (p / "experiments").is_dir() and (p / "piezojax").is_dir())
sys.path.insert(0, str(ROOT))

import fitting  # noqa: E402
from experiments import bafumba2018, calibrate  # noqa: E402

T_START = time.perf_counter()
print("small settings" if SMALL else "full settings")

# %% [markdown]
# ## Part 1 — paper 000: the dynamic-impedance observer on `pj.BafumbaBench`
#
# **What the paper does.** It drives a unimorph with voltage steps held for a long time (1000 s) and recovers the
# displacement from the current through the actuator. The current is integrated into a charge with the static
# feedthrough $C_r V_{in}$ removed (eq. 5, $Q_\delta$); the paper's point is that the actuator's impedance is not
# static: right after a step the charge drops by $\gamma V_{in}$ (Table I: γ = 0.66 nF), and without that correction
# the estimate is several % off. Its identification is staged (Section IV-B):
#
# 1. circuit constants $R_f$, $C_r$, $I_{bias}$ at their nominal values;
# 2. γ from the charge jump at each step (Table I);
# 3. $G(s)$ by a third-order ARMAX model on the transient of a 200 V step (Fig. 9);
# 4. α from the displacement at the end of the transient and β from the creep that follows (eq. 10–11).
#
# **What we do.** Record steps of 25/50/100/150 V and a 200 V step from rest on the bench (a `jax.vmap` of
# `bench.record`), run the paper's four stages (`bafumba2018.staged`), and then the joint fit
# (`bafumba2018.joint`): α, β and the poles and zeros of $G$ fitted at once by `fitting.fit` to the displacement of
# all five records, started from the staged observer. γ and $G(0)$ stay at their staged values, because the
# displacement identifies only $\alpha + \beta\gamma$ and the products $\alpha G(0)$, $\beta G(0)$ (eq. 9:
# $F_t = (\alpha + \beta\gamma)V_{in} + \beta Q_\delta$).
#
# We hold the steps much shorter than the paper's 1000 s, so that this runs in seconds. That matters: the bench's
# creep has time constants of 20 s and 250 s, and the staged β (eq. 11) reads the creep from the end of the
# transient to the end of the record — with short holds it sees only the creep's beginning. The joint fit uses
# every sample of every record instead.

# %%
bench000 = pj.BafumbaBench()
RATE000 = bench000.sample_rate
DT000 = 1 / RATE000
HOLD = 20.0 if SMALL else 60.0  # s per step (the paper: 1000 s)
AFTER = HOLD / 5  # s after the step from which the "late" maximum error is taken (the paper: 200 s of 1000 s)
LEVELS = bafumba2018.LEVELS  # 25, 50, 100, 150 V
JOINT_STEPS_000 = 300


def take(recs, index):
    """The records `index` (an int or a slice) of a batch of records."""
    return jax.tree_util.tree_map(lambda x: x[index], recs)


# every record in one batch: one compilation of the bench (each record its own noise seed)
HELD_NAMES = ("75 V step", "125 V step", "100 V step", "staircase 60/140/90 V")
commands = np.concatenate([bafumba2018.steps([*LEVELS, bafumba2018.G_LEVEL, 75.0, 125.0, 100.0], HOLD, RATE000),
                           bafumba2018.staircase([60.0, 140.0, 90.0], HOLD, RATE000)[None]])
t0 = time.perf_counter()
keys = jax.random.split(jax.random.key(2018), commands.shape[0])
recs000 = eqx.filter_jit(jax.vmap(lambda v, k: bench000.record(v, k)))(jnp.asarray(commands), keys)
recs000 = jax.tree_util.tree_map(np.asarray, recs000)
train000, g_rec, held000 = take(recs000, slice(0, 4)), take(recs000, 4), take(recs000, slice(5, 9))
print(f"{train000.v_in.shape[0] + 1} training and {held000.v_in.shape[0]} held-out records of "
      f"{train000.t.shape[1]} samples ({HOLD:g} s holds) in {time.perf_counter() - t0:.1f} s")

t0 = time.perf_counter()
st = bafumba2018.staged(bench000, train000, g_rec, LEVELS)
t_staged000 = time.perf_counter() - t0
jt = bafumba2018.joint(st["observer"], [take(train000, i) for i in range(len(LEVELS))] + [g_rec],
                       max_steps=JOINT_STEPS_000)
print(f"staged: {t_staged000:.1f} s; joint fit: {jt['steps']} steps, {jt['seconds']:.1f} s ({jt['verdict']})")

# %% [markdown]
# **Table I and the identified products.** γ per level comes from the charge jump 0.5 s after each step. The bench's
# capacitance drop is $\gamma\tanh(|V|/2\,\mathrm{V})$, so at these levels it is complete and the staged γ should
# sit just below the truth. Only the products $\alpha G(0)$ and $\beta G(0)$ reach the estimate, so we compare those
# with the bench's truth rather than α and β themselves.

# %%
g0_true = float(bench000.dynamics.dc_gain())
truth000 = {"gamma_nF": 1e9 * float(bench000.gamma), "aG0": 1e6 * float(bench000.alpha) * g0_true,
            "bG0": float(bench000.beta) * g0_true}
products = {name: (1e6 * r["alpha"] * r["G0_m_per_unit"], r["beta"] * r["G0_m_per_unit"])
            for name, r in (("staged", st), ("joint", jt))}
print("γ per level (nF): " + ", ".join(f"{r['v_in']:g} V: {r['gamma_nF']:.3f}" for r in st["table1"])
      + f"; mean {st['gamma_nF']:.4f}; truth {truth000['gamma_nF']:.2f}; paper {bafumba2018.PAPER['gamma_nF']}")
print(f"ARMAX fit on the 200 V transient: {st['armax_fit_simulation_percent']:.2f} % "
      f"(paper: {bafumba2018.PAPER['armax_fit_percent']} % on its beam)")
print(f"{'':8} {'α·G(0) [µm/V]':>14} {'error':>8} {'β·G(0) [nm/nC]':>15} {'error':>8}")
print(f"{'truth':8} {truth000['aG0']:14.5f} {'':8} {truth000['bG0']:15.4f}")
prod_err = {}
for name, (a, b) in products.items():
    prod_err[name] = (100 * (a / truth000["aG0"] - 1), 100 * (b / truth000["bG0"] - 1))
    print(f"{name:8} {a:14.5f} {prod_err[name][0]:+7.2f}% {b:15.4f} {prod_err[name][1]:+7.2f}%")

# %% [markdown]
# **Held-out records.** Steps of 75, 125 and 100 V and a staircase 0 → 60 → 140 → 90 V, with new noise, none of
# them used by either calibration. We score the static-impedance observer (the staged one with γ = 0, the paper's
# foil), the staged and the joint observers against the bench's noise-free displacement: RMS error over the record
# and maximum error after the first fifth of the hold, both in % of the record's final displacement.

# %%
observers000 = {"static (γ = 0)": st["observer"].static_impedance(), "staged": st["observer"],
                "joint": jt["observer"]}
est000 = {name: bafumba2018.estimate(obs, held000, DT000) for name, obs in observers000.items()}
scores000 = {name: bafumba2018.scores(e, held000, AFTER) for name, e in est000.items()}
print(f"held-out error, RMS / max after {AFTER:g} s, % of final displacement")
print(f"{'record':<24}" + "".join(f"{name:>20}" for name in observers000))
for i, rec_name in enumerate(HELD_NAMES):
    print(f"{rec_name:<24}" + "".join(f"{s['rms_percent'][i]:>11.3f} / {s['max_after_percent'][i]:5.2f}"
                                      for s in scores000.values()))
rms000 = {name: np.asarray(s["rms_percent"]) for name, s in scores000.items()}
ratio000 = rms000["staged"] / rms000["joint"]
print("staged RMS ÷ joint RMS per record: " + ", ".join(f"{r:.1f}" for r in ratio000))

# %%
t_h = held000.t[0] - bafumba2018.REST
fig, axes = plt.subplots(2, 2, figsize=(11, 6), sharex=True)
styles = {"static (γ = 0)": dict(color="tab:gray", ls=":"), "staged": dict(color="tab:orange"),
          "joint": dict(color="tab:blue")}
for col, i in enumerate((HELD_NAMES.index("100 V step"), HELD_NAMES.index("staircase 60/140/90 V"))):
    true = held000.true_displacement[i]
    axes[0, col].plot(t_h, 1e6 * held000.displacement[i], color="0.8", lw=0.5, label="optical sensor (noisy)")
    axes[0, col].plot(t_h, 1e6 * true, "k", lw=1.2, label="true")
    for name, e in est000.items():
        axes[0, col].plot(t_h, 1e6 * e[i], lw=0.9, label=name, **styles[name])
        axes[1, col].plot(t_h, 1e3 * (e[i] - true), lw=0.9, label=name, **styles[name])
    axes[0, col].set(title=f"held out: {HELD_NAMES[i]}", ylabel="displacement [µm]")
    lim = 1.5e3 * np.max(np.abs(est000["staged"][i] - true)[t_h > AFTER])
    axes[1, col].set(xlabel="time after the first step [s]", ylabel="estimate − true [nm]", ylim=(-lim, lim))
    axes[1, col].axhline(0, color="k", lw=0.5)
axes[0, 0].legend(fontsize=8)
axes[1, 0].legend(fontsize=8)
fig.suptitle("Paper 000: dynamic-impedance observer, staged vs joint calibration")
fig.tight_layout()
plt.show()

# %% [markdown]
# **What the numbers mean.** γ from Table I lands a little below the bench's 0.66 nF at every level (the drop is
# complete a few volts into the step), and both calibrations find the products $\alpha G(0)$ and $\beta G(0)$
# within a fraction of a % to about a % of the truth. The staged values are read off a few windows of each record:
# α from a 0.5 s mean at the end of the transient, β from two 1 s means (eq. 11: the creep seen so far in the
# displacement over the creep seen so far in the charge — with holds this short, only the beginning of the bench's
# 250 s lag, and blind to the field dependence of its creep), $G$ from a 0.7 s ARMAX window. So the staged β carries
# the noise of those windows and moves from one noise realisation to another by up to about a %. The joint fit
# adjusts α (given γ), β and the poles and zeros of $G$ against every sample of the five records. On the held-out
# records the joint observer has the lower RMS error on every record, by a factor that varies from record to record
# (the ratio staged ÷ joint printed above; in the figure the joint error stays closer to zero). The static
# observer (γ = 0) is off by several % after every step — the paper's motivation for γ — and both dynamic-impedance
# observers stay well inside the paper's ±1 % band after the transient. With the paper's 1000 s holds the staged β
# has the whole creep to look at and the two calibrations come close (see the `bafumba2018` experiment); with short
# holds the joint fit is the better use of the experiment.

# %%
assert all(abs(r["gamma_nF"] / truth000["gamma_nF"] - 1) < 0.03 for r in st["table1"])  # measured < 1.5 % off
for name in ("staged", "joint"):
    assert abs(prod_err[name][0]) < 0.5, (name, prod_err[name])  # α·G(0): the end of the transient pins it
assert abs(prod_err["joint"][1]) < 1.0 and abs(prod_err["staged"][1]) < 3.0, prod_err  # β·G(0); measured ≤ 1.3 %
assert jt["verdict"] in ("successful", "converged_at_kink", "converged_zero_residual"), jt["verdict"]
# held out: the joint observer beats the staged one on every record, and the dynamic-impedance correction matters
assert np.all(rms000["joint"] < rms000["staged"]), rms000
assert rms000["joint"].mean() < 0.5 * rms000["staged"].mean(), rms000  # measured: about 5x lower on average
assert np.all(np.asarray(scores000["joint"]["max_after_percent"]) < 0.5)  # paper: ±1 %; measured ≤ 0.1 %
assert np.all(np.asarray(scores000["static (γ = 0)"]["max_after_percent"]) > 2.0)  # measured ≈ 5 %

# %% [markdown]
# ## Part 2 — paper 001: the charge-integrator force/displacement observer on `pj.IvanBench`
#
# **What the paper does.** A PZT/Ni cantilever is driven with 0 → −10 V and 0 → −20 V steps and pushes, after a gap,
# on a force sensor. A charge integrator measures the charge $Q$; the observer subtracts the charge the voltage
# alone would have produced — the hysteresis $\mathcal{F}_H$ (Prandtl–Ishlinskii, eq. 7–8) and the creep
# $\mathcal{F}_C$ (eq. 9) — and reads the force from the rest, $F_{est} = (Q - \mathcal{F}_H - \mathcal{F}_C)/\beta$
# (eq. 4), the displacement from $Q/\alpha$ less a low-passed $F_{est}/k_Z$ (eq. 6). Its calibration is staged:
# circuit constants, $C_P$, α, β, $k_Z$ from separate experiments; then, with the force sensor retracted, the PI
# operator from slow triangles and the creep from a long step. It reports the force within +8 %/−6 % of the maximum
# force.
#
# **What we do.** `calibrate.make_records` simulates the bench's records: the identification records with the
# sensor retracted (triangles, a held −10 V step), training contact experiments (the paper's drive and four other
# levels) and three held-out contact experiments (the paper's drive with new noise; steps to −5/−15 V with another
# period; a slow triangle). The staged observer is `fitting.staged_ivan2009` (the bench's nominal constants, PI of
# 15 plays from the triangles, two creep lags from the step, alternated twice; a hand-chosen 20 Hz Butterworth on the
# force term, which the paper does not specify). The joint observer is `fitting.fit` from the staged one, with the
# main command's reparametrisation (`calibrate.joint_start`) and free set (`calibrate.JOINT_FREE`: the PI weights,
# thresholds and linear term, the creep lags, β, α, $k_Z$, the bias current and the filter cutoff), on the measured
# displacement and force of all training records at once, each channel weighted by 1/range. The small settings use
# the main command's `--quick` records (a 60 s creep step instead of 200 s) and fewer Levenberg–Marquardt steps.

# %%
JOINT_STEPS_001 = 8 if SMALL else 80  # as the main command: 80 (--quick: 8)
t0 = time.perf_counter()
train001, held001, bench001 = calibrate.make_records(quick=SMALL)
t_records001 = time.perf_counter() - t0
print(f"{len(train001)} training records ({', '.join(e.name for e in train001)}), {len(held001)} held out; "
      f"simulated in {t_records001:.1f} s")

t0 = time.perf_counter()
staged001 = fitting.staged_ivan2009(bench001.observer(filter_cutoff=calibrate.STAGED_CUTOFF), train001[0],
                                    train001[1])
t_staged001 = time.perf_counter() - t0
t0 = time.perf_counter()
result001 = fitting.fit(calibrate.joint_start(staged001), train001, free=calibrate.JOINT_FREE, weights="range",
                        max_steps=JOINT_STEPS_001, progress=False)
t_joint001 = time.perf_counter() - t0
print(f"staged: {t_staged001:.1f} s; joint fit: {result001.steps} steps ({result001.accepted_steps} accepted), "
      f"{t_joint001:.1f} s, {result001.code}; cost {result001.initial_cost:.4g} -> {result001.cost:.4g}")

# %% [markdown]
# **Held-out errors.** As the paper reports them: the force error band and RMSE in % of the maximum measured force,
# and the displacement RMSE and maximum error in % of its range, both against the (noisy) reference sensors.

# %%
# As `calibrate.evaluate`, but the held-out records zero-padded to one length and run as one batch (the observer is
# causal: the padding changes no estimated sample), so each observer compiles once.
_run_batch = eqx.filter_jit(jax.vmap(lambda obs, v, u, dt: obs(v, u, dt), in_axes=(None, 0, 0, None)))


def evaluate001(observer, held):
    n = max(e.v_in.size for e in held)
    pad = lambda x: np.pad(np.asarray(x), (0, n - len(x)))  # noqa: E731
    est = _run_batch(observer, jnp.asarray(np.stack([pad(e.v_in) for e in held])),
                     jnp.asarray(np.stack([pad(e.channels["v_out"]) for e in held])), held[0].dt)
    out = {}
    for i, e in enumerate(held):
        f, d = np.asarray(est.force[i, :e.v_in.size]), np.asarray(est.displacement[i, :e.v_in.size])
        m = fitting.error_metrics(d, e.channels["displacement"])
        out[e.name] = {"force": calibrate.force_errors(f, e),
                       "displacement": {"rmse_percent": m["nrmse_percent"], "max_percent": m["max_error_percent"],
                                        "rmse_m": m["rmse"]},
                       "estimate": {"force": f, "displacement": d}}
    return out


t0 = time.perf_counter()
ev_staged001, ev_joint001 = evaluate001(staged001, held001), evaluate001(pj.unwrap(result001.model), held001)
print(f"held-out estimates in {time.perf_counter() - t0:.1f} s")
print(calibrate.table(ev_staged001, ev_joint001))
f_rms001 = {k: np.array([ev[e.name]["force"]["rmse_percent"] for e in held001])
            for k, ev in (("staged", ev_staged001), ("joint", ev_joint001))}
d_rms001 = {k: np.array([ev[e.name]["displacement"]["rmse_percent"] for e in held001])
            for k, ev in (("staged", ev_staged001), ("joint", ev_joint001))}

# %%
name001 = "heldout_5_15V"
exp = next(e for e in held001 if e.name == name001)
fig, axes = plt.subplots(2, 2, figsize=(11, 6), sharex=True)
for col, (ch, scale, unit) in enumerate((("force", 1e3, "mN"), ("displacement", 1e6, "µm"))):
    ref = np.asarray(exp.channels[ch])
    axes[0, col].plot(exp.t, scale * ref, color="k", lw=0.8, label="reference sensor")
    for label, ev, color in (("staged (paper's way)", ev_staged001, "tab:orange"),
                             ("joint", ev_joint001, "tab:blue")):
        est = ev[name001]["estimate"][ch]
        axes[0, col].plot(exp.t, scale * est, lw=0.8, color=color, label=label)
        axes[1, col].plot(exp.t, scale * (est - ref), lw=0.6, color=color, label=label)
    axes[0, col].set(title=f"held out ({name001}): {ch}", ylabel=f"{ch} [{unit}]")
    axes[1, col].set(xlabel="time [s]", ylabel=f"estimate − reference [{unit}]")
    axes[1, col].axhline(0, color="k", lw=0.5)
f_max = float(np.max(exp.channels["force"]))
for s in (-0.06, 0.08):  # the paper's band, in mN
    axes[1, 0].axhline(1e3 * s * f_max, color="0.6", ls="--", lw=0.8)
axes[0, 0].legend(fontsize=8)
fig.suptitle("Paper 001: force/displacement observer, staged vs joint calibration (dashed: paper's −6/+8 % band)")
fig.tight_layout()
plt.show()

# %% [markdown]
# **What the numbers mean.** Both observers come close to the paper's force claim (−6 %/+8 % of the maximum force,
# about 1 mN) although the bench's Preisach hysteresis is outside the observer's PI model class; with the short
# records of the small settings the negative end of the band passes −6 % on some records (the staged observer by
# more). The staged calibration identifies $\mathcal{F}_H$ and $\mathcal{F}_C$ from free
# motion and trusts the nominal β, α and $k_Z$; anything those stages miss — the hysteresis' minor loops in contact,
# the creep beyond the identification step, the force filter — goes straight into the estimates. The joint fit
# adjusts all of them against the force and displacement actually measured in contact, and its held-out force RMSE
# is lower than the staged one on every record, its displacement RMSE too. At the small settings the joint fit runs
# only a few steps (it stops at its step limit, not at convergence) and already improves on the staged observer; the
# main command's 80 steps improve it further. The maximum displacement error is many times the RMSE for both: the
# displacement error is concentrated in short excursions rather than spread over the record.

# %%
for method, ev in (("staged", ev_staged001), ("joint", ev_joint001)):
    for name, r in ev.items():
        # a few % of the maximum force, near the paper's -6..+8 % (measured at small settings: -8.0..+6.8 %)
        assert -11.0 < r["force"]["min_percent"] and r["force"]["max_percent"] < 11.0, (method, name, r["force"])
assert result001.cost < result001.initial_cost
assert np.all(f_rms001["joint"] < f_rms001["staged"]), f_rms001
assert np.all(d_rms001["joint"] < d_rms001["staged"]), d_rms001

# %% [markdown]
# ## Summary
#
# One table from the results above: held-out errors averaged over each bench's held-out records (paper 000: RMS in
# % of the final displacement against the true displacement; paper 001: RMSE in % of the maximum force or of the
# displacement range against the reference sensors), and the calibration times on this machine.

# %%
rows = [
    ("000 displacement RMS [% of δ]", f"{rms000['staged'].mean():.3f}", f"{rms000['joint'].mean():.3f}",
     f"static (γ = 0): {rms000['static (γ = 0)'].mean():.2f}"),
    ("000 β·G(0) error [%]", f"{prod_err['staged'][1]:+.2f}", f"{prod_err['joint'][1]:+.2f}",
     f"α·G(0): {prod_err['staged'][0]:+.3f} / {prod_err['joint'][0]:+.3f}"),
    ("000 calibration time [s]", f"{t_staged000:.1f}", f"{jt['seconds']:.1f}", f"{jt['steps']} LM steps"),
    ("001 force RMSE [% of max F]", f"{f_rms001['staged'].mean():.3f}", f"{f_rms001['joint'].mean():.3f}",
     "paper: band −6..+8"),
    ("001 displacement RMSE [% of range]", f"{d_rms001['staged'].mean():.3f}", f"{d_rms001['joint'].mean():.3f}",
     ""),
    ("001 calibration time [s]", f"{t_staged001:.1f}", f"{t_joint001:.1f}", f"{result001.steps} LM steps"),
]
w = max(len(r[0]) for r in rows)
print(f"{'':<{w}} {'staged':>10} {'joint':>10}   note")
for label, s, j, note in rows:
    print(f"{label:<{w}} {s:>10} {j:>10}   {note}")
print(f"\nnotebook ran in {time.perf_counter() - T_START:.0f} s ({'small' if SMALL else 'full'} settings)")

# %% [markdown]
# On both benches the joint calibration of the whole observer beats the paper's staged identification on records it
# never saw, with the same data: in paper 000 because a short experiment is enough for a fit that uses every sample,
# but leaves the staged readings of a few windows at the mercy of their noise; in paper 001 because the stages fix β,
# α and $k_Z$ and identify the charge operators in free motion, while the observer is used in contact. The staged
# procedures remain the better *start*: the joint fits here begin from them.
