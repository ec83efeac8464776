"""The diagnosis as a report: an HTML page with PNG figures (matplotlib, Agg).

Figures: the measurement; the base simulation against it; the residual map
(by cycle, half-cycle and displacement); the named cause and its evidence (what
the effect adds, against what the base model left); the extended simulation;
and a gain table (plus every candidate tested, with why it was or was not named).
"""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from foamlab import FoamlabError
from foamlab.analysis.solve import Fit
from foamlab.diagnosis.result import Candidate, Diagnosis

FIGURES = ("measurement", "base_simulation", "residual_map", "cause", "extended_simulation")


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _cycle_colors(n: int):
    plt = _plt()
    cmap = plt.get_cmap("viridis")
    return [cmap(i / max(n - 1, 1)) for i in range(max(n, 1))]


def _loops(ax, d: Diagnosis, forces: list[np.ndarray] | None, label: str, **style) -> None:
    """Force against displacement per run and cycle."""
    for k, s in enumerate(d.series):
        f = s.y if forces is None else forces[k]
        n_c = int(s.cycle.max())
        colors = _cycle_colors(n_c)
        for c in range(1, n_c + 1):
            sel = s.cycle == c
            lab = f"{label}, cycle {c}" if (k == 0 and label) else None
            ax.plot(s.x[sel], f[sel], color=colors[c - 1], label=lab, **style)


def _predictions(fit: Fit) -> list[np.ndarray]:
    return fit.solution.predictions


def figure_measurement(d: Diagnosis, path: Path) -> None:
    plt = _plt()
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    _loops(a, d, None, "measured", lw=0.8)
    a.set_xlabel("displacement (mm)")
    a.set_ylabel("force (N)")
    a.set_title("measurement")
    a.legend(fontsize=7)
    for s in d.series:
        b.plot(s.t, s.y, lw=0.6, label=s.name)
    b.set_xlabel("time (s)")
    b.set_ylabel("force (N)")
    b.set_title(f"force in time (noise sigma {d.noise_sigma:.3g} N, from the data)")
    if len(d.series) > 1:
        b.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _fit_figure(d: Diagnosis, fit: Fit, title: str, path: Path) -> None:
    plt = _plt()
    fig, axes = plt.subplots(2, 2, figsize=(11, 6.5), gridspec_kw={"height_ratios": [2, 1]})
    a, b, c, e = axes[0, 0], axes[0, 1], axes[1, 0], axes[1, 1]
    preds = _predictions(fit)
    _loops(a, d, None, "", lw=0.6, alpha=0.5)
    _loops(a, d, preds, "model", lw=1.2, ls="--")
    a.set_xlabel("displacement (mm)")
    a.set_ylabel("force (N)")
    a.set_title(title)
    a.legend(fontsize=7)
    for s, p in zip(d.series, preds):
        b.plot(s.t, s.y, lw=0.5, color="0.6")
        b.plot(s.t, p, lw=0.9)
    b.set_xlabel("time (s)")
    b.set_ylabel("force (N)")
    b.set_title("measured (grey) and simulated")
    for s, r in zip(d.series, fit.solution.residuals):
        c.plot(s.x, r, ",", alpha=0.5)
        e.plot(s.t, r, lw=0.4)
    for ax in (c, e):
        ax.axhline(0, color="k", lw=0.5)
        ax.set_ylabel("residual (N)")
    c.set_xlabel("displacement (mm)")
    e.set_xlabel("time (s)")
    e.set_title(f"RMSE {fit.rmse:.3g} N (noise {d.noise_sigma:.3g} N)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def figure_residual_map(d: Diagnosis, path: Path) -> None:
    """Mean residual (in standard errors) by cycle/half-cycle row and displacement bin."""
    plt = _plt()
    an = d.base_analysis
    rows = sorted({(r.run, r.cycle, r.direction) for r in an.regions}, key=lambda k: (k[0], k[1], -k[2]))
    if not rows:
        return
    n_bins = max(1, max(sum(1 for r in an.regions if (r.run, r.cycle, r.direction) == k) for k in rows))
    grid = np.full((len(rows), n_bins), np.nan)
    for i, key in enumerate(rows):
        regs = sorted((r for r in an.regions if (r.run, r.cycle, r.direction) == key), key=lambda r: r.x_lo)
        for j, r in enumerate(regs[:n_bins]):
            grid[i, j] = r.score
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 0.45 * len(rows) + 2.2),
                               gridspec_kw={"width_ratios": [3, 2]})
    lim = max(4.0, float(np.nanmax(np.abs(grid))) if np.any(np.isfinite(grid)) else 4.0)
    im = a.imshow(grid, aspect="auto", cmap="RdBu_r", vmin=-lim, vmax=lim)
    a.set_yticks(range(len(rows)))
    a.set_yticklabels([f"{run + ': ' if run else ''}c{c} {'load' if dr == 1 else 'unload' if dr == -1 else 'rest'}"
                       for run, c, dr in rows], fontsize=7)
    a.set_xlabel(f"displacement bin (of {n_bins}, low to high)")
    a.set_title("base model: mean residual by region (standard errors)")
    fig.colorbar(im, ax=a, shrink=0.8)
    for name in dict.fromkeys(tb[0] for tb in an.time_bins):
        tb = [x for x in an.time_bins if x[0] == name]
        b.plot([x[1] for x in tb], [x[3] for x in tb], "o-", ms=3, label=name)
    b.axhline(4, color="r", lw=0.5, ls=":")
    b.axhline(-4, color="r", lw=0.5, ls=":")
    b.set_xlabel("time (s)")
    b.set_ylabel("mean residual (standard errors)")
    b.set_title("base model: residual in time")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def figure_cause(d: Diagnosis, c: Candidate, path: Path) -> None:
    """What the cause adds to the model, against what the base model left unexplained."""
    plt = _plt()
    fit, before = c.fit, c.before
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    for s, rb, pa, pb in zip(d.series, before.solution.residuals, fit.solution.predictions,
                             before.solution.predictions):
        a.plot(s.t, rb, lw=0.4, color="0.6")
        a.plot(s.t, pa - pb, lw=1.0, color="C3")
        b.plot(s.x, rb, ",", color="0.6", alpha=0.6)
        b.plot(s.x, pa - pb, ".", ms=1, color="C3")
    a.set_xlabel("time (s)")
    a.set_ylabel("force (N)")
    a.set_title(f"{c.name}: what it adds (red) vs what was left (grey)")
    b.set_xlabel("displacement (mm)")
    b.set_title(c.description())
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_report(d: Diagnosis, folder: str | Path, title: str = "") -> Path:
    """Write index.html and its figures into folder; returns the HTML path."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise FoamlabError(f"{folder}: cannot create the report folder ({exc.strerror or exc})") from None
    figs = {}
    figure_measurement(d, folder / "measurement.png")
    figs["measurement"] = "measurement.png"
    _fit_figure(d, d.base, "base model (the paper's) vs measured", folder / "base_simulation.png")
    figs["base_simulation"] = "base_simulation.png"
    figure_residual_map(d, folder / "residual_map.png")
    figs["residual_map"] = "residual_map.png"
    if d.findings:
        figure_cause(d, d.findings[0], folder / "cause.png")
        figs["cause"] = "cause.png"
        _fit_figure(d, d.final, "extended model vs measured", folder / "extended_simulation.png")
        figs["extended_simulation"] = "extended_simulation.png"
    page = folder / "index.html"
    page.write_text(_html(d, figs, title), encoding="utf-8")
    return page


def _fmt(v) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.4g}" if np.isfinite(v) else "–"
    return html.escape(str(v))


def _html(d: Diagnosis, figs: dict[str, str], title: str) -> str:
    e = html.escape
    out = ["<!doctype html><html><head><meta charset='utf-8'>",
           f"<title>foamlab diagnosis {e(title)}</title>",
           "<style>body{font-family:sans-serif;max-width:1150px;margin:auto;padding:1em}"
           "table{border-collapse:collapse;margin:0.5em 0}td,th{border:1px solid #ccc;padding:3px 8px;"
           "font-size:90%}th{background:#eee}img{max-width:100%}.v{font-size:140%;font-weight:bold}</style>",
           "</head><body>",
           f"<h1>Diagnosis{': ' + e(title) if title else ''}</h1>",
           f"<p class='v'>verdict: {e(d.verdict)}</p>"]
    runs = ", ".join(f"{e(s.name)} ({len(s)} samples, {s.speed_mm_min:.3g} mm/min)" for s in d.series)
    out.append(f"<p>runs: {runs}. Noise level from the data: {d.noise_sigma:.3g} N. "
               f"Base model RMSE {d.base.rmse:.3g} N. Diagnosis took {d.seconds:.1f} s.</p>")
    if d.findings:
        c = d.findings[0]
        out.append(f"<p><b>{e(c.name)}</b>: {e(c.cause.meaning)}. Fitted: {e(c.description())}. "
                   f"Signature: {e(c.cause.signature)}.</p>")
    elif d.verdict == "none":
        out.append("<p>The base model explains the data down to the noise: its residuals are white "
                   f"(Ljung-Box p = {d.base_analysis.whiteness.ljung_box_p:.3g}, runs test p = "
                   f"{d.base_analysis.whiteness.runs_p:.3g}) and no candidate cause passes.</p>")
    else:
        out.append("<p>The residuals have structure that no candidate cause explains. Where:</p><ul>")
        out += [f"<li>{e(w)}</li>" for w in d.final_analysis.where()] + ["</ul>"]
    out.append("<h2>Gain</h2><table><tr><th>finding</th><th>RMSE before</th><th>RMSE after</th>"
               "<th>held-out RMSE before</th><th>held-out RMSE after</th><th>ΔBIC</th><th>p</th></tr>")
    for c in d.findings:
        g = c.gain()
        out.append(f"<tr><td>{e(c.name)}</td>" + "".join(
            f"<td>{_fmt(g[k])}</td>" for k in ("rmse_before", "rmse_after", "heldout_rmse_before",
                                              "heldout_rmse_after", "delta_bic")) + f"<td>{_fmt(c.lr_p)}</td></tr>")
    if not d.findings:
        out.append("<tr><td colspan=7>no extension passed</td></tr>")
    out.append("</table>")
    captions = {
        "measurement": "The measurement.",
        "base_simulation": "The base model (the paper's, identified on this data) simulated against the measurement, and its residuals.",
        "residual_map": "Where the base model misses: mean residual by cycle, half-cycle and displacement (left), and in time (right), in standard errors of the noise.",
        "cause": "The named cause: what its extension adds to the simulation (red) against what the base model left (grey).",
        "extended_simulation": "The extended model simulated against the measurement, and its residuals.",
    }
    for key in FIGURES:
        if key in figs:
            out.append(f"<h2>{e(key.replace('_', ' '))}</h2><p>{e(captions[key])}</p><img src='{figs[key]}'>")
    out.append(f"<h2>Where the base model misses</h2><p>{e(d.base_analysis.miss().sentence().capitalize())}.</p><ul>")
    out += [f"<li>{e(w)}</li>" for w in d.base_analysis.where()] or ["<li>nowhere above 4 standard errors</li>"]
    out.append("</ul>")
    if d.limits:
        out.append("<h2>What this run could have seen</h2><p>The smallest size of each cause the diagnosis "
                   "names in 90 % of runs like this one (from the information the run holds at the base fit):</p><ul>")
        out += [f"<li>{e(limit.text)}</li>" for limit in d.limits] + ["</ul>"]
    out.append("<h2>Every candidate tested</h2><table><tr><th>round</th><th>cause</th><th>ΔBIC</th>"
               "<th>fitted</th><th>named</th><th>why not</th></tr>")
    for i, rnd in enumerate(d.tested):
        for c in sorted(rnd, key=lambda c: -c.delta_bic):
            out.append(f"<tr><td>{i + 1}</td><td>{e(c.name)}</td><td>{_fmt(c.delta_bic)}</td>"
                       f"<td>{e(c.description())}</td><td>{'yes' if c in d.findings else ''}</td>"
                       f"<td>{e(c.reason)}</td></tr>")
    for name, why in d.skipped.items():
        out.append(f"<tr><td></td><td>{e(name)}</td><td></td><td></td><td></td><td>{e(why)}</td></tr>")
    out.append("</table></body></html>")
    return "\n".join(out)
