r"""Figures of a fit: time series with residuals, loops against the drive voltage, parameter uncertainty and
convergence, in engineering units.

Every function returns a `matplotlib.figure.Figure` built without `pyplot` (no global state: safe in scripts,
notebooks display it, `fig.savefig(path)` writes it). Axes carry the channel's name and unit with an SI prefix
chosen from the data (`engineering_scale`: 2.3e-5 m is plotted as 23 µm), never an offset or a ×1e-5 multiplier.
"""

import math
import re
from pathlib import Path

import numpy as np

from piezojax import PiezojaxValueError

from ._data import UNITS

_NAMES = {"t": "time", "v_in": "drive voltage", "v_out": "sensor voltage"}
_DRIVES = {"N": "drive force"}  # what `v_in` holds for a model driven by another quantity than a voltage
_PREFIXES = ((1e-15, 1e15, "f"), (1e-12, 1e12, "p"), (1e-9, 1e9, "n"), (1e-6, 1e6, "µ"), (1e-3, 1e3, "m"),
             (1.0, 1.0, ""), (1e3, 1e-3, "k"), (1e6, 1e-6, "M"), (1e9, 1e-9, "G"))  # (size, factor, prefix)
_STYLE = {"axes.grid": True, "grid.alpha": 0.3, "axes.formatter.useoffset": False, "axes.formatter.limits": (-4, 5),
          "font.size": 9, "legend.fontsize": 8, "lines.linewidth": 1.0}


def engineering_scale(values, unit: str) -> tuple[float, str]:
    r"""The factor and prefixed unit that put the largest $|$`values`$|$ in $[1, 1000)$: `(1e6, "µm")` for
    displacements of tens of micrometres. Units that take no prefix (empty, `"%"`) and all-zero or non-finite data
    get `(1.0, unit)`."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    peak = float(np.max(np.abs(v))) if v.size else 0.0
    if not unit or unit == "%" or peak == 0.0:
        return 1.0, unit
    chosen = _PREFIXES[0]
    for p in _PREFIXES:
        if peak >= p[0] * (1 - 1e-9):
            chosen = p
    return chosen[1], chosen[2] + unit


def channel_label(channel: str, values, what: str | None = None) -> tuple[float, str]:
    """`(factor, "displacement [µm]")`: the scale and axis label of `channel` for `values` (`what` replaces the
    channel's readable name, e.g. "residual"); a channel without a known unit is labelled by its name alone."""
    unit, name = UNITS.get(channel, ""), _NAMES.get(channel, channel)
    factor, scaled = engineering_scale(values, unit)
    name = what or name
    return factor, f"{name} [{scaled}]" if scaled else name


def figure_name(name: str) -> str:
    """A file-name stem from an experiment name: runs of characters other than letters, digits, `.` and `-`
    become one `_`, without leading or trailing `_` (`"piezo full (7)"` → `"piezo_full_7"`)."""
    stem = re.sub(r"[^A-Za-z0-9.-]+", "_", str(name)).strip("_.")
    return stem or "experiment"


def _figure(rows: int, cols: int, size: tuple[float, float], **kw):
    import matplotlib
    from matplotlib.figure import Figure

    with matplotlib.rc_context(_STYLE):
        fig = Figure(figsize=size, layout="constrained")
        axes = fig.subplots(rows, cols, squeeze=False, **kw)
    return fig, axes


def _experiment(result, experiment):
    exps = list(result.dataset or [])
    if not exps:
        raise PiezojaxValueError("the fit result holds no dataset to plot (it was loaded from files?)")
    if isinstance(experiment, str):
        for e in exps:
            if e.name == experiment:
                return e
        raise PiezojaxValueError(f"`experiment`: no experiment named {experiment!r}; the fit's experiments are "
                                 f"{[e.name for e in exps]}")
    if isinstance(experiment, bool) or not isinstance(experiment, (int, np.integer)) or not (
            -len(exps) <= experiment < len(exps)):
        raise PiezojaxValueError(f"`experiment` must be a name or an index below {len(exps)}, got {experiment!r}")
    return exps[int(experiment)]


def _styled(fn):
    import functools

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        import matplotlib

        with matplotlib.rc_context(_STYLE):
            return fn(*args, **kwargs)

    return wrapper


def _readable_ticks(ax) -> None:
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(nbins=6))
    ax.yaxis.set_major_locator(MaxNLocator(nbins=6))


@_styled
def plot_timeseries(result, experiment=0, prediction: dict | None = None):
    """Measured and predicted target channels of one experiment of `result` against time, each with its
    residual (model − measured) below, in engineering units.

    **Arguments:** `result` (a `FitResult`), `experiment` (its index in the fit's dataset or its name),
    `prediction` (the experiment's predicted channels, default `result.predict`).

    **Returns:** a `matplotlib.figure.Figure`.
    """
    exp = _experiment(result, experiment)
    pred = prediction if prediction is not None else result.predict([exp], check_finite=False)[0]
    chans = [c for c in pred if exp.has(c)]
    if not chans:
        raise PiezojaxValueError(f"experiment {exp.name!r} has none of the predicted channels {sorted(pred)}")
    fig, axes = _figure(2 * len(chans), 1, (8, 3.0 * len(chans)), sharex=True,
                        gridspec_kw={"height_ratios": [2, 1] * len(chans)})
    for k, c in enumerate(chans):
        y, yh = np.asarray(exp[c], float), np.asarray(pred[c], float)
        ax, axr = axes[2 * k, 0], axes[2 * k + 1, 0]
        f, label = channel_label(c, y)
        ax.plot(exp.t, f * y, color="0.2", lw=1.4, label="measured")
        ax.plot(exp.t, f * yh, color="C1", label="model")
        ax.set_ylabel(label)
        ax.legend(loc="upper right")
        fr, rlabel = channel_label(c, yh - y, what="residual")
        axr.plot(exp.t, fr * (yh - y), color="C3", lw=0.8)
        axr.set_ylabel(rlabel)
        for a in (ax, axr):
            _readable_ticks(a)
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle(exp.name)
    return fig


@_styled
def plot_loops(result, experiment=0, prediction: dict | None = None, input_unit: str = "V"):
    """Measured and predicted target channels of one experiment against the drive `v_in` (the hysteresis loops),
    one panel per channel, in engineering units. Arguments and return as `plot_timeseries`; `input_unit`: the SI
    unit of what `v_in` holds (`"V"`, or `"N"` for a force-driven model such as the Bouc–Wen oscillator)."""
    if not isinstance(input_unit, str) or not input_unit.strip():
        raise PiezojaxValueError(f"`input_unit` must be a unit name such as 'V' or 'N', got {input_unit!r}")
    exp = _experiment(result, experiment)
    pred = prediction if prediction is not None else result.predict([exp], check_finite=False)[0]
    chans = [c for c in pred if exp.has(c)]
    if not chans:
        raise PiezojaxValueError(f"experiment {exp.name!r} has none of the predicted channels {sorted(pred)}")
    fig, axes = _figure(1, len(chans), (4.2 * len(chans), 3.8))
    if input_unit == "V":
        fv, vlabel = channel_label("v_in", exp.v_in)
    else:
        fv, scaled = engineering_scale(exp.v_in, input_unit)
        vlabel = f"{_DRIVES.get(input_unit, 'drive')} [{scaled}]"
    for k, c in enumerate(chans):
        ax = axes[0, k]
        y = np.asarray(exp[c], float)
        f, label = channel_label(c, y)
        ax.plot(fv * np.asarray(exp.v_in), f * y, color="0.2", lw=1.4, label="measured")
        ax.plot(fv * np.asarray(exp.v_in), f * np.asarray(pred[c], float), color="C1", label="model")
        ax.set(xlabel=vlabel, ylabel=label)
        _readable_ticks(ax)
    axes[0, 0].legend(loc="upper left")
    fig.suptitle(exp.name)
    return fig


@_styled
def plot_parameters(result, max_parameters: int = 40):
    """The free parameters' relative standard errors (%, log scale; "inf", "at bound" or "n/a" where not finite)
    and their correlation matrix, for the first `max_parameters`.

    **Returns:** a `matplotlib.figure.Figure`.
    """
    names = list(result.parameter_names)[:max_parameters]
    n = len(names)
    if n == 0:
        raise PiezojaxValueError("the fit has no free parameters to plot")
    vals = np.asarray(result.values, float)[:n]
    errs = np.asarray(result.std_errors, float)[:n]
    status = list(result.std_error_status)[:n]
    rel = np.where((np.asarray(status) == "finite") & (vals != 0), 100 * errs / np.maximum(np.abs(vals), 1e-300),
                   np.nan)
    fig, axes = _figure(1, 2, (10, 0.2 * n + 1.8), gridspec_kw={"width_ratios": [1, 1]})
    ax, axc = axes[0]
    y = np.arange(n)
    finite = np.isfinite(rel)
    ax.barh(y[finite], rel[finite], color="C0")
    ax.set_xscale("log")
    for i in np.nonzero(~finite)[0]:  # inside the panel, at its left (x in axes units: it had spilled to the right)
        text = {"infinite": "inf", "at a bound": "at bound"}.get(status[i], "n/a")
        ax.text(0.01, i, text, transform=ax.get_yaxis_transform(), va="center", ha="left", fontsize=8, color="C3")
    ax.set_yticks(y, [f"{name} ({i})" for i, name in enumerate(names)], fontsize=7)
    ax.invert_yaxis()
    ax.set(xlabel="standard error [% of value]", title="parameter uncertainty")
    c = np.asarray(result.correlation, float)[:n, :n]
    im = axc.imshow(np.where(np.isfinite(c), c, np.nan), vmin=-1, vmax=1, cmap="RdBu_r")
    step = 1 if n <= 15 else 5  # the parameters by their number in the left panel
    axc.set_xticks(y[::step], [str(i) for i in y[::step]], fontsize=7)
    axc.set_yticks(y[::step], [str(i) for i in y[::step]], fontsize=7)
    axc.grid(False)
    axc.set(title="correlation (parameter numbers)")
    fig.colorbar(im, ax=axc, shrink=0.6, label="correlation [-]")
    return fig


@_styled
def plot_convergence(result):
    """The cost $\\tfrac12\\|r\\|^2$ of each accepted step against the step count (log scale), one marker per
    smoothing level's end. **Returns:** a `matplotlib.figure.Figure`."""
    steps = np.asarray(result.history_steps, float)
    cost = np.asarray(result.history, float)
    if cost.size == 0:
        raise PiezojaxValueError("the fit has no cost history to plot")
    fig, axes = _figure(1, 1, (6, 3.5))
    ax = axes[0, 0]
    ax.semilogy(steps, cost, "-o", ms=2.5, color="C0")
    ax.set(xlabel="step [-]", ylabel="cost ½‖r‖² [-]", title=f"convergence: {result.code}")
    ax.xaxis.get_major_locator().set_params(integer=True)
    return fig


def save_figures(result, folder, max_experiments: int = 8, dpi: int = 110, input_unit: str = "V") -> list[Path]:
    """Write the fit's figures into `folder`: `timeseries_<name>.png` and `loops_<name>.png` for the first
    `max_experiments` experiments (names from `figure_name`, made unique), `parameters.png` and
    `convergence.png`; `input_unit` as in `plot_loops`. **Returns:** the paths written."""
    folder = Path(folder)
    written = []
    exps = list(result.dataset or [])[:max_experiments]
    preds = result.predict(exps, check_finite=False) if exps else []
    used: set[str] = set()
    for i, (exp, pred) in enumerate(zip(exps, preds)):
        if not any(exp.has(c) for c in pred):
            continue
        stem, k = figure_name(exp.name), 1
        while stem in used:
            k += 1
            stem = f"{figure_name(exp.name)}_{k}"
        used.add(stem)
        for kind, fig in (("timeseries", plot_timeseries(result, i, prediction=pred)),
                          ("loops", plot_loops(result, i, prediction=pred, input_unit=input_unit))):
            path = folder / f"{kind}_{stem}.png"
            fig.savefig(path, dpi=dpi)
            written.append(path)
    if len(result.parameter_names) and math.isfinite(result.cost):
        path = folder / "parameters.png"
        plot_parameters(result).savefig(path, dpi=dpi)
        written.append(path)
    if len(result.history):
        path = folder / "convergence.png"
        plot_convergence(result).savefig(path, dpi=dpi)
        written.append(path)
    return written
