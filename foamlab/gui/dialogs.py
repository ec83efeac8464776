"""Dialogs that never take the emergency stop away, and Esc as the e-stop everywhere.

A modal dialog (QMessageBox.question, QFileDialog.getOpenFileName, any exec()) runs its
own event loop and blocks input to the main window: while it was open the EMERGENCY STOP
button could not be clicked and Esc only answered the dialog (issue 18). So:

- every question and file chooser of the window is non-modal (show() and a callback), the
  e-stop button stays clickable beside it;
- Esc is caught for the whole application by an event filter, before any widget or
  dialog (modal ones included, e.g. a platform's own message box) sees it, and calls
  the e-stop. Esc therefore never cancels a dialog in this application: it stops the machine.
"""

from __future__ import annotations

import weakref
from pathlib import Path
from typing import Callable

from PySide6 import QtCore, QtGui, QtWidgets

Button = QtWidgets.QMessageBox.StandardButton


class EscapeStops(QtCore.QObject):
    """Application-wide event filter: Esc anywhere calls `stop()` and goes no further."""

    def __init__(self, stop: Callable[[], None], owner: QtWidgets.QWidget) -> None:
        super().__init__(owner)
        self._stop = stop
        self._owner = weakref.ref(owner)

    def eventFilter(self, watched: QtCore.QObject, event: QtCore.QEvent) -> bool:
        kind = event.type()
        if kind not in (QtCore.QEvent.Type.KeyPress, QtCore.QEvent.Type.ShortcutOverride):
            return False
        if not isinstance(event, QtGui.QKeyEvent) or event.key() != QtCore.Qt.Key.Key_Escape:
            return False
        if self._owner() is None:
            return False
        if kind == QtCore.QEvent.Type.KeyPress and not event.isAutoRepeat():
            self._stop()
        event.accept()
        return True          # no dialog, menu or shortcut gets this Esc

    def install(self) -> None:
        QtWidgets.QApplication.instance().installEventFilter(self)

    def remove(self) -> None:
        app = QtWidgets.QApplication.instance()
        if app is not None:
            app.removeEventFilter(self)


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
