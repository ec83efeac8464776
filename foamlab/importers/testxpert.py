"""ZwickRoell testXpert (II / III) CSV or TXT export.

::

    Probenbezeichnung;PU-45 A          optional "key;value" header lines
    Prüfzeit;Standardkraft;Standardweg channel names (English or German)
    s;N;mm                              units row (plain, [s] or (s))
    0,000;0,012;0,0000                  data: ';', ',' or tab separated,
                                        decimal comma with ';' or tab

Channels: "Test time"/"Prüfzeit", "Standard force"/"Standardkraft",
"Standard travel"/"Standardweg" (or deformation / crosshead travel when there
is no standard travel). Units are converted and compression made positive.
"""

from __future__ import annotations

from foamlab.importers._table import FORCE_NAMES, TIME_NAMES, normalize_name
from foamlab.importers._text import TextFile
from foamlab.importers._vendor import Layout, is_data_row, read_export, split_fields
from foamlab.rundata import RunData

FORMAT = "ZwickRoell testXpert"


def find_layout(lines: list[str]) -> Layout | None:
    """A row naming a time and a force channel, followed by a units row."""
    for i, line in enumerate(lines[:400]):
        for sep in (";", "\t", ","):
            if sep not in line:
                continue
            names = [normalize_name(n) for n in split_fields(line, sep)]
            if not (any(n in TIME_NAMES for n in names) and any(n in FORCE_NAMES for n in names)):
                continue
            following = next((j for j in range(i + 1, min(len(lines), i + 4)) if lines[j].strip()),
                             None)
            if following is None or is_data_row(split_fields(lines[following], sep)):
                continue  # no units row: not a testXpert export
            return Layout(names_index=i, units_index=following, sep=sep)
    return None


def looks_like(lines: list[str]) -> bool:
    return find_layout(lines) is not None


def read(text_file: TextFile) -> RunData:
    return read_export(text_file, find_layout, FORMAT)
