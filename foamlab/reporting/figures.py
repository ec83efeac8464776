"""The report's figures as PNG files, drawn by the figures foamlab already has:

- curves: force-displacement per cycle and force-time (as `foamlab show --plot` lays them out);
- fit: `foamlab fit --plot` (measured and fitted per cycle, residuals below);
- diagnosis: `foamlab diagnose --report`'s figure of the named cause, else its residual map;
  for a stored diagnosis (no residual analysis at hand) the residuals of the fit it extended;
- series: the specimens' force-displacement curves over each other.
Each returns the PNG path, or None with the reason in `notes` (a figure never costs the report).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from foamlab import FoamlabError

log = logging.getLogger(__name__)


def _plt():
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    return plt


def _guarded(what: str, notes: list[str], draw, out: Path) -> Path | None:
    try:
        draw(out)
    except (FoamlabError, ValueError, IndexError, KeyError, TypeError) as exc:
        log.debug("%s figure failed", what, exc_info=True)
        notes.append(f"{what} figure not drawn: {exc}")
        return None
    return out if out.is_file() else None


def curves(run, folder: Path, notes: list[str]) -> Path | None:
    return _guarded("curves", notes, lambda out: draw_curves(run, out, notes), folder / "curves.png")


def draw_curves(run, out: Path, notes: list[str] | None = None) -> Path:
    """Force-displacement per cycle (loading solid, unloading dashed) and force-time with the
    displacement on a second axis (the layout of `foamlab show --plot`, without its markers).
    Where the run's labels and its displacement disagree on the cycles, `notes` is told."""
    plt = _plt()
    seg = run.segments()
    if notes is not None:
        notes.extend(n for n in seg.notes if n not in notes)
    fig, (ax_fx, ax_ft) = plt.subplots(1, 2, figsize=(11, 4.0))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for cycle in seg.cycles:
        color = colors[(cycle.number - 1) % len(colors)]
        for half, style in ((cycle.loading, "-"), (cycle.unloading, "--")):
            if half is not None:
                _, x, f = seg.arrays(half)
                ax_fx.plot(x, f, style, color=color, lw=1.0, label=half.label)
    if not seg.cycles:
        ax_fx.plot(run.displacement_mm, run.force_N, lw=1.0)
    ax_fx.set_xlabel("displacement (mm, compression +)")
    ax_fx.set_ylabel("force (N)")
    ax_fx.set_title("force - displacement")
    if seg.cycles:
        ax_fx.legend(fontsize=7, ncol=2)
    ax_fx.grid(alpha=0.3)
    ax_ft.plot(run.time_s, run.force_N, lw=0.8, color="C0")
    ax_ft.set_xlabel("time (s)")
    ax_ft.set_ylabel("force (N)", color="C0")
    ax_ft.set_title("force and displacement in time")
    ax_ft.grid(alpha=0.3)
    ax_x = ax_ft.twinx()
    ax_x.plot(run.time_s, run.displacement_mm, color="C2", lw=0.8, alpha=0.8)
    ax_x.set_ylabel("displacement (mm)", color="C2")
    fig.tight_layout()
    try:
        fig.savefig(out, dpi=110)
    finally:
        plt.close(fig)
    return out


def fit(result, folder: Path, notes: list[str]) -> Path | None:
    from foamlab.identification.plot import plot_fit  # noqa: PLC0415

    return _guarded("fit", notes, lambda out: plot_fit(result, out), folder / "fit.png")


def diagnosis(d, fit_result, verdict: str, folder: Path, notes: list[str]) -> tuple[Path | None, str]:
    """The diagnosis figure and its caption."""
    from foamlab.diagnosis import report  # noqa: PLC0415

    if d is not None and d.findings:
        c = d.findings[0]
        return (_guarded("diagnosis", notes, lambda out: report.figure_cause(d, c, out), folder / "cause.png"),
                f"{c.name}: what its extension adds to the simulation (red) against what the base model "
                "left (grey), in time (left) and over displacement (right).")
    if d is not None:
        return (_guarded("diagnosis", notes, lambda out: report.figure_residual_map(d, out),
                         folder / "residual_map.png"),
                "Where the base model misses: mean residual by cycle, half-cycle and displacement (left) "
                "and in time (right), in standard errors of the noise.")
    if fit_result is None:
        return None, ""
    return (_guarded("diagnosis", notes, lambda out: residuals(fit_result, verdict, out),
                     folder / "residuals.png"),
            "The residuals of the fit the stored diagnosis extended (measured - fitted), over displacement "
            "and in time, with the band of +/- 2 noise standard deviations.")


def residuals(result, verdict: str, out: Path) -> Path:
    """Measured - fitted per cycle over displacement and in time, noise band shaded."""
    plt = _plt()
    labels = result.samples
    obs = np.zeros(len(result.run_force_N), bool)
    obs[result.observed] = True
    r = result.residual_N
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 3.8))
    n_cycles = int(labels.cycle.max()) if len(labels.cycle) else 0
    for k in range(1, n_cycles + 1):
        m = obs & (labels.cycle == k)
        a.plot(result.run_displacement_mm[m], r[m], ".", ms=1.5, label=f"cycle {k}")
        b.plot(result.run_time_s[m], r[m], lw=0.5)
    lim = 1.15 * float(np.nanpercentile(np.abs(r[obs]), 99.5)) if obs.any() else 0.0
    for ax in (a, b):
        if lim > 0:
            ax.set_ylim(-lim, lim)     # 99.5 % of the samples: the largest misfits sit at the turns
        if result.noise_N > 0:
            ax.axhspan(-2 * result.noise_N, 2 * result.noise_N, color="0.85", lw=0)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_ylabel("measured - fitted (N)")
    a.set_xlabel("displacement (mm)")
    b.set_xlabel("time (s)")
    a.legend(fontsize=7, markerscale=4)
    a.set_title(f"verdict: {verdict}")
    b.set_title(f"RMSE {result.rmse:.3g} N (noise {result.noise_N:.3g} N)")
    fig.tight_layout()
    try:
        fig.savefig(out, dpi=110)
    finally:
        plt.close(fig)
    return out


def series_curves(series, out: Path) -> Path:
    """Every specimen's force-displacement curve, one colour each."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(9, 4.2))
    for s in series.specimens:
        ax.plot(s.run.displacement_mm, s.run.force_N, lw=0.7, label=s.label)
    ax.set_xlabel("displacement (mm, compression +)")
    ax.set_ylabel("force (N)")
    ax.set_title(f"{len(series)} specimens, method {series.method.name}")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    try:
        fig.savefig(out, dpi=110)
    finally:
        plt.close(fig)
    return out
