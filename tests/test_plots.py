"""Fit figures: engineering units on every axis, readable ticks, file names from experiment names."""

import jax.numpy as jnp
import numpy as np
import pytest
from matplotlib.figure import Figure

import fitting
import piezojax as pj
from fitting import _plots as fitting_plots
from piezojax import PiezojaxValueError


@pytest.fixture(scope="module")
def result():
    # a PI operator in metres per volt (tens of µm) fitted to two triangle records, one with an awkward name
    truth = pj.PrandtlIshlinskii(jnp.array([4e-8, 2e-8, 1e-8]), jnp.array([0.0, 20.0, 60.0]), w0=0.0)
    t = np.arange(400) * 1e-3
    v = 150 * np.abs(((t * 2.5) % 1) * 2 - 1)
    rng = np.random.default_rng(0)
    exps = []
    for name, scale in (("piezo full (7)", 1.0), ("run/2", 0.6)):
        y = np.asarray(truth(jnp.asarray(scale * v)))
        exps.append(fitting.Experiment.from_arrays(v_in=scale * v, dt=1e-3, name=name,
                                                   displacement=y + 2e-9 * rng.standard_normal(y.size)))
    start = pj.constrain(pj.PrandtlIshlinskii(jnp.array([3e-8, 3e-8, 3e-8]), jnp.array([0.0, 20.0, 60.0]), w0=0.0),
                         lambda m: m.weights, pj.Positive)
    return fitting.fit(start, fitting.Dataset(exps), free=["weights"], max_steps=30, progress=False)


def test_engineering_scale_picks_the_prefix():
    assert fitting_plots.engineering_scale([2.3e-5, -1e-6], "m") == (1e6, "µm")
    assert fitting_plots.engineering_scale([0.5], "N") == (1e3, "mN")
    assert fitting_plots.engineering_scale([150.0, -3.0], "V") == (1.0, "V")
    assert fitting_plots.engineering_scale([1.0e-9], "m") == (1e9, "nm")  # exactly 1 nm stays in nm
    assert fitting_plots.engineering_scale([0.0, np.nan], "m") == (1.0, "m")
    assert fitting_plots.engineering_scale([3.0], "") == (1.0, "")
    assert fitting_plots.channel_label("displacement", [4e-6]) == (1e6, "displacement [µm]")
    assert fitting_plots.channel_label("charge", [2e-5], what="residual") == (1e6, "residual [µC]")
    assert fitting_plots.channel_label("v_in", [150.0]) == (1.0, "drive voltage [V]")
    assert fitting_plots.figure_name("piezo full (7)") == "piezo_full_7"
    assert fitting_plots.figure_name("run/2") == "run_2"
    assert fitting_plots.figure_name("(((") == "experiment"


def _labels(fig: Figure) -> list[str]:
    return [a.get_ylabel() for a in fig.axes] + [a.get_xlabel() for a in fig.axes]


def test_figures_carry_units_and_no_offsets(result):
    fig = result.plot("timeseries", experiment="piezo full (7)")
    assert isinstance(fig, Figure)
    fig.canvas.draw()
    ylabels = [a.get_ylabel() for a in fig.axes]
    assert ylabels[0] == "displacement [µm]"
    assert ylabels[1].startswith("residual [") and ylabels[1].endswith("m]")  # nm here: a 2 nm noise
    assert fig.axes[-1].get_xlabel() == "time [s]"
    for ax in fig.axes:  # no "1e-5" multiplier or offset text above an axis
        assert ax.yaxis.get_offset_text().get_text() == ""
        # plotted in µm: the data are of order 1..100, not 1e-5
        ys = np.concatenate([ln.get_ydata() for ln in ax.get_lines()])
        assert np.max(np.abs(ys)) > 0.5
    loops = fitting.plot_loops(result, 1)
    loops.canvas.draw()
    assert loops.axes[0].get_xlabel() == "drive voltage [V]"
    assert loops.axes[0].get_ylabel() == "displacement [µm]"
    assert len(loops.axes[0].get_xticks()) <= 8  # MaxNLocator(6): no crowded ticks on triangle loops
    # a force-driven model (the Bouc–Wen oscillator's v_in holds newtons): its drive is labelled as such
    assert fitting.plot_loops(result, 1, input_unit="N").axes[0].get_xlabel() == "drive force [N]"
    for bad in (3, ""):
        with pytest.raises(PiezojaxValueError, match="`input_unit`"):
            fitting.plot_loops(result, 1, input_unit=bad)
    par = result.plot("parameters")
    par.canvas.draw()
    assert "standard error [% of value]" in _labels(par)
    assert [t.get_text() for t in par.axes[0].get_yticklabels()] == [f"{n} ({i})" for i, n in
                                                                     enumerate(result.parameter_names)]
    # an undetermined parameter's "inf" marker stays inside its panel (it had been drawn past its right edge)
    import dataclasses

    status = ["infinite"] + list(result.std_error_status)[1:]
    odd = fitting.plot_parameters(dataclasses.replace(result, std_error_status=status))
    odd.canvas.draw()
    box = odd.axes[0].get_window_extent()
    marks = [t for t in odd.axes[0].texts if t.get_text() == "inf"]
    assert len(marks) == 1
    mark = marks[0].get_window_extent()
    assert box.x0 <= mark.x0 and mark.x1 <= box.x1
    conv = result.plot("convergence")
    conv.canvas.draw()
    assert conv.axes[0].get_yscale() == "log" and conv.axes[0].get_xlabel() == "step [-]"


def test_save_figures_names_files_after_experiments(result, tmp_path):
    paths = fitting.save_figures(result, tmp_path)
    names = sorted(p.name for p in paths)
    assert names == sorted(["timeseries_piezo_full_7.png", "loops_piezo_full_7.png", "timeseries_run_2.png",
                            "loops_run_2.png", "parameters.png", "convergence.png"])
    for p in paths:
        assert p.stat().st_size > 5000  # a rendered PNG, not an empty file


def test_plot_errors_name_the_argument(result):
    with pytest.raises(PiezojaxValueError, match="no experiment named 'nope'"):
        result.plot("loops", experiment="nope")
    with pytest.raises(PiezojaxValueError, match="`experiment` must be a name or an index below 2"):
        result.plot("timeseries", experiment=5)
    with pytest.raises(PiezojaxValueError, match="`kind` must be"):
        result.plot("histogram")
