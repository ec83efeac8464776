"""MTS 793 MultiPurpose TestWare (MPT) specimen data export (``specimen.dat``).

::

    MTS793|MPT|DEU|1|2|,|.|:|49|1|1|A                    format line (see below)

    Bediener Information<TAB>...Zeit:<TAB>43,8<TAB>s<TAB>28.01.2015 10:56:24
    Prüfer :<TAB>Kh                                       operator entries (optional)
    Probenbezeichnung :<TAB>Wolf 8.2 Probe 1
    Bediener Information Ende

    Datenerfassung<TAB>...Zeit:<TAB>308,3<TAB>s<TAB>28.01.2015 11:00:49   block title
    Datum<TAB>Laufzeit<TAB>Ch 1 Kraft<TAB>Ch 1 Weg        channel names
    d<TAB>s<TAB>kN<TAB>mm                                 units
    42032<TAB>44,320313<TAB>-0,99271721<TAB>0,050312281   data
    ...                                                   a blank line, then the next block

The format line is ``MTS793|prog|language|version|delimiter|decimal|date
sep|time sep|country|date order|time format|charset``: delimiter 0 space,
1 comma, 2 tab; date order 0 M/D/Y, 1 D/M/Y, 2 Y/M/D. MPT writes a new block
(title, names, units) for every data buffer, every few seconds, unless "Write
First Data Header Only" is set; blocks may order or choose their columns
differently, or hold another process's data (a peak detector's two rows).
Blocks are read by their own names and units and joined in file order where
their time continues; a block whose time does not continue the run is left
out with a note. Channel names such as ``Running Time``/``Laufzeit``,
``Axial Displacement``/``Ch 1 Weg``, ``Axial Force``/``Ch 1 Kraft``; an Excel
day-number time column (unit ``d``) is used when there is no time in seconds.
"""

from __future__ import annotations

import re

import numpy as np

from foamlab import FoamlabError
from foamlab.importers._table import Rows, parse_date
from foamlab.importers._text import TextFile
from foamlab.importers._vendor import (Block, header_items, is_data_row, is_number, make_run,
                                       read_block, split_fields)
from foamlab.rundata import RunData

FORMAT = "MTS 793 MPT"
_DELIMITERS = {"0": " ", "1": ",", "2": "\t"}
# "Ch 1 Kraft", "Axial Force", "Channel 2 Displacement": the prefix names the actuator
_PREFIX = re.compile(r"^\s*(?:(?:ch|channel|kanal|kan\.)\s*\d+|axial|axiale?r?)\s+", re.IGNORECASE)


def looks_like(lines: list[str]) -> bool:
    return bool(lines) and lines[0].lstrip("\ufeff").startswith("MTS793|")


def _format_line(line: str) -> tuple[str | None, str, bool | None]:
    """Separator (None: guess), decimal mark and day-first date order from line 1."""
    parts = line.lstrip("\ufeff").strip().split("|")
    sep = _DELIMITERS.get(parts[4].strip()) if len(parts) > 4 else None
    decimal = parts[5] if len(parts) > 5 and parts[5] in (".", ",") else "."
    order = parts[9].strip() if len(parts) > 9 else ""
    day_first = {"0": False, "1": True}.get(order)
    return sep, decimal, day_first


def _guess_sep(lines: list[str]) -> str:
    sample = "\n".join(lines[1:200])
    return max(("\t", ";", ","), key=sample.count)


def _space_delimited(lines: list[str]) -> list[str]:
    # "plain" exports pad columns with spaces: numbers split on any run of
    # spaces, names on two or more (names such as "Running Time" keep theirs)
    out = []
    for line in lines:
        words = line.split()
        if words and is_data_row(words):
            out.append("\t".join(words))
        else:
            out.append("\t".join(w for w in re.split(r"\s{2,}|\t", line.strip()) if w))
    return out


def _is_text(line: str, sep: str) -> bool:
    return bool(line.strip()) and not is_data_row(split_fields(line, sep))


def _all_numbers(line: str, sep: str) -> bool:
    # strict: operator entries such as "Masse :<TAB>5328" are not data rows
    filled = [f for f in split_fields(line, sep) if f]
    return bool(filled) and all(is_number(f) for f in filled)


def _block_starts(lines: list[str], sep: str) -> list[int]:
    """Indices of the names rows: two text rows (names, units), then a row of numbers."""
    starts, i = [], 1
    while i + 2 < len(lines):
        if (_is_text(lines[i], sep) and _is_text(lines[i + 1], sep)
                and _all_numbers(lines[i + 2], sep)):
            starts.append(i)
            i += 3
        else:
            i += 1
    return starts


def _block_rows(lines: list[str], first: int, stop: int) -> Rows:
    """Data rows from ``first`` up to a blank line or ``stop`` (the next block's title)."""
    end = first
    while end < stop and lines[end].strip():
        end += 1
    return Rows(lines[first:end], range(first + 1, end + 1))


def _read_blocks(text_file: TextFile, lines: list[str], sep: str, decimal: str,
                 notes: list[str]) -> tuple[list[Block], list[int]]:
    source = str(text_file.path)
    starts = _block_starts(lines, sep)
    if not starts:
        raise FoamlabError(f"{source}: no data block (a names row, a units row and numbers) "
                           f"in this MTS 793 export")
    blocks, errors = [], []
    for k, start in enumerate(starts):
        stop = starts[k + 1] if k + 1 < len(starts) else len(lines)
        if k + 1 < len(starts) and _is_text(lines[stop - 1], sep):
            stop -= 1  # the next block's title
        names = [_PREFIX.sub("", n) for n in split_fields(lines[start], sep)]
        units = split_fields(lines[start + 1], sep)
        if len(units) < len(names) and len(lines[start + 1].split()) == len(names):
            units = lines[start + 1].split()  # plain export, units one space apart
        rows = _block_rows(lines, start + 2, stop)
        try:
            blocks.append((start, read_block(source, rows, names, units, sep,
                                             text_file.ends_with_newline, notes, decimal)))
        except FoamlabError as exc:
            if "no time" not in str(exc) and "no displacement" not in str(exc) \
                    and "no force" not in str(exc):
                raise  # a broken number, not a block of other channels
            errors.append((start, exc))
    if not blocks:
        raise errors[0][1]
    for start, exc in errors:
        notes.append(f"block at line {start + 1} left out: {str(exc).split(': ', 1)[-1]}")
    return [b for _, b in blocks], [s for s, _ in blocks]


def _chain(blocks: list[Block]) -> list[int]:
    """The blocks, in file order, whose time continues from one to the next and that
    hold the most samples (a dynamic programme over the blocks)."""
    n = len(blocks)
    ordered = np.array([bool(np.all(np.diff(b.time_s) >= 0)) for b in blocks])
    first = np.array([b.time_s[0] for b in blocks])
    last = np.array([b.time_s[-1] for b in blocks])
    size = np.array([len(b.time_s) for b in blocks], dtype=float)
    best = np.where(ordered, size, -np.inf)
    prev = np.full(n, -1)
    for i in range(1, n):
        if not ordered[i]:
            continue
        fits = ordered[:i] & (last[:i] <= first[i])
        if fits.any():
            j = int(np.argmax(np.where(fits, best[:i], -np.inf)))
            best[i] = size[i] + best[j]
            prev[i] = j
    if not np.isfinite(best).any():
        return []
    chain, i = [], int(np.argmax(best))
    while i >= 0:
        chain.append(i)
        i = int(prev[i])
    return chain[::-1]


def _join(source: str, blocks: list[Block], starts: list[int], notes: list[str]) -> Block:
    chain = _chain(blocks)
    largest = max(range(len(blocks)), key=lambda k: len(blocks[k].time_s))
    kept = sum(len(blocks[k].time_s) for k in chain)
    if not chain or kept < len(blocks[largest].time_s):
        return blocks[largest]  # its own disorder is reported, naming the line
    left = [k for k in range(len(blocks)) if k not in set(chain)]
    t0 = blocks[chain[0]].time_s[0]  # times shown from the run's start (Excel days are huge)
    for k in left[:3]:
        b = blocks[k]
        notes.append(f"block at line {starts[k] + 1} ({len(b.time_s)} rows, t = "
                     f"{b.time_s[0] - t0:g}..{b.time_s[-1] - t0:g} s) left out: its time does "
                     f"not continue the run")
    if len(left) > 3:
        notes.append(f"{len(left) - 3} more blocks left out for the same reason")
    if len(chain) > 1:
        notes.append(f"{len(chain)} data blocks joined in file order")
    parts = [blocks[k] for k in chain]
    return Block(np.concatenate([b.time_s for b in parts]),
                 np.concatenate([b.disp_mm for b in parts]),
                 np.concatenate([b.force_N for b in parts]),
                 [n for b in parts for n in b.line_nos], parts[0].channels)


def _header(lines: list[str], first_block: int, sep: str) -> dict[str, str]:
    """Operator entries above the first block, and the first block title's date."""
    title = lines[first_block - 1] if first_block >= 2 else ""
    header = {}
    stamp = next((f for f in reversed(split_fields(title, sep)) if parse_date(f)[0]), "")
    if stamp:
        header["Start date"] = stamp  # the machine's clock, not a typed date
    header.update(header_items(lines[1:max(first_block - 1, 1)], sep))
    return header


def read(text_file: TextFile) -> RunData:
    lines = text_file.lines
    sep, decimal, day_first = _format_line(lines[0])
    if sep == " ":
        lines, sep = _space_delimited(lines), "\t"
    elif sep is None:
        sep = _guess_sep(lines)
    notes: list[str] = []
    blocks, starts = _read_blocks(text_file, lines, sep, decimal, notes)
    block = _join(str(text_file.path), blocks, starts, notes)
    return make_run(text_file, FORMAT, block, _header(lines, starts[0], sep), notes, day_first)
