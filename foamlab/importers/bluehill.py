"""Instron Bluehill raw-data CSV export.

::

    Text Inputs : Specimen label,"22L.3"        header: "Category : Name,value"
    General : Start Date,13/11/2018 5:14 PM
                                                 blank line
    Time,Extension,Load,Segment ID,...           channel names (any language)
    (sec),(mm),(N),,                             units, in parentheses
    0.00000,-2.04726,-4.31900,22476,0            data

Channel names may be localised (时间/拉伸/负荷, Zeit/Weg/Kraft, ...); a column
with an unknown name is taken when it is the only one with a time, length or
force unit. European installs write ``;`` with a decimal comma. Compression is
stored negative; units are converted (sec/ms, mm/m/in, N/kN/lbf).
"""

from __future__ import annotations

import re

from foamlab.importers._text import TextFile
from foamlab.importers._vendor import SEPARATORS, Layout, read_export, split_fields
from foamlab.rundata import RunData

FORMAT = "Instron Bluehill"
_PARENTHESISED = re.compile(r"^\(.*\)$")


def find_layout(lines: list[str]) -> Layout | None:
    """The names row followed by a units row whose every unit is in parentheses."""
    for i in range(1, min(len(lines), 400)):
        line = lines[i]
        if "(" not in line or not lines[i - 1].strip():
            continue
        for sep in SEPARATORS:
            units = split_fields(line, sep)
            filled = [u for u in units if u]
            if len(units) >= 2 and filled and all(_PARENTHESISED.match(u) for u in filled):
                names = split_fields(lines[i - 1], sep)
                if len(names) >= len(filled) and sum(bool(n) for n in names) >= 2:
                    return Layout(names_index=i - 1, units_index=i, sep=sep)
    return None


def looks_like(lines: list[str]) -> bool:
    return find_layout(lines) is not None


def read(text_file: TextFile) -> RunData:
    return read_export(text_file, find_layout, FORMAT)
