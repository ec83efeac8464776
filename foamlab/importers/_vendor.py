"""The layout Bluehill and testXpert exports share: key/value header lines, a
channel-names row, a units row, then one row per sample."""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from typing import Callable

from foamlab import FoamlabError
from foamlab.importers._table import (Rows, check_samples, normalize_name, parse_date,
                                      parse_length_mm, parse_rows, pick_channels,
                                      to_foamlab_convention)
from foamlab.importers._text import TextFile
from foamlab.rundata import RunData, Specimen

SEPARATORS = (",", ";", "\t")
_NUMBER = re.compile(r'^\s*"?\s*[-+]?(\d+([.,]\d*)?|[.,]\d+)([eE][-+]?\d+)?\s*"?\s*$')
_DECIMAL_COMMA = re.compile(r'^\s*"?\s*[-+]?\d*,\d+([eE][-+]?\d+)?\s*"?\s*$')

# Header keys (after "Category :" for Bluehill), normalised, that fill RunData fields.
LABEL_KEYS = {"specimen label", "specimen name", "specimen id", "sample label", "sample name",
              "specimen", "sample", "probenbezeichnung", "probenname", "probenkennung", "probe",
              "试样标记", "试样标签", "试样名称", "样品名称", "样品编号", "试样编号"}
DATE_KEYS = {"start date", "test date", "date", "start date and time", "prüfdatum", "datum",
             "startdatum", "开始日期", "试验日期", "测试日期", "日期"}
HEIGHT_KEYS = {"height", "thickness", "specimen height", "specimen thickness", "initial height",
               "höhe", "dicke", "probenhöhe", "anfangshöhe", "probendicke", "高度", "厚度", "试样厚度"}
WIDTH_KEYS = {"width", "specimen width", "breite", "probenbreite", "宽度", "试样宽度"}
DEPTH_KEYS = {"depth", "length", "specimen depth", "specimen length", "tiefe", "länge",
              "probenlänge", "深度", "长度", "试样长度"}


@dataclass
class Layout:
    names_index: int         # 0-based line index of the channel-names row
    units_index: int | None  # 0-based line index of the units row
    sep: str


def split_fields(line: str, sep: str) -> list[str]:
    try:
        fields = next(csv.reader([line], delimiter=sep, quotechar='"'), [])
    except csv.Error:
        fields = line.split(sep)
    return [f.strip() for f in fields]


def is_number(text: str) -> bool:
    return bool(_NUMBER.match(text))


def is_data_row(fields: list[str]) -> bool:
    filled = [f for f in fields if f]
    return bool(filled) and sum(is_number(f) for f in filled) >= max(1, len(filled) - 1)


#: A vendor export's channel-name and unit rows are looked for in its first lines.
HEADER_LINES = 400


def read_export(text_file: TextFile, find_layout: Callable[[list[str]], Layout | None], fmt: str) -> RunData:
    """Read a vendor export whose header rows `find_layout` locates (one-line error if none)."""
    layout = find_layout(text_file.lines[:HEADER_LINES])
    if layout is None:
        raise FoamlabError(f"{text_file.path}: no channel-names and units rows of an export from {fmt}")
    return read_vendor(text_file, layout, fmt)


def read_vendor(text_file: TextFile, layout: Layout, fmt: str) -> RunData:
    source = str(text_file.path)
    lines = text_file.lines
    sep = layout.sep
    names = split_fields(lines[layout.names_index], sep)
    units = split_fields(lines[layout.units_index], sep) if layout.units_index is not None else None
    channels = pick_channels(names, units, source)
    first_data = (layout.units_index if layout.units_index is not None else layout.names_index) + 1
    rows, _ = Rows.select(lines, first_data, comments=False)
    if not len(rows):
        raise FoamlabError(f"{source}: no data rows after the column names (line {first_data})")
    decimal = _decimal(rows, sep)
    wanted = {kind: ch.index for kind, ch in channels.items()}
    data = parse_rows(rows, source=source, sep=sep, decimal=decimal,
                      ncols=max(len(names), max(wanted.values()) + 1), wanted=wanted,
                      required=tuple(wanted), ends_with_newline=text_file.ends_with_newline)
    time_s = data["time"] * channels["time"].factor
    check_samples(source, time_s, rows)
    disp = data["displacement"] * channels["displacement"].factor
    force = data["force"] * channels["force"].factor

    header = _header_items(lines[:layout.names_index], sep)
    metadata: dict = {"format": fmt, "encoding": text_file.encoding, "header": header,
                      "channels": {kind: f"{ch.name} ({ch.unit})" for kind, ch in channels.items()}}
    time_s, disp, force = to_foamlab_convention(time_s, disp, force, metadata)
    fields = _fields_from_header(header, metadata)
    return RunData(time_s, disp, force, source=source, status="imported", metadata=metadata,
                   **fields)


def _decimal(rows: Rows, sep: str) -> str:
    if sep == ",":
        return "."
    for text in rows.texts[:200]:
        if any(_DECIMAL_COMMA.match(f) for f in text.split(sep)):
            return ","
    return "."


def _header_items(lines: list[str], sep: str) -> dict[str, str]:
    items: dict[str, str] = {}
    for line in lines:
        if not line.strip():
            continue
        fields = split_fields(line, sep)
        key = fields[0].strip().strip('"')
        value = next((f for f in fields[1:] if f), "")
        if not value and ":" in key and " : " not in key:
            key, _, value = key.partition(":")  # "Key: value" lines
        if key:
            items[key.strip()] = value.strip().strip('"')
    return items


def _fields_from_header(header: dict[str, str], metadata: dict) -> dict:
    label, started, dims = "", "", {}
    for key, value in header.items():
        name = normalize_name(key).rsplit(":", 1)[-1].strip().rstrip(":").strip()
        if name in LABEL_KEYS and not label:
            label = value
        elif name in DATE_KEYS and not started:
            started, ambiguous = parse_date(value)
            if ambiguous:
                metadata["started_at_assumed_day_first"] = value
        else:
            for field, keys in (("height_mm", HEIGHT_KEYS), ("width_mm", WIDTH_KEYS),
                                ("depth_mm", DEPTH_KEYS)):
                if name in keys and field not in dims:
                    length = parse_length_mm(value)
                    if length is not None:
                        dims[field] = length
    return {"specimen": Specimen(label=label, **dims), "started_at": started}
