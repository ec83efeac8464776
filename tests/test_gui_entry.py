"""Issue 18, number entry: what is typed stays as typed; numbers are read in the machine's
locale (a decimal comma too), wrong ones are shown red with the reason, never repaired."""

from __future__ import annotations

import os

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import pytest
from PySide6 import QtCore

from foamlab.gui.forms import INVALID_FIELD_STYLE, SpecimenForm, parse_number

pytestmark = [pytest.mark.gui, pytest.mark.timeout(60)]

ENGLISH = QtCore.QLocale(QtCore.QLocale.Language.English, QtCore.QLocale.Country.UnitedStates)
GERMAN = QtCore.QLocale(QtCore.QLocale.Language.German, QtCore.QLocale.Country.Germany)


@pytest.mark.parametrize("locale, text, value", [
    (ENGLISH, "72.5", 72.5), (ENGLISH, "72,5", 72.5), (GERMAN, "72,5", 72.5), (GERMAN, "72.5", 72.5),
    (ENGLISH, " 100 ", 100.0), (ENGLISH, "-5", -5.0), (GERMAN, ",5", 0.5), (ENGLISH, "1,000", None),
    (GERMAN, "1.000", None), (ENGLISH, "7 2", None), (ENGLISH, "72.5.1", None), (ENGLISH, "abc", None),
    (ENGLISH, "", None), (ENGLISH, "1e3", None),
])
def test_numbers_are_read_in_the_locale_or_refused(locale, text, value):
    if value is None:
        with pytest.raises(ValueError):
            parse_number(text, locale)
    else:
        assert parse_number(text, locale) == value


@pytest.fixture(params=[ENGLISH, GERMAN], ids=["en_US", "de_DE"])
def form(qtbot, request):
    f = SpecimenForm(locale=request.param)
    qtbot.addWidget(f)
    f.show()
    f.label_edit.setText("s1")
    return f


def type_into(qtbot, edit, text):
    edit.clear()
    qtbot.keyClicks(edit, text)


def test_a_negative_height_stays_negative_and_is_shown_invalid(qtbot, form):
    height = form.edits["height_mm"]
    type_into(qtbot, height, "-5")
    assert height.text() == "-5"                       # not "5": nothing typed is dropped
    assert height.styleSheet() == INVALID_FIELD_STYLE
    assert form.message.isVisible() and "Height -5 mm is outside 1 to 1000 mm" in form.message.text()
    assert form.specimen() is None
    assert form.message.text().startswith("Cannot start")


def test_a_decimal_comma_is_read_as_decimals_never_as_725(qtbot, form):
    height = form.edits["height_mm"]
    type_into(qtbot, height, "72,5")
    assert height.text() == "72,5"
    assert height.styleSheet() == "" and not form.message.isVisible()
    assert form.specimen().height_mm == 72.5


def test_an_ambiguous_thousands_separator_is_shown_not_guessed(qtbot, form):
    group = form.number_locale.groupSeparator()
    height = form.edits["height_mm"]
    type_into(qtbot, height, f"72{group}500")
    assert height.styleSheet() == INVALID_FIELD_STYLE
    assert "ambiguous" in form.message.text()
    assert form.specimen() is None
    type_into(qtbot, height, "72")                      # corrected: the complaint goes
    assert not form.message.isVisible() and form.specimen().height_mm == 72.0


def test_limits_are_read_as_typed_never_725(qtbot):
    from foamlab.acquisition import Limits
    from foamlab.gui.forms import LimitsForm

    limits = LimitsForm(locale=ENGLISH)
    qtbot.addWidget(limits)
    limits.set_profile_limits(Limits(450.0, -20.0, 70.0, 500.0))
    lower = limits.fields["travel_lower_mm"]
    type_into(qtbot, lower, "72,5")
    assert lower.text() == "72,5" and lower.value() is None      # 72.5: beyond the 70 mm bound
    assert "Travel, lower 72.5 mm is outside -20 to 70 mm." in limits.message.text()
    type_into(qtbot, lower, "65,5")
    assert lower.value() == 65.5 and limits.values()["travel_lower_mm"] == 65.5
