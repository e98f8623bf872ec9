r"""Paper 002 (Chen & Li 2014, a monolithic self-sensing stage) end to end, on `pj.ChenBench`.

Run: `python -m experiments.chen2014 [--out results/chen2014] [--quick]`

The bench's truth is richer than every model fitted here: a Bouc–Wen hysteresis behind the electrical lag of
amplifier and stack, plus creep (a rate-dependent hysteresis), the stage dynamics of eq. (3), a charge amplifier
that cannot hold DC, crosstalk, noise and 16-bit converters. The steps follow the paper:

1. **Force-sensor calibration** (Section III-B, Fig. 8): the stage on a stiff support, an exciter pushing with a
   chirp (1–200 Hz) through a reference force sensor; the FRF $V_s/F$ (Welch H1) and the sensitivity, its mean
   over 1–100 Hz (paper: 0.015381 V/N, "nearly constant up to 100 Hz").
2. **Crosstalk** (Section III-C, Fig. 12–13): 5 Hz sines of 10–50 V on the stack in the stage and out of it; the
   sensor-voltage amplitudes, the crosstalk coefficient $p_c$ (slope) and the crosstalk as a share of the sensor
   voltage (paper: FEA −0.006636 V at 20 V, "less than 8 %").
3. **Stage dynamics** (Section III-D, eq. 3–9, Fig. 15): a chirp (1 Hz–4 kHz) on the actuator, the laser
   displacement and the sensor voltage. The paper's way, step by step: the displacement sensitivity is the mean of
   $|x_a/V_s|$ over 1–100 Hz (paper: 11.6126 µm/V), with the force sensitivity of step 1 and $p_c$ of step 2. Our
   way: one joint least-squares fit of `pj.SmartStackCircuit` (series stiffness via $k_p$, $m_e$, $c_e$, $k_e$ and
   $p_c$; $d_{33}/C$ from step 1, $k_s$ nominal, as only $k_pk_s/(k_p+k_s)$ is identifiable) to the whole record,
   $V_s$ predicted from $x_a$ and $V_a$. Both observers (eq. 9 with crosstalk) are scored on a held-out 5 Hz
   triangle: displacement error in % of the range.
4. **NARMAX model** of the stage (Section IV-A, eq. 10–16), $u \to \hat y$ (the self-sensed displacement) at the
   control rate of 1 kHz, identified offline on one record and validated (free-run simulation, NRMSE) on another:
   by our joint least squares (`fitting.fit`, simulation error, four random hidden layers fitted at once and the
   best kept: the simulation error of a recurrent network has local minima) and by online back-propagation as the
   paper (`pj.train_narx_online`, one-step error, momentum), from the same start (random hidden layer, output
   weights 0: a constant, stable model); and by `sysidentpy` (polynomial NARX, FROLS), when installed
   (`pip install -e .[narx]`), on the same data, its structure chosen two ways: by its own AIC, and by the
   free-run error on the last quarter of the training record. A model trained on the one-step error can be
   unstable in free run; the table gives both errors.
5. **Control in self-sensing mode** (Section V, Fig. 21–23, eq. 20): 1 kHz, 16-bit DAC, 20 V/V amplifier, 100 V
   offset, the eq. (9) observer of step 3 (paper's way) as the only feedback; triangles of 6 µm peak to peak at 1,
   5, 10 and 20 Hz. Every controller reads the reference one sample ahead (`preview=1`: a command acts from the
   next sample on; without it a feedforward lags by one sample, 4 % of the range at 20 Hz). Controllers: the
   adaptive inverse controller (eq. 12–19 with three reference lags and no measurement lag; its output layer started
   offline from the open-loop record of step 4, then adapted online), a PI-inverse feedforward (a
   Prandtl–Ishlinskii model plus an output offset fitted to the same record) plus a PID, the PID alone, and a
   linear inverse (gain and offset of a straight-line fit) as "before compensation"; the PID gains are tuned by
   gradient through the closed loop (Levenberg–Marquardt on the tracking error of a 10 Hz triangle, `optimistix`; the
   gains kept non-negative). Scored by eq. (20) on the laser (true) displacement after the first period. Also: the
   adaptive controller's error period by period over 30 s at 1 Hz (does the learning settle?), and the closed-loop
   frequency response reference → displacement of three controllers from a 1–400 Hz chirp (Fig. 22).

Prints a table "paper | this project" and writes `report.json` and figures to `--out`.
"""

import argparse
import sys
import time
import warnings
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import scipy.signal

import fitting
import piezojax as pj
from experiments._command import output_folder, run, stop_if_interrupted, writing

KIND = "experiments.chen2014"  # what the output folder's marker records
OUT = "results/chen2014"

PAPER = {
    "force_sensitivity_V_per_N": 0.015381,
    "crosstalk_fea_V_at_20V": -0.006636,
    "crosstalk_share_max": 0.08,
    "displacement_sensitivity_um_per_V": 11.6126,
}
CONTROL_RATE = 1e3
BIAS = 100.0
FREQUENCIES = (1.0, 5.0, 10.0, 20.0)
AMPLITUDE = 3e-6  # 6 µm peak to peak
PREVIEW = 1  # every controller reads the reference one sample ahead: the command acts at the next sample


# ----------------------------------------------------------------------------------------------- signals and helpers


def chirp(f0: float, f1: float, seconds: float, rate: float) -> np.ndarray:
    t = np.arange(int(round(seconds * rate))) / rate
    taper = np.minimum(1.0, np.minimum(t, t[-1] - t) / 0.05)  # 50 ms fade in and out
    return taper * scipy.signal.chirp(t, f0, t[-1], f1, method="logarithmic")


def triangle(frequency: float, n: int, rate: float, amplitude: float = AMPLITUDE) -> np.ndarray:
    """A triangle from 0, rising first, between ±amplitude."""
    ph = (np.arange(n) / rate * frequency) % 1
    return amplitude * np.where(ph < 0.25, 4 * ph, np.where(ph < 0.75, 2 - 4 * ph, 4 * ph - 4))


def frf(u: np.ndarray, y: np.ndarray, rate: float, seconds_per_segment: float = 1.0):
    """H1 estimate y/u and coherence by Welch averaging."""
    nper = min(int(seconds_per_segment * rate), u.size)
    f, puu = scipy.signal.welch(u, rate, nperseg=nper)
    _, puy = scipy.signal.csd(u, y, rate, nperseg=nper)
    _, coh = scipy.signal.coherence(u, y, rate, nperseg=nper)
    return f, puy / puu, coh


def sine_amplitude(y: np.ndarray, frequency: float, rate: float) -> float:
    """The signed amplitude of the `sin` component at `frequency` (least squares with cos and offset)."""
    t = np.arange(y.size) / rate
    A = np.stack([np.sin(2 * np.pi * frequency * t), np.cos(2 * np.pi * frequency * t), np.ones_like(t)], axis=1)
    return float(np.linalg.lstsq(A, y, rcond=None)[0][0])


def observe(observer, v_in, v_out) -> np.ndarray:
    return np.asarray(observer(jnp.asarray(v_in), jnp.asarray(v_out)).displacement)


# ----------------------------------------------------------------------------------------------- 1. calibration


def force_calibration(bench, key, seconds):
    rate = bench.sample_rate
    force = 20.0 * chirp(1.0, 200.0, seconds, rate)
    rec = bench.record_force_calibration(force, key)
    f, h, coh = frf(np.asarray(rec.force), np.asarray(rec.v_out), rate)
    band = (f >= 1) & (f <= 100)
    mag = np.abs(h[band])
    sensitivity = float(np.mean(mag))
    return {
        "sensitivity_V_per_N": sensitivity,
        "flatness_1_100Hz_percent": float(100 * (mag.max() - mag.min()) / sensitivity),
        "truth_V_per_N": float(bench.stack.d33 / bench.stack.amplifier_capacitance),
        "frf": (f, h, coh),
    }


# ----------------------------------------------------------------------------------------------- 2. crosstalk


def crosstalk(bench, key, amplitudes=(10.0, 20.0, 30.0, 40.0, 50.0), frequency=5.0, seconds=1.0):
    rate = bench.sample_rate
    t = np.arange(int(seconds * rate)) / rate
    embedded, isolated = [], []
    for i, a in enumerate(amplitudes):
        v = a * np.sin(2 * np.pi * frequency * t)
        k1, k2 = jax.random.split(jax.random.fold_in(key, i))
        embedded.append(sine_amplitude(np.asarray(bench.record(v, k1).v_out), frequency, rate))
        isolated.append(sine_amplitude(np.asarray(bench.record_isolated(v, k2).v_out), frequency, rate))
    a, emb, iso = np.asarray(amplitudes), np.asarray(embedded), np.asarray(isolated)
    p_c = float(np.dot(a, iso) / np.dot(a, a))
    return {
        "amplitudes_V": a.tolist(),
        "embedded_V": emb.tolist(),
        "isolated_V": iso.tolist(),
        "crosstalk_V_per_V": p_c,
        "crosstalk_at_20V": 20 * p_c,
        "share_max": float(np.max(np.abs(iso / emb))),
        "truth_V_per_V": float(bench.stack.crosstalk),
    }


# ----------------------------------------------------------------------------------------------- 3. stage


def _stage_predictor():
    def fn(model, d):
        return {"v_out": model(d.v_in, d.dt, x_a=d.channels["displacement"])}

    return fitting.Predictor(fn, ("v_out",), inputs=("displacement",))


def stage_identification(bench, key, seconds, force_sensitivity, p_c):
    rate = bench.sample_rate
    v = 20.0 * chirp(1.0, 4000.0, seconds, rate)
    k1, k2 = jax.random.split(key)
    rec = bench.record(v, k1)
    x, v_s, v_a = (np.asarray(a) for a in (rec.displacement, rec.v_out, rec.v_in))
    f, h, coh = frf(v_s - p_c * v_a, x, rate, 0.5)
    band = (f >= 1) & (f <= 100)
    staged_sensitivity = float(np.mean(np.abs(h[band])))

    # joint fit: every stage parameter at once from the one record, started without the answer
    gain = force_sensitivity
    A = np.stack([gain * x, v_a], axis=1)
    k_ser, p_c0 = np.linalg.lstsq(A, v_s, rcond=None)[0]
    k_s = float(bench.stack.k_s)  # only the series stiffness is identifiable: k_s nominal, k_p fitted
    k_p0 = 1 / (1 / k_ser - 1 / k_s)
    hi = (f > 300) & (f < 0.45 * rate)
    f_peak = float(f[hi][np.argmin(np.abs(h[hi]))])  # V_s/x_a peaks where x_a/V_s dips: the stage resonance
    k_e0 = 3 * k_ser
    m_e0 = k_e0 / (2 * np.pi * f_peak) ** 2
    c_e0 = 2 * 0.1 * np.sqrt(k_e0 * m_e0)
    capacitance = float(bench.stack.amplifier_capacitance)
    start = pj.SmartStackCircuit(gain * capacitance, capacitance, k_p0, k_s, m_e0, c_e0, k_e0, crosstalk=p_c0)
    exp = fitting.Experiment.from_arrays(v_in=v_a, dt=1 / rate, v_out=v_s, displacement=x, name="stage_chirp")
    t0 = time.perf_counter()
    result = fitting.fit(start, fitting.Dataset([exp]), predictor=_stage_predictor(),
                         free=["k_p", "m_e", "c_e", "k_e", "crosstalk"], max_steps=100)
    stop_if_interrupted(result)
    seconds_fit = time.perf_counter() - t0
    joint = result.model

    # both observers on a held-out triangle
    n = int(rate * 1.0)
    v_val = 50 + 40 * triangle(5.0, n, rate, 1.0)
    val = bench.record(v_val, k2)
    truth = np.asarray(val.true_displacement)
    staged_obs = pj.SensorLayerObserver(gain * capacitance, capacitance,
                                        1 / (1 / (capacitance / (gain * capacitance * staged_sensitivity)) - 1 / k_s),
                                        k_s, crosstalk=p_c)
    joint_obs = pj.SensorLayerObserver(joint.d33, joint.amplifier_capacitance, joint.k_p, joint.k_s,
                                       crosstalk=joint.crosstalk)

    def err(obs):
        e = observe(obs, val.v_in, val.v_out) - truth
        return float(100 * np.sqrt(np.mean(e**2)) / np.ptp(truth))

    truth_stack = bench.stack
    return {
        "staged": {"sensitivity_um_per_V": 1e6 * staged_sensitivity, "observer_error_percent": err(staged_obs)},
        "joint": {
            "sensitivity_um_per_V": 1e6 * float(joint.displacement_sensitivity()),
            "zero_frequency_Hz": float(joint.zero_frequency()) / (2 * np.pi),
            "resonance_Hz": float(np.sqrt(joint.k_e / joint.m_e)) / (2 * np.pi),
            "crosstalk_V_per_V": float(joint.crosstalk),
            "observer_error_percent": err(joint_obs),
            "fit_seconds": seconds_fit,
            "steps": int(result.steps),
            "verdict": result.code,
            "output_rmse_V": float(result.metrics["stage_chirp"]["v_out"]["rmse"]),
        },
        "truth": {
            "sensitivity_um_per_V": 1e6 * float(truth_stack.displacement_sensitivity()),
            "zero_frequency_Hz": float(truth_stack.zero_frequency()) / (2 * np.pi),
            "resonance_Hz": float(np.sqrt(truth_stack.k_e / truth_stack.m_e)) / (2 * np.pi),
        },
        "staged_observer": staged_obs,
        "frf": (f, h, coh),
        "joint_model": joint,
    }


# ----------------------------------------------------------------------------------------------- 4. NARMAX


def open_loop_records(plant, observer, key, seconds):
    """Two open-loop records at the control rate around the bias: training (two sines, slow amplitude ramp) and
    validation (a triangle sweep); the self-sensed displacement of each."""
    n = int(seconds * CONTROL_RATE)
    t = np.arange(n) / CONTROL_RATE
    ramp = np.minimum(t / 0.3, 1)
    u_train = BIAS + ramp * (28 * np.sin(2 * np.pi * 2 * t) * (0.6 + 0.4 * np.sin(2 * np.pi * 0.31 * t))
                             + 8 * np.sin(2 * np.pi * 13 * t))
    u_val = BIAS + ramp * 30 * triangle(1.0, n, CONTROL_RATE, 1.0) * np.sign(np.sin(2 * np.pi * 0.7 * t) + 1.5)
    u_val += ramp * 5 * np.sin(2 * np.pi * 7 * t)
    out = []
    for i, u in enumerate((u_train, u_val)):
        noise = jax.random.normal(jax.random.fold_in(key, i), (n, 2))
        ch = eqx.filter_jit(lambda p, u, w: p.simulate(u, w))(plant, u, noise)
        y = jax.vmap(lambda a, b: observer.step((), {"v_in": a, "v_out": b})[1])(ch["v_in"], ch["v_out"])
        out.append((u, np.asarray(y)))
    return out


def _nrmse(y, y_hat):
    return float(np.sqrt(np.mean((y - y_hat) ** 2)) / np.std(y))


def narmax(train, val, key, epochs):
    (u, y), (u_val, y_val) = train, val
    # the response to u_k is read at k + 1: eq. (10) with delay 1
    def network(k):
        return pj.NarxNetwork(k, hidden=8, output_lags=2, input_lags=2, delay=1, input_offset=BIAS,
                              input_scale=30.0, output_scale=AMPLITUDE)

    net = network(key)
    start = net  # output weights 0: a stable (constant) model to start from, for both trainings
    out = {}

    def score(model):
        return _nrmse(y_val, np.asarray(model.simulate(u_val, y0=y_val[0])))

    def one_step(model):
        return _nrmse(y_val, np.asarray(model.one_step(u_val, y_val)))

    out["start"] = {"nrmse": score(start), "one_step_nrmse": one_step(start)}
    exp = fitting.Experiment.from_arrays(v_in=u, dt=1 / CONTROL_RATE, displacement=y, name="narx_train")
    pred = fitting.Predictor(lambda m, d: {"displacement": m.simulate(d.v_in)}, ("displacement",))
    t0 = time.perf_counter()
    # the simulation error of a recurrent network has local minima: four hidden layers fitted at once (vmap)
    starts = [start] + [network(k) for k in jax.random.split(key, 3)]
    result = fitting.fit(start, fitting.Dataset([exp]), predictor=pred, max_steps=120, starts=starts)
    stop_if_interrupted(result)
    out["least_squares"] = {"nrmse": score(result.model), "one_step_nrmse": one_step(result.model),
                            "seconds": time.perf_counter() - t0, "steps": int(result.steps), "starts": len(starts)}
    t0 = time.perf_counter()
    bp = pj.train_narx_online(start, u, y, learning_rate=0.002, momentum=0.5, epochs=epochs)
    jax.block_until_ready(bp.output_weights)
    out["online_bp"] = {"nrmse": score(bp), "one_step_nrmse": one_step(bp), "seconds": time.perf_counter() - t0,
                        "epochs": epochs}
    sid = _sysidentpy(u, y, u_val, y_val)
    out["sysidentpy"] = None if sid is None else sid["aic"]
    out["sysidentpy_selected"] = None if sid is None else sid["selected"]
    out["models"] = {"least_squares": result.model, "online_bp": bp}
    return out


def _sysidentpy(u, y, u_val, y_val):
    """sysidentpy's polynomial NARX by FROLS on the same records, two ways of choosing its structure: its own
    (terms by AIC, degree 2), and ours for it (degree and number of terms by the free-run error on the last quarter
    of the training record, the model then refitted on the whole record). None when sysidentpy is not installed."""
    try:
        from sysidentpy.basis_function import Polynomial
        from sysidentpy.model_structure_selection import FROLS
    except ImportError:
        return None
    scale_u, scale_y, lag = 30.0, AMPLITUDE, 2

    def fit_and_run(u_fit, y_fit, u_run, y_run, **structure):
        model = FROLS(ylag=lag, xlag=lag, **structure)
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a free run that diverges overflows: reported as NaN below
            model.fit(X=((u_fit - BIAS) / scale_u)[:, None], y=(y_fit / scale_y)[:, None])
            y_hat = model.predict(X=((u_run - BIAS) / scale_u)[:, None], y=(y_run / scale_y)[:lag, None])
            nrmse = _nrmse(y_run, scale_y * np.asarray(y_hat).ravel()[: y_run.size])
        return (nrmse if np.isfinite(nrmse) else None), len(model.final_model)

    t0 = time.perf_counter()
    nrmse, terms = fit_and_run(u, y, u_val, y_val, order_selection=True, n_terms=None, n_info_values=15,
                               info_criteria="aic", basis_function=Polynomial(degree=2))
    out = {"aic": {"nrmse": nrmse, "seconds": time.perf_counter() - t0,
                   "model": f"FROLS polynomial NARX, degree 2, ylag 2, xlag 2, {terms} terms (AIC)"}}
    t0 = time.perf_counter()
    n = int(0.75 * u.size)
    tried = {}
    for degree in (1, 2):
        for n_terms in (4, 6, 8):
            e, _ = fit_and_run(u[:n], y[:n], u[n:], y[n:], order_selection=False, n_terms=n_terms,
                               basis_function=Polynomial(degree=degree))
            tried[(degree, n_terms)] = np.inf if e is None else e
    degree, n_terms = min(tried, key=tried.get)
    nrmse, terms = fit_and_run(u, y, u_val, y_val, order_selection=False, n_terms=n_terms,
                               basis_function=Polynomial(degree=degree))
    out["selected"] = {"nrmse": nrmse, "seconds": time.perf_counter() - t0,
                       "model": f"FROLS polynomial NARX, degree {degree}, ylag 2, xlag 2, {terms} terms (chosen by "
                                "free-run error on the last quarter of the training record)"}
    return out


# ----------------------------------------------------------------------------------------------- 5. control


# Every closed loop runs on its reference held at the last value up to a multiple of PAD_SAMPLES samples, and is cut
# back: one compilation per kind of controller instead of one per reference length. The loop is causal and the
# preview holds the last sample past the end, so the cut records are those of the unpadded run (tested to the bit).
PAD_SAMPLES = 8192


@eqx.filter_jit
def _closed_loop(controller, plant, observer, ref, noise):
    return pj.closed_loop(controller, plant, ref, observer=observer, noise=noise, preview=PREVIEW)


def _run(controller, plant, observer, ref, noise):
    """`pj.closed_loop` of `controller` on `plant` with `observer` for the reference `ref` and the plant noise
    `noise` (time first), run padded to a multiple of PAD_SAMPLES and cut back to the reference's length."""
    ref, noise = np.asarray(ref), np.asarray(noise)
    n = ref.shape[0]
    extra = -n % PAD_SAMPLES
    rec = _closed_loop(controller, plant, observer, jnp.asarray(np.concatenate([ref, np.full(extra, ref[-1])])),
                       jnp.asarray(np.concatenate([noise, np.zeros((extra, *noise.shape[1:]))])))
    return jax.tree.map(lambda x: jnp.asarray(np.asarray(x)[:n]), rec)


def tune_pid(plant, observer, pid, ref, noise, feedforward=None):
    r"""(kp, ki) by Levenberg–Marquardt on the closed loop's tracking error, gradients through the loop; with a
    `feedforward`, the PID's gains in `pj.FeedforwardFeedback(feedforward, pid)`.

    The gains stay non-negative, $k = s\,\theta^2$ ($s$ = 1e6 V/m for $k_p$, 1e9 V/(m s) for $k_i$; smooth at 0, so
    a gain can settle there): unconstrained, the tuning behind the feedforward had ended at a negative $k_p$
    (−2.7e6 V/m), positive feedback on the error. A gain that starts below $10^{-2} s$ starts there (at 0 the square
    has no slope)."""
    scale = jnp.asarray([1e6, 1e9])

    def gains(theta):
        return scale * theta**2

    def residuals(theta, _):
        kp, ki = gains(theta)
        c = eqx.tree_at(lambda p: (p.kp, p.ki), pid, (kp, ki))
        c = c if feedforward is None else pj.FeedforwardFeedback(feedforward, c)
        rec = pj.closed_loop(c, plant, ref, observer=observer, noise=noise, preview=PREVIEW)
        return (ref - rec.channels["displacement"]) / AMPLITUDE

    theta0 = jnp.sqrt(jnp.maximum(jnp.asarray([pid.kp, pid.ki]) / scale, 1e-2))
    sol = optx.least_squares(residuals, optx.LevenbergMarquardt(rtol=1e-6, atol=1e-8), theta0, max_steps=40,
                             throw=False)
    kp, ki = gains(sol.value)
    return eqx.tree_at(lambda p: (p.kp, p.ki), pid, (kp, ki))


def control(plant, observer, train, key, quick):
    u, y = train
    # adaptive inverse controller: eq. (12)-(19), output layer from the open-loop record, then online learning
    aic = pj.AdaptiveInverseController(key, hidden=6, measurement_lags=0, reference_lags=3, learning_rate=0.02,
                                       momentum=0.5, offset=BIAS, command_scale=30.0, output_scale=AMPLITUDE,
                                       u_min=-20.0, u_max=200.0, preview=PREVIEW)
    aic = aic.fit_output_layer(y, u)
    # PI inverse feedforward: a rate-independent PI fitted to the same record (from the bias, in µm)
    # plus an output offset: the stage rests at the bias on its ascending branch, so its loops around the bias
    # are not centred on the rest point (a PI operator from its virgin state is odd-symmetric)
    pi0 = _OffsetPI(pj.pi_cold_start(u - BIAS, 1e6 * y, 10), jnp.asarray(0.0))
    exp = fitting.Experiment.from_arrays(v_in=u - BIAS, dt=1 / CONTROL_RATE, displacement=1e6 * y, name="pi")
    pred = fitting.Predictor(lambda m, d: {"displacement": m.pi(d.v_in) + m.offset}, ("displacement",))
    result = fitting.fit(pi0, fitting.Dataset([exp]), predictor=pred, max_steps=40)
    stop_if_interrupted(result)
    fitted = result.model
    ff = pj.InverseFeedforward(fitted.pi.inverse(), offset=BIAS, reference_offset=1e-6 * fitted.offset,
                               reference_scale=1e-6)
    pid0 = pj.PID(0.0, 1e9, dt=1 / CONTROL_RATE, offset=0.0, u_min=-40.0, u_max=40.0)
    n_tune = 500 if quick else 1000
    ref_tune = jnp.asarray(triangle(10.0, n_tune, CONTROL_RATE))
    w_tune = jax.random.normal(jax.random.fold_in(key, 99), (n_tune, 2))
    t0 = time.perf_counter()
    pid_alone0 = eqx.tree_at(lambda p: (p.offset, p.u_min, p.u_max), pid0,
                             (jnp.asarray(BIAS), jnp.asarray(-20.0), jnp.asarray(200.0)))
    pid_alone = tune_pid(plant, observer, pid_alone0, ref_tune, w_tune)
    # the 2-DOF loop's PID tuned with the feedforward in the loop (from the same start; measured: starting from the
    # PID-alone gains ends in a worse local minimum, as the P term on the previewed reference then doubles the
    # feedforward)
    ffpid = pj.FeedforwardFeedback(ff, tune_pid(plant, observer, pid0, ref_tune, w_tune, ff))
    tuning_seconds = time.perf_counter() - t0

    def tune_error(c):
        return float(pj.tracking_error_percent(ref_tune, _run(c, plant, observer, ref_tune, w_tune).channels[
            "displacement"]))

    tuning = {"start_error_percent": tune_error(pid_alone0), "tuned_error_percent": tune_error(pid_alone)}
    slope, intercept = np.polyfit(u - BIAS, y, 1)
    open_loop = pj.InverseFeedforward(_Linear(jnp.asarray(1e6 * float(slope))), offset=BIAS,
                                      reference_offset=float(intercept), reference_scale=1e-6)

    controllers = {"open loop (linear inverse)": open_loop, "PID": pid_alone, "PI inverse + PID": ffpid,
                   "adaptive inverse": aic}
    rows, traces = {}, {}
    for f in FREQUENCIES:
        periods = 2 if quick else 4
        n = int(max(periods / f, 1.0) * CONTROL_RATE)
        ref = jnp.asarray(triangle(f, n, CONTROL_RATE))
        noise = jax.random.normal(jax.random.fold_in(key, int(f)), (n, 2))
        skip = int(CONTROL_RATE / f) if n > int(CONTROL_RATE / f) else 0
        rows[f] = {}
        for name, c in controllers.items():
            rec = _run(c, plant, observer, ref, noise)
            x = rec.channels["displacement"]
            rows[f][name] = float(pj.tracking_error_percent(ref[skip:], x[skip:]))
            traces[(f, name)] = (np.asarray(ref), np.asarray(x), np.asarray(rec.control))
    gains = {"PID kp": float(pid_alone.kp), "PID ki": float(pid_alone.ki),
             "PI inverse + PID kp": float(ffpid.feedback.kp), "PI inverse + PID ki": float(ffpid.feedback.ki)}

    # the adaptive controller over many periods at 1 Hz: the error of each period (does the learning settle?)
    periods = 6 if quick else 30
    ref = jnp.asarray(triangle(1.0, int(periods * CONTROL_RATE), CONTROL_RATE))
    noise = jax.random.normal(jax.random.fold_in(key, 1000), (ref.size, 2))
    x = _run(aic, plant, observer, ref, noise).channels["displacement"]
    per_period = [float(pj.tracking_error_percent(ref[i * 1000:(i + 1) * 1000], x[i * 1000:(i + 1) * 1000]))
                  for i in range(periods)]

    # Fig. 22: the closed-loop frequency response reference -> displacement, a logarithmic chirp 1-400 Hz of the
    # triangles' amplitude (H1 estimate; the adaptive controller keeps learning during the chirp, as in the paper)
    ref = jnp.asarray(AMPLITUDE * chirp(1.0, 400.0, 4.0 if quick else 16.0, CONTROL_RATE))
    noise = jax.random.normal(jax.random.fold_in(key, 2000), (ref.size, 2))
    response = {}
    for name in ("PID", "PI inverse + PID", "adaptive inverse"):
        x = np.asarray(_run(controllers[name], plant, observer, ref, noise).channels["displacement"])
        f, h, coh = frf(np.asarray(ref), x, CONTROL_RATE, seconds_per_segment=1.0)
        band = (f >= 1) & (f <= 400)
        low = np.abs(h[(f >= 1) & (f <= 5)]).mean()
        below = band & (f <= 350) & (np.abs(h) < low / np.sqrt(2))  # the chirp fades out above 350 Hz
        response[name] = {"frequency_Hz": f[band], "frf": h[band], "coherence": coh[band],
                          "gain_1_5Hz": float(low),
                          "bandwidth_Hz": float(f[below][0]) if below.any() else None,
                          "gain_at_20Hz": float(np.abs(h[np.argmin(np.abs(f - 20))])),
                          "phase_at_20Hz_deg": float(np.degrees(np.angle(h[np.argmin(np.abs(f - 20))])))}
    return {"rms_error_percent": rows, "pid_gains": gains, "tuning_seconds": tuning_seconds, "tuning": tuning,
            "pid_start": {"kp": 0.0, "ki": 1e9}, "traces": traces, "adaptive_per_period_1Hz": per_period,
            "closed_loop_frf": response}


class _OffsetPI(eqx.Module):
    """A PI operator plus a constant output offset (fitted together)."""

    pi: pj.PrandtlIshlinskii
    offset: jax.Array


class _Linear(pj.AbstractCell):
    """The static inverse y / g of a linear fit (a cell), for the uncompensated reference."""

    gain: jax.Array

    def init(self):
        return ()

    def step(self, state, y):
        return state, y / self.gain


# ----------------------------------------------------------------------------------------------- report


def _figures(out: Path, cal, stage, narx, val, ctl):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def save(fig, name):
        with fitting.files.atomic_file(out / name) as tmp:
            fig.savefig(tmp, dpi=110, format="png")
        plt.close(fig)

    f, h, _ = cal["frf"]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    band = (f >= 1) & (f <= 200)
    ax.semilogx(f[band], np.abs(h[band]), label="measured |V_s / F|")
    ax.axhline(PAPER["force_sensitivity_V_per_N"], color="k", ls="--", lw=0.8, label="paper 0.015381 V/N")
    ax.set(xlabel="frequency (Hz)", ylabel="V/N", title="force-sensor calibration (Fig. 8)")
    ax.legend()
    save(fig, "force_calibration.png")

    f, h, _ = stage["frf"]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    band = (f >= 1) & (f <= 4500)
    ax.loglog(f[band], 1e6 * np.abs(h[band]), label="measured |x_a / V_s|")
    ax.axhline(PAPER["displacement_sensitivity_um_per_V"], color="k", ls="--", lw=0.8, label="paper 11.6126 µm/V")
    ax.set(xlabel="frequency (Hz)", ylabel="µm/V", title="stage displacement sensitivity (Fig. 15)")
    ax.legend()
    save(fig, "stage_frf.png")

    u_val, y_val = val
    fig, ax = plt.subplots(figsize=(7, 3.5))
    t = np.arange(y_val.size) / CONTROL_RATE
    ax.plot(t, 1e6 * y_val, "k", lw=0.8, label="self-sensed")
    for name, m in narx["models"].items():
        ax.plot(t, 1e6 * np.asarray(m.simulate(u_val, y0=y_val[0])), lw=0.7, label=name.replace("_", " "))
    ax.set(xlabel="time (s)", ylabel="µm", title="NARMAX validation (free run)")
    ax.legend()
    save(fig, "narmax_validation.png")

    fig, axes = plt.subplots(len(FREQUENCIES), 1, figsize=(7, 8))
    for ax, f in zip(axes, FREQUENCIES, strict=True):
        for name in ("PI inverse + PID", "adaptive inverse"):
            r, x, _ = ctl["traces"][(f, name)]
            tt = np.arange(r.size) / CONTROL_RATE
            ax.plot(tt, 1e6 * x, lw=0.8, label=name)
        ax.plot(tt, 1e6 * r, "k--", lw=0.6, label="reference")
        ax.set_ylabel(f"{f:g} Hz (µm)")
    axes[0].legend(fontsize=7)
    axes[-1].set_xlabel("time (s)")
    fig.suptitle("tracking of 6 µm triangles, self-sensing (Fig. 21)")
    save(fig, "tracking.png")

    fig, axes = plt.subplots(2, 1, figsize=(6, 5), sharex=True)
    for name, r in ctl["closed_loop_frf"].items():
        b = r["frequency_Hz"] <= 350  # the chirp fades out before 400 Hz
        axes[0].semilogx(r["frequency_Hz"][b], 20 * np.log10(np.abs(r["frf"][b])), lw=0.9, label=name)
        axes[1].semilogx(r["frequency_Hz"][b], np.degrees(np.unwrap(np.angle(r["frf"][b]))), lw=0.9)
    axes[0].axhline(-3, color="k", ls=":", lw=0.6)
    axes[0].set(ylabel="magnitude (dB)", title="closed-loop response reference -> displacement (Fig. 22)")
    axes[1].set(xlabel="frequency (Hz)", ylabel="phase (deg)")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    save(fig, "closed_loop_frf.png")

    fig, axes = plt.subplots(1, 2, figsize=(8, 3.5))
    r, x, u = ctl["traces"][(1.0, "open loop (linear inverse)")]
    skip = int(CONTROL_RATE) if x.size > CONTROL_RATE else 0  # after the first period, as the error
    axes[0].plot(u[skip:], 1e6 * x[skip:], lw=0.8)
    axes[0].set(xlabel="stack voltage (V)", ylabel="displacement (µm)", title="before compensation")
    r, x, _ = ctl["traces"][(1.0, "adaptive inverse")]
    skip = int(CONTROL_RATE)
    axes[1].plot(1e6 * r[skip:] if r.size > skip else 1e6 * r, 1e6 * x[skip:] if x.size > skip else 1e6 * x, lw=0.8)
    axes[1].set(xlabel="reference (µm)", ylabel="displacement (µm)", title="adaptive inverse control")
    fig.suptitle("hysteresis at 1 Hz (Fig. 23)")
    fig.tight_layout()
    save(fig, "hysteresis.png")


def main(argv=None) -> dict:
    """Command-line entry point; returns the report dict."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=OUT, help=f"output folder (default {OUT}); an earlier output of this "
                        "experiment is replaced whole, any other folder is refused")
    parser.add_argument("--quick", action="store_true", help="short records and fewer periods")
    parser.add_argument("--no-figures", action="store_true", help="write report.json only")
    args = parser.parse_args(argv)
    pj.enable_fast_cpu_scans()
    jax.config.update("jax_enable_x64", True)
    pj.enable_compilation_cache()  # compiled programs kept for the next run ($PIEZOJAX_CACHE_DIR)
    out = output_folder(args.out, KIND, default=OUT)  # before any long work
    start = time.perf_counter()
    key = jax.random.key(2014)
    keys = jax.random.split(key, 6)
    bench = pj.ChenBench()
    q = args.quick

    cal = force_calibration(bench, keys[0], 4.0 if q else 20.0)
    xt = crosstalk(bench, keys[1], seconds=0.6 if q else 1.0)
    stage = stage_identification(bench, keys[2], 2.0 if q else 8.0, cal["sensitivity_V_per_N"],
                                 xt["crosstalk_V_per_V"])
    observer = stage["staged_observer"]
    plant = bench.plant(1 / CONTROL_RATE, bias=BIAS, substeps=10)
    train, val = open_loop_records(plant, observer, keys[3], 4.0 if q else 6.0)
    narx = narmax(train, val, keys[4], epochs=5 if q else 20)
    ctl = control(plant, observer, train, keys[5], q)
    elapsed = time.perf_counter() - start

    rows = [
        ("force sensitivity (V/N)", f"{PAPER['force_sensitivity_V_per_N']:.6f}",
         f"{cal['sensitivity_V_per_N']:.6f} (truth {cal['truth_V_per_N']:.6f})"),
        ("sensitivity spread 1-100 Hz", "nearly constant", f"{cal['flatness_1_100Hz_percent']:.2f} % peak to peak"),
        ("crosstalk at 20 V (V)", f"{PAPER['crosstalk_fea_V_at_20V']:.6f} (FEA)",
         f"{xt['crosstalk_at_20V']:.6f} (truth {20 * xt['truth_V_per_V']:.6f})"),
        ("crosstalk share of V_s", "< 8 %", f"{100 * xt['share_max']:.2f} %"),
        ("displacement sensitivity, step by step (µm/V)", f"{PAPER['displacement_sensitivity_um_per_V']}",
         f"{stage['staged']['sensitivity_um_per_V']:.4f} (truth {stage['truth']['sensitivity_um_per_V']:.4f})"),
        ("displacement sensitivity, joint fit (µm/V)", "-", f"{stage['joint']['sensitivity_um_per_V']:.4f}"),
        ("zero frequency eq. 5 / resonance, joint (Hz)", "not given",
         f"{stage['joint']['zero_frequency_Hz']:.0f} / {stage['joint']['resonance_Hz']:.0f} (truth "
         f"{stage['truth']['zero_frequency_Hz']:.0f} / {stage['truth']['resonance_Hz']:.0f})"),
        ("eq. 9 observer error, step by step / joint", "not given",
         f"{stage['staged']['observer_error_percent']:.3f} % / {stage['joint']['observer_error_percent']:.3f} % "
         "of range"),
    ]
    for name in ("least_squares", "online_bp", "sysidentpy", "sysidentpy_selected"):
        r = narx[name]
        label = {"least_squares": "NARMAX by joint least squares", "online_bp": "NARMAX by online BP",
                 "sysidentpy": "NARX by sysidentpy (FROLS, AIC)",
                 "sysidentpy_selected": "NARX by sysidentpy (FROLS, structure by us)"}[name]
        if r is None:
            text = "not installed (pip install -e .[narx])"
        else:
            free = "diverged" if r["nrmse"] is None else f"{r['nrmse']:.4f}"
            text = f"{free}, {r['seconds']:.1f} s"
            if "one_step_nrmse" in r:
                text += f" (one step ahead {r['one_step_nrmse']:.4f})"
        rows.append((f"{label}: free-run validation NRMSE, time", "not given", text))
    errs = ctl["rms_error_percent"]
    for name in errs[FREQUENCIES[0]]:
        rows.append((f"{name}: e_rms 1/5/10/20 Hz (eq. 20)",
                     "Table IV (values not in our text)" if name == "adaptive inverse" else "-",
                     " / ".join(f"{errs[f][name]:.2f}" for f in FREQUENCIES) + " %"))
    adaptive = [errs[f]["adaptive inverse"] for f in FREQUENCIES]
    grows = bool(all(b >= a for a, b in zip(adaptive, adaptive[1:], strict=False)))
    rows.append(("error grows with frequency (adaptive)", "yes", "yes" if grows else "no"))
    pp = ctl["adaptive_per_period_1Hz"]
    marks = [i for i in (1, 9, len(pp) - 1) if i < len(pp)]
    rows.append((f"adaptive inverse, 1 Hz: e_rms of periods {' / '.join(str(i + 1) for i in marks)}", "-",
                 " / ".join(f"{pp[i]:.2f}" for i in marks) + " %"))
    resp = ctl["closed_loop_frf"]
    rows.append(("closed-loop -3 dB bandwidth: " + " / ".join(resp), "Fig. 22 (no number in our text)",
                 " / ".join("> 350" if r["bandwidth_Hz"] is None else f"{r['bandwidth_Hz']:.0f}"
                            for r in resp.values()) + " Hz"))
    tu = ctl["tuning"]
    rows.append(("PID tuned by gradient through the loop (10 Hz)", "-",
                 f"e_rms {tu['start_error_percent']:.2f} % -> {tu['tuned_error_percent']:.2f} %"))

    width = max(len(r[0]) for r in rows)
    print(f"{'':<{width}}  {'paper':<34}  this project")
    for name, paper, ours in rows:
        print(f"{name:<{width}}  {paper:<34}  {ours}")
    print(f"joint stage fit: {stage['joint']['steps']} steps, {stage['joint']['fit_seconds']:.1f} s "
          f"({stage['joint']['verdict']}); PID gains by gradient through the loop: {ctl['pid_gains']} "
          f"({ctl['tuning_seconds']:.1f} s); total {elapsed:.0f} s")

    report = {
        "quick": q,
        "paper": PAPER,
        "force_calibration": {k: v for k, v in cal.items() if k != "frf"},
        "crosstalk": xt,
        "stage": {k: stage[k] for k in ("staged", "joint", "truth")},
        "narmax": {k: v for k, v in narx.items() if k != "models"},
        "control": {"rms_error_percent": {f"{f:g} Hz": v for f, v in errs.items()},
                    "pid_gains": ctl["pid_gains"], "pid_start": ctl["pid_start"],
                    "tuning_seconds": ctl["tuning_seconds"], "tuning": ctl["tuning"],
                    "error_grows_with_frequency": grows,
                    "adaptive_per_period_1Hz_percent": ctl["adaptive_per_period_1Hz"],
                    "closed_loop_frf": {k: {q: v for q, v in r.items() if q not in ("frequency_Hz", "frf",
                                                                                     "coherence")}
                                        for k, r in ctl["closed_loop_frf"].items()}},
        "table": [{"quantity": a, "paper": b, "this_project": c} for a, b, c in rows],
        "run_seconds": elapsed,
    }
    with writing(out, KIND) as tmp:
        fitting.files.save_json(tmp / "report.json", report)
        if not args.no_figures:
            _figures(tmp, cal, stage, narx, val, ctl)
    print(f"wrote {out}")
    return report


if __name__ == "__main__":
    sys.exit(run(main, "python -m experiments.chen2014"))
