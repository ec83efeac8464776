"""Plot of a fit: measured and fitted force per cycle, residuals below (matplotlib, Agg)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from foamlab import FoamlabError
from foamlab.identification.result import FitReport


def plot_fit(result: FitReport, out: str | Path, title: str | None = None) -> Path:
    """Write a PNG: one column per cycle, force-displacement on top (measured grey,
    fitted: loading / unloading), measured - fitted below."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    labels = result.samples
    x, f, fit = result.run_displacement_mm, result.run_force_N, result.predicted_force_N
    n_cycles = labels.n_cycles
    observed = np.zeros(len(x), bool)
    observed[result.observed] = True
    fig, axes = plt.subplots(2, n_cycles, figsize=(4.2 * n_cycles, 6.2), squeeze=False,
                             gridspec_kw={"height_ratios": [3, 1.3]}, sharex="col")
    res_lim, res_max = 0.0, 0.0
    for k in range(n_cycles):
        top, bottom = axes[0, k], axes[1, k]
        in_cycle = (labels.cycle == k + 1) & observed
        top.plot(x[in_cycle], f[in_cycle], color="0.65", lw=2.2, label="measured")
        for direction, colour, name in ((1, "C0", "fitted, loading"), (-1, "C3", "fitted, unloading")):
            m = in_cycle & (labels.direction == direction)
            top.plot(np.where(m, x, np.nan), np.where(m, fit, np.nan), color=colour, lw=1.0, label=name)
            r = np.where(m, f - fit, np.nan)
            bottom.plot(np.where(m, x, np.nan), r, color=colour, lw=0.6)
            if np.any(m):
                res_lim = max(res_lim, float(np.nanpercentile(np.abs(r), 99.5)))
                res_max = max(res_max, float(np.nanmax(np.abs(r))))
        bottom.axhline(0.0, color="0.3", lw=0.5)
        top.set_title(f"cycle {k + 1}")
        bottom.set_xlabel("displacement [mm]")
        if k == 0:
            top.set_ylabel("force [N]")
            bottom.set_ylabel("measured - fitted [N]")
            top.legend(loc="upper left", fontsize=8)
    lim = 1.15 * res_lim or 1.0
    for ax in axes[1]:
        ax.set_ylim(-lim, lim)
    if res_max > lim:   # say what the axis leaves out (the largest misfits, at the turning points)
        axes[1, 0].text(0.01, 0.03, f"axis: 99.5 % of samples; max |residual| {res_max:.3g} N",
                        transform=axes[1, 0].transAxes, fontsize=7, color="0.3")
    fig.suptitle(title or (f"{Path(result.source).name if result.source else 'run'}: orders {result.orders}, "
                           f"RMSE {result.rmse:.3g} N, R² {result.statistics['joint'].r2:.5f}"))
    fig.tight_layout()
    try:
        fig.savefig(out, dpi=100)
    except OSError as exc:
        raise FoamlabError(f"{out}: cannot write the plot ({exc.strerror or exc})") from None
    finally:
        plt.close(fig)
    return out
