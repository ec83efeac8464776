"""The shared vendor reader: key/value header lines, a channel-names row, a units
row (or the unit inside each name), then one row per sample; and what every
vendor format ends with (decimal mark and digit grouping, repeated timestamps,
foamlab's sign and units, specimen label / operator / date from the header)."""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from typing import Callable

import numpy as np

from foamlab import FoamlabError
from foamlab.importers._numbers import detect_decimal, remove_grouping
from foamlab.importers._table import (FORCE_UNITS, LENGTH_UNITS, TIME_UNITS, Channel, Rows,
                                      normalize_name, normalize_unit, order_times, parse_date,
                                      parse_length_mm, parse_rows, pick_channels,
                                      to_foamlab_convention)
from foamlab.importers._text import TextFile
from foamlab.rundata import RunData, Specimen

ALL_UNITS = set(TIME_UNITS) | set(LENGTH_UNITS) | set(FORCE_UNITS)

SEPARATORS = (",", ";", "\t")
_NUMBER = re.compile(r'^\s*"?\s*[-+]?(\d[\d,.\u00a0\u202f\u2009\' ]*|[.,]\d+)([eE][-+]?\d+)?\s*"?\s*$')

# Header keys (after "Category :" for Bluehill), normalised, that fill RunData fields.
LABEL_KEYS = {"specimen label", "specimen name", "specimen id", "sample label", "sample name",
              "specimen", "sample", "probenbezeichnung", "probenname", "probenkennung", "probe",
              "probenbeschriftung", "aktuelle probe", "probenbez.", "etykieta próbki",
              "nazwa próbki", "oznaczenie próbki", "próbka", "etiqueta de la muestra",
              "étiquette de l'éprouvette", "éprouvette", "označení vzorku",
              "试样标记", "试样标签", "试样名称", "样品名称", "样品编号", "试样编号"}
DATE_KEYS = {"start date", "test date", "date", "start date and time", "prüfdatum", "datum",
             "startdatum", "data", "data badania", "data rozpoczęcia", "fecha", "datum zkoušky",
             "开始日期", "试验日期", "测试日期", "日期"}
OPERATOR_KEYS = {"operator", "operator name", "tester", "tested by", "user", "prüfer",
                 "bediener", "benutzer", "opérateur", "operateur", "operador", "operatore",
                 "wykonawca", "obsługujący", "试验员", "操作员", "测试员", "试验人员"}
HEIGHT_KEYS = {"height", "thickness", "specimen height", "specimen thickness", "initial height",
               "höhe", "dicke", "probenhöhe", "anfangshöhe", "probendicke", "länge l0",
               "wysokość", "grubość", "高度", "厚度", "试样厚度"}
WIDTH_KEYS = {"width", "specimen width", "breite", "probenbreite", "szerokość", "宽度", "试样宽度"}
DEPTH_KEYS = {"depth", "length", "specimen depth", "specimen length", "tiefe", "länge",
              "probenlänge", "długość", "深度", "长度", "试样长度"}
_UNIT_AT_END = re.compile(r"^(.*?)(\s*)[(\[]([^()\[\]]*)[)\]]\s*$")


@dataclass
class Layout:
    names_index: int         # 0-based line index of the channel-names row
    units_index: int | None  # 0-based line index of the units row
    sep: str
    # set when the names row is not used as it is (a unit inside each name, vendor prefixes)
    names: list[str] | None = None
    units: list[str] | None = None


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


def split_unit(field: str) -> tuple[str, str]:
    """'Time measurement (s)' -> ('Time measurement', 's'); no unit -> (field, '').

    A trailing group glued to the name counts only when it is a known unit
    ('Time(s)'), so 'Total Cycle Count(Linear Waveform)' keeps its name.
    """
    text = field.strip().strip('"').strip()
    m = _UNIT_AT_END.match(text)
    if not m or not m.group(1).strip():
        return text, ""
    name, space, unit = m.group(1).strip(), m.group(2), m.group(3).strip()
    if not space and normalize_unit(unit) not in ALL_UNITS:
        return text, ""
    return name, unit


#: A vendor export's channel-name and unit rows are looked for in its first lines.
HEADER_LINES = 400


def read_export(text_file: TextFile, find_layout: Callable[[list[str]], Layout | None], fmt: str) -> RunData:
    """Read a vendor export whose header rows `find_layout` locates (one-line error if none)."""
    layout = find_layout(text_file.lines[:HEADER_LINES])
    if layout is None:
        raise FoamlabError(f"{text_file.path}: no channel-names and units rows of an export from {fmt}")
    return read_vendor(text_file, layout, fmt)


@dataclass
class Block:
    """One table of a file: scaled samples and the file lines they came from."""
    time_s: np.ndarray
    disp_mm: np.ndarray
    force_N: np.ndarray
    line_nos: list[int]
    channels: dict[str, Channel]


def read_block(source: str, rows: Rows, names: list[str], units: list[str] | None, sep: str,
               ends_with_newline: bool, notes: list[str], decimal: str | None = None) -> Block:
    """The time/displacement/force columns of a table's data rows, in s / mm / N."""
    channels = pick_channels(names, units, source)
    if not len(rows):
        raise FoamlabError(f"{source}: no data rows after the column names")
    decimal = decimal or detect_decimal(rows.texts, sep)
    rows.texts, changed = remove_grouping(rows.texts, sep, decimal)
    if changed:
        notes.append(f"digit grouping (thousands separators) removed from numbers in "
                     f"{len(changed)} rows (first at line {rows.line_nos[changed[0]]})")
    wanted = {kind: ch.index for kind, ch in channels.items()}
    data = parse_rows(rows, source=source, sep=sep, decimal=decimal,
                      ncols=max(len(names), max(wanted.values()) + 1), wanted=wanted,
                      required=tuple(wanted), ends_with_newline=ends_with_newline)
    return Block(data["time"] * channels["time"].factor,
                 data["displacement"] * channels["displacement"].factor,
                 data["force"] * channels["force"].factor, list(rows.line_nos), channels)


def read_vendor(text_file: TextFile, layout: Layout, fmt: str) -> RunData:
    source = str(text_file.path)
    lines = text_file.lines
    sep = layout.sep
    names = layout.names or split_fields(lines[layout.names_index], sep)
    units = layout.units
    if units is None and layout.units_index is not None:
        units = split_fields(lines[layout.units_index], sep)
    first_data = (layout.units_index if layout.units_index is not None else layout.names_index) + 1
    rows, _ = Rows.select(lines, first_data, comments=False)
    notes: list[str] = []
    block = read_block(source, rows, names, units, sep, text_file.ends_with_newline, notes)
    header = header_items(lines[:layout.names_index], sep)
    return make_run(text_file, fmt, block, header, notes)


def make_run(text_file: TextFile, fmt: str, block: Block, header: dict[str, str],
             notes: list[str], day_first: bool | None = None) -> RunData:
    """RunData in foamlab's conventions from a file's samples and header."""
    source = str(text_file.path)
    time_s = order_times(source, block.time_s, block.line_nos, notes)
    disp = join_rezeroed(block.disp_mm, block.line_nos, notes)
    metadata: dict = {"format": fmt, "encoding": text_file.encoding, "header": header,
                      "channels": {kind: f"{ch.name} ({ch.unit})" for kind, ch in block.channels.items()}}
    time_s, disp, force = to_foamlab_convention(time_s, disp, block.force_N, metadata)
    fields = _fields_from_header(header, metadata, day_first)
    if notes:
        metadata["import_notes"] = notes
    return RunData(time_s, disp, force, source=source, status="imported", metadata=metadata,
                   **fields)


def header_items(lines: list[str], sep: str) -> dict[str, str]:
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


def _fields_from_header(header: dict[str, str], metadata: dict,
                        day_first: bool | None = None) -> dict:
    label, started, dims = "", "", {}
    for key, value in header.items():
        # "Text Inputs : Specimen label" -> "specimen label"; MTS "Prüfer :" -> "prüfer"
        name = normalize_name(key).rstrip(":").strip().rsplit(":", 1)[-1].strip()
        if name in LABEL_KEYS and not label and value:
            label = value
        elif name in OPERATOR_KEYS and value and "operator" not in metadata:
            metadata["operator"] = value
        elif name in DATE_KEYS and not started:
            started, ambiguous = parse_date(value, day_first)
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


def join_rezeroed(disp: np.ndarray, line_nos, notes: list[str]) -> np.ndarray:
    """Displacement with the machine's re-zeroing undone (MTS zeroes the channel when
    the test starts: 38 mm to 0 between two samples). A jump counts when it is over
    half the range and 20 times the largest ordinary step; the samples before it are
    shifted to join the ones after."""
    disp = disp.copy()
    for _ in range(3):
        steps = np.abs(np.diff(disp))
        if len(steps) < 10:
            return disp
        i = int(np.argmax(steps))
        ordinary = np.percentile(np.delete(steps, i), 99)
        if not (steps[i] > 0.5 * np.ptp(disp) and steps[i] > 20 * ordinary):
            return disp
        jump = float(disp[i + 1] - disp[i])
        disp[:i + 1] += jump
        notes.append(f"displacement jumps by {jump:g} between lines {line_nos[i]} and "
                     f"{line_nos[i + 1]} (the channel was zeroed): the samples before it shifted "
                     f"to join")
    return disp


def find_single_header(lines: list[str], accept: Callable[[list[str], list[str], list[str]], bool],
                       clean: Callable[[str], str] = str.strip, max_lines: int = 60) -> Layout | None:
    """A names row with the unit inside each name ('Time (s)'), followed by data.

    ``accept(raw_fields, names, units)`` says whether the row is the vendor's;
    ``clean`` tidies a name once its unit is split off.
    """
    for i, line in enumerate(lines[:max_lines]):
        text = line.lstrip("\ufeff")
        for sep in SEPARATORS:
            if sep not in text:
                continue
            fields = split_fields(text, sep)
            if len(fields) < 3 or is_data_row(fields):
                continue
            pairs = [split_unit(f) for f in fields]
            names, units = [clean(n) for n, _ in pairs], [u for _, u in pairs]
            if not accept(fields, names, units):
                continue
            following = next((j for j in range(i + 1, min(len(lines), i + 4)) if lines[j].strip()),
                             None)
            if following is None or is_data_row(split_fields(lines[following], sep)):
                return Layout(names_index=i, units_index=None, sep=sep, names=names, units=units)
    return None


def has_channels(names: list[str], units: list[str]) -> bool:
    """Whether time, displacement and force columns can be told from these names and units."""
    try:
        pick_channels(names, units, "")
    except FoamlabError:
        return False
    return True
