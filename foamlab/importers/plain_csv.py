"""Plain CSV: header row ``time_s,displacement_mm,force_N`` after any ``#`` lines.

Already in foamlab's conventions (compression positive, s / mm / N), so nothing
is converted. ``# key: value`` comment lines fill the RunData fields: the
project's own run files (foamlab.storage.runfile) are a superset of this format.
"""

from __future__ import annotations

import numpy as np

from foamlab import FoamlabError
from foamlab.importers._table import Rows, check_samples, parse_rows
from foamlab.importers._text import TextFile
from foamlab.rundata import RunData
from foamlab.runformat import BASE_COLUMNS, LABEL_COLUMNS, NO_TRAILER_REASON, header_value, runfile_fields

FORMAT = "plain CSV"
HEADER = ",".join(BASE_COLUMNS)


def header_fields(line: str) -> list[str]:
    return [f.strip().strip('"').strip() for f in line.split(",")]


def looks_like(lines: list[str]) -> bool:
    for line in lines:
        if line.startswith("#") or not line.strip():
            continue
        return header_fields(line.lstrip("\ufeff"))[:3] == list(BASE_COLUMNS)
    return False


def parse(text_file: TextFile, run_file: bool = False) -> RunData:
    source = str(text_file.path)
    lines = text_file.lines
    header: dict[str, str] = {}
    comments: list[str] = []
    names: list[str] | None = None
    header_index = 0
    for header_index, line in enumerate(lines):
        if line.startswith("#"):
            item = header_value(line)
            if item:
                header[item[0]] = item[1]
            elif line.strip("# ") and not line.startswith("# foamlab run file"):
                comments.append(line.lstrip("# ").rstrip())
            continue
        if not line.strip():
            continue
        names = header_fields(line.lstrip("\ufeff"))
        if names[:3] != list(BASE_COLUMNS):
            shown = line if len(line) <= 60 else line[:57] + "..."
            raise FoamlabError(f"{source}: line {header_index + 1}: header row is {shown!r}; "
                               f"expected '{HEADER}'")
        break
    if names is None:
        raise FoamlabError(f"{source}: no header row '{HEADER}' (only comments)")
    rows, trailer_lines = Rows.select(lines, header_index + 1, comments=True)
    for _, line in trailer_lines:  # e.g. the run file's status trailer
        item = header_value(line)
        if item:
            header[item[0]] = item[1]
    finished = "status" in header
    metadata_extra: dict = {}
    if run_file and not finished and len(rows) and not text_file.ends_with_newline:
        if len(rows.texts[-1].split(",")) < len(names):
            # the writer was killed while writing this line: the sample in flight
            line_no = rows.drop_last()
            metadata_extra["dropped_partial_line"] = line_no
    if not len(rows):
        raise FoamlabError(f"{source}: no data rows after the header row")
    wanted = {c: i for i, c in enumerate(BASE_COLUMNS)}
    wanted.update({c: names.index(c, 3) for c in LABEL_COLUMNS if c in names[3:]})
    data = parse_rows(rows, source=source, sep=",", decimal=".", ncols=len(names), wanted=wanted,
                      required=BASE_COLUMNS, ends_with_newline=text_file.ends_with_newline)
    check_samples(source, data["time_s"], rows)
    # the engine's step and cycle of each sample (a foamlab run); a column with gaps is not labels
    labelled = all(c in data and np.all(np.isfinite(data[c])) for c in LABEL_COLUMNS)
    fields = runfile_fields(header)
    metadata = fields.pop("metadata")
    if run_file and not finished:
        fields["status"] = "aborted"
        fields["abort_reason"] = NO_TRAILER_REASON
    elif not run_file:
        fields.setdefault("status", "imported")
    metadata.update(metadata_extra)
    metadata["format"] = "foamlab run file" if run_file else FORMAT
    metadata["encoding"] = text_file.encoding
    if len(names) > 3:
        metadata["extra_columns"] = names[3:]
    if comments:
        metadata["comments"] = comments
    labels = {c: data[c].astype(int) for c in LABEL_COLUMNS} if labelled else {}
    return RunData(data["time_s"], data["displacement_mm"], data["force_N"],
                   source=source, metadata=metadata, **labels, **fields)


def read(text_file: TextFile) -> RunData:
    return parse(text_file, run_file=False)
