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
# # Quickstart: a piezo actuator as one differentiable JAX function
#
# A piezoelectric stack does not respond linearly to its voltage: the displacement lags the voltage in a
# rate-independent **hysteresis** loop, keeps moving for seconds after a step (**creep**) and rings at its
# mechanical **resonance**. piezojax composes these blocks into one `pj.Actuator`, a pure JAX function of its
# parameters: it runs under `jit`, is batched with `vmap`, and is differentiated exactly with `grad` and
# `jacfwd` — which is what calibrating it end to end needs.
#
# This notebook builds an actuator, simulates it, draws its hysteresis loops, checks that the hysteresis really is
# rate-independent, compares the exact gradient with finite differences, and simulates a batch of drives at once.

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
import piezojax as pj  # noqa: E402

SMALL = os.environ.get("PIEZOJAX_NOTEBOOK_SMALL") == "1"  # small settings for the automated test
jax.config.update("jax_enable_x64", True)
pj.enable_fast_cpu_scans()

# %% [markdown]
# ## An actuator from three blocks
#
# - hysteresis: a Prandtl–Ishlinskii operator, $H[v] = w_0 v + \sum_i w_i P_{r_i}[v]$, eight play operators of
#   thresholds 3–45 V;
# - creep: two Kelvin–Voigt lags (0.5 s and 30 s);
# - dynamics: a 400 Hz resonance with 5 % damping and a static gain of 1 µm per unit of the hysteresis output.
#
# Every array in the module is a parameter.

# %%
dt = 1e-3
t = jnp.arange(0.0, 2.0 if SMALL else 4.0, dt)
v_in = 50.0 * jnp.sin(2 * jnp.pi * t) * jnp.exp(-0.3 * t)  # volts: a decaying 1 Hz sine
actuator = pj.Actuator(
    pj.PrandtlIshlinskii(jnp.full(8, 0.02), jnp.linspace(3.0, 45.0, 8), w0=0.1),
    pj.KelvinVoigtCreep(jnp.array([50.0, 20.0]), jnp.array([0.5, 30.0]), k0=None),
    pj.StableTransferFunction(1e-6, omega=jnp.array([2 * jnp.pi * 400.0]), zeta=jnp.array([0.05])),
    capacitance=1.7e-9,
)
simulate = eqx.filter_jit(lambda a, v: a.simulate(v, dt))
out = simulate(actuator, v_in)
print("outputs:", [f for f in ("displacement", "charge", "current") if getattr(out, f, None) is not None])
print(f"peak displacement {1e6 * float(jnp.max(out.displacement)):.3f} µm, "
      f"peak charge {1e9 * float(jnp.max(out.charge)):.1f} nC")

# %%
fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))
axes[0].plot(t, 1e6 * out.displacement)
axes[0].set(xlabel="time [s]", ylabel="displacement [µm]", title="response to a decaying sine")
axes[1].plot(v_in, 1e6 * out.displacement)
axes[1].set(xlabel="drive voltage [V]", ylabel="displacement [µm]", title="hysteresis loops")
fig.tight_layout()
plt.show()

# %% [markdown]
# ## Rate independence
#
# The hysteresis operators act on the input *path*, which runs straight between samples: sampling the same path
# ten times more finely (inserting nine points on every segment) must give the same output at the common samples,
# whatever the speed (a per-sample soft clip would drift with the sample rate). We check it on the hysteresis block
# alone, the creep and dynamics being rate-dependent by nature.

# %%
op = actuator.hysteresis
coarse = jnp.linspace(0.0, 1.0, 201)
fine = jnp.linspace(0.0, 1.0, 2001)
v_coarse = 45 * jnp.sin(3 * jnp.pi * coarse) * (1 - 0.6 * coarse)
v_fine = jnp.interp(fine, coarse, v_coarse)  # the same piecewise-linear path, 10x the samples
y_coarse = op(v_coarse)
y_fine = op(v_fine)[::10]
rate_error = float(jnp.max(jnp.abs(y_coarse - y_fine)))
print(f"max |H(coarse) - H(fine)| = {rate_error:.2e} (output range {float(jnp.ptp(y_coarse)):.2f})")
assert rate_error < 1e-12 * float(jnp.ptp(y_coarse))

# %% [markdown]
# ## Exact gradients
#
# A calibration needs the derivative of the residuals with respect to every parameter. `jax.grad` gives it
# exactly, through the plays' clamps (with their tie rules), the creep lags and the exact discretisation of the
# dynamics. We compare one entry with a central finite difference.

# %%
target = out.displacement + 1e-8 * jnp.sin(7 * t)  # a "measurement" near the simulation


def loss(a):
    return 0.5 * jnp.sum((a.simulate(v_in, dt).displacement - target) ** 2)


grads = eqx.filter_jit(jax.grad(loss))(actuator)
h = 1e-6
bump = lambda d: eqx.tree_at(lambda a: a.hysteresis.w0, actuator, actuator.hysteresis.w0 + d)  # noqa: E731
fd = (loss(bump(h)) - loss(bump(-h))) / (2 * h)
print(f"d loss / d w0: grad {float(grads.hysteresis.w0):.6e}, central difference {float(fd):.6e}")
assert abs(float(grads.hysteresis.w0) / float(fd) - 1) < 1e-5

jac = eqx.filter_jit(jax.jacfwd(lambda a: a.simulate(v_in, dt).displacement))(actuator)
print("Jacobian of the displacement w.r.t. the play weights:", jac.hysteresis.weights.shape)

# %% [markdown]
# ## Batched simulation
#
# `jax.vmap` simulates many drives (or many actuators) in one compiled call. Here a family of amplitudes: the
# loops widen with the amplitude, the signature of rate-independent hysteresis. We time the batch against a Python
# loop over the same compiled single simulation.

# %%
n = 16 if SMALL else 128
amplitudes = jnp.linspace(10.0, 60.0, n)
drives = amplitudes[:, None] * jnp.sin(2 * jnp.pi * t)[None, :]
batch = eqx.filter_jit(jax.vmap(lambda v: actuator.simulate(v, dt).displacement))
batch(drives).block_until_ready()  # compile once
t0 = time.perf_counter()
ys = batch(drives).block_until_ready()
t_batch = time.perf_counter() - t0
rows = [drives[i] for i in range(n)]  # sliced before the timing: indexing an array compiles a slice the first time
simulate(actuator, rows[0]).displacement.block_until_ready()  # compile once
t0 = time.perf_counter()
for v in rows:
    simulate(actuator, v).displacement.block_until_ready()
t_loop = time.perf_counter() - t0
print(f"{n} drives of {t.size} samples: vmap {1e3 * t_batch:.1f} ms, loop {1e3 * t_loop:.1f} ms "
      f"({t_loop / t_batch:.1f}x)")
assert np.allclose(ys[3], simulate(actuator, drives[3]).displacement, rtol=1e-10, atol=1e-18)

fig, ax = plt.subplots(figsize=(5, 4))
for i in range(0, n, max(1, n // 8)):
    ax.plot(drives[i], 1e6 * ys[i], lw=0.8)
ax.set(xlabel="drive voltage [V]", ylabel="displacement [µm]", title="loops for growing amplitudes")
plt.show()

# %% [markdown]
# ## Where next
#
# - `02_your_own_data`: calibrate this kind of model on a measured record, from a file, with uncertainties.
# - `03_self_sensing`: estimate displacement and force from the electrical signals (papers 000 and 001).
# - `04_compensation_and_control`: invert the model for feedforward, close the loop.
# - `05_scale`: simulate and calibrate a fleet of actuators at once.
