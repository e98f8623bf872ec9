"""Fleet calibration (`fitting.fit_fleet`): the same iterates as one fit per actuator, per-actuator refusals and
results, batches, devices, and clear errors."""

import os
import subprocess
import sys
import textwrap

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _jaxpr_helpers import loop_under_cond

import fitting
import piezojax as pj
from piezojax._checks import PiezojaxValueError, check_value

DT = 1e-3
N = 400


def _records(n_actuators, seed=0, n=N):
    """Per actuator: two records of a PI(4) + one-lag creep plant with its own weights (numpy, no piezojax)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    inputs = [40 * np.sin(2 * np.pi * 3 * t) * np.exp(-2 * t) + 40, np.repeat([0.0, 60.0, 20.0, 70.0], n // 4)]
    thresholds = np.array([0.0, 10.0, 20.0, 30.0])
    sets = []
    for i in range(n_actuators):
        w = np.array([1.0, 0.5, 0.3, 0.2]) * np.exp(0.1 * rng.standard_normal(4)) * 1e-7
        exps = []
        for j, v in enumerate(inputs):
            z = np.zeros(4)
            y = np.empty(n)
            a, x, prev = np.exp(-DT / 0.05), 0.0, 0.0
            for k in range(n):
                z = np.clip(z + v[k] - prev, -thresholds, thresholds)
                prev = v[k]
                y[k] = w @ (v[k] - z) + 0.2e-7 * x
                x = a * x + (1 - a) * v[k]
            y = y + 1e-3 * np.ptp(y) * rng.standard_normal(n)
            exps.append(fitting.Experiment.from_arrays(t=t, v_in=v, displacement=y, name=f"r{j}"))
        sets.append(fitting.Dataset(exps))
    return sets


def _model():
    m = pj.Actuator(pj.PrandtlIshlinskii(jnp.full(4, 0.5e-7), jnp.array([0.0, 8.0, 18.0, 33.0]), w0=0.0),
                    pj.KelvinVoigtCreep(jnp.array([4e7]), jnp.array([0.03]), k0=None), None)
    m = pj.constrain(m, lambda m: m.hysteresis.weights, pj.Positive)
    return pj.constrain(m, lambda m: m.creep.time_constants, pj.Positive)


FREE = ["hysteresis.weights", "creep"]
WEIGHTS = {"displacement": 1e6}


@pytest.fixture(scope="module")
def fleet():
    sets = _records(3)
    # the default weights: each actuator's from its own records' ranges, as `fitting.fit` computes them
    return sets, fitting.fit_fleet(_model(), sets, free=FREE, max_steps=12, progress=False)


def test_each_actuator_takes_the_steps_of_its_own_fit(fleet):
    sets, res = fleet
    assert len(res) == 3 and res.devices == len(jax.devices())
    for i, data in enumerate(sets):
        one = fitting.fit(_model(), data, free=FREE, max_steps=12, progress=False, kink_restarts=0)
        assert res[i].weights == one.weights
        assert res.steps[i] == one.steps and res.accepted_steps[i] == one.accepted_steps
        np.testing.assert_allclose(np.asarray(res._u[i]), np.asarray(one.u), rtol=1e-9, atol=1e-9)
        assert res.cost[i] == pytest.approx(one.cost, rel=1e-9)
        assert res.initial_cost[i] == pytest.approx(one.initial_cost, rel=1e-12)
        # actuator i's full result: the fit's parameters, errors and metrics
        full = res[i]
        np.testing.assert_allclose(full.values, one.values, rtol=1e-7)
        np.testing.assert_allclose(full.std_errors, one.std_errors, rtol=1e-4)
        assert full.parameter_names == one.parameter_names
        rmse = full.metrics["r0"]["displacement"]["rmse"]
        assert rmse == pytest.approx(one.metrics["r0"]["displacement"]["rmse"], rel=1e-7)
        # the fleet's RMSE over both records, in metres
        err = np.concatenate([fitting.predict(res.model_at(i), e)["displacement"] - e.channels["displacement"]
                              for e in data])
        assert res.rmse["displacement"][i] == pytest.approx(np.sqrt(np.mean(err**2)), rel=1e-9)
    assert len({res[i].weights["displacement"] for i in range(3)}) == 3  # each actuator's own
    assert "fleet of 3 actuators" in res.report() and "displacement RMSE" in res.report()
    with pytest.raises(PiezojaxValueError, match="actuator index"):
        res[3]


def test_an_actuator_that_no_longer_gains_at_max_steps_has_converged_as_in_its_own_fit():
    """`fitting.solve` calls a start stopped by max_steps converged in practice when its cost fell over its last 50
    accepted steps by less than cost/(m - p) (`settled`); the fleet judges each actuator alike. No test of the
    solver's can end these fits (rtol = atol = 0, and a negative ftol: no accepted step raises the cost), so only
    max_steps stops them: after 130 steps each has crawled at its minimum for more than 50 accepted steps, after 40
    none has had 50."""
    sets = _records(3)
    for max_steps, code in ((130, "successful"), (40, "max_steps_reached")):
        kw = dict(free=FREE, max_steps=max_steps, rtol=0.0, atol=0.0, ftol=-1.0, progress=False)
        res = fitting.fit_fleet(_model(), sets, **kw)
        assert list(res.steps) == [max_steps] * 3
        for i, data in enumerate(sets):
            one = fitting.fit(_model(), data, kink_restarts=0, **kw)
            assert res.codes[i] == one.code == code and bool(res.success[i]) == (code == "successful")
            assert ("converged in practice" in res.reasons[i]) == (code == "successful")
            assert res[i].code == code


def test_batches_and_host_devices_give_the_same_fit(fleet):
    sets, res = fleet
    batched = fitting.fit_fleet(_model(), sets, free=FREE, max_steps=12, progress=False, batch_size=2)
    np.testing.assert_allclose(np.asarray(batched._u), np.asarray(res._u), rtol=1e-9, atol=1e-9)
    assert list(batched.steps) == list(res.steps)
    # split over two host devices (a fresh process: the device count is fixed when JAX starts)
    code = textwrap.dedent(f"""
        import os, sys
        os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"
        sys.path.insert(0, {os.path.dirname(__file__)!r})
        import jax, numpy as np
        jax.config.update("jax_enable_x64", True)
        import fitting, fitting._fleet as F
        from test_fleet import _records, _model, FREE, WEIGHTS
        seen = []
        advance = F._fleet_step
        def spy(*args):
            out = advance(*args)
            seen.append(str(getattr(out.y.sharding, "spec", "one device")))
            return out
        F._fleet_step = spy
        sets = _records(3)
        two = fitting.fit_fleet(_model(), sets, free=FREE, weights=WEIGHTS, max_steps=12, progress=False)
        one = fitting.fit_fleet(_model(), sets, free=FREE, weights=WEIGHTS, max_steps=12, progress=False,
                                devices=jax.devices()[:1])
        print(two.devices, seen[0], float(np.max(np.abs(np.asarray(two._u) - np.asarray(one._u)))))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    devices, spec, diff = out.stdout.split()
    assert devices == "2" and "fleet" in spec and float(diff) <= 1e-9


class Gain(eqx.Module):
    a: jax.Array


def _refusing(m, d):  # a block's runtime check: the model refuses a > 1.2
    y = check_value(jnp.exp(m.a) * d.v_in, m.a <= 1.2, "`a` must be at most 1.2")
    return {"displacement": y}


def test_frozen_values_of_every_actuator_go_to_the_step_once_and_differing_ones_stay_per_actuator():
    """A frozen value equal for every actuator is not mapped over the fleet: a batched `lax.cond` runs both of its
    branches, and the PI chooses its exact or smooth (sequential) form by a `cond` on `smoothing` — a stacked
    smoothing made a GPU linearisation 35x slower. Frozen values that differ between actuators (here the
    thresholds and the smoothing) stay per actuator, each actuator's fit its own."""
    from fitting import _fleet

    sets = _records(2, seed=3)
    seen, compiled_step = [], _fleet._fleet_step

    def step(solver, window, max_rejections, statics, arrays, carry):
        seen.append(((solver, window, max_rejections), statics, arrays, carry))
        return compiled_step(solver, window, max_rejections, statics, arrays, carry)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(_fleet, "_fleet_step", step)
        fitting.fit_fleet(_model(), sets, free=FREE, weights=WEIGHTS, max_steps=1, progress=False)
    step_args, statics, arrays, carry = seen[0]
    assert arrays.frozen.hysteresis.smoothing is None and statics.frozen.hysteresis.smoothing.shape == ()
    # the operator's choice between its exact and general loops stays a cond: one loop runs
    assert loop_under_cond(jax.make_jaxpr(lambda a, c: compiled_step(*step_args, statics, a, c))(arrays, carry))

    starts = [_model(), eqx.tree_at(lambda m: (m.hysteresis.thresholds, m.hysteresis.smoothing), _model(),
                                    (jnp.array([0.0, 9.0, 21.0, 30.0]), jnp.asarray(0.5)))]
    res = fitting.fit_fleet(_model(), sets, starts=starts, free=FREE, weights=WEIGHTS, max_steps=6, progress=False)
    for i in range(2):
        one = fitting.fit(starts[i], sets[i], free=FREE, weights=WEIGHTS, max_steps=6, progress=False,
                          kink_restarts=0)
        assert res.cost[i] == pytest.approx(one.cost, rel=1e-9)
        np.testing.assert_array_equal(np.asarray(res.model_at(i).hysteresis.thresholds),
                                      np.asarray(starts[i].hysteresis.thresholds))
    assert float(res.model_at(1).hysteresis.smoothing) == 0.5
    # a fleet of one (stepped without the unit fleet axis) is that actuator's fit
    alone = fitting.fit_fleet(starts[1], sets[1:], free=FREE, weights=WEIGHTS, max_steps=6, progress=False)
    assert alone.cost[0] == pytest.approx(res.cost[1], rel=1e-9) and alone.steps[0] == res.steps[1]


def test_a_refused_trial_is_a_rejected_step_of_that_actuator_alone():
    t = np.arange(300) * DT
    v = 10 * np.sin(2 * np.pi * 5 * t)
    rng = np.random.default_rng(1)
    data = [fitting.Dataset([fitting.Experiment.from_arrays(t=t, v_in=v, name="g", displacement=np.e * v
                                                            + 1e-3 * rng.standard_normal(t.size))])
            for _ in range(2)]
    predictor = fitting.Predictor(_refusing, ("displacement",))
    starts = [Gain(jnp.asarray(-3.0)), Gain(jnp.asarray(0.5))]  # the first one's first trial lands at a > 1.2
    w = {"displacement": 0.1}
    both = fitting.fit_fleet(starts[0], data, starts=starts, predictor=predictor, weights=w, max_steps=3,
                             progress=False)
    alone = fitting.fit_fleet(starts[1], data[1:], predictor=predictor, weights=w, max_steps=3, progress=False)
    assert both.cost[1] == alone.cost[0] and both.steps[1] == alone.steps[0]  # untouched by the refusal
    assert both.accepted_steps[0] < 3 and np.isfinite(both.cost[0])
    full = fitting.fit_fleet(starts[0], data, starts=starts, predictor=predictor, progress=False)
    assert all(full.success), full.reasons
    np.testing.assert_allclose([full[i].values[0] for i in range(2)], 1.0, atol=0.01)
    # outside a fleet the same check still raises (the NaN mode is only traced inside it)
    with pytest.raises(Exception, match="at most 1.2"):
        jax.block_until_ready(eqx.filter_jit(_refusing)(Gain(jnp.asarray(2.0)), fitting.ExperimentArrays(
            t=jnp.asarray(t), dt=jnp.asarray(DT), v_in=jnp.asarray(v), channels={})))


def test_bad_fleets_are_refused_naming_the_argument():
    sets = _records(2)
    short = _records(1, n=200)
    with pytest.raises(PiezojaxValueError, match=r"`datasets\[1\]` does not have the layout"):
        fitting.fit_fleet(_model(), [sets[0], short[0]], free=FREE, progress=False)
    with pytest.raises(PiezojaxValueError, match="one model per actuator"):
        fitting.fit_fleet(_model(), sets, starts=[_model()], free=FREE, progress=False)
    with pytest.raises(PiezojaxValueError, match="`max_steps`"):
        fitting.fit_fleet(_model(), sets, free=FREE, max_steps=0, progress=False)
    with pytest.raises(PiezojaxValueError, match="`batch_size`"):
        fitting.fit_fleet(_model(), sets, free=FREE, batch_size=0, progress=False)
    with pytest.raises(PiezojaxValueError, match="one dataset per actuator"):
        fitting.fit_fleet(_model(), sets[0], free=FREE, progress=False)
    with pytest.raises(PiezojaxValueError, match="`scales`"):
        fitting.fit_fleet(_model(), sets, free=FREE, scales="unit", progress=False)


class _Interrupt(fitting.AbstractProgressMeter):
    """Ctrl-C at the first report."""

    def init(self, label, starts):
        return None

    def step(self, state, progress):
        raise KeyboardInterrupt

    def close(self, state):
        return None


def test_ctrl_c_keeps_every_actuators_last_accepted_parameters(fleet):
    sets, _ = fleet
    res = fitting.fit_fleet(_model(), sets, free=FREE, weights=WEIGHTS, max_steps=12, batch_size=1,
                            steps_per_call=1, progress=_Interrupt())
    assert res.codes == ["interrupted"] * 3 and not any(res.success)
    assert list(res.steps) == [1, 0, 0]  # the first batch took one step; the others never began
    assert np.isfinite(res.cost[0]) and np.all(np.isnan(res.cost[1:]))  # not begun: not even linearised
    start = fitting.Problem(_model(), sets[1], free=FREE, weights=WEIGHTS)
    np.testing.assert_allclose(res[1].values, start.physical(start.u0), rtol=1e-12)
    assert res[1].std_error_status == ["not computed"] * len(res[1].values)
    # a batch that ran to max_steps before the interrupt keeps that verdict
    two = fitting.fit_fleet(_model(), sets, free=FREE, weights=WEIGHTS, max_steps=2, batch_size=1,
                            steps_per_call=1, progress=_InterruptAt(4))
    assert two.codes == ["max_steps_reached", "interrupted", "interrupted"] and list(two.steps) == [2, 2, 0]


class _InterruptAt(_Interrupt):
    """Ctrl-C at the report number `at`."""

    at: int

    def init(self, label, starts):
        return 0

    def step(self, state, progress):
        if state + 1 == self.at:
            raise KeyboardInterrupt
        return state + 1
