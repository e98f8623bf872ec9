"""`pj.Delay`, a dead time of fractional samples: against scipy's monotone cubic interpolant, exact at whole
samples, continuously differentiable in the delay (finite differences), in an `Actuator` and undone by its inverse."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.interpolate
from test_cli import CONFIG, DT as CLI_DT, _truth

import fitting
import piezojax as pj

DT = 1e-3
T = np.arange(400) * DT
U = np.sin(2 * np.pi * 3 * T) + 0.4 * np.sin(2 * np.pi * 17 * T + 0.3)


@pytest.mark.parametrize("samples", [0.0, 1.0, 3.0, 0.25, 2.5, 7.8])
def test_delay_is_the_monotone_cubic_interpolant_read_late(samples):
    y = np.asarray(pj.Delay(samples * DT)(U, DT))
    # an independent reference: scipy's PCHIP (Fritsch-Carlson slopes; its end slopes differ from a held end)
    spline = scipy.interpolate.PchipInterpolator(T, U)
    inside = slice(int(np.ceil(samples)) + 3, -3)
    np.testing.assert_allclose(y[inside], spline(T[inside] - samples * DT), rtol=0, atol=1e-12)
    if samples == int(samples):  # a whole number of samples: the samples themselves, the first held before
        k = int(samples)
        np.testing.assert_allclose(y, np.concatenate([np.full(k, U[0]), U[: U.size - k]]), rtol=0, atol=1e-14)


def test_a_delayed_step_does_not_overshoot():
    """A hysteresis operator remembers every extreme of its input: a step read between samples stays within the
    step's levels (a Catmull-Rom interpolant would read 106.25 and -6.25 here)."""
    step = np.r_[np.zeros(5), np.full(5, 100.0)]
    for d in (0.5, 1.5, 2.25):
        y = np.asarray(pj.Delay(d * DT)(step, DT))
        assert y.min() >= 0.0 and y.max() <= 100.0 and np.all(np.diff(y) >= 0)


def test_delay_is_differentiable_in_its_time_across_whole_samples():
    def loss(tau):
        return jnp.sum(jnp.sin(pj.Delay(tau)(jnp.asarray(U), DT)) ** 2)

    for tau in [0.4 * DT, 1.0 * DT, 1.0 * DT * (1 - 1e-9), 2.7 * DT]:
        h = 1e-9
        fd = (loss(tau + h) - loss(tau - h)) / (2 * h)
        assert float(jax.grad(loss)(tau)) == pytest.approx(float(fd), rel=1e-5)
    # jit and vmap over delays
    taus = jnp.array([0.0, 1.5 * DT, 3.0 * DT])
    batch = jax.jit(jax.vmap(lambda tau: pj.Delay(tau)(jnp.asarray(U), DT)))(taus)
    np.testing.assert_allclose(batch[2], pj.Delay(3.0 * DT)(U, DT), rtol=0, atol=1e-15)


def test_bad_delays_are_named():
    with pytest.raises(pj.PiezojaxValueError, match="`time`"):
        pj.Delay(-1e-3)
    with pytest.raises(pj.PiezojaxValueError, match="`time` must be a scalar"):
        pj.Delay([1e-3, 2e-3])
    with pytest.raises(pj.PiezojaxValueError, match="`delay` must be a pj.Delay"):
        pj.Actuator(delay=1e-3)


def _actuator(delay=None):
    return pj.Actuator(pj.PrandtlIshlinskii(jnp.array([1.0, 0.5, 0.3]), jnp.array([0.0, 20.0, 40.0])),
                       pj.KelvinVoigtCreep([20.0], [0.2], k0=None),
                       pj.StableTransferFunction(1.0, omega=[2 * np.pi * 80.0], zeta=[0.3]), capacitance=1e-9,
                       coupling=0.1, delay=delay)


def test_an_actuators_delay_reads_its_voltage_late_and_its_inverse_reads_ahead():
    v = 60 - 60 * np.cos(2 * np.pi * 2 * T)
    plain, late = _actuator(), _actuator(pj.Delay(3 * DT))
    shifted = np.concatenate([np.zeros(3), v[:-3]])
    for a, b in zip(jax.tree.leaves(late.simulate(v, DT)), jax.tree.leaves(plain.simulate(shifted, DT))):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-18)
    # a fractional delay, fitted by gradient with the other parameters: its derivative through the whole chain
    def displacement_sum(tau):
        m = eqx.tree_at(lambda a: a.delay.time, late, tau)
        return jnp.sum(m.simulate(v, DT).displacement)

    h = 1e-8
    fd = (displacement_sum(2.5 * DT + h) - displacement_sum(2.5 * DT - h)) / (2 * h)
    assert float(jax.grad(displacement_sum)(2.5 * DT)) == pytest.approx(float(fd), rel=1e-5)
    # the inverse reads the voltage ahead by the delay: tracking as good as without one, far better than ignoring it
    target = plain.simulate(v, DT).displacement
    late = _actuator(pj.Delay(2.4 * DT))

    def error(model, voltage):
        return float(jnp.sqrt(jnp.mean((model.simulate(voltage, DT).displacement - target)[:-5] ** 2)))

    with_delay = error(late, late.inverse(0.0, 200.0)(target, DT))
    without = error(plain, plain.inverse(0.0, 200.0)(target, DT))
    ignored = error(late, plain.inverse(0.0, 200.0)(target, DT))
    assert with_delay < 1.1 * without and ignored > 10 * with_delay
    # read ahead, the voltage stays within the drive limits
    voltage = np.asarray(_actuator(pj.Delay(1.5 * DT)).inverse(0.0, 100.0)(target, DT))
    assert voltage.min() >= 0.0 and voltage.max() <= 100.0


# ------------------------------------------------------------------------------------ in a CONFIG, fitted


def _late_plant_records(delay):
    """Two records of the PI + creep + resonance plant of tests/test_cli.py whose voltage arrives `delay` seconds
    late (the latency by NumPy's linear interpolation, not by `pj.Delay`), with noise 2e-9 m."""
    dt = CLI_DT
    out = []
    for i, f in enumerate((2.0, 3.0)):
        t = np.arange(2500) * dt
        v = (30 + 10 * i) * np.sin(2 * np.pi * f * t) * np.minimum(1, t / 0.2) + 10 * np.sin(2 * np.pi * 3.1 * f * t)
        late = np.interp(t - delay, t, v, left=v[0])
        y = np.asarray(_truth().simulate(jnp.asarray(late), dt).displacement)
        noise = 2e-9 * np.random.default_rng(i).standard_normal(t.size)
        out.append(fitting.Experiment.from_arrays(t=t, v_in=v, displacement=y + noise, name=f"r{i}"))
    return fitting.Dataset(out), dt


def test_a_config_fits_the_input_delay_with_the_other_parameters(tmp_path):
    dataset, dt = _late_plant_records(2.6e-3)
    config = fitting.parse_config(CONFIG.replace("max_steps = 100", "max_steps = 300") + "\n[input]\ndelay = true\n",
                                  "late.toml")
    assert "delay.time" in config.default_free() and "[input] delay" in config.missing_values()
    cal = fitting.calibrate(config, dataset, progress=False)
    assert cal.result.success
    assert float(cal.result.model.delay.time) == pytest.approx(2.6e-3, rel=0.02)
    assert all(m["displacement"]["rmse_over_noise"] < 1.1 for m in cal.result.metrics.values())
    # the fit folder predicts with the fitted delay
    cal.save(tmp_path / "fit", figures=False)
    folder = fitting.load_fit(tmp_path / "fit")
    assert float(folder.model.delay.time) == float(cal.result.model.delay.time)


@pytest.mark.parametrize("text, message", [
    ("[input]\ndelay = -1e-3\n", r"\[input\] delay: must be true .* a number of seconds > 0"),
    ("[input]\ndelay = 0\n", r"\[input\] delay: must be true .* a number of seconds > 0"),
    ("[input]\ndelay = \"late\"\n", r"\[input\] delay: must be true"),
    ("[input]\nlatency = 1e-3\n", r"unknown key 'latency'.*delay"),
])
def test_bad_input_tables_are_named(text, message):
    with pytest.raises(pj.PiezojaxValueError, match=message):
        fitting.parse_config("[hysteresis]\nkind = \"prandtl_ishlinskii\"\nplays = 3\n" + text, "d.toml")


def test_a_given_delay_is_a_start_and_simulates():
    cfg = fitting.parse_config("[hysteresis]\nkind = \"prandtl_ishlinskii\"\nplays = 2\nweights = [1.0, 0.5]\n"
                               "thresholds = [1.0, 10.0]\n[state]\noffset = false\n[input]\ndelay = 2e-3\n", "d.toml")
    model = pj.unwrap(cfg.build(None))
    assert float(model.delay.time) == pytest.approx(2e-3, rel=1e-12) and "delay.time" in cfg.default_free()
    v = 40 * np.sin(2 * np.pi * 3 * T)
    plain = eqx.tree_at(lambda a: a.delay, model, None)
    np.testing.assert_allclose(model.simulate(v, DT).displacement[2:], plain.simulate(v, DT).displacement[:-2],
                               rtol=0, atol=1e-12)
