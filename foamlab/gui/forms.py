"""Input forms of the window: the specimen and the safety limits, with validation.

The forms only check and return values; what is allowed for a run (limits inside
the machine profile's, the method's speed under the limit) is decided by the run
engine, which the window asks before it starts anything.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from PySide6 import QtCore, QtWidgets

from foamlab.rundata import Specimen

ERROR_STYLE = "color: #B00020;"
INVALID_FIELD_STYLE = "QLineEdit { border: 1px solid #B00020; }"


@dataclass(frozen=True)
class DimensionField:
    key: str
    label: str
    low_mm: float
    high_mm: float
    default: str


# Plausible foam block sizes: a millimetre to a metre; the paper's block is 100 x 100 x 72.5 mm.
DIMENSIONS = (
    DimensionField("height_mm", "Height", 1.0, 1000.0, "72.5"),
    DimensionField("width_mm", "Width", 1.0, 2000.0, "100"),
    DimensionField("depth_mm", "Depth", 1.0, 2000.0, "100"),
)
MAX_LABEL_CHARS = 80

_NUMBER = re.compile(r"^[+-]?(\d+([.,]\d*)?|[.,]\d+)$")


def parse_number(text: str, locale: QtCore.QLocale) -> float:
    """The number typed, read in `locale`; ValueError with a plain reason when it is not one.

    The locale's decimal separator is read as such, and so is the other of '.' and ','
    when it cannot be a thousands separator (72,5 is 72.5 everywhere). A thousands
    separator followed by three digits (72,500 where ',' groups) is refused as
    ambiguous, never guessed; grouping is not accepted at all.
    """
    t = text.strip()
    if not t:
        raise ValueError("is missing")
    if not _NUMBER.match(t):
        raise ValueError(f"'{t}' is not a number")
    decimal, group = locale.decimalPoint(), locale.groupSeparator()
    sep = next((c for c in t if c in ".,"), None)
    if sep is not None and sep != decimal and sep == group and len(t) - t.index(sep) - 1 == 3:
        raise ValueError(f"'{t}' is ambiguous ('{sep}' also separates thousands): "
                         f"write the decimals after '{decimal}'")
    return float(t.replace(",", "."))


class SpecimenForm(QtWidgets.QGroupBox):
    """Label, height, width, depth. `specimen()` returns a Specimen or None and shows why."""

    changed = QtCore.Signal()

    def __init__(self, parent: QtWidgets.QWidget | None = None, locale: QtCore.QLocale | None = None) -> None:
        super().__init__("Specimen", parent)
        # The machine's (the desktop's) locale; numbers are never edited as they are typed
        # (a QValidator silently drops what it rejects: "-5" became "5", "72,5" became "725").
        self.number_locale = locale or QtCore.QLocale()
        form = QtWidgets.QFormLayout(self)
        self.label_edit = QtWidgets.QLineEdit()
        self.label_edit.setPlaceholderText("e.g. PU-foam-01")
        self.label_edit.setMaxLength(MAX_LABEL_CHARS)
        self.label_edit.setObjectName("specimen_label")
        form.addRow("Label", self.label_edit)
        self.edits: dict[str, QtWidgets.QLineEdit] = {}
        for dim in DIMENSIONS:
            edit = QtWidgets.QLineEdit(self._show_number(float(dim.default)))
            edit.setObjectName(f"specimen_{dim.key}")
            edit.setToolTip(f"{dim.label} in mm, {dim.low_mm:g} to {dim.high_mm:g}")
            edit.textChanged.connect(self._on_edit)
            self.edits[dim.key] = edit
            form.addRow(f"{dim.label} [mm]", edit)
        self.label_edit.textChanged.connect(self._on_edit)
        self.message = QtWidgets.QLabel("")
        self.message.setObjectName("specimen_message")
        self.message.setStyleSheet(ERROR_STYLE)
        self.message.setWordWrap(True)
        self.message.hide()
        form.addRow(self.message)

    def _show_number(self, value: float) -> str:
        return self.number_locale.toString(float(value), "g", 6)

    def _on_edit(self) -> None:
        # Numbers are checked as they are typed: a wrong one turns red with the reason below,
        # as typed (never repaired); the label's complaint waits for Start (empty while typing).
        self._mark(self.problems(with_label=False), prefix="")
        self.changed.emit()

    def _mark(self, problems: list[tuple[QtWidgets.QLineEdit, str]], prefix: str) -> None:
        bad = {id(edit) for edit, _ in problems}
        for edit in (self.label_edit, *self.edits.values()):
            edit.setStyleSheet(INVALID_FIELD_STYLE if id(edit) in bad else "")
        self.message.setText(prefix + " ".join(text for _, text in problems))
        self.message.setVisible(bool(problems))

    def set_values(self, label: str, height_mm: float | None, width_mm: float | None,
                   depth_mm: float | None) -> None:
        """Show a specimen (None: not known, the field is left empty)."""
        self.label_edit.setText(label)
        for key, value in (("height_mm", height_mm), ("width_mm", width_mm), ("depth_mm", depth_mm)):
            self.edits[key].setText("" if value is None else self._show_number(value))

    def values(self) -> dict[str, float | None]:
        """Each dimension as read (None where the entry is not a number)."""
        out: dict[str, float | None] = {}
        for dim in DIMENSIONS:
            try:
                out[dim.key] = parse_number(self.edits[dim.key].text(), self.number_locale)
            except ValueError:
                out[dim.key] = None
        return out

    def problems(self, with_label: bool = True) -> list[tuple[QtWidgets.QLineEdit, str]]:
        found = []
        if with_label and not self.label_edit.text().strip():
            found.append((self.label_edit, "Enter a specimen label."))
        for dim in DIMENSIONS:
            edit = self.edits[dim.key]
            try:
                value = parse_number(edit.text(), self.number_locale)
            except ValueError as exc:
                found.append((edit, f"{dim.label} {exc} (mm)."))
                continue
            if not dim.low_mm <= value <= dim.high_mm:
                found.append((edit, f"{dim.label} {self._show_number(value)} mm is outside "
                                    f"{dim.low_mm:g} to {dim.high_mm:g} mm."))
        return found

    def specimen(self) -> Specimen | None:
        """The entered specimen, or None after showing what is wrong."""
        problems = self.problems()
        if problems:
            self._mark(problems, prefix="Cannot start: ")
            problems[0][0].setFocus()
            return None
        values = self.values()
        return Specimen(label=self.label_edit.text().strip(), **values)

    def show_error(self, text: str) -> None:
        self.message.setText(text)
        self.message.show()


class LimitsForm(QtWidgets.QGroupBox):
    """The run's safety limits, editable only inside the machine profile's bounds."""

    FIELDS = (
        ("force_N", "Force limit [N]", 1),
        ("travel_upper_mm", "Travel, upper [mm]", 2),
        ("travel_lower_mm", "Travel, lower [mm]", 2),
        ("max_speed_mm_min", "Max speed [mm/min]", 1),
    )

    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__("Safety limits", parent)
        form = QtWidgets.QFormLayout(self)
        self.spins: dict[str, QtWidgets.QDoubleSpinBox] = {}
        for key, label, decimals in self.FIELDS:
            spin = QtWidgets.QDoubleSpinBox()
            spin.setDecimals(decimals)
            spin.setKeyboardTracking(False)
            spin.setObjectName(f"limit_{key}")
            spin.setLocale(QtCore.QLocale.c())
            self.spins[key] = spin
            form.addRow(label, spin)
        self.bounds_label = QtWidgets.QLabel("Connect to see the machine's limits.")
        self.bounds_label.setWordWrap(True)
        self.bounds_label.setStyleSheet("color: #555;")
        form.addRow(self.bounds_label)
        self.profile_limits = None
        self.setEnabled(False)

    def set_profile_limits(self, limits) -> None:
        """`limits`: the profile's engine Limits; they bound what can be entered."""
        self.profile_limits = limits
        force, upper, lower, speed = (self.spins[k] for k, _, _ in self.FIELDS)
        force.setRange(0.1, limits.force_N)
        upper.setRange(limits.travel_upper_mm, limits.travel_lower_mm)
        lower.setRange(limits.travel_upper_mm, limits.travel_lower_mm)
        speed.setRange(1.0, limits.max_speed_mm_min)
        force.setValue(limits.force_N)
        upper.setValue(limits.travel_upper_mm)
        lower.setValue(limits.travel_lower_mm)
        speed.setValue(limits.max_speed_mm_min)
        self.bounds_label.setText(
            f"Profile bounds: force <= {limits.force_N:g} N, travel {limits.travel_upper_mm:g} to "
            f"{limits.travel_lower_mm:g} mm, speed <= {limits.max_speed_mm_min:g} mm/min")
        self.setEnabled(True)

    def values(self) -> dict[str, float]:
        return {key: self.spins[key].value() for key, _, _ in self.FIELDS}
