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


if __name__ == "__main__":
    main()
