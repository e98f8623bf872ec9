"""The solver as components: results enumeration, progress meters, solver instances, per-start refusal, throw."""

import io

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
import pytest

import fitting
from piezojax._checks import PiezojaxValueError

DT = 1e-3
T = np.arange(400) * DT
V = 10 * np.sin(2 * np.pi * 5 * T)


class Gain(eqx.Module):
    a: jax.Array


def _refusing(m, d):  # the model refuses a > 1.2 (a runtime check, as a physical block's parameter check)
    y = jnp.exp(m.a) * d.v_in
    return {"displacement": eqx.error_if(y, m.a > 1.2, "`a` must be at most 1.2")}


PREDICTOR = fitting.Predictor(_refusing, ("displacement",))


@pytest.fixture(scope="module")
def problem():
    rng = np.random.default_rng(0)
    ds = fitting.Dataset([fitting.Experiment.from_arrays(t=T, v_in=V, name="g",
                                                         displacement=np.e * V + 1e-3 * rng.standard_normal(T.size))])
    return fitting.Problem(Gain(jnp.asarray(-3.0)), ds, predictor=PREDICTOR)


def test_results_enumeration_names_every_code_with_a_message():
    """One enumeration with messages: what the loop carries per start, and every code, verdict and success set
    derived from it."""
    from fitting._solver import CODES, HARD_FAILURES, LOOP_ONLY, NAMES, SUCCESSES, result_code, result_message

    assert len(fitting.RESULTS) == len(NAMES)
    assert set(CODES) == {"successful", "converged_at_kink", "converged_zero_residual", "max_steps_reached", "stalled",
                          "not_stationary", "interrupted", "nonfinite_initial", "nonfinite", "linear_solve_failed",
                          "outpaced"}
    assert set(CODES) | set(LOOP_ONLY) | {"successful_flat"} == set(NAMES)
    assert set(SUCCESSES) | set(HARD_FAILURES) < set(CODES) and not set(SUCCESSES) & set(HARD_FAILURES)
    for code in CODES:
        item = getattr(fitting.RESULTS, code)
        assert result_code(item) == code and result_message(code) == fitting.RESULTS[item] and result_message(code)
    assert result_code(fitting.RESULTS.successful_flat) == "successful"  # two tests of convergence, one code
    # usable under jit and vmap, as optx.RESULTS
    batch = jax.vmap(lambda ok: fitting.RESULTS.where(ok, fitting.RESULTS.successful_flat, fitting.RESULTS.stalled))(
        jnp.array([True, False]))
    assert result_code(batch) == ["successful", "stalled"]
    assert fitting.Verdict("converged_at_kink", "r").success and fitting.Verdict("nonfinite", "r").hard


def test_the_loops_stopping_tests_are_one_function_in_order():
    # `advance` is the stopping bookkeeping of both loops (`fitting.solve`'s and the fleet's), under jit and vmap
    from fitting import _solver as S

    def run(costs, takes, *, ok=True, terminate=False, finite=True, window=3, max_rejections=4, start=10.0):
        book = S.begin(jnp.asarray(start), jnp.asarray(True), window)
        step = jax.jit(lambda b, c, t: S.advance(b, cost=c, take=t, ok=jnp.asarray(ok), finite=jnp.asarray(finite),
                                                 terminate=jnp.asarray(terminate), ftol=1e-2, window=window,
                                                 max_rejections=max_rejections))
        names = []
        for c, t in zip(costs, takes):
            book = step(book, jnp.asarray(c), jnp.asarray(t))
            names.append(S.result_names(book.result))
        return book, names

    # decreasing costs keep running; three accepted steps that lower the cost by < 1 % each: converged (flat)
    book, names = run([5.0, 2.0, 1.0, 0.999, 0.998, 0.997], [True] * 6)
    assert names == ["running"] * 5 + ["successful_flat"] and int(book.accepted) == 6
    assert np.asarray(book.recent).tolist() == [1.0, 0.999, 0.998, 0.997]
    # a longer record of costs (`keep`, the fleet's `settled` window) does not change the test
    long = S.begin(jnp.asarray(10.0), jnp.asarray(True), 3, keep=8)
    assert long.recent.shape == (9,)
    for c in [5.0, 2.0, 1.0, 0.999, 0.998, 0.997]:
        long = S.advance(long, cost=jnp.asarray(c), take=jnp.asarray(True), ok=jnp.asarray(True),
                         terminate=jnp.asarray(False), finite=jnp.asarray(True), ftol=1e-2, window=3, max_rejections=4)
    assert S.result_names(long.result) == "successful_flat"
    # a stopped start stays as it is: later steps change nothing
    again = S.advance(book, cost=jnp.asarray(0.1), take=jnp.asarray(True), ok=jnp.asarray(True),
                      terminate=jnp.asarray(False), finite=jnp.asarray(True), ftol=1e-2, window=3, max_rejections=4)
    assert jax.tree.all(jax.tree.map(lambda a, b: bool(jnp.all(a == b)), again, book))
    # fewer than `window` accepted steps are never flat, however small the decrease
    assert run([9.9999, 9.9998], [True, True])[1] == ["running", "running"]
    # rejected trials count up to the stall; an accepted one in between resets the count
    book, names = run([np.nan] * 2 + [9.0] + [np.inf] * 4, [False, False, True] + [False] * 4)
    assert names == ["running"] * 6 + ["stalled"] and int(book.since) == 4
    # precedence: a failed linear solve before the solver's own test, that before the flat test, a non-finite
    # Jacobian at the accepted point last
    assert run([1.0], [False], ok=False, terminate=True)[1] == ["linear_solve_failed"]
    assert run([9.99], [True], terminate=True, window=1)[1] == ["successful"]  # flat too, but the solver first
    assert run([9.99], [True], window=1)[1] == ["successful_flat"]
    assert run([5.0], [True], finite=False)[1] == ["nonfinite"]
    assert run([5.0], [False], finite=False)[1] == ["running"]  # not accepted: its Jacobian is not used
    # a start that is not finite at its initial point never runs
    assert S.result_names(S.begin(jnp.asarray(np.nan), jnp.asarray(True), 3).result) == "nonfinite_initial"
    assert S.result_names(S.begin(jnp.asarray(1.0), jnp.asarray(False), 3).result) == "nonfinite_initial"
    # every state the loop ends in has a verdict; the reasons carry the numbers of the run
    solver = fitting.LevenbergMarquardt(rtol=1e-8, atol=1e-8)
    verdicts = {"successful": "successful", "successful_flat": "successful", "stalled": "stalled",
                "linear_solve_failed": "linear_solve_failed", "nonfinite": "nonfinite",
                "nonfinite_initial": "nonfinite_initial", "running": "max_steps_reached", "outpaced": "outpaced"}
    for name, code in verdicts.items():
        assert S.verdict_of(name, solver=solver, window=3, since=7, max_steps=11).code == code
    assert "in 7 consecutive" in S.verdict_of("stalled", solver=solver, window=3, since=7, max_steps=11).reason
    assert "max_steps = 11" in S.verdict_of("running", solver=solver, window=3, since=0, max_steps=11).reason
    assert "last 3 below ftol" in S.verdict_of("successful_flat", solver=solver, window=3, since=0,
                                               max_steps=11).reason
    assert S.verdict_of("running", solver=solver, window=3, since=0, max_steps=11, interrupted=True).code == (
        "interrupted")
    for name in ("padding", "no_such_state"):
        with pytest.raises(ValueError, match="no verdict"):
            S.verdict_of(name, solver=solver, window=3, since=0, max_steps=11)


def test_a_refused_trial_shrinks_only_its_own_start(problem):
    # start 0's first trial lands at a > 1.2, which the model refuses; the starts at 0.5 step as they do beside a
    # start that is never refused (before, every start's step shrank with it)
    starts = [Gain(jnp.asarray(-3.0)), Gain(jnp.asarray(0.5))]
    with_refusal = fitting.solve(problem, starts=starts, progress=False, max_steps=3)
    calm = fitting.solve(problem, starts=[Gain(jnp.asarray(0.3)), Gain(jnp.asarray(0.5))], progress=False,
                         max_steps=3)
    assert [s["code"] for s in with_refusal.starts] == ["max_steps_reached"] * 2
    assert with_refusal.starts[1]["cost"] == calm.starts[1]["cost"]  # the same steps, bit for bit
    alone = fitting.solve(problem, progress=False, max_steps=1)  # start 0 alone: its first trial is refused
    assert alone.accepted_steps == 0 and alone.cost == alone.initial_cost
    full = fitting.solve(problem, starts=starts, progress=False)
    assert full.success and all(s["success"] for s in full.starts), full.starts
    assert full.values[0] == pytest.approx(1.0, abs=5 * full.std_errors[0])


class _Recorder(fitting.AbstractProgressMeter):
    log: list

    def init(self, label, starts):
        self.log.append(("init", label, starts))
        return 0

    def step(self, state, progress):
        self.log.append(("step", progress.label, progress.step, progress.best_cost, progress.running))
        return state + 1

    def close(self, state):
        self.log.append(("close", state))


def test_progress_meters_are_pluggable(problem):
    log = []
    res = fitting.solve(problem, progress=_Recorder(log), smoothing=None, max_steps=50)
    assert log[0] == ("init", "", 1) and log[-1] == ("close", res.steps)
    steps = [e for e in log if e[0] == "step"]
    assert [e[2] for e in steps] == list(range(1, res.steps + 1))
    assert steps[-1][3] == pytest.approx(res.cost, rel=1e-12)  # the best accepted cost so far
    text = io.StringIO()
    fitting.solve(problem, progress=fitting.TextProgressMeter(stream=text), max_steps=2)
    assert text.getvalue().startswith("  step    1  cost ") and text.getvalue().endswith("\n")  # not a terminal
    with pytest.raises(PiezojaxValueError, match="`progress`"):
        fitting.solve(problem, progress="loud")


def test_a_solver_instance_is_a_method(problem):
    by_name = fitting.solve(problem, progress=False, rtol=1e-9, atol=1e-11)
    lm = fitting.LevenbergMarquardt(rtol=1e-9, atol=1e-11,
                                    descent=optx.DampedNewtonDescent(linear_solver=lx.Cholesky()))
    by_instance = fitting.solve(problem, progress=False, method=lm)
    assert by_instance.u == by_name.u and by_instance.steps == by_name.steps
    trf = fitting.solve(problem, progress=False, method=fitting.TrustRegion())
    assert trf.success and trf.cost == pytest.approx(by_name.cost, rel=1e-9)
    # a different search is a different algorithm (here: a search that never enlarges the step)
    cautious = fitting.LevenbergMarquardt(search=optx.ClassicalTrustRegion(high_constant=1.0))
    slow = fitting.solve(problem, progress=False, method=cautious, max_steps=5)
    assert slow.steps == 5 and slow.cost > by_name.cost
    with pytest.raises(PiezojaxValueError, match="`linear_solver`"):
        fitting.solve(problem, progress=False, method=lm, linear_solver=lx.LU())


def test_problem_is_immutable(problem):
    with pytest.raises(AttributeError, match="immutable"):
        problem.u0 = problem.u0 * 2
    w = problem.weights
    w["displacement"] = 1.0  # a copy
    assert problem.weights["displacement"] != 1.0
    import pickle

    assert pickle.loads(pickle.dumps(problem)).weights == problem.weights
    other = problem.with_frozen(problem.frozen)
    assert other is not problem and other.core is not problem.core and problem.u0 == other.u0


def test_fit_error_carries_the_failed_result_and_pickles(problem):
    import pickle

    with pytest.raises(fitting.FitError) as raised:
        fitting.solve(problem, progress=False, max_steps=1, throw=True)
    error = raised.value
    assert error.code == "max_steps_reached" and not error.result.success and "max_steps" in str(error)
    again = pickle.loads(pickle.dumps(error))
    assert str(again) == str(error) and again.result.cost == error.result.cost


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def _progress(step, seconds):
    return fitting.Progress(label="", step=step, best_cost=1.0 / step, accepted=step, running=1, starts=1,
                            seconds=seconds)


def test_text_progress_meter_live_line_on_a_terminal_complete_lines_elsewhere():
    # a terminal gets one line rewritten in place
    tty = _Terminal()
    meter = fitting.TextProgressMeter(stream=tty)
    state = meter.init("", 1)
    for k in range(1, 4):
        state = meter.step(state, _progress(k, 0.1 * k))
    meter.close(state)
    assert tty.getvalue().count("\r") == 3 and tty.getvalue().count("\n") == 1
    # a log file gets whole lines: the first step, then one per `interval`, and the last step at the end
    log = io.StringIO()
    meter = fitting.TextProgressMeter(stream=log, interval=1.0)
    state = meter.init("", 1)
    for k, t in enumerate((0.1, 0.5, 1.2, 1.3, 1.4), start=1):
        state = meter.step(state, _progress(k, t))
    meter.close(state)
    text = log.getvalue()
    assert "\r" not in text
    steps = [int(line.split("step")[1].split()[0]) for line in text.splitlines()]
    assert steps == [1, 3, 5]
    # nothing pending: the last printed line is not repeated
    log = io.StringIO()
    meter = fitting.TextProgressMeter(stream=log, interval=1.0)
    state = meter.init("", 1)
    meter.close(meter.step(state, _progress(1, 0.1)))
    assert log.getvalue().count("\n") == 1


def test_fit_in_single_precision_warns(tmp_path):
    # JAX's 64-bit mode off (a fresh process: the tests run with it on): the fit runs and says it is float32
    import subprocess
    import sys

    script = tmp_path / "f32.py"
    script.write_text(
        "import warnings, jax.numpy as jnp, numpy as np, fitting, piezojax as pj\n"
        "v = 10 * np.sin(np.linspace(0, 6.28, 200))\n"
        "exp = fitting.Experiment.from_arrays(v_in=v, dt=1e-3, displacement=2e-7 * v)\n"
        "model = pj.Actuator(pj.PrandtlIshlinskii(jnp.array([0.1]), jnp.array([1.0]), w0=1.0),\n"
        "                    dynamics=pj.StableTransferFunction(1e-7))\n"
        "with warnings.catch_warnings(record=True) as caught:\n"
        "    warnings.simplefilter('always')\n"
        "    res = fitting.fit(model, [exp], free=['hysteresis.w0'], progress=False, max_steps=5)\n"
        "hits = [w for w in caught if issubclass(w.category, fitting.PrecisionWarning)]\n"
        "assert len(hits) == 1 and 'float32' in str(hits[0].message), [str(w.message) for w in caught]\n"
        "assert hits[0].filename == __file__, hits[0].filename\n"
        "assert res.summary()['precision'] == 'float32' and '64-bit mode off' in res.report()\n"
        "print('ok', res.model.hysteresis.w0.dtype)\n")
    env = {k: v for k, v in __import__("os").environ.items() if k != "JAX_ENABLE_X64"}
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "ok float32" in proc.stdout


def test_a_start_is_outpaced_only_when_it_cannot_catch_up():
    """`outpaced`: a running start is stopped once another converged below it, it has had twice that one's steps,
    and at the rate of its last ten accepted steps it would not reach that cost within max_steps."""
    from fitting._solver import outpaced

    steps_done = list(range(0, 41, 2))  # 20 accepted steps, one every other step

    def crawling(rate, top=2.0):  # a cost falling by `rate` (relative) per step
        return [top * np.exp(-rate * k) for k in steps_done]

    winner = ([5.0, 1.0], [0, 20])  # converged after 20 steps at cost 1
    slow, fast = crawling(1e-4), crawling(0.05, top=9.0)  # fast: 9 e^{-2} = 1.22 at step 40, halving every 14 steps
    histories = [winner[0], slow, fast, crawling(1e-4, top=0.9), slow[:5]]
    steps_of = [winner[1], steps_done, steps_done, steps_done, steps_done[:5]]
    codes = ["successful_flat", "running", "running", "running", "running"]
    steps = np.array([20, 40, 40, 40, 40])
    out = outpaced(histories, steps_of, codes, steps, 40, max_steps=500)
    # the slow one needs ln 2 / 1e-4 ~ 6900 more steps; the fast one ~ 4; the third is below the winner; the last has
    # too few accepted steps to judge
    assert list(out) == [1] and "converged at cost 1.000000e+00 after 20" in out[1]
    assert outpaced(histories, steps_of, codes, steps, 40, max_steps=10_000) == {}  # enough steps left for it
    assert outpaced(histories, steps_of, codes, np.array([21, 39, 39, 39, 39]), 39, max_steps=500) == {}  # < 2 k*
    assert outpaced(histories, steps_of, ["running"] * 5, steps, 40, max_steps=500) == {}  # none converged
    assert outpaced(histories, steps_of, codes, steps, 40, max_steps=40) == {}  # the last step: max_steps_reached


def test_a_fit_at_max_steps_that_no_longer_gains_what_the_data_resolve_has_converged():
    """`settled`: stopped by max_steps, a start whose cost fell over its last 50 accepted steps by less than
    cost / (m - p) (a one-standard-error change of one parameter) is converged, with the numbers in the reason;
    one still falling by more, one with fewer accepted steps and other verdicts stay as they are."""
    from fitting._solve import SETTLED_WINDOW, settled

    stopped = fitting.Verdict("max_steps_reached", "max_steps = 500 reached before convergence")
    m, p = 10_020, 20  # cost / (m - p) = 1e-4 of the cost
    crawl = 1.0 + 1e-7 * np.arange(200)[::-1]  # 5e-6 over the last 50
    falling = 1.0 + 1e-5 * np.arange(200)[::-1]  # 5e-4 over the last 50
    verdict = settled(stopped, list(crawl), 500, m, p)
    assert verdict.success and verdict.code == "successful" and "converged in practice" in verdict.reason
    assert f"over the last {SETTLED_WINDOW} accepted steps" in verdict.reason and "1.00e-04" in verdict.reason
    assert "max_steps = 500 reached" in verdict.reason
    assert settled(stopped, list(falling), 500, m, p) == stopped
    assert settled(stopped, list(crawl[-SETTLED_WINDOW:]), 500, m, p) == stopped  # too few accepted steps to judge
    other = fitting.Verdict("stalled", "r")
    assert settled(other, list(crawl), 500, m, p) == other
