"""Instron WaveMatrix tracking export (``*.steps.tracking.csv``).

::

    "Total Time (s)","Total Cycles","Elapsed Cycles","Step","Position(Linear:Position) (mm)","Load(Linear:Load) (kN)",
    "0.00000","0","0","1","-0.00021","0.00130",
    "1,000.06200","25","5","2","-4.99812","-1.25410",      thousands grouped past 1000

One header row, quoted, the unit inside each name and the transducer inside
another pair of parentheses (``Position(Linear:Position)``); every row ends
with a comma; often a UTF-8 BOM; German installs write ``Gesamtzeit (s);
Gesamtzyklen;...;Position des Aktuators (mm);Kraft (N)`` with ``;`` and a
decimal comma. Recognised by the total-time column beside a cycle counter or
a ``(Linear:...)`` channel. Time: Total Time; displacement: Displacement
(digital position) or Position (actuator); force: Load or Force. Tens to
hundreds of cycles; compression made positive, units converted.
"""

from __future__ import annotations

import re

from foamlab.importers._table import normalize_name
from foamlab.importers._text import TextFile
from foamlab.importers._vendor import (Layout, find_single_header, has_channels, read_export)
from foamlab.rundata import RunData

FORMAT = "Instron WaveMatrix"
_TRANSDUCER = re.compile(r"\([^()]*[:|][^()]*\)")   # "(Linear:Position)", some tools write "|"
_TOTAL_TIME = {"total time", "gesamtzeit", "temps total", "tiempo total"}
_CYCLES = {"total cycles", "elapsed cycles", "gesamtzyklen", "verstrichene zyklen",
           "cycles totaux", "ciclos totales"}


def _clean(name: str) -> str:
    return _TRANSDUCER.sub("", name).strip()


def _accept(fields: list[str], names: list[str], units: list[str]) -> bool:
    norm = [normalize_name(n) for n in names]
    tracked = any(n in _CYCLES for n in norm) or any(_TRANSDUCER.search(f) for f in fields)
    return any(n in _TOTAL_TIME for n in norm) and tracked and has_channels(names, units)


def find_layout(lines: list[str]) -> Layout | None:
    return find_single_header(lines, _accept, _clean)


def looks_like(lines: list[str]) -> bool:
    return find_layout(lines) is not None


def read(text_file: TextFile) -> RunData:
    return read_export(text_file, find_layout, FORMAT)
