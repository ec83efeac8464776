"""Instron Bluehill 3 raw data: one header row, the unit inside each name.

::

    Time measurement (s),Primary load measurement (N),Extension (mm)
    0.000,-0.0123,0.00000
    0.100,-0.5310,-0.01670

Other columns (strain, cycle count, ...) may follow; European installs write
``;`` with a decimal comma. Any table whose header names a time, a length and
a force channel with their units this way is read like it (``Time (s),
Displacement (mm),Force (N)``). Compression made positive, units converted.
"""

from __future__ import annotations

from foamlab.importers._text import TextFile
from foamlab.importers._vendor import (Layout, find_single_header, has_channels, read_export)
from foamlab.rundata import RunData

FORMAT = "Instron Bluehill 3"


def _accept(fields: list[str], names: list[str], units: list[str]) -> bool:
    # units in the names, at least for the three channels foamlab needs
    return sum(bool(u) for u in units) >= 3 and has_channels(names, units)


def find_layout(lines: list[str]) -> Layout | None:
    return find_single_header(lines, _accept)


def looks_like(lines: list[str]) -> bool:
    return find_layout(lines) is not None


def read(text_file: TextFile) -> RunData:
    return read_export(text_file, find_layout, FORMAT)
