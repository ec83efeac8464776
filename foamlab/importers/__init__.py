"""Measured data in, RunData out: ``load_run(path)`` recognises the format.

Formats (one module each):
- foamlab run files (foamlab.storage.runfile) and plain CSVs whose header row is
  ``time_s,displacement_mm,force_N`` after any ``#`` lines (plain_csv);
- Instron Bluehill raw-data CSV exports, any language and encoding (bluehill);
- Instron Bluehill 3 single-header raw data, unit inside each name (bluehill3);
- Instron WaveMatrix tracking exports, ``*.steps.tracking.csv`` (wavematrix);
- MTS 793 MultiPurpose TestWare ``specimen.dat`` exports, multi-block (mts793);
- ZwickRoell testXpert CSV/TXT exports (testxpert); its native binary files
  (.zs2, .zse) are refused with how to export text from testXpert (native).
Vendor data is converted to foamlab's conventions (compression positive, s, mm,
N, time and displacement starting at 0; see foamlab.rundata). Anything
malformed raises FoamlabError with one line that says what is wrong and where.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from foamlab import FoamlabError
from foamlab.importers import (bluehill, bluehill3, mts793, native, plain_csv, testxpert,
                               wavematrix)
from foamlab.importers._text import read_text
from foamlab.rundata import RunData
from foamlab.runformat import is_run_file

# Tried in this order: each recognised by its own header rows. Bluehill 3 comes
# last: any table whose names carry units ('Time (s)') is read like it.
VENDORS = (mts793, bluehill, testxpert, wavematrix, bluehill3)
FORMATS = ("foamlab run file", plain_csv.FORMAT) + tuple(m.FORMAT for m in VENDORS)


def detect_format(lines: list[str]) -> str | None:
    if lines and is_run_file(lines[0]):
        return "foamlab run file"
    if plain_csv.looks_like(lines):
        return plain_csv.FORMAT
    for module in VENDORS:
        if module.looks_like(lines):
            return module.FORMAT
    return None


def load_run(path: str | Path) -> RunData:
    """Read any supported file into a RunData (see the module docstring)."""
    native.refuse(path)
    text_file = read_text(path)
    lines = text_file.lines
    fmt = detect_format(lines[:400])
    try:
        if fmt == "foamlab run file":
            return plain_csv.parse(text_file, run_file=True)
        if fmt == plain_csv.FORMAT:
            return plain_csv.read(text_file)
        for module in VENDORS:
            if fmt == module.FORMAT:
                return module.read(text_file)
    except FoamlabError:
        raise
    except (ValueError, TypeError, IndexError, KeyError, OverflowError, ZeroDivisionError,
            pd.errors.ParserError) as exc:
        # Last line of defence so that a user never sees a traceback; the
        # property-based tests look for this text to find parser gaps.
        raise FoamlabError(f"{path}: internal parser error on this {fmt} file "
                           f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
                           ) from exc
    first = next((ln.strip() for ln in lines if ln.strip()), "")
    table = [ln for ln in lines if ln.strip() and not ln.startswith("#")]
    if not table:
        raise FoamlabError(f"{path}: no header row '{plain_csv.HEADER}' (only # comment lines)")
    if first.startswith("#") or first.count(",") >= 2:
        shown = table[0]
        shown = shown if len(shown) <= 60 else shown[:57] + "..."
        raise FoamlabError(f"{path}: unknown format: header row is {shown!r}; expected "
                           f"'{plain_csv.HEADER}' or a Bluehill, WaveMatrix, MTS or testXpert export")
    shown = first if len(first) <= 60 else first[:57] + "..."
    raise FoamlabError(f"{path}: unknown format (starts with {shown!r}); supported: "
                       f"{', '.join(FORMATS)}")
