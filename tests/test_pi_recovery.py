"""Parameter recovery for a 15-play Prandtl–Ishlinskii operator (paper 001 uses n = 15) with optimistix LM."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import piezojax as pj

N_PLAYS = 15


def triangles(amplitudes, samples_per_leg):
    """A piecewise-linear signal through 0 → a1 → −a1 → a2 → −a2 … → 0, sampled uniformly on each leg."""
    corners = [0.0]
    for a in amplitudes:
        corners += [a, -a]
    corners.append(0.0)
    legs = [np.linspace(c0, c1, samples_per_leg, endpoint=False) for c0, c1 in zip(corners[:-1], corners[1:])]
    return jnp.asarray(np.concatenate(legs + [np.array([0.0])]))


def truth():
    rng = np.random.default_rng(7)
    thresholds = np.linspace(0.04, 0.84, N_PLAYS) + rng.uniform(-0.015, 0.015, N_PLAYS)
    weights = rng.uniform(0.2, 1.0, N_PLAYS)
    return pj.PrandtlIshlinskii(jnp.asarray(weights), jnp.asarray(thresholds), w0=0.8)


def cold_start(v, y):
    """The library's data-driven initialisation: it uses nothing of the true parameters."""
    return pj.pi_cold_start(v, y, N_PLAYS)


def parametrise(op):
    params = pj.constrain(op, lambda m: m.w0, pj.Positive)
    params = pj.constrain(params, lambda m: m.weights, pj.Positive)
    return pj.constrain(params, lambda m: m.thresholds, pj.OrderedPositive)


def fit(v, y, op0, max_steps=400):
    """LM over the unconstrained arrays of the reparametrised operator; everything else (smoothing) stays frozen."""
    params = parametrise(op0)
    is_free = jax.tree_util.tree_map(
        lambda x: isinstance(x, pj.AbstractReparam), params, is_leaf=lambda x: isinstance(x, pj.AbstractReparam)
    )
    free, frozen = eqx.partition(params, is_free)

    def residuals(free, args):
        return pj.unwrap(eqx.combine(free, frozen))(v) - y

    solver = optx.LevenbergMarquardt(rtol=1e-12, atol=1e-12)
    sol = optx.least_squares(residuals, solver, free, max_steps=max_steps, throw=False)
    return pj.unwrap(eqx.combine(sol.value, frozen)), sol


@pytest.fixture(scope="module")
def train_signal():
    return triangles([1.0, 0.85, 0.7, 0.55, 0.4, 0.25, 0.1], 60)


def test_recovers_weights_and_thresholds_from_noiseless_data(train_signal):
    op = truth()
    y = op(train_signal)
    op0 = cold_start(train_signal, y)
    # The start is close but not the answer: LM has to move every threshold to reach 1e-3.
    assert float(jnp.max(jnp.abs(op0.thresholds - op.thresholds) / op.thresholds)) > 1e-3
    assert float(jnp.sqrt(jnp.mean((op0(train_signal) - y) ** 2))) > 1e-5
    fitted, sol = fit(train_signal, y, op0)
    assert sol.result == optx.RESULTS.successful
    np.testing.assert_allclose(fitted.thresholds, op.thresholds, rtol=1e-3)
    np.testing.assert_allclose(fitted.weights, op.weights, rtol=1e-3)
    np.testing.assert_allclose(fitted.w0, op.w0, rtol=1e-3)


def test_noisy_fit_predicts_held_out_signal_at_noise_level(train_signal):
    op = truth()
    y_clean = op(train_signal)
    noise_level = 0.01  # noise std as a fraction of the output range
    y_range = float(jnp.max(y_clean) - jnp.min(y_clean))
    rng = np.random.default_rng(3)
    y = y_clean + noise_level * y_range * jnp.asarray(rng.standard_normal(y_clean.shape))
    fitted, _ = fit(train_signal, y, cold_start(train_signal, y))

    held_out = triangles([0.95, 0.3, 0.75, 0.5, 0.15, 0.6], 55)  # other amplitudes and reversal order
    y_test_clean = op(held_out)
    y_test = y_test_clean + noise_level * y_range * jnp.asarray(rng.standard_normal(y_test_clean.shape))
    test_range = float(jnp.max(y_test_clean) - jnp.min(y_test_clean))
    nrmse = float(jnp.sqrt(jnp.mean((fitted(held_out) - y_test) ** 2))) / test_range
    noise_nrmse = noise_level * y_range / test_range
    assert nrmse < 1.5 * noise_nrmse, (nrmse, noise_nrmse)
    # and the prediction of the noiseless output is well below the noise
    clean_nrmse = float(jnp.sqrt(jnp.mean((fitted(held_out) - y_test_clean) ** 2))) / test_range
    assert clean_nrmse < 0.5 * noise_nrmse


def test_cold_start_in_groups_of_plays_is_the_same(train_signal, monkeypatch):
    """A long record's dense grid of plays is formed a few plays at a time (within a memory budget), each group cut
    to the least-squares rows: the same start, bit for bit, as all plays at once."""
    from piezojax._hysteresis import initialise

    v = np.asarray(train_signal)
    y = np.asarray(truth()(train_signal))
    whole = pj.pi_cold_start(v, y, N_PLAYS, max_rows=500)
    # 7 plays per group: the 120-threshold grid in 18 groups, the last of one play
    monkeypatch.setattr(initialise, "COLUMNS_BUDGET", 7 * 8 * v.size)
    grouped = pj.pi_cold_start(v, y, N_PLAYS, max_rows=500)
    for a, b in zip(jax.tree_util.tree_leaves(whole), jax.tree_util.tree_leaves(grouped)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
