"""Figures and numbers of docs/findings.md: the diagnosis of the real Bluehill file.

    python scripts/make_findings.py        # writes docs/img/findings_*.png, prints the numbers

Runs `foamlab.diagnosis.diagnose` on tests/data/real/Specimen_RawData_6.csv exactly as
`foamlab diagnose` does, then draws: the measurement, the base model against it, the
residual map, a zoom on the turning points, and the partial cause's evidence.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from foamlab.diagnosis import diagnose  # noqa: E402
from foamlab.diagnosis.report import _fit_figure, _plt, figure_cause, figure_measurement, figure_residual_map  # noqa: E402
from foamlab.importers import load_run  # noqa: E402

DATA = ROOT / "tests" / "data" / "real" / "Specimen_RawData_6.csv"
IMG = ROOT / "docs" / "img"


def turning_zoom(d, path: Path) -> None:
    """Measured and simulated force around each reversal (base, and the best partial cause)."""
    plt = _plt()
    s = d.series[0]
    peaks = list(s.labels.peaks)
    fig, axes = plt.subplots(1, len(peaks), figsize=(4 * len(peaks), 3.6), sharey=False)
    axes = np.atleast_1d(axes)
    other = d.partial[0] if d.partial else (d.findings[0] if d.findings else None)
    for ax, p in zip(axes, peaks):
        sel = (s.t >= s.t[p] - 1.0) & (s.t <= s.t[p] + 2.0)
        ax.plot(s.t[sel] - s.t[p], s.y[sel], "k.", ms=3, label="measured")
        ax.plot(s.t[sel] - s.t[p], d.base.solution.predictions[0][sel], "C0-", label="base model")
        if other is not None:
            ax.plot(s.t[sel] - s.t[p], other.fit.solution.predictions[0][sel], "C3--",
                    label=f"with {other.name}")
        ax.set_xlabel("time after the reversal (s)")
        ax.set_title(f"reversal at {s.t[p]:.1f} s")
    axes[0].set_ylabel("force (N)")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def reversal_evidence(d) -> list[str]:
    """What the data say about the release after each reversal, model aside: how long the
    crosshead takes to turn, how the force falls (backlash would hold it first), and how much
    of the residual power after the reversals the largest finding removes."""
    s = d.series[0]
    t, x, y = s.t, s.x_measured, s.y
    h = float(np.median(np.diff(t)))
    v = np.gradient(x, t)
    speed = float(np.median(np.abs(v[np.abs(v) > 0.5 * np.percentile(np.abs(v), 95)])))
    out = [f"sampling step {1000 * h:.3g} ms, crosshead speed {60 * speed:.3g} mm/min"]
    for p in s.labels.peaks:
        near = np.arange(max(p - 25, 0), min(p + 50, len(t)))
        up = near[(v[near] > 0.9 * speed) & (near <= p)]
        down = near[(v[near] < -0.9 * speed) & (near > p)]
        turn = (t[down[0]] - t[up[-1]]) if len(up) and len(down) else float("nan")
        drops = [y[p] - y[min(p + k, len(y) - 1)] for k in (1, 2, 3, 5, 10, 15, 30)]
        out.append(f"reversal at {t[p]:.2f} s: the crosshead turns from +90 % to -90 % of its speed in "
                   f"{1000 * turn:.0f} ms; the force falls by " +
                   ", ".join(f"{dr:.2f} N at +{1000 * k * h:.0f} ms" for dr, k in zip(drops, (1, 2, 3, 5, 10, 15, 30))))
    shown = d.findings[0] if d.findings else (d.partial[0] if d.partial else None)
    if shown is not None:
        after = np.zeros(len(s), dtype=bool)
        for p in s.labels.peaks:
            after |= (t > t[p]) & (t <= t[p] + 0.6)
        u = s.used

        def power(res):
            return float(res[u & after] @ res[u & after]), float(res[u & ~after] @ res[u & ~after])
        b_after, b_else = power(shown.before.solution.residuals[0])
        e_after, e_else = power(shown.fit.solution.residuals[0])
        out.append(f"residual power (N^2) in the 0.6 s after the reversals: {b_after:.1f} -> {e_after:.1f} "
                   f"with {shown.name} ({1 - e_after / b_after:.0%} removed); elsewhere {b_else:.1f} -> "
                   f"{e_else:.1f} ({1 - e_else / b_else:.0%} removed)")
    return out


def main() -> None:
    IMG.mkdir(parents=True, exist_ok=True)
    run = load_run(DATA)
    d = diagnose([run])
    figure_measurement(d, IMG / "findings_measurement.png")
    _fit_figure(d, d.base, "the paper's model, identified on this run", IMG / "findings_base.png")
    figure_residual_map(d, IMG / "findings_residual_map.png")
    turning_zoom(d, IMG / "findings_turning_points.png")
    shown = d.findings[0] if d.findings else (d.partial[0] if d.partial else None)
    if shown is not None:
        figure_cause(d, shown, IMG / "findings_cause.png")
        _fit_figure(d, shown.fit, f"extended with {shown.name}", IMG / "findings_extended.png")
    print(json.dumps(d.to_dict(), indent=1))
    print("\ncandidates:")
    for i, rnd in enumerate(d.tested):
        for c in sorted(rnd, key=lambda c: -c.delta_bic):
            print(f"  round {i + 1} {c.name:<22} dBIC {c.delta_bic:10.1f}  rmse {c.fit.rmse:.4f}  "
                  f"{c.description()}  [{c.reason}]")
    print(f"\nnoise {d.noise_sigma:.4g} N, base RMSE {d.base.rmse:.4g} N, "
          f"held-out {d.base.heldout_rmse}, {d.seconds:.1f} s")
    print("where:", *d.base_analysis.where(), sep="\n  ")
    print("reversals:", *reversal_evidence(d), sep="\n  ")


if __name__ == "__main__":
    main()
