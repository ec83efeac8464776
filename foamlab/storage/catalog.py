"""The run catalog: an SQLite index (stdlib sqlite3, WAL) of runs, fits and diagnoses.

The files are the truth; the catalog is only an index and can always be rebuilt
from them (``Catalog.rebuild(folder)``):
- runs: the foamlab run files (``*.csv`` whose first line is ``# foamlab run file``);
- fits: ``<run stem>.fit.json`` beside a run (written by identification; its
  top-level ``rmse`` is indexed);
- diagnoses: ``<run stem>.diagnosis.json`` beside a run (its ``verdict`` is indexed).
``sidecar_path(run, "fit")`` is the one definition of those names.

Default location: ``<data dir>/catalog.sqlite``; the data dir is $FOAMLAB_DATA,
or ``~/foamlab-data``.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

from foamlab import FoamlabError
from foamlab.rundata import RunData
from foamlab.runformat import is_run_file_path

CATALOG_NAME = "catalog.sqlite"
SIDECAR_KINDS = ("fit", "diagnosis")
SCHEMA_VERSION = 1

_SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    id          INTEGER PRIMARY KEY,
    path        TEXT NOT NULL UNIQUE,
    started_at  TEXT,
    method      TEXT,
    specimen    TEXT,
    machine     TEXT,
    status      TEXT,
    n_samples   INTEGER,
    duration_s  REAL,
    file_mtime_ns INTEGER,
    file_size   INTEGER,
    indexed_at  TEXT
);
CREATE TABLE IF NOT EXISTS fits (
    id        INTEGER PRIMARY KEY,
    run_id    INTEGER NOT NULL REFERENCES runs(id) ON DELETE CASCADE,
    json_path TEXT NOT NULL UNIQUE,
    rmse      REAL,
    created   TEXT
);
CREATE TABLE IF NOT EXISTS diagnoses (
    id        INTEGER PRIMARY KEY,
    run_id    INTEGER NOT NULL REFERENCES runs(id) ON DELETE CASCADE,
    json_path TEXT NOT NULL UNIQUE,
    verdict   TEXT,
    created   TEXT
);
CREATE INDEX IF NOT EXISTS fits_run ON fits(run_id);
CREATE INDEX IF NOT EXISTS diagnoses_run ON diagnoses(run_id);
"""


def data_dir() -> Path:
    """Where runs are kept by default: $FOAMLAB_DATA or ~/foamlab-data."""
    env = os.environ.get("FOAMLAB_DATA", "").strip()
    return Path(env).expanduser() if env else Path.home() / "foamlab-data"


def catalog_for_run(run_path: Path) -> Path | None:
    """The catalog that indexes a run file: its folder's own, else the data folder's when
    the run lies inside it, else None (``foamlab catalog`` can index that folder later)."""
    folder_catalog = run_path.resolve().parent / CATALOG_NAME
    if folder_catalog.exists():
        return folder_catalog
    if run_path.resolve().is_relative_to(data_dir().resolve()):
        return data_dir() / CATALOG_NAME
    return None


def default_catalog_path() -> Path:
    return data_dir() / CATALOG_NAME


def sidecar_path(run_path: str | Path, kind: str) -> Path:
    """``<run stem>.fit.json`` / ``<run stem>.diagnosis.json`` beside the run file."""
    if kind not in SIDECAR_KINDS:
        raise ValueError(f"sidecar kind must be one of {SIDECAR_KINDS}, not {kind!r}")
    p = Path(run_path)
    return p.with_name(f"{p.stem}.{kind}.json")


@dataclass(frozen=True)
class SidecarTarget:
    """Where an analysis of a run is kept: beside a foamlab run file (and catalogued), in the
    folder the user named, or nowhere - never beside someone else's export unasked."""

    path: Path | None
    ours: bool                    # the run is a foamlab run file (catalogued)
    note: str = ""


def sidecar_target(run_path: str | Path, kind: str, out_dir: str | Path | None = None) -> SidecarTarget:
    run_path = Path(run_path)
    ours = is_run_file_path(run_path)
    if out_dir is not None:
        out = Path(out_dir)
        if not out.is_dir():
            raise FoamlabError(f"--out {out}: not a folder")
        return SidecarTarget(out / sidecar_path(run_path, kind).name, ours)
    if ours:
        return SidecarTarget(sidecar_path(run_path, kind), True)
    return SidecarTarget(None, False, f"not a foamlab run file: nothing written beside it "
                                      f"(--out DIR keeps the {kind})")


@dataclass
class Stored:
    path: Path | None             # the sidecar written (None: nothing written)
    catalog: Path | None          # the catalog it was indexed in, if any
    note: str = ""                # why it was not written or not indexed


def store_sidecar(run_path: str | Path, kind: str, out_dir: str | Path | None,
                  write: Callable[[Path], None], index: "Callable[[Catalog, Path, Path], None]") -> Stored:
    """Keep an analysis of a run where sidecar_target says (fit and diagnosis alike): ``write``
    puts it at the path, ``index(catalog, run, sidecar)`` records it for a foamlab run file."""
    run_path = Path(run_path)
    target = sidecar_target(run_path, kind, out_dir)
    if target.path is None:
        return Stored(None, None, target.note)
    try:
        write(target.path)
    except OSError as exc:
        raise FoamlabError(f"{target.path}: cannot write the {kind} ({exc.strerror or exc})") from None
    if not target.ours:
        return Stored(target.path, None, "not a foamlab run file: not catalogued")
    catalog_path = catalog_for_run(run_path)
    if catalog_path is None:
        return Stored(target.path, None, "no catalog for this folder ('foamlab catalog' indexes it later)")
    with Catalog(catalog_path) as catalog:
        index(catalog, run_path, target.path)
    return Stored(target.path, catalog_path)


@dataclass
class RunRecord:
    id: int
    path: str
    started_at: str
    method: str
    specimen: str
    machine: str
    status: str
    n_samples: int
    duration_s: float | None
    rmse: float | None = None      # of the newest fit, if any
    verdict: str | None = None     # of the newest diagnosis, if any

    @property
    def specimen_label(self) -> str:
        return self.specimen

    def get(self, key: str, default: Any = None) -> Any:
        return getattr(self, key, default)


@dataclass
class SyncReport:
    runs: int = 0
    fits: int = 0
    diagnoses: int = 0
    removed: int = 0
    skipped: list[tuple[str, str]] = field(default_factory=list)  # (path, why)


def _iso_mtime(path: Path) -> str:
    return _dt.datetime.fromtimestamp(path.stat().st_mtime).astimezone().isoformat(timespec="seconds")


class Catalog:
    """Index of runs, fits and diagnoses. Use as a context manager or call close()."""

    def __init__(self, path: str | Path | None = None) -> None:
        self.path = Path(path) if path is not None else default_catalog_path()
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._db = sqlite3.connect(self.path, timeout=10.0)
            self._db.row_factory = sqlite3.Row
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA foreign_keys=ON")
            with self._db:
                self._db.executescript(_SCHEMA)
                self._db.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
        except sqlite3.DatabaseError as exc:
            raise FoamlabError(f"{self.path}: cannot open the run catalog ({exc}); delete it and "
                               f"run 'foamlab catalog rebuild' to recreate it from the files") from None
        except OSError as exc:
            raise FoamlabError(f"{self.path}: cannot create the run catalog ({exc.strerror or exc})") from None

    @classmethod
    def for_folder(cls, folder: str | Path, sync: bool = True) -> "Catalog":
        """The catalog of a data folder (``<folder>/catalog.sqlite``), brought up to date."""
        catalog = cls(Path(folder) / CATALOG_NAME)
        if sync:
            catalog.sync(folder)
        return catalog

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> "Catalog":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- writing -------------------------------------------------------------------------
    def add_run(self, path: str | Path, run: RunData | None = None) -> int:
        """Index (or re-index) one run file; ``run`` saves reading it again."""
        p = Path(path).resolve()
        if run is None:
            from foamlab.storage.runfile import read_run_file  # noqa: PLC0415
            run = read_run_file(p)
        stat = p.stat()
        duration = float(run.time_s[-1] - run.time_s[0]) if len(run) else None
        values = (str(p), run.started_at, run.method, run.specimen.label, run.machine, run.status,
                  len(run), duration, stat.st_mtime_ns, stat.st_size,
                  _dt.datetime.now().astimezone().isoformat(timespec="seconds"))
        with self._db:
            self._db.execute(
                """INSERT INTO runs (path, started_at, method, specimen, machine, status, n_samples,
                                     duration_s, file_mtime_ns, file_size, indexed_at)
                   VALUES (?,?,?,?,?,?,?,?,?,?,?)
                   ON CONFLICT(path) DO UPDATE SET started_at=excluded.started_at,
                     method=excluded.method, specimen=excluded.specimen, machine=excluded.machine,
                     status=excluded.status, n_samples=excluded.n_samples,
                     duration_s=excluded.duration_s, file_mtime_ns=excluded.file_mtime_ns,
                     file_size=excluded.file_size, indexed_at=excluded.indexed_at""", values)
        return self._run_id(p)

    def add_fit(self, run_path: str | Path, json_path: str | Path | None = None,
                rmse: float | None = None, created: str | None = None) -> int:
        """Index a fit result (default: the run's ``.fit.json`` sidecar)."""
        return self._add_sidecar("fits", "rmse", run_path, json_path, rmse, created, "fit")

    def add_diagnosis(self, run_path: str | Path, json_path: str | Path | None = None,
                      verdict: str | None = None, created: str | None = None) -> int:
        """Index a diagnosis (default: the run's ``.diagnosis.json`` sidecar)."""
        return self._add_sidecar("diagnoses", "verdict", run_path, json_path, verdict, created,
                                 "diagnosis")

    def _add_sidecar(self, table: str, column: str, run_path, json_path, value, created,
                     kind: str) -> int:
        run_p = Path(run_path).resolve()
        json_p = Path(json_path).resolve() if json_path else sidecar_path(run_p, kind)
        run_id = self._run_id(run_p)
        if run_id is None:
            run_id = self.add_run(run_p)
        if value is None or created is None:
            content = _read_json(json_p)
            if value is None:
                value = content.get(column)
                if column == "rmse":
                    value = float(value) if isinstance(value, (int, float)) else None
                elif value is not None:
                    value = str(value)
            created = created or content.get("created") or _iso_mtime(json_p)
        with self._db:
            self._db.execute(
                f"""INSERT INTO {table} (run_id, json_path, {column}, created) VALUES (?,?,?,?)
                    ON CONFLICT(json_path) DO UPDATE SET run_id=excluded.run_id,
                      {column}=excluded.{column}, created=excluded.created""",
                (run_id, str(json_p), value, str(created)))
            row = self._db.execute(f"SELECT id FROM {table} WHERE json_path=?", (str(json_p),)).fetchone()
        return int(row["id"])

    def _run_id(self, path: Path) -> int | None:
        row = self._db.execute("SELECT id FROM runs WHERE path=?", (str(path),)).fetchone()
        return int(row["id"]) if row else None

    # -- reading -------------------------------------------------------------------------
    def runs(self) -> list[RunRecord]:
        """All indexed runs, newest first, with their newest fit RMSE and verdict."""
        rows = self._db.execute(
            """SELECT r.*,
                 (SELECT rmse FROM fits f WHERE f.run_id=r.id ORDER BY created DESC, id DESC LIMIT 1) AS rmse,
                 (SELECT verdict FROM diagnoses d WHERE d.run_id=r.id ORDER BY created DESC, id DESC LIMIT 1) AS verdict
               FROM runs r ORDER BY started_at DESC, path DESC""").fetchall()
        return [RunRecord(id=r["id"], path=r["path"], started_at=r["started_at"] or "",
                          method=r["method"] or "", specimen=r["specimen"] or "",
                          machine=r["machine"] or "", status=r["status"] or "",
                          n_samples=r["n_samples"] or 0, duration_s=r["duration_s"],
                          rmse=r["rmse"], verdict=r["verdict"]) for r in rows]

    def fits(self, run_path: str | Path | None = None) -> list[dict]:
        return self._sidecars("fits", run_path)

    def diagnoses(self, run_path: str | Path | None = None) -> list[dict]:
        return self._sidecars("diagnoses", run_path)

    def _sidecars(self, table: str, run_path) -> list[dict]:
        query = f"SELECT t.*, r.path AS run_path FROM {table} t JOIN runs r ON r.id=t.run_id"
        args: tuple = ()
        if run_path is not None:
            query += " WHERE r.path=?"
            args = (str(Path(run_path).resolve()),)
        return [dict(row) for row in self._db.execute(query + " ORDER BY t.created, t.id", args)]

    # -- from the files --------------------------------------------------------------------
    def sync(self, folder: str | Path) -> SyncReport:
        """Index new or changed run files under ``folder``, forget vanished ones."""
        return self._scan(Path(folder), full=False)

    def rebuild(self, folder: str | Path) -> SyncReport:
        """Forget everything and index every run file (and sidecar) under ``folder``."""
        with self._db:
            self._db.execute("DELETE FROM fits")
            self._db.execute("DELETE FROM diagnoses")
            self._db.execute("DELETE FROM runs")
        return self._scan(Path(folder), full=True)

    def _scan(self, folder: Path, full: bool) -> SyncReport:
        if not folder.is_dir():
            raise FoamlabError(f"{folder}: no such data folder")
        report = SyncReport()
        known = {r["path"]: (r["file_mtime_ns"], r["file_size"])
                 for r in self._db.execute("SELECT path, file_mtime_ns, file_size FROM runs")}
        seen: set[str] = set()
        for path in _run_files(folder):
            key = str(path.resolve())
            seen.add(key)
            try:
                stat = path.stat()
                if full or known.get(key) != (stat.st_mtime_ns, stat.st_size):
                    self.add_run(path)
                    report.runs += 1
                for kind, adder in (("fit", self.add_fit), ("diagnosis", self.add_diagnosis)):
                    side = sidecar_path(path, kind)
                    if side.exists():
                        adder(path, side)
                        if kind == "fit":
                            report.fits += 1
                        else:
                            report.diagnoses += 1
            except FoamlabError as exc:
                report.skipped.append((str(path), str(exc)))
            except OSError as exc:
                report.skipped.append((str(path), exc.strerror or str(exc)))
        for table in ("fits", "diagnoses"):
            stale = [(row["id"],) for row in self._db.execute(f"SELECT id, json_path FROM {table}")
                     if not Path(row["json_path"]).exists()]
            if stale:
                with self._db:
                    self._db.executemany(f"DELETE FROM {table} WHERE id=?", stale)
        gone = [p for p in known if p not in seen and Path(p).is_relative_to(folder.resolve())]
        if gone:
            with self._db:
                self._db.executemany("DELETE FROM runs WHERE path=?", [(p,) for p in gone])
            report.removed = len(gone)
        return report


def _run_files(folder: Path) -> Iterator[Path]:
    return (path for path in sorted(folder.rglob("*.csv")) if is_run_file_path(path))


def _read_json(path: Path) -> dict:
    try:
        content = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise FoamlabError(f"{path}: file not found") from None
    except (OSError, ValueError) as exc:
        raise FoamlabError(f"{path}: not readable JSON ({exc})") from None
    if not isinstance(content, dict):
        raise FoamlabError(f"{path}: expected a JSON object")
    return content
