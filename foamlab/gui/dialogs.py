"""Dialogs that never take the emergency stop away, and Esc as the e-stop everywhere.

A modal dialog (QMessageBox.question, QFileDialog.getOpenFileName, any exec()) runs its
own event loop and blocks input to the main window: while it was open the EMERGENCY STOP
button could not be clicked and Esc only answered the dialog (issue 18). So:

- every question and file chooser of the window is non-modal (show() and a callback), the
  e-stop button stays clickable beside it;
- Esc is an application-wide shortcut for the e-stop, matched before the focused
  widget's own key handling (a dialog's reject): Esc never cancels a dialog here, it
  stops the machine. (A popup list open inside a dialog, e.g. a completer, would take
  that one Esc for itself; the e-stop button stays clickable.)
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from PySide6 import QtCore, QtGui, QtWidgets

Button = QtWidgets.QMessageBox.StandardButton


class EscapeStops(QtCore.QObject):
    """Esc calls `stop()` from any window of the application that has the focus.

    An application-wide shortcut, not an event filter: a Python filter on QApplication
    runs Python for every event of the program, and measured here it deadlocked with
    PySide's deferred deletion of a closed window (the GIL against a QObject mutex).
    A shortcut is matched in C++ and only calls Python when Esc is pressed. It is
    taken before a dialog's own Esc (reject); modal dialogs would shadow it, and this
    window opens none."""

    def __init__(self, stop: Callable[[], None], owner: QtWidgets.QWidget) -> None:
        super().__init__(owner)
        self.shortcut = QtGui.QShortcut(QtGui.QKeySequence(QtCore.Qt.Key.Key_Escape), owner)
        self.shortcut.setContext(QtCore.Qt.ShortcutContext.ApplicationShortcut)
        self.shortcut.setAutoRepeat(False)
        self.shortcut.activated.connect(stop)

    def remove(self) -> None:
        self.shortcut.setEnabled(False)


def ask(parent: QtWidgets.QWidget, title: str, text: str, on_yes: Callable[[], None],
        name: str = "question") -> QtWidgets.QMessageBox:
    """A non-modal Yes/No question (No is the default); `on_yes()` runs if Yes is clicked."""
    box = QtWidgets.QMessageBox(QtWidgets.QMessageBox.Icon.Question, title, text,
                                Button.Yes | Button.No, parent)
    box.setObjectName(name)
    box.setDefaultButton(Button.No)
    box.setWindowModality(QtCore.Qt.WindowModality.NonModal)
    box.setAttribute(QtCore.Qt.WidgetAttribute.WA_DeleteOnClose)

    def clicked(button: QtWidgets.QAbstractButton) -> None:
        if box.standardButton(button) == Button.Yes:
            on_yes()

    box.buttonClicked.connect(clicked)
    box.show()
    return box


def choose_file(parent: QtWidgets.QWidget, caption: str, start: str | Path, filters: str,
                on_chosen: Callable[[str], None], save: bool = False) -> QtWidgets.QFileDialog:
    """A non-modal file chooser; `on_chosen(path)` when a file is picked (not on cancel).

    Qt's own dialog, not the platform's: a native one may be modal for the whole desktop
    session and its key presses never reach the application's Esc filter. Saving over an
    existing file is asked with a non-modal question too (Qt's own prompt is modal)."""
    dialog = QtWidgets.QFileDialog(parent, caption, str(start), filters)
    dialog.setObjectName("save_dialog" if save else "open_dialog")
    dialog.setOption(QtWidgets.QFileDialog.Option.DontUseNativeDialog, True)
    dialog.setOption(QtWidgets.QFileDialog.Option.DontConfirmOverwrite, True)
    dialog.setAcceptMode(QtWidgets.QFileDialog.AcceptMode.AcceptSave if save
                         else QtWidgets.QFileDialog.AcceptMode.AcceptOpen)
    dialog.setFileMode(QtWidgets.QFileDialog.FileMode.AnyFile if save
                       else QtWidgets.QFileDialog.FileMode.ExistingFile)
    dialog.setWindowModality(QtCore.Qt.WindowModality.NonModal)
    dialog.setAttribute(QtCore.Qt.WidgetAttribute.WA_DeleteOnClose)

    def chosen(path: str) -> None:
        if save and Path(path).exists():
            ask(parent, caption, f"{path} exists. Replace it?", lambda: on_chosen(path), name="replace_question")
        else:
            on_chosen(path)

    dialog.fileSelected.connect(chosen)
    dialog.show()
    return dialog


class DialogSlot:
    """The window's one open question or file chooser: a new one replaces the one open,
    and closing the window closes it."""

    def __init__(self) -> None:
        self.dialog: QtWidgets.QDialog | None = None

    def show(self, dialog: QtWidgets.QDialog) -> None:
        self.close()
        self.dialog = dialog
        dialog.destroyed.connect(lambda *_: self._gone(dialog))

    def close(self) -> None:
        dialog, self.dialog = self.dialog, None
        if dialog is not None:
            try:
                dialog.close()
            except RuntimeError:      # already deleted by Qt (closed by its own buttons)
                pass

    def _gone(self, dialog: QtWidgets.QDialog) -> None:
        if self.dialog is dialog:
            self.dialog = None
