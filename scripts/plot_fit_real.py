"""Fit the bundled real Bluehill file and draw docs/img/fit_real.png (docs/identification.md).

Run:  .venv/bin/python scripts/plot_fit_real.py   (prints the fit's summary too)
"""

from __future__ import annotations

from pathlib import Path

from foamlab.identification import fit_run
from foamlab.identification.plot import plot_fit
from foamlab.importers import load_run

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "real" / "Specimen_RawData_6.csv"
OUT = ROOT / "docs" / "img" / "fit_real.png"


def main() -> None:
    result = fit_run(load_run(DATA))
    print(result.summary())
    plot_fit(result, OUT, title=f"{DATA.name} (3D-printed lattice, Bluehill export): orders {result.orders}, "
                                f"RMSE {result.rmse:.3f} N, R² {result.statistics['joint'].r2:.5f}")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
