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
# # Scale: a fleet of actuators simulated and calibrated at once
#
# A production batch of piezo actuators shares one design, but every unit has its own hysteresis, creep and
# resonance. Calibrating them one by one in a Python loop pays the per-call overhead and leaves most of the
# hardware idle. Because a piezojax model is a pure function of its parameters, a whole fleet is one `vmap`:
# simulated in one call, and calibrated in one compiled loop by `fitting.fit_fleet`, each actuator with its own
# records, parameters and convergence verdict.
#
# Here: a fleet of actuators drawn around a nominal design, their records simulated with noise, every actuator
# calibrated from the same nominal start, and the time per actuator measured against fitting them one at a time.

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

ROOT = next(p for p in (Path.cwd(), *Path.cwd().parents) if (p / "experiments").is_dir() and (p / "piezojax").is_dir())
sys.path.insert(0, str(ROOT))
import fitting  # noqa: E402
import piezojax as pj  # noqa: E402

SMALL = os.environ.get("PIEZOJAX_NOTEBOOK_SMALL") == "1"  # small settings for the automated test
jax.config.update("jax_enable_x64", True)
pj.enable_fast_cpu_scans()

N = 8 if SMALL else 64  # actuators
SAMPLES = 1000 if SMALL else 4000  # per record, two records per actuator
MAX_STEPS = 25 if SMALL else 60
dt = 1e-3
print(f"JAX backend: {jax.default_backend()}, {len(jax.devices())} device(s)")

# %% [markdown]
# ## The design and the fleet
#
# The nominal design: a Prandtl–Ishlinskii hysteresis of six plays, a lag creep and a 60 Hz resonance (slow enough
# to show in 1 kHz records). Each unit's play weights vary by 10 %, its creep fraction by 20 %, its resonance by 3 %
# and its damping by 15 % (log-normal).

# %%
nominal = pj.Actuator(
    pj.PrandtlIshlinskii(jnp.full(6, 0.03), jnp.linspace(0.0, 50.0, 6), w0=0.4),
    pj.LagCreep(fractions=jnp.array([0.15]), time_constants=jnp.array([0.3])),
    pj.StableTransferFunction(1e-7, omega=jnp.array([2 * jnp.pi * 60.0]), zeta=jnp.array([0.2])),
    structure="series",
)
key = jax.random.key(0)
k1, k2, k3, k4, k5 = jax.random.split(key, 5)
weights = nominal.hysteresis.weights * jnp.exp(0.10 * jax.random.normal(k1, (N, 6)))
fractions = nominal.creep.fractions * jnp.exp(0.20 * jax.random.normal(k2, (N, 1)))
omegas = nominal.dynamics.omega * (1 + 0.03 * jax.random.normal(k3, (N, 1)))
zetas = nominal.dynamics.zeta * jnp.exp(0.15 * jax.random.normal(k4, (N, 1)))
fleet = jax.vmap(lambda w, f, o, z: eqx.tree_at(
    lambda a: (a.hysteresis.weights, a.creep.fractions, a.dynamics.omega, a.dynamics.zeta), nominal, (w, f, o, z)))(
    weights, fractions, omegas, zetas)  # one Module whose leaves carry a leading fleet axis

# %% [markdown]
# ## The whole fleet simulated in one call
#
# Two records per actuator — a decaying 2 Hz sine and a staircase — simulated for all actuators by one `vmap` over
# the stacked Module, then 0.2 % of range of white noise.

# %%
t = np.arange(SAMPLES) * dt
drives = np.stack([60 * np.sin(2 * np.pi * 2 * t) * np.exp(-1.5 * t),
                   np.repeat([0.0, 40.0, 10.0, 55.0, 25.0], -(-SAMPLES // 5))[:SAMPLES]])
sim = eqx.filter_jit(jax.vmap(jax.vmap(lambda a, v: a.simulate(v, dt).displacement, in_axes=(None, 0)),
                              in_axes=(0, None)))
sim(fleet, jnp.asarray(drives)).block_until_ready()
t0 = time.perf_counter()
clean = np.asarray(sim(fleet, jnp.asarray(drives)).block_until_ready())  # (N, 2, SAMPLES)
t_sim = time.perf_counter() - t0
print(f"simulated {N} actuators x 2 records x {SAMPLES} samples in {1e3 * t_sim:.1f} ms")
rng = np.random.default_rng(1)
noise = 0.002 * np.ptp(clean, axis=(1, 2), keepdims=True)
measured = clean + noise * rng.standard_normal(clean.shape)
datasets = [fitting.Dataset([fitting.Experiment.from_arrays(v_in=drives[j], dt=dt, displacement=measured[i, j],
                                                            name=f"unit{i}-record{j}") for j in range(2)])
            for i in range(N)]

fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))
for i in range(min(N, 8)):
    axes[0].plot(drives[0], 1e6 * measured[i, 0], lw=0.6)
    axes[1].plot(t, 1e6 * measured[i, 1], lw=0.6)
axes[0].set(xlabel="drive voltage [V]", ylabel="displacement [µm]", title="decaying sine: one loop per unit")
axes[1].set(xlabel="time [s]", ylabel="displacement [µm]", title="staircase")
fig.tight_layout()
plt.show()

# %% [markdown]
# ## Calibrating the fleet
#
# Every unit starts from the nominal design; its play weights (kept positive), creep and resonance are fitted to
# its own two records. `fit_fleet` runs one compiled Levenberg–Marquardt iteration for all units at once, each unit
# accepting or rejecting its own step and stopping on its own verdict. We compile with one step first, so that
# the timing that follows is the calibration alone.

# %%
start = pj.constrain(nominal, lambda a: a.hysteresis.weights, pj.Positive)
start = pj.constrain(start, lambda a: a.creep.fractions, pj.Fractions)
free = ["hysteresis.weights", "creep.fractions", "dynamics.omega", "dynamics.zeta"]
fitting.fit_fleet(start, datasets, free=free, max_steps=1, progress=False)  # compile
t0 = time.perf_counter()
fleet_fit = fitting.fit_fleet(start, datasets, free=free, max_steps=MAX_STEPS, progress=False)
t_fleet = time.perf_counter() - t0
print(fleet_fit.report())

# %% [markdown]
# ## Did every unit find its own parameters?
#
# The records were simulated from known parameters, so we can compare: the resonance and the creep fraction of
# each unit, fitted against true, and the residual RMSE against the noise.

# %%
fitted = [fleet_fit.model_at(i) for i in range(N)]
f_true = np.asarray(omegas[:, 0]) / (2 * np.pi)
f_fit = np.array([float(m.dynamics.omega[0]) / (2 * np.pi) for m in fitted])
c_true = np.asarray(fractions[:, 0])
c_fit = np.array([float(m.creep.fractions[0]) for m in fitted])
rmse = np.asarray(fleet_fit.rmse["displacement"])
print(f"resonance: max |fitted - true| {np.max(np.abs(f_fit - f_true)):.3f} Hz over {N} units "
      f"(spread of the fleet {np.ptp(f_true):.2f} Hz)")
print(f"creep fraction: max |fitted - true| {np.max(np.abs(c_fit - c_true)):.4f} (spread {np.ptp(c_true):.4f})")
print(f"RMSE / noise: median {np.median(rmse / noise[:, 0, 0]):.3f}, max {np.max(rmse / noise[:, 0, 0]):.3f}")
assert np.max(np.abs(f_fit - f_true)) < 0.2 * np.ptp(f_true)
assert np.max(rmse / noise[:, 0, 0]) < 1.5

fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
axes[0].plot(f_true, f_fit, "o")
axes[0].plot(f_true, f_true, "k-", lw=0.8)
axes[0].set(xlabel="true resonance [Hz]", ylabel="fitted resonance [Hz]")
axes[1].plot(c_true, c_fit, "o")
axes[1].plot(c_true, c_true, "k-", lw=0.8)
axes[1].set(xlabel="true creep fraction [-]", ylabel="fitted creep fraction [-]")
fig.tight_layout()
plt.show()

# %% [markdown]
# ## One at a time, for comparison
#
# The same solver, start, step limit and channel weights (each unit's from its own records, in the fleet as in
# `fitting.fit`) with `fitting.fit`, unit by unit (after one warm-up fit that compiles). `fleet_fit[i]` is unit i's full
# `FitResult`; the two ways run the same iterations, so the units that converged reach the same cost.

# %%
single = min(N, 4)
fitting.fit(start, datasets[0], free=free, max_steps=MAX_STEPS, progress=False)  # compile
t0 = time.perf_counter()
one = [fitting.fit(start, datasets[i], free=free, max_steps=MAX_STEPS, progress=False) for i in range(single)]
t_one = (time.perf_counter() - t0) / single
agree = max(abs(one[i].cost / fleet_fit[i].cost - 1) for i in range(single) if fleet_fit[i].success)
print(f"per unit: fleet {1e3 * t_fleet / N:.0f} ms, one at a time {1e3 * t_one:.0f} ms "
      f"({t_one / (t_fleet / N):.1f}x); final costs agree to {agree:.1e} (relative)")
assert agree < 1e-6
