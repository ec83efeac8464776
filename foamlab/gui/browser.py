"""Browser of past runs, read from the run catalog (foamlab.storage.catalog)."""

from __future__ import annotations

import importlib.util
import logging
from pathlib import Path

from PySide6 import QtCore, QtWidgets

from foamlab.gui.background import BackgroundQueue

log = logging.getLogger(__name__)

COLUMNS = ["started", "specimen", "method", "status", "samples", "fit RMSE [N]", "verdict", "file"]


def catalog_rows(out_dir: Path) -> list[dict]:
    """Runs known to the catalog of `out_dir`, newest first, as plain dicts (COLUMNS keys)."""
    if importlib.util.find_spec("foamlab.storage.catalog") is None:
        raise LookupError("the run catalog is not available in this installation")
    from foamlab.storage.catalog import Catalog

    catalog = Catalog.for_folder(out_dir)
    try:
        return [catalog_row(run) for run in catalog.runs()]
    finally:
        catalog.close()


def catalog_row(entry) -> dict:
    get = entry.get if isinstance(entry, dict) else (lambda k, d=None: getattr(entry, k, d))
    return {
        "started": (get("started_at", "") or "").replace("T", " ")[:19],
        "specimen": get("specimen_label", "") or get("specimen", "") or "",
        "method": get("method", "") or "",
        "status": get("status", "") or "",
        "samples": get("n_samples", "") or "",
        "fit RMSE [N]": f"{get('rmse'):.3g}" if isinstance(get("rmse"), (int, float)) else "",
        "verdict": get("verdict", "") or "",
        "file": str(get("path", "") or ""),
    }


class RunBrowser(QtWidgets.QWidget):
    open_requested = QtCore.Signal(str)

    def __init__(self, out_dir: Path, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.out_dir = Path(out_dir)
        # Syncing the catalog reads new run files: off the GUI thread.
        self.queue = BackgroundQueue("foamlab-catalog", self)
        layout = QtWidgets.QVBoxLayout(self)
        bar = QtWidgets.QHBoxLayout()
        self.where = QtWidgets.QLabel("")
        self.refresh_button = QtWidgets.QPushButton("Refresh")
        self.open_button = QtWidgets.QPushButton("Open selected")
        bar.addWidget(self.where, 1)
        bar.addWidget(self.refresh_button)
        bar.addWidget(self.open_button)
        layout.addLayout(bar)
        self.table = QtWidgets.QTableWidget(0, len(COLUMNS))
        self.table.setObjectName("run_table")
        self.table.setHorizontalHeaderLabels(COLUMNS)
        self.table.setSelectionBehavior(QtWidgets.QAbstractItemView.SelectionBehavior.SelectRows)
        self.table.setSelectionMode(QtWidgets.QAbstractItemView.SelectionMode.SingleSelection)
        self.table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.verticalHeader().setVisible(False)
        self.table.horizontalHeader().setStretchLastSection(True)
        self.table.setSortingEnabled(True)
        layout.addWidget(self.table, 1)
        self.message = QtWidgets.QLabel("")
        self.message.setWordWrap(True)
        layout.addWidget(self.message)
        self.refresh_button.clicked.connect(self.refresh)
        self.open_button.clicked.connect(self._open_selected)
        self.table.cellDoubleClicked.connect(lambda row, _col: self._open_row(row))
        self.rows: list[dict] = []
        self.refresh()

    def refresh(self) -> None:
        self.where.setText(f"Runs in {self.out_dir.resolve()}")
        self.message.setText("Reading the catalog…")
        self.queue.submit(lambda: catalog_rows(self.out_dir), self._show_rows, self._show_error)

    def _show_error(self, message: str) -> None:
        self.message.setText(f"Catalog unavailable: {message}")

    def _show_rows(self, rows: list[dict]) -> None:
        self.rows = rows
        self.message.setText(f"{len(rows)} runs. Double-click one to open it." if rows else "No runs yet.")
        self.table.setSortingEnabled(False)
        self.table.setRowCount(len(self.rows))
        for r, row in enumerate(self.rows):
            for c, key in enumerate(COLUMNS):
                item = QtWidgets.QTableWidgetItem(str(row.get(key, "")))
                item.setData(QtCore.Qt.ItemDataRole.UserRole, row["file"])
                self.table.setItem(r, c, item)
        self.table.setSortingEnabled(True)
        self.table.resizeColumnsToContents()

    def _open_selected(self) -> None:
        rows = self.table.selectionModel().selectedRows()
        if rows:
            self._open_row(rows[0].row())

    def _open_row(self, row: int) -> None:
        item = self.table.item(row, 0)
        path = item.data(QtCore.Qt.ItemDataRole.UserRole) if item else ""
        if path:
            self.open_requested.emit(path)
