"""Where a batch's results go, as they come: the journal, the output file, the catalog.

- ``<out>.journal.jsonl``: one JSON line per finished run, flushed and fsynced when the result
  arrives, so a batch that dies (or is interrupted) loses nothing that was done;
- ``<out>`` (.csv or .parquet): the table, written (atomically) when the batch ends; the journal
  is then removed;
- a re-run reads both and skips every file whose content (SHA-256) has a current result: made by
  this foamlab version, and not a run the batch machinery lost (BatchRow.is_result);
- the catalog (foamlab.storage.catalog) indexes every run read: a foamlab run file in its
  folder's catalog with the sidecars the pipeline wrote beside it (pipeline rules), any other
  file (a vendor export is not ours to add to) in the batch's catalog, its fit and diagnosis
  JSON in ``<out stem>.files/``.
"""

from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from foamlab import FoamlabError, __version__, pipeline
from foamlab.batch.rows import BatchRow
from foamlab.batch.task import Outcome
from foamlab.storage.catalog import CATALOG_NAME, sidecar_path

SUFFIXES = (".csv", ".parquet")
#: Columns read back as text whatever they look like (a specimen "007" stays "007").
TEXT_COLUMNS = tuple(f.name for f in dataclasses.fields(BatchRow) if f.type == "str")


@dataclass
class Destination:
    """The files a batch writes (all None: only the returned table)."""

    out: Path | None = None
    catalog: Path | None = None

    @classmethod
    def choose(cls, out: str | Path | None, catalog: str | Path | None = None) -> "Destination":
        out_p = Path(out).expanduser() if out is not None else None
        if out_p is not None and out_p.suffix.lower() not in SUFFIXES:
            raise FoamlabError(f"{out_p}: the output must be a .csv or a .parquet file")
        if out_p is not None and out_p.is_dir():
            raise FoamlabError(f"{out_p}: is a folder; give the output file's name")
        if catalog is not None:
            catalog_p = Path(catalog).expanduser()
        else:
            catalog_p = out_p.parent / CATALOG_NAME if out_p is not None else None
        return cls(out_p, catalog_p)

    @property
    def journal(self) -> Path | None:
        return self.out.with_name(self.out.name + ".journal.jsonl") if self.out else None

    @property
    def files(self) -> Path | None:
        """The fit and diagnosis JSON of runs that are not foamlab run files."""
        if self.out is not None:
            return self.out.with_name(self.out.stem + ".files")
        return self.catalog.with_name("batch.files") if self.catalog is not None else None

    def written(self) -> set[Path]:
        """What the batch writes, to be left out when it walks a folder."""
        return {p.resolve() for p in (self.out, self.journal, self.catalog, self.files) if p is not None}


class ResultStore:
    """The results of a batch: the earlier ones (to skip), each new one as it arrives."""

    def __init__(self, dest: Destination) -> None:
        self.dest = dest
        self._journal = None
        if dest.out is not None:
            try:
                dest.out.parent.mkdir(parents=True, exist_ok=True)
                self._journal = open(dest.journal, "a", encoding="utf-8")
            except OSError as exc:
                raise FoamlabError(f"{dest.journal}: cannot write the batch journal "
                                   f"({exc.strerror or exc})") from None

    def previous(self) -> dict[str, BatchRow]:
        """Current results by content hash: the output file's, then the journal's (newer)."""
        rows: list[BatchRow] = []
        if self.dest.out is not None and self.dest.out.exists():
            rows += [BatchRow.from_record(r) for r in _read_table(self.dest.out)]
        if self.dest.journal is not None:
            rows += [BatchRow.from_record(r) for r in _read_journal(self.dest.journal)]
        return {r.sha256: r for r in rows if r.is_result and r.version == __version__}

    def add(self, outcome: Outcome) -> BatchRow:
        """Index the run and journal its row (flushed to the disk) before anything else."""
        row = outcome.row
        if outcome.run is not None and row.error_kind != "task":
            note = self._index(outcome)
            row.note = "; ".join(n for n in (row.note, note) if n)
        if self._journal is not None:
            self._journal.write(json.dumps(row.to_record()) + "\n")
            self._journal.flush()
            os.fsync(self._journal.fileno())
        return row

    def _index(self, outcome: Outcome) -> str:
        row, file = outcome.row, Path(outcome.row.file)
        try:
            if outcome.ours:
                pipeline.index_run(file.parent / CATALOG_NAME, file, outcome.run,
                                   Path(outcome.fit_path) if outcome.fit_path else None, row.rmse,
                                   Path(outcome.diagnosis_path) if outcome.diagnosis_path else None,
                                   row.verdict)
            elif self.dest.catalog is not None:
                fit_json, diagnosis_json = self._documents(outcome)
                pipeline.index_run(self.dest.catalog, file, outcome.run, fit_json, row.rmse,
                                   diagnosis_json, row.verdict)
        except Exception as exc:   # the row is the result; the catalog is an index of it
            return f"not added to the catalog: {_one_line(exc)}"
        return ""

    def _documents(self, outcome: Outcome) -> tuple[Path | None, Path | None]:
        folder = self.dest.files
        folder.mkdir(parents=True, exist_ok=True)
        stand_in = folder / f"{Path(outcome.row.file).stem}-{outcome.row.sha256[:12]}.csv"
        written: list[Path | None] = []
        for kind, text in (("fit", outcome.fit_document), ("diagnosis", outcome.diagnosis_document)):
            if not text:
                written.append(None)
                continue
            path = sidecar_path(stand_in, kind)
            tmp = path.with_name(path.name + ".tmp")
            tmp.write_text(text, encoding="utf-8")
            tmp.replace(path)
            written.append(path)
        return written[0], written[1]

    def finish(self, rows: list[BatchRow]) -> pd.DataFrame:
        """The table of the batch; written to the output file, the journal then removed."""
        self.close()
        table = table_of(rows)
        out = self.dest.out
        if out is not None:
            tmp = out.with_name(out.name + ".tmp")
            try:
                if out.suffix.lower() == ".parquet":
                    table.to_parquet(tmp, index=False)
                else:
                    table.to_csv(tmp, index=False)
                tmp.replace(out)
            except (OSError, ImportError, ValueError) as exc:
                raise FoamlabError(f"{out}: cannot write the results ({_one_line(exc)}); "
                                   f"they are in {self.dest.journal}") from None
            self.dest.journal.unlink(missing_ok=True)
        return table

    def close(self) -> None:
        if self._journal is not None:
            self._journal.close()
            self._journal = None


def table_of(rows: list[BatchRow]) -> pd.DataFrame:
    """One row per run; the columns of BatchRow, then one p_<name> per fitted parameter."""
    base = list(BatchRow("", "").to_record())
    table = pd.DataFrame.from_records([r.to_record() for r in rows])
    if table.empty:
        return pd.DataFrame(columns=base)
    return table[base + [c for c in table.columns if c not in base]]


def _read_table(path: Path) -> list[dict]:
    try:
        if path.suffix.lower() == ".parquet":
            table = pd.read_parquet(path)
        else:
            table = pd.read_csv(path, dtype=dict.fromkeys(TEXT_COLUMNS, str))
    except Exception as exc:
        raise FoamlabError(f"{path}: cannot read the earlier results ({_one_line(exc)}); "
                           "move it away to start afresh") from None
    if "sha256" not in table.columns:
        raise FoamlabError(f"{path}: not a foamlab batch table (no sha256 column); "
                           "give another --out")
    return table.to_dict("records")


def _read_journal(path: Path) -> list[dict]:
    records = []
    try:
        with open(path, encoding="utf-8") as fh:
            for line in fh:
                try:
                    records.append(json.loads(line))
                except ValueError:     # the line being written when the batch died
                    continue
    except FileNotFoundError:
        return []
    return records


def _one_line(exc: object) -> str:
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    return lines[0] if lines else type(exc).__name__
