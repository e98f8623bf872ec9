"""Bad input through the public API: NaN/inf parameters, complex and boolean inputs, unstable Bouc–Wen sets.

Two tables. `CONCRETE`: each row builds or calls a public object with one bad argument and must raise a
`PiezojaxValueError` whose message names the argument. `TRACED`: the same checks under `eqx.filter_jit`, with the
module built inside the jitted function from traced arrays, or built outside and a leaf replaced afterwards
(`eqx.tree_at`, as a fitter does); value problems must fail at run time with an `eqx.EquinoxRuntimeError` naming the
argument, dtype problems at trace time with a `PiezojaxValueError`. Signals are a few samples long: every row is one
cheap construction or one small compilation.
"""

import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import piezojax as pj
from piezojax import PiezojaxValueError

NAN, INF = np.nan, np.inf
SIG = np.array([0.0, 0.4, 1.0, 0.6, -0.2, 0.3])  # a tiny drive signal
DT = 1e-3


def cplx(x):
    """`x` as a complex array (a zero imaginary part is still a complex dtype)."""
    return np.asarray(x, dtype=np.complex128)


def pi(**kw):
    args = dict(weights=[1.0, 0.5], thresholds=[0.0, 0.5], w0=1.0)
    args.update(kw)
    return pj.PrandtlIshlinskii(args.pop("weights"), args.pop("thresholds"), **args)


def bouc_wen(*args, **kw):
    full = (1.0, 0.5, 0.3)
    return pj.BoucWen(*(args + full[len(args):]), **kw)


def preisach(**kw):
    args = dict(alpha=[0.5, 1.0, 1.0], beta=[0.5, 0.5, 1.0], mu=[0.2, 0.3, 0.5])
    args.update(kw)
    return pj.Preisach(args.pop("alpha"), args.pop("beta"), args.pop("mu"), **args)


def kelvin_voigt(**kw):
    args = dict(stiffnesses=[20.0, 50.0], time_constants=[0.5, 20.0])
    args.update(kw)
    return pj.KelvinVoigtCreep(**args)


def electromechanical(**kw):
    args = dict(m=0.01, b=5.0, k=1e5, capacitance=1e-6, t_em=[0.5], element_capacitances=[2e-6, 2e-6],
                breakaway_voltages=[1.0, 2.0])
    args.update(kw)
    return pj.ElectromechanicalActuator(**args)


def tia(**kw):
    args = dict(feedback_resistance=1e6, capacitance=4.2e-9, gamma=0.66e-9, bias_current=0.0)
    args.update(kw)
    return pj.TransimpedanceCircuit(**args)


def charge_integrator(**kw):
    args = dict(integrator_capacitance=1e-7, reference_capacitance=1.7e-9, leakage_resistance=1e12, bias_current=0.0,
                force_sensitivity=1e-6, capacitance_p=1.7e-9)
    args.update(kw)
    return pj.ChargeIntegratorCircuit(**args)


def smart_stack(**kw):
    args = dict(d33=1.6e-12, amplifier_capacitance=104e-12, k_p=6.3e6, k_s=5e7, m_e=0.05, c_e=20.0, k_e=2e7)
    args.update(kw)
    return pj.SmartStackCircuit(**args)


TF = pj.TransferFunction([1.0], [1e-3, 1.0])


def dynamic_impedance(**kw):
    args = dict(feedback_resistance=1e6, capacitance=4.2e-9, gamma=0.66e-9, bias_current=0.0, alpha=0.9, beta=7e7,
                dynamics=TF)
    args.update(kw)
    return pj.DynamicImpedanceObserver(**args)


def force_displacement(**kw):
    args = dict(integrator_capacitance=1e-7, reference_capacitance=1.7e-9, leakage_resistance=1e12, bias_current=0.0,
                force_sensitivity=1e-6, displacement_coefficient=-4e-3, stiffness=150.0)
    args.update(kw)
    return pj.ForceDisplacementObserver(**args)


def sensor_layer(**kw):
    args = dict(d33=1.6e-12, amplifier_capacitance=104e-12, k_p=6.3e6, k_s=5e7)
    args.update(kw)
    return pj.SensorLayerObserver(**args)


KEY = jax.random.key(0)


def narx(**kw):
    args = dict(hidden=2, output_lags=1, input_lags=1)
    args.update(kw)
    return pj.NarxNetwork(KEY, **args)


class _Plant(pj.AbstractPlant):
    """x_{k+1} = 0.9 x_k + 0.5 u_k, read as the displacement."""

    def init(self):
        return jnp.zeros(())

    def output(self, state, noise):
        return {"displacement": state + (0.0 if noise is None else noise)}

    def step(self, state, command):
        return 0.9 * state + 0.5 * command


def plant():
    return _Plant()


def replaced(module, where, value):
    """`module` with one leaf replaced after __init__ (bypassing the constructor's checks)."""
    return eqx.tree_at(where, module, jnp.asarray(value))


# (id, callable, substring the message must contain)
CONCRETE = [
    # -- play and stop operators
    ("play-thresholds-nan", lambda: pj.PlayOperator([0.1, NAN]), "`thresholds`"),
    ("play-thresholds-inf", lambda: pj.PlayOperator(INF), "`thresholds`"),
    ("play-smoothing-nan", lambda: pj.PlayOperator(0.5, smoothing=NAN), "`smoothing`"),
    ("play-thresholds-complex", lambda: pj.PlayOperator(cplx([0.5])), "`thresholds`"),
    ("play-signal-complex", lambda: pj.PlayOperator(0.5)(cplx(SIG)), "`signal`"),
    ("play-signal-bool", lambda: pj.PlayOperator(0.5)(SIG > 0.5), "`signal`"),
    ("stop-thresholds-nan", lambda: pj.StopOperator([NAN]), "`thresholds`"),
    ("stop-signal-complex", lambda: pj.StopOperator(0.5)(cplx(SIG)), "`signal`"),
    # -- Prandtl–Ishlinskii
    ("pi-weights-nan", lambda: pi(weights=[1.0, NAN]), "`weights`"),
    ("pi-weights-inf", lambda: pi(weights=[INF, 1.0]), "`weights`"),
    ("pi-w0-nan", lambda: pi(w0=NAN), "`w0`"),
    ("pi-w0-inf", lambda: pi(w0=-INF), "`w0`"),
    ("pi-thresholds-nan", lambda: pi(thresholds=[0.0, NAN]), "`thresholds`"),
    ("pi-smoothing-inf", lambda: pi(smoothing=INF), "`smoothing`"),
    ("pi-weights-complex", lambda: pi(weights=cplx([1.0, 0.5])), "`weights`"),
    ("pi-w0-complex", lambda: pi(w0=1.0 + 0.5j), "`w0`"),
    ("pi-w0-bool", lambda: pi(w0=True), "`w0`"),
    ("pi-signal-complex", lambda: pi()(cplx(SIG)), "`signal`"),
    ("pi-signal-bool", lambda: pi()(SIG > 0.5), "`signal`"),
    ("pi-signal-nan", lambda: pi()(np.where(SIG > 0.5, NAN, SIG)), "`signal`"),
    ("pi-replaced-weights-nan", lambda: replaced(pi(), lambda m: m.weights, [1.0, NAN])(SIG), "`weights`"),
    ("pi-replaced-w0-inf", lambda: replaced(pi(), lambda m: m.w0, INF)(SIG), "`w0`"),
    # -- Maxwell slip
    ("maxwell-stiffness-nan", lambda: pj.MaxwellSlip([2.0, NAN], [1.0, 2.0]), "`stiffness`"),
    ("maxwell-breakaway-inf", lambda: pj.MaxwellSlip([2.0, 1.0], [1.0, INF]), "`breakaway`"),
    ("maxwell-smoothing-nan", lambda: pj.MaxwellSlip([2.0], [1.0], smoothing=NAN), "`smoothing`"),
    ("maxwell-stiffness-complex", lambda: pj.MaxwellSlip(cplx([2.0]), [1.0]), "`stiffness`"),
    ("maxwell-signal-complex", lambda: pj.MaxwellSlip([2.0], [1.0])(cplx(SIG)), "`signal`"),
    ("maxwell-capacitances-nan", lambda: pj.MaxwellSlip.electrical([NAN], [1.0]), "`capacitances`"),
    # -- Bouc–Wen
    ("bw-A-nan", lambda: bouc_wen(NAN), "`A`"),
    ("bw-A-inf", lambda: bouc_wen(INF), "`A`"),
    ("bw-beta-nan", lambda: bouc_wen(1.0, NAN), "`beta`"),
    ("bw-gamma-inf", lambda: bouc_wen(1.0, 0.5, -INF), "`gamma`"),
    ("bw-n-nan", lambda: bouc_wen(n=NAN), "`n`"),
    ("bw-d-inf", lambda: bouc_wen(d=INF), "`d`"),
    ("bw-smoothing-nan", lambda: bouc_wen(n=1.5, smoothing=NAN), "`smoothing`"),
    ("bw-A-complex", lambda: bouc_wen(1.0 + 1j), "`A`"),
    ("bw-signal-complex", lambda: bouc_wen()(cplx(SIG)), "`signal`"),
    ("bw-signal-bool", lambda: bouc_wen()(SIG > 0.5), "`signal`"),
    ("bw-z0-nan", lambda: bouc_wen().init(0.0, NAN), "`z0`"),
    ("bw-unstable-probe", lambda: pj.BoucWen(1.0, -0.5, 0.01, d=1.0), "`beta` >= 0"),
    ("bw-unstable-beta-negative", lambda: bouc_wen(1.0, -0.1, 0.5, 1.5), "`beta` >= 0"),
    ("bw-unstable-sum-negative", lambda: bouc_wen(1.0, 0.5, -0.6), "`beta` + `gamma` >= 0"),
    ("bw-unstable-negative-A", lambda: bouc_wen(-1.0, 0.4, 0.6), "`beta` - `gamma` >= 0"),
    ("bw-replaced-unstable", lambda: replaced(bouc_wen(), lambda m: m.beta, -0.5)(SIG), "`beta`"),
    ("bw-replaced-A-nan", lambda: replaced(bouc_wen(method="rk4"), lambda m: m.A, NAN)(SIG), "`A`"),
    # -- Preisach
    ("preisach-mu-nan", lambda: preisach(mu=[0.2, NAN, 0.5]), "`mu`"),
    ("preisach-mu-inf", lambda: preisach(mu=[INF, 0.3, 0.5]), "`mu`"),
    ("preisach-alpha-nan", lambda: preisach(alpha=[0.5, NAN, 1.0]), "`alpha`"),
    ("preisach-beta-inf", lambda: preisach(beta=[-INF, 0.5, 1.0]), "`beta`"),
    ("preisach-offset-nan", lambda: preisach(offset=NAN), "`offset`"),
    ("preisach-smoothing-inf", lambda: preisach(smoothing=INF), "`smoothing`"),
    ("preisach-mu-complex", lambda: preisach(mu=cplx([0.2, 0.3, 0.5])), "`mu`"),
    ("preisach-signal-complex", lambda: preisach()(cplx(SIG)), "`signal`"),
    ("preisach-uniform-mu-nan", lambda: pj.Preisach.uniform(-1.0, 1.0, 2, mu=[0.1, NAN, 0.3]), "`mu`"),
    ("preisach-replaced-mu-nan", lambda: replaced(preisach(), lambda m: m.mu, [0.2, NAN, 0.5])(SIG), "`mu`"),
    # -- creep
    ("kv-stiffnesses-nan", lambda: kelvin_voigt(stiffnesses=[NAN, 50.0]), "`stiffnesses`"),
    ("kv-time_constants-inf", lambda: kelvin_voigt(time_constants=[0.5, INF]), "`time_constants`"),
    ("kv-k0-nan", lambda: kelvin_voigt(k0=NAN), "`k0`"),
    ("kv-k0-bool", lambda: kelvin_voigt(k0=True), "`k0`"),
    ("kv-stiffnesses-complex", lambda: kelvin_voigt(stiffnesses=cplx([20.0, 50.0])), "`stiffnesses`"),
    ("kv-u-complex", lambda: kelvin_voigt().simulate(cplx(SIG), DT), "`u`"),
    ("kv-u-bool", lambda: kelvin_voigt().simulate(SIG > 0.5, DT), "`u`"),
    ("kv-dt-nan", lambda: kelvin_voigt().simulate(SIG, NAN), "`dt`"),
    ("kv-dt-complex", lambda: kelvin_voigt().simulate(SIG, 1e-3 + 0j), "`dt`"),
    ("kv-replaced-tau-nan", lambda: replaced(kelvin_voigt(), lambda m: m.time_constants, [NAN, 1.0])(SIG, DT),
     "`time_constants`"),
    ("log-gamma-nan", lambda: pj.LogarithmicCreep(NAN, 0.1), "`gamma`"),
    ("log-t0-inf", lambda: pj.LogarithmicCreep(0.02, INF), "`t0`"),
    ("log-gain-inf", lambda: pj.LogarithmicCreep(0.02, 0.1, gain=INF), "`gain`"),
    ("log-gain-complex", lambda: pj.LogarithmicCreep(0.02, 0.1, gain=1j), "`gain`"),
    ("log-u-complex", lambda: pj.LogarithmicCreep(0.02, 0.1)(cplx(SIG), DT), "`u`"),
    ("linear-creep-num-nan", lambda: pj.LinearCreep.from_tf([NAN, 1.0], [1.0, 1.0]), "`num`"),
    # -- linear systems
    ("tf-num-nan", lambda: pj.TransferFunction([NAN], [1.0, 1.0]), "`num`"),
    ("tf-den-inf", lambda: pj.TransferFunction([1.0], [1.0, INF]), "`den`"),
    ("tf-num-complex", lambda: pj.TransferFunction(cplx([1.0]), [1.0, 1.0]), "`num`"),
    ("tf-u-complex", lambda: TF.simulate(cplx(SIG), DT), "`u`"),
    ("tf-u-bool", lambda: TF(SIG > 0.5, DT), "`u`"),
    ("tf-replaced-num-nan", lambda: replaced(TF, lambda m: m.num, [0.0, NAN]).simulate(SIG, DT), "`num`"),
    ("ss-A-nan", lambda: pj.StateSpace([[NAN]], [1.0], [1.0]), "`A`"),
    ("ss-D-inf", lambda: pj.StateSpace([[-1.0]], [1.0], [1.0], INF), "`D`"),
    ("ss-B-complex", lambda: pj.StateSpace([[-1.0]], cplx([1.0]), [1.0]), "`B`"),
    ("stf-gain-nan", lambda: pj.StableTransferFunction(NAN, poles=[-1.0]), "`gain`"),
    ("stf-omega-inf", lambda: pj.StableTransferFunction(1.0, [INF], [0.1]), "`omega`"),
    ("stf-zeros-nan", lambda: pj.StableTransferFunction(1.0, poles=[-1.0], zeros=[NAN]), "`zeros`"),
    ("stf-zero_zeta-inf", lambda: pj.StableTransferFunction(1.0, [1.0], [0.1], zero_omega=[2.0], zero_zeta=[INF]),
     "`zero_zeta`"),
    ("stf-num-nan", lambda: pj.StableTransferFunction(1.0, poles=[-1.0], num=[NAN, 1.0]), "`num`"),
    ("stf-replaced-gain-inf",
     lambda: replaced(pj.StableTransferFunction(1.0, poles=[-1.0]), lambda m: m.gain, INF).simulate(SIG, DT),
     "`gain`"),
    ("butterworth-cutoff-nan", lambda: pj.butterworth(2, NAN), "`cutoff`"),
    ("butterworth-cutoff-complex", lambda: pj.butterworth(2, 1.0 + 1j), "`cutoff`"),
    ("dss-Ad-nan", lambda: pj.DiscreteStateSpace([[NAN]], [1.0], [1.0], 0.0, [[0.0]], [0.0], 0.1, "zoh"), "`Ad`"),
    ("dss-dt-inf", lambda: pj.DiscreteStateSpace([[1.0]], [1.0], [1.0], 0.0, [[0.0]], [0.0], INF, "zoh"), "`dt`"),
    ("discretise-dt-nan", lambda: TF.discretise(NAN), "`dt`"),
    # -- actuator
    ("actuator-capacitance-nan", lambda: pj.Actuator(capacitance=NAN), "`capacitance`"),
    ("actuator-coupling-inf", lambda: pj.Actuator(coupling=INF), "`coupling`"),
    ("actuator-capacitance-complex", lambda: pj.Actuator(capacitance=1e-9 + 0j), "`capacitance`"),
    ("actuator-v_in-complex", lambda: pj.Actuator(pi())(cplx(SIG), DT), "`v_in`"),
    ("actuator-v_in-bool", lambda: pj.Actuator(pi()).simulate(SIG > 0.5, DT), "`v_in`"),
    ("actuator-dt-inf", lambda: pj.Actuator(pi()).simulate(SIG, INF), "`dt`"),
    ("actuator-replaced-coupling-nan",
     lambda: replaced(pj.Actuator(pi()), lambda m: m.coupling, NAN).simulate(SIG, DT), "`coupling`"),
    # -- nonlinear ODE models
    ("bwo-k-nan", lambda: pj.BoucWenOscillator(k=NAN), "`k`"),
    ("bwo-alpha-inf", lambda: pj.BoucWenOscillator(alpha=INF), "`alpha`"),
    ("bwo-delta-complex", lambda: pj.BoucWenOscillator(delta=-1.1 + 0j), "`delta`"),
    ("bwo-u-complex", lambda: pj.BoucWenOscillator().simulate(cplx(SIG), DT), "`u`"),
    ("em-m-nan", lambda: electromechanical(m=NAN), "`m`"),
    ("em-t_em-inf", lambda: electromechanical(t_em=[0.5, INF]), "`t_em`"),
    ("em-element_capacitances-nan", lambda: electromechanical(element_capacitances=[2e-6, NAN]),
     "`element_capacitances`"),
    ("em-v_in-complex", lambda: electromechanical().simulate(cplx(SIG), DT), "`v_in`"),
    ("sampled-u-complex", lambda: pj.SampledInput.from_samples(cplx(SIG), DT), "`u`"),
    ("sampled-t0-nan", lambda: pj.SampledInput.from_samples(SIG, DT, t0=NAN), "`t0`"),
    ("sampled-knots-nan", lambda: pj.SampledInput([0.0, NAN], np.zeros((1, 4)), "linear"), "`knots`"),
    ("sampled-coeffs-inf", lambda: pj.SampledInput([0.0, 1.0], np.full((1, 4), INF), "linear"), "`coeffs`"),
    # -- circuits
    ("tia-feedback_resistance-nan", lambda: tia(feedback_resistance=NAN), "`feedback_resistance`"),
    ("tia-bias_current-inf", lambda: tia(bias_current=INF), "`bias_current`"),
    ("tia-v_in-complex", lambda: tia()(cplx(SIG), DT), "`v_in`"),
    ("tia-replaced-gamma-nan", lambda: replaced(tia(), lambda m: m.gamma, NAN)(SIG, DT), "`gamma`"),
    ("ci-leakage_resistance-inf", lambda: charge_integrator(leakage_resistance=INF), "`leakage_resistance`"),
    ("ci-f_ext-complex", lambda: charge_integrator()(SIG, DT, f_ext=cplx(SIG)), "`f_ext`"),
    ("stack-crosstalk-nan", lambda: smart_stack(crosstalk=NAN), "`crosstalk`"),
    ("stack-d33-complex", lambda: smart_stack(d33=1.6e-12 + 0j), "`d33`"),
    ("stack-x_a-bool", lambda: smart_stack()(SIG, DT, x_a=SIG > 0.5), "`x_a`"),
    # -- observers
    ("dio-alpha-nan", lambda: dynamic_impedance(alpha=NAN), "`alpha`"),
    ("dio-v_out-complex", lambda: dynamic_impedance()(SIG, cplx(SIG), DT), "`v_out`"),
    ("fdo-displacement_coefficient-inf", lambda: force_displacement(displacement_coefficient=INF),
     "`displacement_coefficient`"),
    ("fdo-displacement_coefficient-zero", lambda: force_displacement(displacement_coefficient=0.0),
     "`displacement_coefficient`"),
    ("fdo-filter_cutoff-nan", lambda: force_displacement(filter_cutoff=NAN), "`filter_cutoff`"),
    ("slo-crosstalk-inf", lambda: sensor_layer(crosstalk=INF), "`crosstalk`"),
    ("slo-v_out-bool", lambda: sensor_layer()(SIG, SIG > 0.5), "`v_out`"),
    # -- reparametrisations
    ("positive-value-nan", lambda: pj.Positive.from_value([1.0, NAN]), "`value`"),
    ("positive-value-inf", lambda: pj.Positive.from_value(INF), "`value`"),
    ("positive-raw-nan", lambda: pj.Positive([NAN]), "`raw`"),
    ("ordered-value-inf", lambda: pj.OrderedPositive.from_value([0.5, INF]), "`value`"),
    ("bounded-raw-complex", lambda: pj.Bounded(cplx([0.0]), 0.0, 1.0), "`raw`"),
    ("bounded-high-inf", lambda: pj.Bounded([0.0], 0.0, INF), "`high`"),
    # -- control
    ("pid-kp-nan", lambda: pj.PID(NAN, dt=DT), "`kp`"),
    ("pid-ki-inf", lambda: pj.PID(1.0, INF, dt=DT), "`ki`"),
    ("pid-offset-nan", lambda: pj.PID(1.0, dt=DT, offset=NAN), "`offset`"),
    ("pid-u_min-nan", lambda: pj.PID(1.0, dt=DT, u_min=NAN), "`u_min`"),
    ("pid-replaced-dt-negative", lambda: replaced(pj.PID(1.0, dt=DT), lambda m: m.dt, -DT)(SIG, SIG), "`dt`"),
    ("pid-replaced-tracking_time-zero",
     lambda: pj.closed_loop(replaced(pj.PID(1.0, dt=DT), lambda m: m.tracking_time, 0.0), plant(), SIG),
     "`tracking_time`"),
    ("pid-step-old-state", lambda: pj.PID(1.0, dt=DT).step(np.zeros(3), 1.0, 0.3), "`state`"),
    ("loop-observer-replaced-d33-nan",
     lambda: pj.closed_loop(pj.PID(1.0, dt=DT), pj.ChenBench().plant(), SIG,
                            observer=replaced(pj.ChenBench().observer(), lambda m: m.d33, NAN)), "`d33`"),
    ("feedforward-inverse-replaced-weights-nan",
     lambda: replaced(pj.InverseFeedforward(pi().inverse()), lambda m: m.inverse.weights, [NAN, 1.0])(SIG, SIG),
     "`weights`"),
    ("aic-offset-nan", lambda: pj.AdaptiveInverseController(KEY, hidden=2, offset=NAN), "`offset`"),
    ("aic-output_offset-inf", lambda: pj.AdaptiveInverseController(KEY, hidden=2, output_offset=INF),
     "`output_offset`"),
    ("aic-command_scale-vector", lambda: pj.AdaptiveInverseController(KEY, hidden=2, command_scale=[1.0, 2.0]),
     "`command_scale`"),
    ("feedforward-reference_scale-zero", lambda: pj.InverseFeedforward(pi().inverse(), reference_scale=0.0),
     "`reference_scale`"),
    ("feedforward-reference_scale-vector", lambda: pj.InverseFeedforward(pi().inverse(), reference_scale=[1.0, 2.0]),
     "`reference_scale`"),
    ("narx-output_offset-nan", lambda: narx(output_offset=NAN), "`output_offset`"),
    ("narx-delay-bool", lambda: narx(delay=True), "`delay`"),
    ("narx-train-learning_rate-nan", lambda: pj.train_narx_online(narx(), SIG, SIG, learning_rate=NAN),
     "`learning_rate`"),
    ("narx-train-learning_rate-negative", lambda: pj.train_narx_online(narx(), SIG, SIG, learning_rate=-1.0),
     "`learning_rate`"),
    ("narx-train-momentum-5", lambda: pj.train_narx_online(narx(), SIG, SIG, learning_rate=0.1, momentum=5.0),
     "`momentum`"),
    ("narx-train-epochs-bool", lambda: pj.train_narx_online(narx(), SIG, SIG, learning_rate=0.1, epochs=True),
     "`epochs`"),
    ("loop-noise-nan", lambda: pj.closed_loop(pj.PID(1.0, dt=DT), plant(), SIG, noise=np.full(SIG.size, NAN)),
     "`noise`"),
    ("tracking-error-constant-reference", lambda: pj.tracking_error_percent(np.ones(4), SIG[:4]), "`reference`"),
    ("bwo-state0-nan", lambda: pj.BoucWenOscillator().simulate(SIG, DT, state0=[NAN, 0.0, 0.0]), "`state0`"),
    ("bwo-rtol-negative", lambda: pj.BoucWenOscillator().simulate(SIG, DT, rtol=-1e-8), "`rtol`"),
    ("bwo-num_samples-bool", lambda: pj.BoucWenOscillator().simulate(SIG, DT, num_samples=True), "`num_samples`"),
    ("sampled-evaluate-vector-t", lambda: pj.SampledInput.from_samples(SIG, DT).evaluate(np.zeros(3)), "`t`"),
    # -- virtual benches
    ("bafumba-alpha-nan", lambda: pj.BafumbaBench(alpha=NAN), "`alpha`"),
    ("bafumba-v_command-complex", lambda: pj.BafumbaBench().record(cplx(SIG), None), "`v_command`"),
    ("chen-stroke-inf", lambda: pj.ChenBench(stroke=INF), "`stroke`"),
    ("chen-plant-bias-nan", lambda: pj.ChenBench().plant(bias=NAN), "`bias`"),
    ("chen-plant-amplifier_gain-nan", lambda: pj.ChenBench().plant(amplifier_gain=NAN), "`amplifier_gain`"),
    ("chen-plant-dac_bits-negative", lambda: pj.ChenBench().plant(dac_bits=-1), "`dac_bits`"),
    ("ivan-gap-nan", lambda: pj.IvanBench(gap=NAN), "`gap`"),
]


@pytest.mark.parametrize("make, expected", [row[1:] for row in CONCRETE], ids=[row[0] for row in CONCRETE])
def test_concrete_bad_input_raises_naming_the_argument(make, expected):
    with pytest.raises(PiezojaxValueError, match=re.escape(expected)):
        make()


def test_tables_are_large_and_unique():
    assert len(CONCRETE) >= 60 and len(TRACED) >= 15
    ids = [row[0] for row in CONCRETE + TRACED]
    assert len(ids) == len(set(ids))


# -- under jit -----------------------------------------------------------------------------------------------------

J = jnp.asarray
SIG_J = J(SIG)


def _outside(module, where, value, call):
    """Build `module` outside `jit`, replace a leaf with `value` (no __init__ checks), run `call(module)` under jit."""
    bad = eqx.tree_at(where, module, J(value))
    return lambda: eqx.filter_jit(call)(bad)


def _inside(build_and_call, *args):
    """Run `build_and_call(*args)` under jit: the module is built inside from traced arrays."""
    return lambda: eqx.filter_jit(build_and_call)(*(J(a) for a in args))


# (id, callable, expected exception, substring of its message)
RUNTIME = eqx.EquinoxRuntimeError
TRACED = [
    ("jit-pi-weights-nan-inside", _inside(lambda w: pi(weights=w)(SIG_J), [1.0, NAN]), RUNTIME, "`weights`"),
    ("jit-pi-w0-inf-inside", _inside(lambda w0: pi(w0=w0)(SIG_J), INF), RUNTIME, "`w0`"),
    ("jit-pi-weights-nan-replaced", _outside(pi(), lambda m: m.weights, [NAN, 1.0], lambda m: m(SIG_J)), RUNTIME,
     "`weights`"),
    ("jit-pi-w0-nan-replaced", _outside(pi(), lambda m: m.w0, NAN, lambda m: m(SIG_J)), RUNTIME, "`w0`"),
    ("jit-play-thresholds-nan-inside", _inside(lambda r: pj.PlayOperator(r)(SIG_J), [0.5, NAN]), RUNTIME,
     "`thresholds`"),
    ("jit-maxwell-stiffness-nan-inside", _inside(lambda k: pj.MaxwellSlip(k, [1.0])(SIG_J), [NAN]), RUNTIME,
     "`stiffness`"),
    ("jit-maxwell-breakaway-inf-replaced",
     _outside(pj.MaxwellSlip([2.0], [1.0]), lambda m: m.breakaway, [INF], lambda m: m(SIG_J)), RUNTIME, "`breakaway`"),
    ("jit-bw-A-nan-inside", _inside(lambda a: bouc_wen(a)(SIG_J), NAN), RUNTIME, "`A`"),
    ("jit-bw-unstable-inside", _inside(lambda b: pj.BoucWen(1.0, b, 0.01, d=1.0)(SIG_J), -0.5), RUNTIME,
     "`beta` >= 0"),
    ("jit-bw-unstable-replaced", _outside(bouc_wen(), lambda m: m.gamma, -0.9, lambda m: m(SIG_J)), RUNTIME,
     "`beta` + `gamma` >= 0"),
    ("jit-preisach-mu-nan-inside", _inside(lambda mu: preisach(mu=mu)(SIG_J), [0.2, NAN, 0.5]), RUNTIME, "`mu`"),
    ("jit-preisach-offset-inf-replaced", _outside(preisach(), lambda m: m.offset, INF, lambda m: m(SIG_J)), RUNTIME,
     "`offset`"),
    ("jit-kv-stiffnesses-inf-inside", _inside(lambda k: kelvin_voigt(stiffnesses=k)(SIG_J, DT), [INF, 1.0]), RUNTIME,
     "`stiffnesses`"),
    ("jit-kv-tau-nan-replaced",
     _outside(kelvin_voigt(), lambda m: m.time_constants, [0.5, NAN], lambda m: m(SIG_J, DT)), RUNTIME,
     "`time_constants`"),
    ("jit-log-gamma-nan-replaced",
     _outside(pj.LogarithmicCreep(0.02, 0.1), lambda m: m.gamma, NAN, lambda m: m(SIG_J, DT)), RUNTIME, "`gamma`"),
    ("jit-tf-num-nan-replaced", _outside(TF, lambda m: m.num, [0.0, NAN], lambda m: m(SIG_J, DT)), RUNTIME, "`num`"),
    ("jit-stf-gain-nan-inside", _inside(lambda g: pj.StableTransferFunction(g, poles=[-1.0])(SIG_J, DT), NAN),
     RUNTIME, "`gain`"),
    ("jit-actuator-coupling-nan-replaced",
     _outside(pj.Actuator(pi()), lambda m: m.coupling, NAN, lambda m: m(SIG_J, DT).charge), RUNTIME,
     "`coupling`"),  # the check is attached to what uses `coupling` (the charge), as every `eqx.error_if`
    ("jit-actuator-nested-weights-nan-replaced",
     _outside(pj.Actuator(pi()), lambda m: m.hysteresis.weights, [1.0, INF], lambda m: m(SIG_J, DT).charge),
     RUNTIME, "`weights`"),
    ("jit-pid-kd-nan-replaced",
     _outside(pj.PID(1.0, dt=DT), lambda m: m.kd, NAN, lambda m: pj.closed_loop(m, plant(), SIG_J).control), RUNTIME,
     "`kd`"),
    ("jit-tia-bias_current-nan-replaced",
     _outside(tia(), lambda m: m.bias_current, NAN, lambda m: m(SIG_J, DT)), RUNTIME, "`bias_current`"),
    ("jit-positive-raw-nan-inside", _inside(lambda r: pj.Positive(r).unwrap(), [NAN]), RUNTIME, "`raw`"),
    # dtype problems are found while tracing
    ("jit-pi-signal-complex", lambda: eqx.filter_jit(pi())(J(cplx(SIG))), PiezojaxValueError, "`signal`"),
    ("jit-pi-weights-complex-inside", _inside(lambda w: pi(weights=w)(SIG_J), cplx([1.0, 0.5])), PiezojaxValueError,
     "`weights`"),
    ("jit-actuator-v_in-bool", lambda: eqx.filter_jit(pj.Actuator(pi()))(J(SIG > 0.5), DT), PiezojaxValueError,
     "`v_in`"),
]


@pytest.mark.parametrize("run, error, expected", [row[1:] for row in TRACED], ids=[row[0] for row in TRACED])
def test_traced_bad_input_fails_naming_the_argument(run, error, expected):
    with pytest.raises(error, match=re.escape(expected)):
        jnp.asarray(run()).block_until_ready()


def test_valid_parameters_still_run():
    """The boundary cases that stay allowed: beta + gamma = 0 (linear growth), A < 0 mirrored, A = 0."""
    for args in ((0.8, 0.3, -0.3), (-0.5, 0.4, 0.1), (0.0, 0.3, -0.9), (1.0, 0.0, 0.5)):
        assert np.all(np.isfinite(np.asarray(pj.BoucWen(*args)(SIG))))
    assert np.all(np.isfinite(np.asarray(eqx.filter_jit(lambda w: pi(weights=w)(SIG_J))(J([1.0, 0.5])))))


def test_a_check_of_a_concrete_value_against_a_traced_one_runs_with_the_computation():
    """`u_max` is concrete and its check reads the traced `u_min`: valid values run under jit and vmap, an invalid
    one fails when the checked value is used (the check once fired at trace time for every value)."""
    def u_max(u_min):
        return pj.PID(1.0, dt=1e-3, u_min=u_min, u_max=200.0).u_max

    assert float(jax.jit(u_max)(jnp.asarray(-10.0))) == 200.0
    np.testing.assert_array_equal(jax.vmap(u_max)(jnp.array([-10.0, 5.0])), [200.0, 200.0])
    with pytest.raises(Exception, match="`u_max` must be greater than `u_min`"):
        eqx.filter_jit(u_max)(jnp.asarray(300.0)).block_until_ready()


@pytest.mark.parametrize("where, value, expected", [
    (lambda a: a.hysteresis.weights, jnp.full(3, 0.02), r"`weights` and `thresholds` must have the same shape, got "
     r"\(3,\) and \(4,\) \(was one of them replaced"),
    (lambda a: a.creep.time_constants, jnp.array([1.0, 2.0]), r"`stiffnesses` and `time_constants` must have the "
     r"same shape, got \(1,\) and \(2,\)"),
])
def test_a_leaf_replaced_with_another_shape_is_named(where, value, expected):
    act = pj.Actuator(pj.PrandtlIshlinskii(jnp.full(4, 0.02), jnp.arange(4.0) * 10, w0=0.05),
                      pj.KelvinVoigtCreep(jnp.array([20.0]), jnp.array([2.0]), k0=None), None)
    bad = eqx.tree_at(where, act, value)
    v = jnp.linspace(0.0, 50.0, 40)
    with pytest.raises(pj.PiezojaxValueError, match=expected):
        bad.simulate(v, 1e-3)
    with pytest.raises(pj.PiezojaxValueError, match=expected):  # also while tracing: shapes are static
        eqx.filter_jit(lambda m: m.simulate(v, 1e-3))(bad)


def test_replaced_maxwell_slip_breakaway_of_another_shape_is_named():
    ms = eqx.tree_at(lambda m: m.breakaway, pj.MaxwellSlip(jnp.ones(3), jnp.arange(3.0)), jnp.arange(2.0))
    with pytest.raises(pj.PiezojaxValueError, match=r"`stiffness` and `breakaway` must have the same shape"):
        ms(jnp.linspace(0.0, 3.0, 20))
