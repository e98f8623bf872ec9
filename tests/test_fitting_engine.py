"""The calibration engine: Jacobian, parameter selection, padding, failure modes, bad input, save/load."""

import dataclasses
import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fitting
import fitting._plots as fitting_plots
import piezojax as pj
from piezojax._checks import PiezojaxValueError

DT = 1e-3


def _model(smoothing=0.0):
    return pj.Actuator(
        pj.PrandtlIshlinskii(jnp.array([0.3, 0.2]), jnp.array([10.0, 30.0]), w0=1.0, smoothing=smoothing),
        None,
        pj.StableTransferFunction(1.0, omega=jnp.array([2 * np.pi * 40.0]), zeta=jnp.array([0.4])),
        capacitance=1e-9,
        coupling=2e-9,
    )


def _experiments(model, lengths=(600, 600, 520), noise=1e-3, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for i, n in enumerate(lengths):
        t = np.arange(n) * DT
        v = (30 + 15 * i) * np.sin(2 * np.pi * (2 + i) * t) * np.minimum(1, t / 0.1)
        y = np.asarray(model.simulate(v, DT).displacement)
        out.append(fitting.Experiment.from_arrays(t=t, v_in=v, name=f"e{i}",
                                                  displacement=y + noise * rng.standard_normal(n)))
    return fitting.Dataset(out)


@pytest.fixture(scope="module")
def data():
    return _experiments(_model())


def test_jacobian_matches_central_differences(data):
    # smooth plays, so that the residuals are differentiable everywhere and FD is a fair reference
    model = _model(smoothing=0.1)
    model = pj.constrain(model, lambda m: m.hysteresis.thresholds, pj.OrderedPositive)
    prob = fitting.Problem(model, data, free=["hysteresis", "dynamics.omega", "dynamics.zeta"])
    u = prob.u0 * 1.01
    r, jt = prob.residuals_and_jacobian(u)
    res = jax.jit(prob.residuals)
    h = 1e-6
    fd = np.stack([(np.asarray(res(u + h * e)) - np.asarray(res(u - h * e))) / (2 * h) for e in np.eye(u.size)])
    np.testing.assert_allclose(np.asarray(jt), fd, rtol=1e-5, atol=1e-7 * np.abs(fd).max())
    assert np.allclose(np.asarray(r), np.asarray(res(u)))


def _two_groups():
    # two channels, two groups (lengths in different power-of-2 brackets, padding in the first)
    model = pj.constrain(_model(smoothing=0.1), lambda m: m.hysteresis.thresholds, pj.OrderedPositive)
    rng = np.random.default_rng(3)
    exps = []
    for i, n in enumerate((300, 280, 270, 700)):
        t = np.arange(n) * DT
        v = (20 + 10 * i) * np.sin(2 * np.pi * (3 + i) * t)
        out = pj.unwrap(model).simulate(v, DT)
        exps.append(fitting.Experiment.from_arrays(
            t=t, v_in=v, name=f"e{i}", displacement=np.asarray(out.displacement) + 1e-3 * rng.standard_normal(n),
            charge=np.asarray(out.charge) * (1 + 1e-3 * rng.standard_normal(n))))
    ds = fitting.Dataset(exps)
    free = ["hysteresis.weights", "hysteresis.thresholds", "dynamics.omega", "capacitance"]
    return model, ds, free


def test_normal_equations_equal_the_full_jacobian_for_any_chunk(monkeypatch):
    # chunks of 1, 2 and all experiments
    model, ds, free = _two_groups()
    ref = fitting.Problem(model, ds, free=free)
    assert len(ref.core.groups) == 2
    u = ref.u0 * 1.02
    r, jt = (np.asarray(x) for x in ref.residuals_and_jacobian(u))

    def check(normal_equations):
        rn, g, h = (np.asarray(x) for x in normal_equations(u))
        np.testing.assert_allclose(rn, r, rtol=0, atol=1e-14)
        np.testing.assert_allclose(g, jt @ r, rtol=1e-10, atol=1e-12 * np.abs(jt @ r).max())
        np.testing.assert_allclose(h, jt @ jt.T, rtol=1e-10, atol=1e-12 * np.abs(h).max())

    for chunk in (None, 1, 2):
        check(fitting.Problem(model, ds, free=free, jacobian_chunk=chunk).normal_equations)
    # the directions of a long record in blocks (`tangent_block`), the last one padded with zero directions: one
    # direction at a time in both groups, then 4 of the 6 at a time in the first group and fewer in the second
    m = [sum(int(k.shape[-1]) for k in grp.masks.values()) for grp in ref.core.groups]
    p = u.size
    chunked = fitting.Problem(model, ds, free=free, jacobian_chunk=2)  # the blocks under `vmap` over experiments
    for budget in (1, 4 * 8 * m[0]):
        monkeypatch.setattr(fitting._problem, "_TANGENT_BUDGET", budget)
        blocks = [fitting._problem.tangent_block(n, p) for n in m]
        assert blocks == ([1, 1] if budget == 1 else [4, 4 * m[0] // m[1]]) and max(blocks) < p
        for prob in (ref, chunked):
            # traced anew (a new function), under the patched budget
            check(lambda v, c=prob.core: eqx.filter_jit(lambda c, x: c.normal_equations(x))(c, v))

    # the results' metrics come from the residuals unweighted: equal to the simulated predictions' errors
    errors, preds = ref.experiment_errors(r), ref.experiment_predictions(u)
    for exp, err, pred in zip(ds, errors, preds):
        assert set(err) == set(pred) == {"displacement", "charge"}
        for c in err:
            assert err[c].shape == (exp.n,)
            np.testing.assert_allclose(err[c], pred[c] - exp.channels[c], rtol=0,
                                       atol=1e-12 * np.abs(exp.channels[c]).max())
    with pytest.raises(PiezojaxValueError, match="`r`"):
        ref.experiment_errors(r[:-1])
    # the compiled reparametrisation Jacobian (standard errors) equals autodiff of `physical`
    np.testing.assert_allclose(np.asarray(ref.physical_jacobian(u)), np.asarray(jax.jacfwd(ref.physical)(u)),
                               rtol=1e-13, atol=0)


def test_steps_are_those_of_optimistix_levenberg_marquardt(data):
    # the normal-equation loop (linearising only at accepted points) is optx.LevenbergMarquardt's algorithm: after k
    # trials it stands where optimistix stands after k + 1 steps (its first step only evaluates the start)
    import optimistix as optx

    model = pj.constrain(_model(smoothing=0.1), lambda m: m.hysteresis.thresholds, pj.OrderedPositive)
    start = eqx.tree_at(lambda m: m.dynamics.omega, model, model.dynamics.omega * 1.3)
    prob = fitting.Problem(start, data, free=["hysteresis.w0", "hysteresis.weights", "hysteresis.thresholds",
                                              "dynamics.omega", "dynamics.zeta"])
    core = prob.core

    @jax.custom_jvp
    def residuals(u):  # J from forward mode as a matrix (optimistix's own linearisation trips a batched error check)
        return core.residuals(u)

    @residuals.defjvp
    def _residuals_jvp(primals, tangents):
        return core.residuals(primals[0]), tangents[0] @ core.jacobian_t(primals[0])

    res_fn = jax.jit(lambda u, _: residuals(u))
    for k in (3, 9):
        ours = fitting.solve(prob, max_steps=k, ftol=0.0, progress=False)
        ref = optx.least_squares(res_fn, optx.LevenbergMarquardt(rtol=1e-8, atol=1e-10), prob.u0, max_steps=k + 1,
                                 throw=False)
        assert ours.steps == k and ours.code == "max_steps_reached"
        np.testing.assert_allclose(np.asarray(ours.u), np.asarray(ref.value), rtol=1e-7, atol=1e-9)
        assert ours.accepted_steps == int(ref.state.num_accepted_steps) - 1


@pytest.mark.parametrize("method", ["levenberg_marquardt", "trust_region"])
def test_multistart_runs_each_start_as_alone_and_reports_the_best(data, method):
    def guarded(m, d):  # predictions are NaN for w0 > 5: a start there fails at once
        y = m.simulate(d.v_in, d.dt).displacement
        return {"displacement": jnp.where(m.hysteresis.w0 > 5.0, jnp.nan, 1.0) * y}

    pred = fitting.Predictor(guarded, ("displacement",))
    model = _model()
    free = ["hysteresis.w0", "hysteresis.weights", "dynamics.omega"]
    starts = [
        eqx.tree_at(lambda m: m.dynamics.omega, model, model.dynamics.omega * 1.2),
        eqx.tree_at(lambda m: m.hysteresis.w0, model, jnp.asarray(10.0)),
        eqx.tree_at(lambda m: (m.hysteresis.w0, m.hysteresis.weights), model,
                    (jnp.asarray(0.7), jnp.array([0.1, 0.4]))),
    ]
    prob = fitting.Problem(model, data, predictor=pred, free=free)
    res = fitting.solve(prob, starts=starts, progress=False, method=method)
    assert [st["code"] for st in res.starts][1] == "nonfinite_initial"
    ok = [i for i, st in enumerate(res.starts) if st["success"]]
    assert ok == [0, 2]
    best = min(ok, key=lambda i: res.starts[i]["cost"])
    assert res.starts[best]["best"] and res.success and res.cost == pytest.approx(res.starts[best]["cost"], rel=1e-12)
    assert "multi-start: 3 starts, 2 converged" in res.report()
    assert "(nonfinite_initial)" in res.report() and "(* reported)" in res.report()
    # the first of several fits (the command line's re-seeding rounds): the line says so, the verdict is not its own
    later = dataclasses.replace(res, starts=[dict(st, first_of=3) for st in res.starts])
    line = next(li for li in later.report().splitlines() if "multi-start" in li)
    assert line.startswith("  multi-start of the first fit (of 3; the second started from *): 3 starts")
    assert "(* reported)" not in line
    # the starts do not interact: without the failing start, each takes the same steps to the same cost; alone (a
    # single start runs unbatched, so rounding differs and the last steps near machine precision may differ), each
    # reaches the same cost
    pair = fitting.solve(prob, starts=[starts[i] for i in ok], progress=False, method=method)
    for j, i in enumerate(ok):
        assert pair.starts[j]["steps"] == res.starts[i]["steps"]
        assert pair.starts[j]["cost"] == pytest.approx(res.starts[i]["cost"], rel=1e-12)
        alone = fitting.solve(fitting.Problem(starts[i], data, predictor=pred, free=free, scales=prob.scales),
                              progress=False, method=method)
        assert alone.success and alone.cost == pytest.approx(res.starts[i]["cost"], rel=1e-9)
    with pytest.raises(PiezojaxValueError, match=r"`starts\[0\]` does not have the structure"):
        fitting.solve(prob, starts=[pj.constrain(model, lambda m: m.hysteresis.w0, pj.Positive)], progress=False)
    with pytest.raises(PiezojaxValueError, match="`starts` must list at least one"):
        fitting.solve(prob, starts=[], progress=False)


def test_a_start_that_cannot_catch_up_is_outpaced(data):
    """Two starts: one next to the truth converges in about ten steps; the other, from a negative w0, crawls towards
    a worse minimum (left alone it converges there after about 50 steps). Once it has had twice the winner's steps
    and its cost would not reach the winner's within max_steps at its recent rate, it stops ("outpaced"); the
    result is the winner's, and the report marks the start."""
    def constrained(m):
        m = pj.constrain(m, lambda m: m.hysteresis.thresholds, pj.OrderedPositive)
        m = pj.constrain(m, lambda m: m.dynamics.zeta, pj.Positive)
        return pj.constrain(m, lambda m: m.dynamics.omega, pj.Positive)

    model = _model()
    free = ["hysteresis.w0", "hysteresis.weights", "hysteresis.thresholds", "dynamics.omega", "dynamics.zeta"]
    near = constrained(eqx.tree_at(lambda m: m.dynamics.omega, model, model.dynamics.omega * 1.05))
    far = constrained(eqx.tree_at(lambda m: m.hysteresis.w0, model, jnp.asarray(-1.0)))
    prob = fitting.Problem(constrained(model), data, free=free)
    res = fitting.solve(prob, starts=[near, far], progress=False, max_steps=200)
    winner, other = res.starts
    assert winner["best"] and winner["success"] and res.cost == pytest.approx(winner["cost"], rel=1e-12)
    assert other["code"] == "outpaced" and not other["success"] and other["cost"] > 10 * winner["cost"]
    assert 2 * winner["steps"] <= other["steps"] < 40
    assert f"stopped after {other['steps']} steps: another start converged" in other["reason"]
    assert "(outpaced)" in res.report()
    alone = fitting.solve(prob, starts=[far, far], progress=False, max_steps=200)  # nobody to outpace it
    assert "outpaced" not in {st["code"] for st in alone.starts}
    assert min(st["steps"] for st in alone.starts) > other["steps"]


def test_trust_region_is_scipys_trf(data):
    # method="trust_region" is scipy's least_squares(method="trf", x_scale="jac") for unbounded problems: with the
    # same exact Jacobian, the same iterates (after 3 trials, and at convergence) and the same counts
    import scipy.optimize

    model = pj.constrain(_model(smoothing=0.1), lambda m: m.hysteresis.thresholds, pj.OrderedPositive)
    start = eqx.tree_at(lambda m: (m.dynamics.omega, m.hysteresis.w0), model,
                        (model.dynamics.omega * 1.4, jnp.asarray(0.6)))
    prob = fitting.Problem(start, data, free=["hysteresis.w0", "hysteresis.weights", "hysteresis.thresholds",
                                              "dynamics.omega", "dynamics.zeta"])
    res_fn = jax.jit(prob.residuals)

    def scipy_fit(max_nfev):
        return scipy.optimize.least_squares(
            lambda u: np.asarray(res_fn(jnp.asarray(u))), np.asarray(prob.u0),
            jac=lambda u: np.asarray(prob.residuals_and_jacobian(jnp.asarray(u))[1]).T,
            method="trf", x_scale="jac", ftol=1e-8, xtol=1e-8, gtol=None, max_nfev=max_nfev)

    early = fitting.solve(prob, method="trust_region", max_steps=3, progress=False)
    ref = scipy_fit(4)  # scipy counts the evaluation at the start
    np.testing.assert_allclose(np.asarray(early.u), ref.x, rtol=1e-8, atol=1e-10)
    assert early.accepted_steps + 1 == ref.njev
    full = fitting.solve(prob, method="trust_region", max_steps=200, progress=False)
    ref = scipy_fit(None)
    assert full.success and ref.status in (2, 3, 4), (full.reason, ref.message)
    assert full.cost == pytest.approx(float(ref.cost), rel=1e-9)
    np.testing.assert_allclose(np.asarray(full.u), ref.x, rtol=1e-6, atol=1e-8)
    assert (full.steps + 1, full.accepted_steps + 1) == (ref.nfev, ref.njev)


@pytest.mark.parametrize("method", ["levenberg_marquardt", "trust_region"])
def test_a_trial_the_model_refuses_is_a_failed_trial(method):
    # a runtime check of the model (eqx.error_if) on trial parameters rejects that trial and shrinks the step; it
    # does not abort the fit (here the first Levenberg–Marquardt trial lands at a > 20)
    class Gain(eqx.Module):
        a: jax.Array

    def predict(m, d):
        y = jnp.exp(m.a) * d.v_in
        return {"displacement": eqx.error_if(y, m.a > 1.2, "`a` must be at most 1.2")}

    t = np.arange(400) * DT
    v = 10 * np.sin(2 * np.pi * 5 * t)
    rng = np.random.default_rng(0)
    ds = fitting.Dataset([fitting.Experiment.from_arrays(t=t, v_in=v, name="g",
                                                         displacement=np.e * v + 1e-3 * rng.standard_normal(t.size))])
    prob = fitting.Problem(Gain(jnp.asarray(-3.0)), ds, predictor=fitting.Predictor(predict, ("displacement",)))
    if method == "levenberg_marquardt":
        first = fitting.solve(prob, method=method, max_steps=1, progress=False)
        assert first.accepted_steps == 0 and first.cost == first.initial_cost
    res = fitting.solve(prob, method=method, progress=False)
    assert res.success, res.reason
    assert res.values[0] == pytest.approx(1.0, abs=5 * res.std_errors[0])


@pytest.mark.parametrize("method", ["levenberg_marquardt", "trust_region"])
def test_an_accepted_point_with_a_nonfinite_jacobian_is_undone(method):
    # the model's derivative is NaN at the first point the clean fit accepts (as d exp(-dt/tau)/d tau at a time
    # constant stepped to 1e-249 s): that step is undone and counted as refused, and the fit goes on to the truth
    # instead of failing at that point
    class Gain(eqx.Module):
        a: jax.Array

    def problem(bad_at=None):
        @jax.custom_jvp
        def through(a):
            return a

        @through.defjvp
        def _through_jvp(primals, tangents):
            (a,), (da,) = primals, tangents
            bad = jnp.zeros((), bool) if bad_at is None else jnp.abs(a - bad_at) <= 1e-9 * abs(bad_at)
            return a, jnp.where(bad, jnp.nan, 1.0) * da

        def predict(m, d):
            return {"displacement": jnp.exp(through(m.a)) * d.v_in}

        return fitting.Problem(Gain(jnp.asarray(-1.0)), ds, predictor=fitting.Predictor(predict, ("displacement",)))

    t = np.arange(400) * DT
    v = 10 * np.sin(2 * np.pi * 5 * t)
    rng = np.random.default_rng(0)
    ds = fitting.Dataset([fitting.Experiment.from_arrays(t=t, v_in=v, name="g",
                                                         displacement=np.e * v + 1e-3 * rng.standard_normal(t.size))])
    clean = problem()
    first = next(r for k in range(1, 10) if (r := fitting.solve(clean, method=method, max_steps=k,
                                                                progress=False)).accepted_steps == 1)
    a1 = float(first.values[0])
    assert abs(a1 - 1.0) > 1e-3  # the first accepted point is not yet the optimum
    res = fitting.solve(problem(bad_at=a1), method=method, progress=False)
    ref = fitting.solve(clean, method=method, progress=False)
    assert res.success, res.reason
    assert res.code != "nonfinite" and res.steps > ref.steps
    assert res.values[0] == pytest.approx(ref.values[0], abs=1e-6 * ref.std_errors[0])
    assert a1 not in [float(x) for x in res.values]


def test_padding_equals_separate_problems(data):
    model = _model()
    joint = fitting.Problem(model, data, free=["hysteresis.weights"], scales="value")
    assert len(joint.core.groups) == 1  # one dt, one channel set, lengths in (512, 1024]: padded to 600, vmapped
    long = fitting.Dataset([*data, fitting.Experiment.from_arrays(dt=DT, v_in=np.ones(2000), name="long",
                                                                  displacement=np.ones(2000))])
    assert len(fitting.Problem(model, long, free=["hysteresis.weights"], scales="value").core.groups) == 2
    r_joint = np.asarray(joint.residuals(joint.u0))
    parts = [np.asarray(fitting.Problem(model, [e], free=["hysteresis.weights"], weights=joint.weights,
                                            scales="value").residuals(
        joint.u0)) for e in data]
    n = [e.n for e in data]
    # padded layout: experiment j occupies [j*600, j*600 + n_j); the padding is exactly zero
    for j, (p, nj) in enumerate(zip(parts, n)):
        np.testing.assert_allclose(r_joint[j * 600 : j * 600 + nj], p, rtol=0, atol=1e-15)
        assert np.all(r_joint[j * 600 + nj : (j + 1) * 600] == 0)
    assert joint.num_residuals == sum(n)


def test_free_selection_by_path_and_selector(data):
    model = pj.constrain(_model(), lambda m: m.hysteresis.thresholds, pj.OrderedPositive)
    p1 = fitting.Problem(model, data, free=["hysteresis.thresholds", "coupling"], scales="value")
    assert p1.parameter_names() == ["hysteresis.thresholds[0]", "hysteresis.thresholds[1]", "coupling"]
    np.testing.assert_allclose(np.asarray(p1.physical(p1.u0)), [10.0, 30.0, 2e-9], rtol=1e-12)
    p2 = fitting.Problem(model, data, free=lambda m: (m.hysteresis.thresholds, m.coupling), scales="value")
    assert p2.parameter_names() == p1.parameter_names()
    # default: every parameter except the fields declared as settings (pj.setting(): the smoothing), by declaration,
    # not by name: a field called `smoothing` that is not declared a setting is a parameter, a setting of another
    # name is not; naming a setting in `free` frees it
    p3 = fitting.Problem(model, data, scales="value")
    assert not any("smoothing" in n for n in p3.parameter_names())
    assert "dynamics.omega[0]" in p3.parameter_names()
    assert [jax.tree_util.keystr(k) for k in pj.setting_key_paths(model)] == [".hysteresis.smoothing"]

    class Knob(eqx.Module):
        smoothing: jax.Array
        level: jax.Array = pj.setting()

    names = fitting.free_mask(Knob(jnp.asarray(0.1), jnp.asarray(2.0)))
    assert (names.smoothing, names.level) == (True, False)
    freed = fitting.Problem(model, data, free=["hysteresis.smoothing"], scales="value")
    assert freed.parameter_names() == ["hysteresis.smoothing"]
    with pytest.raises(PiezojaxValueError, match="no parameter 'hysteresis.gain'.*available: .*hysteresis.weights"):
        fitting.Problem(model, data, free=["hysteresis.gain"])


def test_bad_input_errors(data):
    model = _model()
    only_v = fitting.Dataset([fitting.Experiment.from_arrays(t=data[0].t, v_in=data[0].v_in, name="x",
                                                             force=data[0].v_in * 0 + 1.0)])
    with pytest.raises(PiezojaxValueError, match="none of the channels the model predicts"):
        fitting.Problem(model, only_v)
    with pytest.raises(PiezojaxValueError, match="does not predict 'force'"):
        fitting.Problem(model, data, targets=["force"])
    assert fitting.Problem(model, data[0]).parameter_names() == fitting.Problem(model, data).parameter_names()
    with pytest.raises(PiezojaxValueError, match="`weights` has an entry for 'displacment', which is no channel"):
        fitting.Problem(model, data, weights={"displacement": 1.0, "displacment": 1.0})
    with pytest.raises(PiezojaxValueError, match="`text` must be the TOML text"):
        fitting.parse_config({"hysteresis": {"kind": "prandtl_ishlinskii"}})
    with pytest.raises(PiezojaxValueError, match="experiment 'x' has none of the target channels"):
        fitting.Problem(model, fitting.Dataset([*data, *only_v]))
    obs = pj.IvanBench().observer()
    with pytest.raises(PiezojaxValueError, match="lacks the channel.*v_out"):
        fitting.Problem(obs, data)
    with pytest.raises(PiezojaxValueError, match="weights"):
        fitting.Problem(model, data, weights="loudness")
    with pytest.raises(PiezojaxValueError, match="underdetermined"):
        short = fitting.Dataset([fitting.Experiment.from_arrays(dt=DT, v_in=[0.0, 1.0, 2.0], name="s",
                                                                displacement=[0.0, 1.0, 2.0])])
        fitting.Problem(model, short)
    with pytest.raises(PiezojaxValueError, match="`method`"):
        fitting.solve(fitting.Problem(model, data, free=["hysteresis.w0"]), method="bfgs", progress=False)
    with pytest.raises(PiezojaxValueError, match="v_in.*NaN|NaN.*v_in|non-finite|finite"):
        fitting.Experiment.from_arrays(dt=DT, v_in=[0.0, np.nan, 2.0], name="nan", displacement=[0.0, 1.0, 2.0])


def _recover(data, **kw):
    start = eqx.tree_at(lambda m: (m.hysteresis.weights, m.dynamics.omega), _model(),
                        (jnp.array([0.2, 0.3]), jnp.array([2 * np.pi * 30.0])))
    return fitting.fit(start, data, free=["hysteresis.weights", "hysteresis.w0", "dynamics.omega", "dynamics.zeta"],
                       progress=False, **kw)


def test_ctrl_c_outside_the_steps_keeps_the_fit(data, monkeypatch):
    """Ctrl-C between two smoothing levels, or while the result's linearisation is formed, returns the fit so far
    (code "interrupted"), as one during the steps does."""
    import fitting._solve as solve_module

    real_iterate, calls = solve_module.iterate, []

    def interrupted_at_the_second_level(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real_iterate(*args, **kwargs)

    monkeypatch.setattr(solve_module, "iterate", interrupted_at_the_second_level)
    res = _recover(data, smoothing=(0.05, 0.0), max_steps=5)
    assert res.code == "interrupted" and not res.success and len(res.levels) == 1
    assert np.all(np.isfinite(res.values)) and set(res.std_error_status) == {"finite"}
    monkeypatch.setattr(solve_module, "iterate", real_iterate)

    def no_linearisation(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(solve_module, "_linearisation", no_linearisation)
    res = _recover(data, max_steps=5)
    assert res.code == "interrupted" and "after the steps" in res.reason
    assert set(res.std_error_status) == {"not computed"} and np.all(np.isfinite(res.values))
    assert np.isfinite(res.cost) and np.isfinite(next(iter(res.metrics.values()))["displacement"]["rmse"])


def test_a_block_frees_its_parameters_not_its_settings(data):
    model = eqx.tree_at(lambda m: m.hysteresis.smoothing, _model(), jnp.asarray(0.1))
    names = fitting.Problem(model, data, free=["hysteresis"]).parameter_names()
    assert names and not any("smoothing" in n for n in names)
    names = fitting.Problem(model, data, free=lambda m: m.hysteresis).parameter_names()
    assert names and not any("smoothing" in n for n in names)
    assert fitting.Problem(model, data, free=lambda m: m.hysteresis.smoothing).parameter_names() == [
        "hysteresis.smoothing"]
    with pytest.raises(PiezojaxValueError, match="`smoothing` levels set 'hysteresis.smoothing', which `free`"):
        fitting.fit(model, data, free=["hysteresis.smoothing", "hysteresis.w0"], smoothing=(0.05, 0.0))


def test_fit_recovers_and_reports(data):
    res = _recover(data)
    assert res.success, res.reason
    truth = {"hysteresis.weights[0]": 0.3, "hysteresis.weights[1]": 0.2, "hysteresis.w0": 1.0,
             "dynamics.omega[0]": 2 * np.pi * 40.0, "dynamics.zeta[0]": 0.4}
    for name, v, se in zip(res.parameter_names, res.values, res.std_errors):
        assert abs(v - truth[name]) < 5 * se, (name, v, se)
        assert 0 < se < 0.05 * abs(truth[name])
    for e in data:
        m = res.metrics[e.name]["displacement"]
        assert abs(m["rmse"] - 1e-3) < 2e-4  # the noise level
    assert res.cost < res.initial_cost and res.history[-1] == pytest.approx(res.cost, rel=1e-12)
    # the step of each accepted cost: from 0 (the start), increasing, the last at most the steps taken
    hs = res.history_steps
    assert len(hs) == len(res.history) == res.accepted_steps + 1 and hs[0] == 0
    assert all(b > a for a, b in zip(hs, hs[1:])) and hs[-1] <= res.steps
    text = res.report()
    assert "converged" in text and "dynamics.omega[0]" in text
    assert np.allclose(np.diag(res.correlation), 1.0)
    # predictions: the fitted channels of every record, equal to the fit's own; a 10-sample record works too, and
    # after its first part as history a record's end is the whole record's end
    # (the result holds how it was fitted, not the problem; the fit's padded, batched residuals are the same numbers)
    assert not hasattr(res, "problem") and res.targets == ("displacement",) and res.dataset is data
    preds = res.predict(res.dataset)
    again = fitting.Problem(res.params, data, free=["hysteresis.w0"], weights=res.weights)
    for p, e, exp in zip(preds, again.experiment_errors(again.residuals(again.u0)), data):
        y = exp.channels["displacement"]
        np.testing.assert_allclose(p["displacement"], y + e["displacement"], rtol=0, atol=1e-12 * np.abs(y).max())
    e = data[0]
    head, tail = e.slice(None, e.t[10], name="head"), e.slice(e.t[10], e.t[19] + 0.5 * e.dt, name="tail")
    (y,) = res.predict(tail, history=head)
    assert tail.n == 10 and set(y) == {"displacement"}
    np.testing.assert_allclose(y["displacement"], preds[0]["displacement"][10:20], rtol=1e-10, atol=1e-14)


def test_failed_fits_return_reasons_not_nan(data):
    res = _recover(data, max_steps=2)
    assert not res.success and res.code == "max_steps_reached" and "max_steps" in res.reason
    assert np.all(np.isfinite(res.values))

    def nan_after_start(m, d):  # predictions are NaN once the gain leaves its start: every trial step fails
        g = m.hysteresis.w0
        y = m.simulate(d.v_in, d.dt).displacement
        return {"displacement": jnp.where(jnp.abs(g - 1.0) > 0, jnp.nan, 1.0) * y}

    pred = fitting.Predictor(nan_after_start, ("displacement",))
    start = eqx.tree_at(lambda m: m.hysteresis.weights, _model(), jnp.array([0.25, 0.25]))
    res = fitting.fit(start, data, predictor=pred, free=["hysteresis.w0", "hysteresis.weights"], progress=False,
                      kink_restarts=0)
    assert not res.success and res.code in ("stalled", "not_stationary")
    np.testing.assert_allclose(res.values, [0.25, 0.25, 1.0])  # the last accepted (= initial) parameters
    # with the restarts past kinks (default): a restart that does not converge is dropped, and the verdict says
    # that the cost still falls (along the weights, where the model stays finite)
    more = fitting.fit(start, data, predictor=pred, free=["hysteresis.w0", "hysteresis.weights"], progress=False)
    assert not more.success and more.code == "not_stationary" and "the cost falls along" in more.reason
    assert more.cost <= res.cost and np.all(np.isfinite(more.values))
    with pytest.raises(fitting.FitError, match="fit failed: (no decrease|stopped where)") as raised:
        fitting.fit(start, data, predictor=pred, free=["hysteresis.w0"], progress=False, throw=True)
    # the project's error type, holding the failed result (its last accepted, finite parameters)
    assert isinstance(raised.value, pj.PiezojaxError) and isinstance(raised.value, RuntimeError)
    failed = raised.value.result
    assert raised.value.code == failed.code and not failed.success and np.all(np.isfinite(failed.values))

    always_nan = fitting.Predictor(lambda m, d: {"displacement": d.v_in * jnp.nan}, ("displacement",))
    res = fitting.fit(start, data, predictor=always_nan, free=["hysteresis.w0"], progress=False)
    assert not res.success and res.code == "nonfinite_initial"


def test_continuation_levels_and_smoothing(data):
    res = _recover(data, smoothing=(0.05, 0.0))
    assert [lv["smoothing"] for lv in res.levels] == [0.05, 0.0]
    assert float(res.model.hysteresis.smoothing) == 0.0
    assert res.success, res.reason


def test_save_load_atomic(data, tmp_path, monkeypatch):
    res = _recover(data)
    out = res.save(tmp_path / "fit", extra={"note": "test"})
    summary = json.loads((out / "result.json").read_text())
    assert summary["success"] and summary["note"] == "test"
    assert list(summary["parameters"]) == summary["correlation_names"] == list(res.parameter_names)
    assert np.shape(summary["correlation"]) == (len(res.parameter_names),) * 2
    assert summary["precision"] == "float64" and "64-bit mode off" not in res.report()
    assert (out / "report.txt").read_text().startswith("fit converged")
    assert list(out.glob("timeseries_*.png")) and list(out.glob("loops_*.png"))
    loaded = fitting.load_model(out, like=_model())
    v = data[0].v_in
    np.testing.assert_array_equal(np.asarray(loaded.simulate(v, DT).displacement),
                                  np.asarray(res.model.simulate(v, DT).displacement))
    # a `like` reparametrised otherwise has leaves of the same shapes: refused, not read as physical values
    other = eqx.tree_at(lambda m: m.hysteresis.thresholds, _model(),
                        pj.OrderedPositive.from_value(jnp.array([10.0, 30.0])))
    with pytest.raises(PiezojaxValueError, match=r"`like` does not have the structure of the saved model \(saved "
                       r"'hysteresis.thresholds: array', `like` has 'hysteresis.thresholds: OrderedPositive'\)"):
        fitting.load_model(out, like=other)
    with pytest.raises(PiezojaxValueError):
        res.save(tmp_path / "fit")  # exists
    # interrupted while writing the figures: nothing appears
    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(fitting_plots, "save_figures", boom)
    with pytest.raises(KeyboardInterrupt):
        res.save(tmp_path / "fit2")
    assert not (tmp_path / "fit2").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["fit"]
