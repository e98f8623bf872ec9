"""Figures of a fit: time series with residuals, and loops against the drive voltage."""

from pathlib import Path

import numpy as np


def plot_result(result, folder, max_experiments: int = 8) -> list[Path]:
    """Save `timeseries_<experiment>.png` (measured, predicted, residual per target channel) and
    `loops_<experiment>.png` (channel against `v_in`) for the first `max_experiments` experiments of the fit.

    **Returns:** the paths written.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder = Path(folder)
    exps = list(result.dataset)[:max_experiments]
    preds = result.predict(exps, check_finite=False)
    written = []
    for exp, pred in zip(exps, preds):
        chans = [c for c in pred if exp.has(c)]
        if not chans:
            continue
        safe = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in exp.name)
        fig, axes = plt.subplots(2 * len(chans), 1, figsize=(9, 3.2 * len(chans)), sharex=True, squeeze=False)
        for k, c in enumerate(chans):
            y, yh = np.asarray(exp.channels[c]), pred[c]
            ax, axr = axes[2 * k, 0], axes[2 * k + 1, 0]
            ax.plot(exp.t, y, lw=0.8, label="measured")
            ax.plot(exp.t, yh, lw=0.8, label="model")
            ax.set_ylabel(c)
            ax.legend(loc="upper right", fontsize=8)
            axr.plot(exp.t, yh - y, lw=0.6, color="C3")
            axr.set_ylabel(f"{c} residual")
        axes[-1, 0].set_xlabel("t [s]")
        fig.suptitle(exp.name)
        fig.tight_layout()
        p = folder / f"timeseries_{safe}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        written.append(p)

        fig, axes = plt.subplots(1, len(chans), figsize=(4.5 * len(chans), 4), squeeze=False)
        for k, c in enumerate(chans):
            ax = axes[0, k]
            ax.plot(exp.v_in, exp.channels[c], lw=0.8, label="measured")
            ax.plot(exp.v_in, pred[c], lw=0.8, label="model")
            ax.set_xlabel("v_in [V]")
            ax.set_ylabel(c)
            ax.legend(fontsize=8)
        fig.suptitle(exp.name)
        fig.tight_layout()
        p = folder / f"loops_{safe}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        written.append(p)
    return written
