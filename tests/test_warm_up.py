"""`fitting.warm_up`: a record's sensor zero and initial state from a window at its start, on a model that is the
plant (so only the unknown state and the noise remain): a record from rest with a moved zero, and a record cut from
a longer drive, whose creep has not settled."""

import jax.numpy as jnp
import numpy as np
import pytest

import fitting
import piezojax as pj

DT = 1e-3
N = 3000


def _model():
    pi = pj.PrandtlIshlinskii(jnp.asarray([2.5e-8, 1.5e-8, 1e-8]), jnp.asarray([8.0, 20.0, 35.0]), w0=1e-7)
    return pj.Actuator(pi, pj.KelvinVoigtCreep(jnp.asarray([1.25e8, 5e7]), jnp.asarray([0.2, 8.0]), k0=None))


def _drive():
    t = np.arange(N) * DT
    return t, 40 * np.sin(2 * np.pi * 1.7 * t) * np.minimum(1, t / 0.2) + 10 * np.sin(2 * np.pi * 5.3 * t)


@pytest.mark.parametrize("sigma", [5e-9, 1e-9])
def test_a_record_from_rest_gets_its_offset_and_no_creep(sigma):
    """From rest: the offset to a fraction of the noise and the rest predicted at it (the 8 s lag, 16 windows long,
    would fit any drift of the noise as a creep and extrapolate it unless the window's second half refuses it)."""
    m = _model()
    t, v = _drive()
    y = np.asarray(m.simulate(jnp.asarray(v), DT).displacement) + 2e-7
    y = y + sigma * np.random.default_rng(0).standard_normal(N)
    w = fitting.warm_up(m, fitting.Experiment.from_arrays(t=t, v_in=v, displacement=y), 0.5)
    assert w.offsets["displacement"] == pytest.approx(2e-7, abs=3 * sigma / np.sqrt(w.samples) * 3)
    assert w.samples == 500 and w.scored.sum() == N - 500
    err = (w.predictions["displacement"] - y)[w.scored]
    assert np.sqrt(np.mean(err**2)) < 1.1 * sigma


@pytest.mark.parametrize("sigma", [5e-9, 1e-9])
def test_a_record_cut_from_a_longer_drive_gets_its_creep_state(sigma):
    """After 4 s of another drive the creep is far from settled: its free response (both lags) is fitted on a 1 s
    window, and the rest is predicted at the noise, against 25x or more with the offset alone. (With 0.5 s, a
    sixteenth of the 8 s lag, its amplitude rests on the window's slope: 1.0-3.2x the noise over four noise draws.)"""
    m = _model()
    t, v = _drive()
    before = 40 * np.sin(2 * np.pi * 1.3 * np.arange(4000) * DT) + 20
    full = np.concatenate([before, v + before[-1]])
    y = np.asarray(m.simulate(jnp.asarray(full), DT).displacement)[4000:] + 2e-7
    y = y + sigma * np.random.default_rng(1).standard_normal(N)
    rec = fitting.Experiment.from_arrays(t=t, v_in=full[4000:], displacement=y)
    w = fitting.warm_up(m, rec, 1.0)
    assert sorted(w.creep) == [0.2, 8.0]
    err = (w.predictions["displacement"] - y)[w.scored]
    assert np.sqrt(np.mean(err**2)) < 1.2 * sigma
    plain = fitting.predict(m, rec)["displacement"] + w.offsets["displacement"] - y
    assert np.sqrt(np.mean(plain[w.scored] ** 2)) > 25 * sigma


def test_bad_windows_are_refused():
    m = _model()
    t, v = _drive()
    rec = fitting.Experiment.from_arrays(t=t, v_in=v, displacement=np.zeros(N))
    for seconds in (0.0, -1.0, float("nan"), True, "1"):
        with pytest.raises(pj.PiezojaxValueError, match="seconds > 0"):
            fitting.warm_up(m, rec, seconds)
    with pytest.raises(pj.PiezojaxValueError, match="leaves 0"):
        fitting.warm_up(m, rec, 3.0)
    assert fitting.warm_up(m, rec, np.float32(0.5)).samples == 500  # any real number
    with pytest.raises(pj.PiezojaxValueError, match="measured channel"):
        fitting.warm_up(m, fitting.Experiment.from_arrays(t=t, v_in=v), 0.5)
