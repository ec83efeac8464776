"""What the plots' axes show: force–displacement as measured, or stress–strain of the specimen.

Stress is force over the specimen's loaded area (width x depth): kPa = N / mm² x 1000;
strain is the displacement as a percentage of the specimen's height. Both need the
specimen's size, which an imported run may not record: then only force–displacement is
offered, and the choice says why.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from PySide6 import QtCore, QtWidgets

from foamlab.rundata import Specimen


@dataclass(frozen=True)
class PlotUnits:
    title: str                    # the force–displacement plot's title
    x: str                        # the displacement axis: name, unit
    x_unit: str
    y: str                        # the force axis (both plots): name, unit
    y_unit: str
    x_per_mm: float = 1.0         # plotted x = displacement_mm * x_per_mm
    y_per_N: float = 1.0          # plotted y = force_N * y_per_N
    # pyqtgraph's automatic k/m prefixes suit N and mm; on kPa and % they would read "kkPa", "m%".
    si_prefix: bool = True


FORCE_DISPLACEMENT = PlotUnits("Force – displacement", "Displacement", "mm", "Force", "N")
CHOICES = ("Force–displacement [N, mm]", "Stress–strain [kPa, %]")


def _known(value: float | None) -> bool:
    return value is not None and math.isfinite(value) and value > 0


def stress_strain_problem(specimen: Specimen | None) -> str:
    """'' when stress–strain can be shown for `specimen`, else why not (one sentence)."""
    names = ("height", "width", "depth")
    values = (None, None, None) if specimen is None else (specimen.height_mm, specimen.width_mm, specimen.depth_mm)
    missing = [name for name, value in zip(names, values) if not _known(value)]
    if not missing:
        return ""
    verb = "is" if len(missing) == 1 else "are"
    return (f"Stress–strain needs the specimen's height and area (width x depth): "
            f"its {' and '.join(missing)} {verb} not known.")


def stress_strain(specimen: Specimen) -> PlotUnits:
    """Stress [kPa] and strain [%] of `specimen` (stress_strain_problem() must be '')."""
    return PlotUnits("Stress – strain", "Strain", "%", "Stress", "kPa",
                     x_per_mm=100.0 / specimen.height_mm, y_per_N=1000.0 / specimen.area_mm2, si_prefix=False)


class UnitsChoice(QtWidgets.QComboBox):
    """The plots' axes: force–displacement, or stress–strain when the specimen's size is known.
    `changed` carries the PlotUnits to show; the operator's choice is kept across runs that
    cannot show stress (it comes back with the next run that can)."""

    changed = QtCore.Signal(object)

    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.setObjectName("units_choice")
        self.addItems(CHOICES)
        self._specimen: Specimen | None = None
        self._wanted = 0                       # the operator's last pick
        self.activated.connect(self._picked)
        self.set_specimen(None)

    def units(self) -> PlotUnits:
        if self.currentIndex() == 1 and self._specimen is not None:
            return stress_strain(self._specimen)
        return FORCE_DISPLACEMENT

    def set_specimen(self, specimen: Specimen | None) -> None:
        """The specimen of the run shown (or about to run); emits `changed`."""
        problem = stress_strain_problem(specimen)
        self._specimen = None if problem else specimen
        self.setEnabled(not problem)
        self.setToolTip(problem or f"Stress = force / {specimen.width_mm:g} x {specimen.depth_mm:g} mm²; "
                                   f"strain = displacement / {specimen.height_mm:g} mm")
        self.setCurrentIndex(0 if problem else self._wanted)
        self.changed.emit(self.units())

    def _picked(self, index: int) -> None:
        self._wanted = index
        self.changed.emit(self.units())
