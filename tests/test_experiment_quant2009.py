"""`python -m experiments.quant2009 --quick` end to end (paper 003 on `pj.QuantBench`), and its staged steps on
models whose answer is known."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import piezojax as pj
from experiments import quant2009


def test_rising_curve_recovers_maxwell_slip_elements():
    # V(q) = V_H(q) + q / C_e on a rise from the relaxed state, with element thresholds q_j = C_j v_j on the
    # hinge grid: the NNLS fit returns the elements and C_e exactly (to the least-squares round-off)
    n = quant2009.ELEMENTS
    q_max = 2e-5
    knots = q_max * np.arange(1, n + 1) / (n + 1)
    caps = np.linspace(1e-6, 4e-6, n)
    limits = knots / caps
    c_eff = 1.5e-7
    q = np.linspace(0.0, q_max, 3001)
    v_h = np.asarray(pj.MaxwellSlip.electrical(jnp.asarray(caps), jnp.asarray(limits))(jnp.asarray(q)))
    v = v_h + q / c_eff
    fit = quant2009.rising_curve(np.concatenate([v, v[::-1]]), np.concatenate([q, q[::-1]]))
    np.testing.assert_allclose(fit["caps"], caps, rtol=1e-8)
    np.testing.assert_allclose(fit["limits"], limits, rtol=1e-8)
    np.testing.assert_allclose(fit["c_eff"], c_eff, rtol=1e-8)
    # a second peak of the same level reading a little higher (converter noise) does not change the rise used
    down = np.linspace(q_max, -q_max, 3001)
    v_down = np.asarray(pj.MaxwellSlip.electrical(jnp.asarray(caps), jnp.asarray(limits))(
        jnp.asarray(np.concatenate([q, down, down[::-1]]))))[q.size:] + np.concatenate([down, down[::-1]]) / c_eff
    later = np.concatenate([v, v_down + 1e-3 * (np.arange(v_down.size) >= down.size)])  # the second rise higher
    again = quant2009.rising_curve(later, np.concatenate([q, down, down[::-1]]))
    np.testing.assert_allclose(again["caps"], caps, rtol=1e-8)


def test_second_order_fit_recovers_gain_frequency_and_damping():
    f = np.linspace(5.0, 500.0, 400)
    s = 2j * np.pi * f
    w = 2 * np.pi * 310.0
    h = 0.45 * w**2 / (s**2 + 2 * 0.03 * w * s + w**2)
    got = quant2009.second_order_fit(f, h * (1 + 0.01 * np.cos(f)))  # 1 % ripple
    assert abs(got["gain"] / 0.45 - 1) < 0.01
    assert abs(got["omega"] / w - 1) < 1e-3
    assert abs(got["zeta"] / 0.03 - 1) < 0.05


def test_padded_bench_records_are_the_unpadded_ones():
    # the experiment runs the bench on commands held up to PAD_SAMPLES samples (one compilation for every length)
    # and cuts the outputs back: to the bit the record and truth of the command itself
    bench = pj.QuantBench()
    command = np.concatenate([np.linspace(0.0, 150.0, 300), np.linspace(150.0, -60.0, 301)])
    key = jax.random.key(7)
    got = quant2009._record(bench, command, key)
    rec = quant2009._bench_record(bench, jnp.asarray(command), key)  # the same compiled functions, unpadded
    truth = quant2009._bench_truth(bench, jnp.asarray(command))
    assert got["x"].shape == (command.size,)
    np.testing.assert_array_equal(got["v_in"], np.asarray(rec.v_in))
    np.testing.assert_array_equal(got["x"], np.asarray(rec.displacement))
    np.testing.assert_array_equal(got["charge"], np.asarray(bench.charge(rec.v_out)))
    for name in ("x", "charge", "v"):
        np.testing.assert_array_equal(got[f"true_{name}"], np.asarray(truth[name]))


@pytest.mark.slow
def test_quant2009_quick(tmp_path):
    out = tmp_path / "q"
    report = quant2009.main(["--quick", "--out", str(out)])
    st, jt, bench = report["staged"], report["joint"], report["bench"]
    # the staged steps find the first resonance (300 Hz) and a coupling factor T^2/(Ck) of the truth's order
    # (its 0.12 against a model whose C also carries the Preisach's small-signal charge): measured 294 Hz, 0.14
    f_r = np.sqrt(st["params"]["k_N_per_m"] / st["params"]["m_kg"]) / (2 * np.pi)
    assert abs(f_r / bench["frequencies_Hz"][0] - 1) < 0.05
    assert 0.08 < st["coupling_factor"] < 0.2
    # the joint fit lowers the cost many times over (measured 7.7 -> 0.18 in the 25 steps of --quick)
    assert jt["cost"] < 0.1 * jt["initial_cost"]
    table = report["validation"]
    assert len(table) == 5
    for name, row in table.items():
        # every validation signal within a few % of range (the staged strain of the zero-centred sine: 8.6 %, its
        # d31(V) measured at positive voltages only), the sines within 1 % RMS after the joint fit
        for way, bound in (("staged", 15.0), ("joint", 3.0)):
            for channel in ("strain", "charge"):
                assert row[way][channel]["rms_percent"] < bound, (name, way, channel)
        if "sine" in name or "triangle" in name:
            assert row["joint"]["strain"]["rms_percent"] < 1.0, name
            assert row["joint"]["charge"]["rms_percent"] < 1.0, name
    # the joint fit beats the staged identification on the strain of every signal but the rectangle (its edges
    # between samples limit both: measured 1.6 and 1.4 %)
    for name, row in table.items():
        if "rectangle" not in name:
            assert row["joint"]["strain"]["rms_percent"] < row["staged"]["strain"]["rms_percent"], name
    # open-loop linearisation on the bench's truth: the whole inverse cuts the plain gain's error 4x or more
    for ref, rows in report["linearisation"].items():
        plain = rows["plain gain"]["max_percent"]
        assert plain > 5.0, ref
        assert rows["joint whole inverse"]["max_percent"] < plain / 4, ref
    # the cantilever: the model with the load's stiffness and mass added predicts the loaded strain far better
    for name in ("1 Hz zero-centred sine", "150 V 10 Hz rectangle"):
        rows = report["load"][name]
        assert rows["model with the load"]["strain"]["rms_percent"] < 4.0  # measured 2.6 and 1.7 %
        assert rows["model ignoring the load"]["strain"]["rms_percent"] > 4 * rows["model with the load"]["strain"][
            "rms_percent"]
    for f in ("report.json", "loops.png", "time_series.png", "inverse.png", "load.png"):
        assert (out / f).stat().st_size > 0, f
