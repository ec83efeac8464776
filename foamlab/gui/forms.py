"""Input forms of the window: the specimen and the safety limits, with validation.

Numbers are typed into NumberFields: read in the machine's (the desktop's) locale,
checked as they are typed, shown red with the reason when wrong, and never edited (a
QValidator or a QDoubleSpinBox silently drops or reinterprets what it rejects: "-5"
became "5", "72,5" became 725 and was then clamped to the range).

The forms only check and return values; what is allowed for a run (limits inside
the machine profile's, the method's speed under the limit) is decided by the run
engine, which the window asks before it starts anything.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from PySide6 import QtCore, QtWidgets

from foamlab import FoamlabError
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


class NumberField(QtWidgets.QLineEdit):
    """One number with a unit and a range; `value()` is None while the entry is wrong, and
    `problem()` says why in one sentence."""

    def __init__(self, label: str, unit: str, low: float = -math.inf, high: float = math.inf,
                 locale: QtCore.QLocale | None = None) -> None:
        super().__init__()
        self.label, self.unit = label, unit
        self.number_locale = locale or QtCore.QLocale()
        self.low, self.high = low, high
        self.textChanged.connect(self._mark)

    def setRange(self, low: float, high: float) -> None:  # noqa: N802 (Qt's spelling)
        self.low, self.high = low, high
        self.setToolTip(f"{self.label} in {self.unit}, {low:g} to {high:g}")
        self._mark()

    def setValue(self, value: float) -> None:  # noqa: N802
        self.setText(self.as_text(value))

    def as_text(self, value: float) -> str:
        return self.number_locale.toString(float(value), "g", 6)

    def value(self) -> float | None:
        return None if self.problem() else parse_number(self.text(), self.number_locale)

    def problem(self) -> str | None:
        unit = f" {self.unit}" if self.unit else ""
        try:
            v = parse_number(self.text(), self.number_locale)
        except ValueError as exc:
            return f"{self.label} {exc}" + (f" ({self.unit})." if self.unit else ".")
        if not self.low <= v <= self.high:
            return f"{self.label} {self.as_text(v)}{unit} is outside {self.low:g} to {self.high:g}{unit}."
        return None

    def _mark(self) -> None:
        self.setStyleSheet(INVALID_FIELD_STYLE if self.problem() else "")


class SpecimenForm(QtWidgets.QGroupBox):
    """Label, height, width, depth. `specimen()` returns a Specimen or None and shows why."""

    changed = QtCore.Signal()

    def __init__(self, parent: QtWidgets.QWidget | None = None, locale: QtCore.QLocale | None = None) -> None:
        super().__init__("Specimen", parent)
        self.number_locale = locale or QtCore.QLocale()
        form = QtWidgets.QFormLayout(self)
        self.label_edit = QtWidgets.QLineEdit()
        self.label_edit.setPlaceholderText("e.g. PU-foam-01")
        self.label_edit.setMaxLength(MAX_LABEL_CHARS)
        self.label_edit.setObjectName("specimen_label")
        form.addRow("Label", self.label_edit)
        self.edits: dict[str, NumberField] = {}
        for dim in DIMENSIONS:
            edit = NumberField(dim.label, "mm", dim.low_mm, dim.high_mm, self.number_locale)
            edit.setRange(dim.low_mm, dim.high_mm)
            edit.setValue(float(dim.default))
            edit.setObjectName(f"specimen_{dim.key}")
            edit.textChanged.connect(self._on_edit)
            self.edits[dim.key] = edit
            form.addRow(f"{dim.label} [mm]", edit)
        self.label_edit.textChanged.connect(self._on_edit)
        self.message = _message_label("specimen_message")
        form.addRow(self.message)

    def _on_edit(self) -> None:
        # Numbers are checked as they are typed (the reason shows below them); the label's
        # complaint waits for Start (it is empty while being typed).
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
            self.edits[key].setText("" if value is None else self.edits[key].as_text(value))

    def values(self) -> dict[str, float | None]:
        """Each dimension as read (None where the entry is wrong)."""
        return {dim.key: self.edits[dim.key].value() for dim in DIMENSIONS}

    def problems(self, with_label: bool = True) -> list[tuple[QtWidgets.QLineEdit, str]]:
        found: list[tuple[QtWidgets.QLineEdit, str]] = []
        if with_label and not self.label_edit.text().strip():
            found.append((self.label_edit, "Enter a specimen label."))
        for dim in DIMENSIONS:
            problem = self.edits[dim.key].problem()
            if problem:
                found.append((self.edits[dim.key], problem))
        return found

    def specimen(self) -> Specimen | None:
        """The entered specimen, or None after showing what is wrong."""
        problems = self.problems()
        if problems:
            self._mark(problems, prefix="Cannot start: ")
            problems[0][0].setFocus()
            return None
        return Specimen(label=self.label_edit.text().strip(), **self.values())

    def show_error(self, text: str) -> None:
        self.message.setText(text)
        self.message.show()


def _message_label(name: str) -> QtWidgets.QLabel:
    label = QtWidgets.QLabel("")
    label.setObjectName(name)
    label.setStyleSheet(ERROR_STYLE)
    label.setWordWrap(True)
    label.hide()
    return label


class LimitsForm(QtWidgets.QGroupBox):
    """The run's safety limits, to be entered inside the machine profile's bounds."""

    FIELDS = (
        ("force_N", "Force limit", "N"),
        ("travel_upper_mm", "Travel, upper", "mm"),
        ("travel_lower_mm", "Travel, lower", "mm"),
        ("max_speed_mm_min", "Max speed", "mm/min"),
    )

    def __init__(self, parent: QtWidgets.QWidget | None = None, locale: QtCore.QLocale | None = None) -> None:
        super().__init__("Safety limits", parent)
        form = QtWidgets.QFormLayout(self)
        self.fields: dict[str, NumberField] = {}
        for key, label, unit in self.FIELDS:
            field = NumberField(label, unit, locale=locale)
            field.setObjectName(f"limit_{key}")
            field.textChanged.connect(self._on_edit)
            self.fields[key] = field
            form.addRow(f"{label} [{unit}]", field)
        self.message = _message_label("limits_message")
        form.addRow(self.message)
        self.bounds_label = QtWidgets.QLabel("Connect to see the machine's limits.")
        self.bounds_label.setWordWrap(True)
        self.bounds_label.setStyleSheet("color: #555;")
        form.addRow(self.bounds_label)
        self.profile_limits = None
        self.setEnabled(False)

    def set_profile_limits(self, limits) -> None:
        """`limits`: the profile's engine Limits; they bound what can be entered."""
        self.profile_limits = limits
        bounds = {"force_N": (0.1, limits.force_N),
                  "travel_upper_mm": (limits.travel_upper_mm, limits.travel_lower_mm),
                  "travel_lower_mm": (limits.travel_upper_mm, limits.travel_lower_mm),
                  "max_speed_mm_min": (1.0, limits.max_speed_mm_min)}
        for key, (low, high) in bounds.items():
            self.fields[key].setRange(low, high)
            self.fields[key].setValue(high if key != "travel_upper_mm" else low)
        self.bounds_label.setText(
            f"Profile bounds: force <= {limits.force_N:g} N, travel {limits.travel_upper_mm:g} to "
            f"{limits.travel_lower_mm:g} mm, speed <= {limits.max_speed_mm_min:g} mm/min")
        self.setEnabled(True)

    def problems(self) -> list[str]:
        return [p for p in (f.problem() for f in self.fields.values()) if p]

    def _on_edit(self) -> None:
        problems = self.problems() if self.profile_limits is not None else []
        self.message.setText(" ".join(problems))
        self.message.setVisible(bool(problems))

    def values(self) -> dict[str, float]:
        """The limits entered; FoamlabError naming every wrong entry."""
        problems = self.problems()
        if problems:
            raise FoamlabError("safety limits: " + " ".join(problems))
        return {key: self.fields[key].value() for key, _, _ in self.FIELDS}
